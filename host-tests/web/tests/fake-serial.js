// Injected by the browser tests before any script of the page runs: a
// `navigator.serial` whose ports are WebSockets to `serial-ws`, which holds
// the real serial port (the pseudo-terminal of `sim --bridge-pty`). The page's
// own code is unchanged; this stands in only for the browser's port picker
// and the USB device behind it.
//
// `window.__fakeSerial = {url, path}` is set first (the test's init
// script); the test may change it between connections (a restarted bridge
// has a new pty). Every byte from the port is also kept in
// `window.__fakeSerial.received` (the test reads what the page got).
(() => {
  const cfg = window.__fakeSerial;
  cfg.received = [];

  class FakePort extends EventTarget {
    constructor() {
      super();
      this.ws = null;
      this.current = null;
      this.backlog = [];
      this.writer = null;
    }

    getInfo() {
      // The ESP32-C3/C6's own USB (USB-Serial-JTAG).
      return { usbVendorId: 0x303a, usbProductId: 0x1001 };
    }

    get readable() {
      if (!this.ws) return null;
      if (!this.current) {
        let ctrl;
        const stream = new ReadableStream({
          start: (c) => {
            ctrl = c;
          },
          cancel: () => {
            if (this.current && this.current.stream === stream) this.current = null;
          },
        });
        this.current = { stream, ctrl };
        for (const chunk of this.backlog.splice(0)) ctrl.enqueue(chunk);
      }
      return this.current.stream;
    }

    get writable() {
      if (!this.ws) return null;
      if (!this.writer) {
        this.writer = new WritableStream({
          write: (chunk) => {
            if (!this.ws) throw new DOMException("The port is closed.", "InvalidStateError");
            this.ws.send(chunk);
          },
        });
      }
      return this.writer;
    }

    async open({ baudRate }) {
      if (this.ws) throw new DOMException("The port is already open.", "InvalidStateError");
      const ws = new WebSocket(cfg.url);
      ws.binaryType = "arraybuffer";
      await new Promise((resolve, reject) => {
        ws.onopen = resolve;
        ws.onerror = () => reject(new DOMException("Failed to open serial port.", "NetworkError"));
      });
      ws.send(JSON.stringify({ open: cfg.path, baudRate }));
      const answer = await new Promise((resolve) => {
        ws.onmessage = (e) => resolve(JSON.parse(e.data));
      });
      if (answer.error) {
        ws.close();
        throw new DOMException(`Failed to open serial port: ${answer.error}`, "NetworkError");
      }
      this.ws = ws;
      ws.onmessage = (e) => {
        if (typeof e.data === "string") return;
        const bytes = new Uint8Array(e.data);
        cfg.received.push(...bytes);
        if (this.current) this.current.ctrl.enqueue(bytes);
        else this.backlog.push(bytes);
      };
      ws.onclose = () => {
        if (this.current) {
          try {
            this.current.ctrl.error(new DOMException("The device has been lost.", "NetworkError"));
          } catch {
            /* already closed */
          }
        }
        this.ws = null;
        this.current = null;
        this.writer = null;
      };
    }

    async setSignals(signals) {
      if (this.ws) this.ws.send(JSON.stringify({ signals }));
    }

    async close() {
      const ws = this.ws;
      this.ws = null;
      if (this.current) {
        try {
          this.current.ctrl.close();
        } catch {
          /* already closed */
        }
      }
      this.current = null;
      this.writer = null;
      this.backlog = [];
      if (ws) ws.close();
    }

    async forget() {}
  }

  const port = new FakePort();
  const serial = new EventTarget();
  serial.requestPort = async () => port;
  serial.getPorts = async () => [port];
  Object.defineProperty(navigator, "serial", { value: serial, configurable: true });
  cfg.port = port;
})();
