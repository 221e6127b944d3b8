// The firmware's rules compiled to WebAssembly (host-tests/web/wasm): the
// configuration field table and value parser, the relations between BMS
// settings, the freshness rule, the board table — with the desktop tool's
// messages. One export does it all: `tb_call(name, arg)`, JSON both ways.

interface Exports {
  memory: WebAssembly.Memory;
  tb_alloc(len: number): number;
  tb_free(ptr: number, len: number): void;
  tb_call(name: number, nameLen: number, arg: number, argLen: number): bigint;
}

let exports: Exports | undefined;

/** Loads the module (once). */
export async function loadRules(url = "tinybms_web.wasm"): Promise<void> {
  if (exports) return;
  const response = await fetch(url);
  if (!response.ok) throw new Error(`${url}: ${response.status}`);
  const { instance } = await WebAssembly.instantiate(await response.arrayBuffer(), {});
  exports = instance.exports as unknown as Exports;
}

function put(e: Exports, text: string): [number, number] {
  const bytes = new TextEncoder().encode(text);
  const ptr = e.tb_alloc(bytes.length);
  new Uint8Array(e.memory.buffer, ptr, bytes.length).set(bytes);
  return [ptr, bytes.length];
}

/** Calls a rule by name with a JSON argument; its JSON answer. */
export function rules<T = any>(name: string, arg: unknown = null): T {
  const e = exports;
  if (!e) throw new Error("the rules are not loaded");
  const [n, nl] = put(e, name);
  const [a, al] = put(e, JSON.stringify(arg));
  const r = e.tb_call(n, nl, a, al);
  e.tb_free(n, nl);
  e.tb_free(a, al);
  const ptr = Number(r >> 32n);
  const len = Number(r & 0xffffffffn);
  const text = new TextDecoder().decode(new Uint8Array(e.memory.buffer, ptr, len));
  e.tb_free(ptr, len);
  const out = JSON.parse(text);
  if (out && typeof out === "object" && "error" in out && Object.keys(out).length === 1) {
    throw new Error(out.error);
  }
  return out as T;
}
