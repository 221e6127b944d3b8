// The bridge's host link (JSON Lines, firmware/src/host_link/PROTOCOL.md) on
// a Web Serial port: lines in, commands out, answers matched by `req`. Lines
// that are not JSON objects (an Improv packet of the installer, a line cut
// by a host that was away) are skipped, as the desktop tool skips them.

export type Line = Record<string, any> & { type: string };

type Waiter = {
  req: number;
  lines: Line[];
  done: (l: Line) => boolean;
  resolve: (lines: Line[]) => void;
  reject: (e: Error) => void;
  timer: number;
};

/** What both kinds of link share: lines in, commands out, answers by `req`. */
export abstract class Link {
  protected reader?: ReadableStreamDefaultReader<Uint8Array>;
  protected writer?: WritableStreamDefaultWriter<Uint8Array>;
  protected nextReq = 1;
  protected waiters: Waiter[] = [];
  protected closed = false;
  /** Every line, as it comes. */
  onLine: (l: Line) => void = () => {};
  /** The port went away (unplugged, closed). */
  onClose: (why: string) => void = () => {};

  constructor(protected port: SerialPort) {}

  /** Opens the port and starts reading. */
  abstract open(): Promise<void>;
  /** Writes one command line (with its newline). */
  protected abstract write(line: string): Promise<void>;

  /** The port at 115200 Bd (the host link's, and the TinyBMS's 8N1), its reader and writer. */
  protected async openPort(): Promise<void> {
    await this.port.open({ baudRate: 115200, bufferSize: 8192 });
    if (!this.port.readable || !this.port.writable) throw new Error("the port is not readable and writable");
    this.reader = this.port.readable.getReader();
    this.writer = this.port.writable.getWriter();
  }

  /** Closes the port (a bridge starts a clean session at the next hello). */
  async close(): Promise<void> {
    this.closed = true;
    try {
      await this.reader?.cancel();
    } catch {
      /* already gone */
    }
    this.reader?.releaseLock();
    this.writer?.releaseLock();
    try {
      await this.port.close();
    } catch {
      /* already closed */
    }
  }

  /** The port ended: every waiting request fails. */
  protected ended(why: string): void {
    this.closed = true;
    for (const w of this.waiters) {
      clearTimeout(w.timer);
      w.reject(new Error(why));
    }
    this.waiters = [];
    this.onClose(why);
  }

  /** One line from the bridge (its text, without the newline). */
  protected take(text: string): void {
    if (!text.startsWith("{")) return;
    let l: Line;
    try {
      l = JSON.parse(text);
    } catch {
      return;
    }
    if (typeof l !== "object" || l === null || typeof l.type !== "string") return;
    this.onLine(l);
    for (const w of [...this.waiters]) {
      if (l.req === w.req || (w.req === 0 && l.type === "hello")) {
        w.lines.push(l);
        if (w.done(l)) {
          clearTimeout(w.timer);
          this.waiters.splice(this.waiters.indexOf(w), 1);
          w.resolve(w.lines);
        }
      }
    }
  }

  /** Sends one command line (without waiting for anything). */
  async send(command: Record<string, unknown>): Promise<void> {
    if (this.closed) throw new Error("not connected");
    await this.write(JSON.stringify(command) + "\n");
  }

  /**
   * Sends `command` with a new `req` and collects the lines that answer it
   * until `done` says the answer is complete (or an `error` line comes).
   */
  async request(
    command: Record<string, unknown>,
    done: (l: Line) => boolean,
    timeoutMs = 5000,
  ): Promise<Line[]> {
    const req = command.cmd === "hello" ? 0 : this.nextReq++;
    const promise = new Promise<Line[]>((resolve, reject) => {
      const timer = window.setTimeout(() => {
        this.waiters = this.waiters.filter((w) => w !== waiter);
        reject(new Error(`no answer to ${String(command.cmd)} within ${timeoutMs / 1000} s`));
      }, timeoutMs);
      const waiter: Waiter = {
        req,
        lines: [],
        done: (l) => l.type === "error" || done(l),
        resolve,
        reject,
        timer,
      };
      this.waiters.push(waiter);
    });
    await this.send(req === 0 ? command : { ...command, req });
    return promise;
  }
}

/** A bridge on the port: its host link. */
export class HostLink extends Link {
  /** Opens the port at the host link's 115200 Bd and starts reading. */
  async open(): Promise<void> {
    await this.openPort();
    void this.readLoop();
  }

  private async readLoop(): Promise<void> {
    const decoder = new TextDecoder();
    let pending = "";
    let why = "the port closed";
    try {
      for (;;) {
        const { value, done } = await this.reader!.read();
        if (done) break;
        if (!value) continue;
        pending += decoder.decode(value, { stream: true });
        let nl: number;
        while ((nl = pending.indexOf("\n")) >= 0) {
          const text = pending.slice(0, nl).replace(/\r$/, "");
          pending = pending.slice(nl + 1);
          this.take(text);
        }
        if (pending.length > 65536) pending = "";
      }
    } catch (e) {
      why = `the port failed: ${(e as Error).message}`;
    }
    this.ended(why);
  }

  protected async write(line: string): Promise<void> {
    if (!this.writer) throw new Error("not connected");
    await this.writer.write(new TextEncoder().encode(line));
  }
}

/** The error of an answer, if it is one: `code: detail`. */
export function errorOf(lines: Line[]): string | undefined {
  const e = lines.find((l) => l.type === "error");
  return e ? `${e.error}: ${e.detail ?? ""}` : undefined;
}

/**
 * A TinyBMS on the port (behind a USB-UART adapter), no bridge: the page runs
 * the firmware's own station (compiled to WebAssembly with the rules), as
 * `tinybms` does in its direct mode — what the BMS sends goes into it, what it
 * transmits goes to the port, and its host-link lines are read as a bridge's.
 */
export class DirectLink extends Link {
  private rx: number[] = [];
  private host = "";
  private timer?: number;
  private busy = false;

  constructor(
    port: SerialPort,
    private rules: <T>(name: string, arg: unknown) => T,
  ) {
    super(port);
  }

  async open(): Promise<void> {
    // The TinyBMS's UART: 115200 8N1 (Rev D).
    await this.openPort();
    this.rules("direct_start", { now_ms: performance.now() });
    void this.readLoop();
    this.soon(0);
  }

  private async readLoop(): Promise<void> {
    let why = "the port closed";
    try {
      for (;;) {
        const { value, done } = await this.reader!.read();
        if (done) break;
        if (value && value.length) {
          for (const b of value) this.rx.push(b);
          this.soon(0);
        }
      }
    } catch (e) {
      why = `the port failed: ${(e as Error).message}`;
    }
    if (this.timer !== undefined) clearTimeout(this.timer);
    this.ended(why);
  }

  private soon(ms: number): void {
    if (this.timer !== undefined) clearTimeout(this.timer);
    this.timer = window.setTimeout(() => void this.step(), Math.max(0, Math.min(ms, 100)));
  }

  /** One round of the station: bytes and lines in, bytes and lines out. */
  private async step(): Promise<void> {
    if (this.closed || this.busy) return;
    this.busy = true;
    try {
      const rx = this.rx;
      this.rx = [];
      const host = this.host;
      this.host = "";
      const r = this.rules<{ tx: number[]; lines: string[]; wake_ms: number }>("direct_step", {
        now_ms: performance.now(),
        rx,
        host,
      });
      if (r.tx.length && this.writer) await this.writer.write(new Uint8Array(r.tx));
      for (const l of r.lines) this.take(l);
      // More came meanwhile: at once; else when the station wants to be back.
      this.soon(this.rx.length || this.host ? 0 : r.wake_ms - performance.now());
    } finally {
      this.busy = false;
    }
  }

  protected async write(line: string): Promise<void> {
    this.host += line;
    this.soon(0);
  }

  async close(): Promise<void> {
    if (this.timer !== undefined) clearTimeout(this.timer);
    await super.close();
  }
}
