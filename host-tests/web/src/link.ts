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

export class HostLink {
  private reader?: ReadableStreamDefaultReader<Uint8Array>;
  private writer?: WritableStreamDefaultWriter<Uint8Array>;
  private nextReq = 1;
  private waiters: Waiter[] = [];
  private closed = false;
  /** Every line, as it comes. */
  onLine: (l: Line) => void = () => {};
  /** The port went away (unplugged, closed). */
  onClose: (why: string) => void = () => {};

  constructor(private port: SerialPort) {}

  /** Opens the port at the host link's 115200 Bd and starts reading. */
  async open(): Promise<void> {
    await this.port.open({ baudRate: 115200, bufferSize: 8192 });
    if (!this.port.readable || !this.port.writable) throw new Error("the port is not readable and writable");
    this.reader = this.port.readable.getReader();
    this.writer = this.port.writable.getWriter();
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
    this.closed = true;
    for (const w of this.waiters) {
      clearTimeout(w.timer);
      w.reject(new Error(why));
    }
    this.waiters = [];
    this.onClose(why);
  }

  private take(text: string): void {
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
    if (this.closed || !this.writer) throw new Error("not connected");
    await this.writer.write(new TextEncoder().encode(JSON.stringify(command) + "\n"));
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

  /** Closes the port (the bridge starts a clean session at the next hello). */
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
}

/** The error of an answer, if it is one: `code: detail`. */
export function errorOf(lines: Line[]): string | undefined {
  const e = lines.find((l) => l.type === "error");
  return e ? `${e.error}: ${e.detail ?? ""}` : undefined;
}
