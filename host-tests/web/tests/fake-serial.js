// Injected by the browser tests before any script of the page runs: a
// `navigator.serial` whose one port stands for an ESP32-C3 on its own USB
// (USB-Serial-JTAG). The pages' own code is unchanged; this stands in only for
// the browser's port picker and the board behind it.
//
// The board runs one of two things, as a real one does:
// * its firmware: the port is a WebSocket to `serial-ws`, which holds the real
//   serial port — the pseudo-terminal of `sim --bridge-pty`, the firmware's
//   own station against a simulated TinyBMS;
// * its ROM download mode: a small model of the ESP32-C3's serial bootloader
//   and esptool's flasher stub (SLIP packets: sync, registers, the stub
//   upload, erase, compressed writes) over a 4 MiB flash kept here, so
//   esptool-js, inside ESP Web Tools, is fed the images and really writes
//   them, and a test can read back what landed where.
// The DTR/RTS lines switch between them as on the chip: a reset released with
// the boot strap held (DTR) starts the ROM, any other reset the firmware.
//
// `window.__fakeSerial = {url, path, mode}` is set first by the test's init
// script (`mode`: "firmware" or "rom"); the test may change `url`/`path`
// (a restarted bridge has a new pty). Every byte the page receives from the
// firmware is kept in `window.__fakeSerial.received`; what the ROM did, in
// `window.__fakeSerial.rom` (`flash`, `erased`, `writes`).
(() => {
  const cfg = window.__fakeSerial;
  cfg.received = [];
  cfg.mode = cfg.mode || "firmware";
  cfg.rom = { flash: null, erased: false, writes: [], stub: false, resets: [] };

  const FLASH_SIZE = 4 * 1024 * 1024;
  // ESP32-C3 (esptool's CHIP_DETECT_MAGIC_VALUE) and a 4 MB flash's JEDEC id.
  const REGS = { 0x40001000: 0x1b31506f, 0x60002058: 0x001640ef };

  function flash() {
    if (!cfg.rom.flash) cfg.rom.flash = new Uint8Array(FLASH_SIZE).fill(0xff);
    return cfg.rom.flash;
  }

  const u32 = (b, i) => (b[i] | (b[i + 1] << 8) | (b[i + 2] << 16) | (b[i + 3] << 24)) >>> 0;

  function slip(packet) {
    const out = [0xc0];
    for (const b of packet) {
      if (b === 0xc0) out.push(0xdb, 0xdc);
      else if (b === 0xdb) out.push(0xdb, 0xdd);
      else out.push(b);
    }
    out.push(0xc0);
    return new Uint8Array(out);
  }

  async function inflate(bytes) {
    const stream = new Blob([bytes]).stream().pipeThrough(new DecompressionStream("deflate"));
    return new Uint8Array(await new Response(stream).arrayBuffer());
  }

  /** The serial bootloader and the flasher stub, as far as esptool-js uses them. */
  class Rom {
    constructor(send) {
      this.send = send;
      this.frame = null;
      this.escape = false;
      this.defl = null;
      this.queue = Promise.resolve();
    }

    input(bytes) {
      for (const b of bytes) {
        if (b === 0xc0) {
          if (this.frame && this.frame.length) {
            const f = new Uint8Array(this.frame);
            this.queue = this.queue.then(() => this.command(f));
          }
          this.frame = [];
          continue;
        }
        if (!this.frame) continue;
        if (this.escape) {
          this.frame.push(b === 0xdc ? 0xc0 : b === 0xdd ? 0xdb : b);
          this.escape = false;
        } else if (b === 0xdb) this.escape = true;
        else this.frame.push(b);
      }
    }

    reply(op, val = 0, data = [0, 0]) {
      const p = new Uint8Array(8 + data.length);
      p[0] = 1;
      p[1] = op;
      p[2] = data.length & 0xff;
      p[3] = data.length >> 8;
      p.set([val & 0xff, (val >>> 8) & 0xff, (val >>> 16) & 0xff, (val >>> 24) & 0xff], 4);
      p.set(data, 8);
      this.send(slip(p));
    }

    async command(f) {
      if (f.length < 8 || f[0] !== 0) return;
      const op = f[1];
      const data = f.subarray(8);
      switch (op) {
        case 0x08: // SYNC: the ROM answers eight times, with a non-zero value.
          for (let i = 0; i < 8; i++) this.reply(op, 0x07071220);
          break;
        case 0x0a: // READ_REG
          this.reply(op, REGS[u32(data, 0)] ?? 0);
          break;
        case 0x09: // WRITE_REG (the SPI registers of the flash id read)
        case 0x0b: // SPI_SET_PARAMS
        case 0x0d: // SPI_ATTACH
        case 0x0f: // CHANGE_BAUDRATE
        case 0x05: // MEM_BEGIN
        case 0x07: // MEM_DATA
          this.reply(op);
          break;
        case 0x06: // MEM_END: the stub runs and says hello.
          this.reply(op);
          cfg.rom.stub = true;
          this.send(slip(new TextEncoder().encode("OHAI")));
          break;
        case 0xd0: // ERASE_FLASH
          flash().fill(0xff);
          cfg.rom.erased = true;
          this.reply(op);
          break;
        case 0x10: {
          // FLASH_DEFL_BEGIN: uncompressed size, blocks, block size, offset.
          const size = u32(data, 0);
          const offset = u32(data, 12);
          // Whole sectors are erased before they are written, as the stub does.
          const end = Math.min(FLASH_SIZE, offset + Math.ceil(size / 4096) * 4096);
          flash().fill(0xff, offset, end);
          this.defl = { offset, size, chunks: [] };
          this.reply(op);
          break;
        }
        case 0x11: {
          // FLASH_DEFL_DATA: length, sequence, two reserved words, the block.
          const len = u32(data, 0);
          if (!this.defl) return this.reply(op, 0, [1, 0x05]);
          this.defl.chunks.push(data.slice(16, 16 + len));
          this.reply(op);
          break;
        }
        case 0x12: {
          // FLASH_DEFL_END: the stream inflated into the flash.
          const d = this.defl;
          this.defl = null;
          if (!d) return this.reply(op, 0, [1, 0x05]);
          const bytes = await inflate(new Uint8Array(await new Blob(d.chunks).arrayBuffer()));
          flash().set(bytes.subarray(0, d.size), d.offset);
          cfg.rom.writes.push({ offset: d.offset, size: d.size });
          this.reply(op);
          break;
        }
        default:
          // Not a command of this model: the ROM's "invalid command".
          this.reply(op, 0, [1, 0x05]);
      }
    }
  }

  class FakePort extends EventTarget {
    constructor() {
      super();
      this.opened = false;
      this.ws = null;
      this.rom = null;
      this.current = null;
      this.backlog = [];
      this.writer = null;
      this.dtr = false;
      this.rts = false;
      this.inReset = false;
      this.bootStrap = false;
    }

    getInfo() {
      return { usbVendorId: 0x303a, usbProductId: 0x1001 };
    }

    deliver(bytes) {
      if (this.current) this.current.ctrl.enqueue(bytes);
      else this.backlog.push(bytes);
    }

    get readable() {
      if (!this.opened) return null;
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
      if (!this.opened) return null;
      if (!this.writer) {
        this.writer = new WritableStream({
          write: (chunk) => {
            if (!this.opened) throw new DOMException("The port is closed.", "InvalidStateError");
            if (this.rom) this.rom.input(new Uint8Array(chunk));
            else if (this.ws && this.ws.readyState === WebSocket.OPEN) this.ws.send(chunk);
            // else: the board is resetting or booting; the bytes are lost, as on the wire
          },
        });
      }
      return this.writer;
    }

    async open({ baudRate }) {
      if (this.opened) throw new DOMException("The port is already open.", "InvalidStateError");
      this.baudRate = baudRate;
      if (cfg.mode === "firmware") await this.runFirmware(true);
      else this.runRom();
      this.opened = true;
    }

    runRom() {
      this.stopFirmware();
      this.rom = new Rom((b) => this.deliver(b));
    }

    /** The firmware's port: the bridge's pty through serial-ws. */
    async runFirmware(strict) {
      this.rom = null;
      const ws = new WebSocket(cfg.url);
      ws.binaryType = "arraybuffer";
      const ok = await new Promise((resolve) => {
        ws.onopen = () => resolve(true);
        ws.onerror = () => resolve(false);
      });
      if (ok) {
        ws.send(JSON.stringify({ open: cfg.path, baudRate: this.baudRate }));
        const answer = await new Promise((resolve) => {
          ws.onmessage = (e) => resolve(JSON.parse(e.data));
        });
        if (!answer.error) {
          this.ws = ws;
          ws.onmessage = (e) => {
            if (typeof e.data === "string") return;
            const bytes = new Uint8Array(e.data);
            cfg.received.push(...bytes);
            this.deliver(bytes);
          };
          ws.onclose = () => {
            if (this.ws === ws) {
              this.ws = null;
              if (this.current) {
                try {
                  this.current.ctrl.error(new DOMException("The device has been lost.", "NetworkError"));
                } catch {
                  /* already closed */
                }
                this.current = null;
              }
              this.opened = false;
              this.writer = null;
            }
          };
          return;
        }
        ws.close();
        if (strict) throw new DOMException(`Failed to open serial port: ${answer.error}`, "NetworkError");
      } else if (strict) {
        throw new DOMException("Failed to open serial port.", "NetworkError");
      }
    }

    stopFirmware() {
      const ws = this.ws;
      this.ws = null;
      if (ws) ws.close();
    }

    async setSignals(s) {
      if (s.dataTerminalReady !== undefined) this.dtr = s.dataTerminalReady;
      if (s.requestToSend !== undefined) this.rts = s.requestToSend;
      // USB-Serial-JTAG: DTR alone pulls the boot strap; RTS resets the chip.
      if (this.dtr && !this.rts) this.bootStrap = true;
      if (this.rts && !this.dtr) this.inReset = true;
      if (this.inReset && !this.rts) {
        this.inReset = false;
        cfg.mode = this.bootStrap ? "rom" : "firmware";
        this.bootStrap = false;
        cfg.rom.resets.push(cfg.mode);
        if (!this.opened) return;
        if (cfg.mode === "rom") this.runRom();
        else {
          this.stopFirmware();
          await this.runFirmware(false);
        }
      }
    }

    async close() {
      this.opened = false;
      this.stopFirmware();
      this.rom = null;
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
