// The console: the bridge (or a TinyBMS behind the bridge) from a browser,
// over Web Serial, speaking the host link as the desktop tool does. Every
// value an owner types is checked by the firmware's own rules compiled to
// WebAssembly (./wasm.ts), with the tool's messages; the bridge checks again.

import { DirectLink, errorOf, HostLink, Line, Link } from "./link";
import { loadRules, rules } from "./wasm";

const $ = <T extends HTMLElement = HTMLElement>(id: string) => document.getElementById(id) as T;

function text(id: string, value: string): void {
  $(id).textContent = value;
}

function fixed(v: unknown, decimals: number, unit: string): string {
  return typeof v === "number" && Number.isFinite(v) ? `${v.toFixed(decimals)} ${unit}` : "–";
}

function words(key: unknown): string {
  return typeof key === "string" ? key.replace(/_/g, " ") : "–";
}

/** One line in a list, newest first, at most `keep`. */
function prepend(list: HTMLElement, content: string, cls = "", keep = 200): void {
  const li = document.createElement("li");
  li.textContent = content;
  if (cls) li.className = cls;
  list.prepend(li);
  while (list.children.length > keep) list.lastElementChild?.remove();
}

/** Messages under a form: each its own line. */
function say(id: string, lines: string[], cls: string): void {
  const box = $(id);
  box.replaceChildren(
    ...lines.map((m) => {
      const p = document.createElement("pre");
      p.className = cls;
      p.textContent = m;
      return p;
    }),
  );
}

interface Session {
  link: Link;
  /** A TinyBMS behind a USB-UART adapter, the station running in the page. */
  direct: boolean;
  hello: Line;
  telemetry?: Line;
  receivedAt: number;
  config: Line[];
  settings: Line[];
}

let session: Session | undefined;
let timer: number | undefined;
/** The newest lines from the bridge (or the station in the page). */
const recent: Line[] = [];
(window as unknown as { tinybms: unknown }).tinybms = { recent };

/** Waits until `check` holds (polled), at most `ms`. */
function until(check: () => boolean, ms: number): Promise<void> {
  return new Promise((resolve, reject) => {
    const end = performance.now() + ms;
    const t = window.setInterval(() => {
      if (check()) {
        window.clearInterval(t);
        resolve();
      } else if (performance.now() > end) {
        window.clearInterval(t);
        reject(new Error("timed out"));
      }
    }, 100);
  });
}

// ------------------------------------------------------------------ live

function showTelemetry(t: Line): void {
  text("pack-voltage", fixed(t.pack_voltage_v, 2, "V"));
  text("pack-current", fixed(t.pack_current_a, 2, "A"));
  const power =
    typeof t.pack_voltage_v === "number" && typeof t.pack_current_a === "number"
      ? t.pack_voltage_v * t.pack_current_a
      : undefined;
  text("pack-power", fixed(power, 0, "W"));
  text("soc", fixed(t.soc_percent, 1, "%"));
  text("soh", fixed(t.soh_percent, 0, "%"));
  text("status", words(t.online_status));
  text("cell-min", fixed(t.min_cell_voltage_v, 3, "V"));
  text("cell-max", fixed(t.max_cell_voltage_v, 3, "V"));
  const delta =
    typeof t.max_cell_voltage_v === "number" && typeof t.min_cell_voltage_v === "number"
      ? (t.max_cell_voltage_v - t.min_cell_voltage_v) * 1000
      : undefined;
  text("cell-delta", fixed(delta, 0, "mV"));
  const temp = (v: unknown) => (v === null ? "not connected" : fixed(v, 1, "°C"));
  text("temp-internal", temp(t.internal_temperature_c));
  text("temp-ext1", temp(t.external_temperature_1_c));
  text("temp-ext2", temp(t.external_temperature_2_c));
  showCells(t);
  const inv = t.inverter;
  text(
    "inverter",
    inv
      ? `${inv.protocol}, CAN ${words(inv.can)}, inverter ${inv.heard ? "heard" : "not heard"}; ` +
          `CVL ${fixed(inv.cvl_v, 1, "V")}, CCL ${fixed(inv.ccl_a, 1, "A")}, DCL ${fixed(inv.dcl_a, 1, "A")}`
      : "this image has no inverter output",
  );
}

function showCells(t: Line): void {
  const cells: number[] = Array.isArray(t.cell_voltages_v) ? t.cell_voltages_v : [];
  const box = $("cells");
  if (!cells.length) {
    box.replaceChildren();
    return;
  }
  const lo = Math.min(...cells);
  const hi = Math.max(...cells);
  // At least 50 mV of span, as the desktop monitor draws them: a healthy
  // pack's few millivolts do not look alarming.
  const floor = Math.min(lo, hi - 0.05);
  const span = Math.max(hi - floor, 0.05);
  text("cells-scale", `bars from ${floor.toFixed(3)} V to ${(floor + span).toFixed(3)} V`);
  const balancing = Number(t.real_balancing_bits ?? 0);
  const rows = cells.map((v, i) => {
    const row = document.createElement("div");
    row.className = "cell";
    row.dataset.index = String(i + 1);
    if (v === lo) row.classList.add("lowest");
    if (v === hi) row.classList.add("highest");
    const name = document.createElement("span");
    name.textContent = `${i + 1}${balancing & (1 << i) ? "*" : ""}`;
    const bar = document.createElement("span");
    bar.className = "bar";
    bar.style.width = `${Math.max(2, ((v - floor) / span) * 100)}%`;
    const value = document.createElement("span");
    value.className = "cell-value";
    value.textContent = `${v.toFixed(3)} V`;
    row.append(name, bar, value);
    return row;
  });
  box.replaceChildren(...rows);
}

/** The freshness pill, by the firmware's rule, every quarter second. */
function tick(): void {
  if (!session) return;
  const f = rules<{ state: string; text: string }>("freshness", {
    telemetry: session.telemetry ?? null,
    received_ago_ms: performance.now() - session.receivedAt,
  });
  const pill = $("state");
  const label: Record<string, string> = { fresh: "LIVE", offline: "OFFLINE", no_data: "NO DATA" };
  pill.textContent = label[f.state] ?? f.state.toUpperCase();
  pill.className = `pill ${f.state}`;
  text("age", f.text);
}

/** A table cell with this text. */
function cell(content: string, cls = ""): HTMLTableCellElement {
  const td = document.createElement("td");
  td.textContent = content;
  if (cls) td.className = cls;
  return td;
}

// ----------------------------------------------------------- configuration

/** The configuration's groups as `tinybms config` heads them. */
const CONFIG_GROUPS: Record<string, string> = {
  inverter: "Inverter (CAN)",
  charge: "Charge control: the limits the inverter is told",
  host: "Host link (USB)",
  network: "Network: Wi-Fi, MQTT, Home Assistant",
};

function showConfig(lines: Line[]): void {
  const body = $("config").querySelector("tbody")!;
  const fields = lines.filter((l) => l.type === "config");
  const rows: HTMLTableRowElement[] = [];
  let group = "";
  for (const f of fields) {
    if (f.group !== group) {
      // A heading row per group, as `tinybms config` prints them.
      group = f.group;
      const tr = document.createElement("tr");
      tr.className = "group";
      const th = document.createElement("th");
      th.colSpan = 5;
      th.textContent = CONFIG_GROUPS[group] ?? group;
      tr.append(th);
      rows.push(tr);
    }
    rows.push(fieldRow(f));
  }
  body.replaceChildren(...rows);
}

function fieldRow(f: Line): HTMLTableRowElement {
  const tr = document.createElement("tr");
  tr.dataset.field = f.name;
  const value = f.secret
    ? f.value
    : `${f.value}${f.unit && /^-?\d/.test(f.value) ? " " + f.unit : ""}${f.effective ? ` (${f.effective})` : ""}`;
  const input = document.createElement("input");
  input.name = f.name;
  input.type = f.secret ? "password" : "text";
  input.placeholder = f.secret ? "unchanged" : "";
  input.autocomplete = "off";
  const edit = document.createElement("td");
  edit.append(input);
  tr.append(
    cell(f.name, "name"),
    cell(value + (f.restart_pending ? " (restart pending)" : ""), "current"),
    edit,
    cell(f.range ?? ""),
    cell(f.applies === "now" ? "at once" : "at the next restart"),
  );
  tr.title = f.help ?? "";
  return tr;
}

/** An update file's bytes as base64 (the `update_chunk` data). */
function base64(bytes: Uint8Array): string {
  let s = "";
  for (const b of bytes) s += String.fromCharCode(b);
  return btoa(s);
}

/** The file's header, as the bridge reads it (docs/updates.md). */
function updateHeader(bytes: Uint8Array): { version: string; board: string; chip: string } | undefined {
  const text = (a: number, b: number) => new TextDecoder().decode(bytes.subarray(a, b)).replace(/\0.*$/s, "");
  if (bytes.length < 256 || text(0, 8) !== "TBMSUPD1") return undefined;
  return { chip: text(44, 60), board: text(60, 84), version: text(124, 148) };
}

/**
 * Sends the chosen update file in chunks of 128 bytes, each answered with the
 * offset the bridge wants next (`update_…`, the protocol's update commands),
 * as `tinybms update` does.
 */
async function sendUpdate(): Promise<void> {
  const s = session;
  if (!s) return;
  const file = ($("update-file") as HTMLInputElement).files?.[0];
  if (!file) {
    say("update-messages", ["choose an update file (.tbu) first"], "error");
    return;
  }
  const bytes = new Uint8Array(await file.arrayBuffer());
  const h = updateHeader(bytes);
  if (!h) {
    say("update-messages", [`${file.name} is not an update file (no TBMSUPD1 header)`], "error");
    return;
  }
  const progress = $("update-progress") as HTMLProgressElement;
  const ask = async (cmd: Record<string, unknown>): Promise<Line> => {
    for (let tries = 0; ; tries++) {
      try {
        const lines = await s.link.request(cmd, (l) => l.type === "update", 3000);
        const err = errorOf(lines);
        if (err) throw new Error(err);
        return lines[lines.length - 1];
      } catch (e) {
        if (tries >= 9) throw e;
      }
    }
  };
  const downgrade = ($("update-downgrade") as HTMLInputElement).checked;
  say("update-messages", [`sending ${h.chip} ${h.board} ${h.version} (${Math.round(bytes.length / 1024)} KiB)…`], "ok");
  progress.hidden = false;
  let a = await ask({ cmd: "update_begin", size: bytes.length, downgrade });
  for (;;) {
    if (a.state === "ended") throw new Error(`the bridge refused the update: ${a.detail}`);
    if (a.state !== "next" && a.state !== "busy") throw new Error(`the bridge answered ${a.state}`);
    const at = a.at as number;
    progress.value = at / bytes.length;
    if (at >= bytes.length) break;
    if (a.state === "busy") await new Promise((r) => window.setTimeout(r, 10));
    // Within the header, or within one 4 KiB sector of the image.
    const boundary = at < 256 ? 256 : 256 + (Math.floor((at - 256) / 4096) + 1) * 4096;
    const end = Math.min(at + 128, bytes.length, boundary);
    a = await ask({ cmd: "update_chunk", at, data: base64(bytes.subarray(at, end)) });
  }
  for (let i = 0; i < 300; i++) {
    const st = await ask({ cmd: "update_status" });
    if (st.phase === "installed") {
      say("update-messages", [
        `installed ${st.version}: the bridge restarts into it on trial; it confirms itself once BMS data and the inverter output run, else it goes back to ${s.hello.firmware} by itself`,
      ], "ok");
      return;
    }
    if (st.phase === "idle") throw new Error(`the bridge refused the update: ${st.detail ?? st.ended}`);
    await new Promise((r) => window.setTimeout(r, 100));
  }
  throw new Error("the bridge did not finish the update in 30 s");
}

async function fetchConfig(s: Session): Promise<void> {
  const lines = await s.link.request({ cmd: "get", what: "config" }, (l) => l.type === "config_end");
  const err = errorOf(lines);
  if (err) throw new Error(err);
  s.config = lines.filter((l) => l.type === "config");
  showConfig(s.config);
  $("config-section").hidden = false;
}

async function applyConfig(): Promise<void> {
  const s = session;
  if (!s) return;
  const changes: string[] = [];
  for (const input of $("config").querySelectorAll<HTMLInputElement>("input")) {
    if (input.value.trim() !== "") changes.push(`${input.name}=${input.value.trim()}`);
  }
  if (!changes.length) {
    say("config-messages", ["nothing to change: type a new value first"], "error");
    return;
  }
  const check = rules<{ ok: boolean; messages: string[]; wire: Record<string, string> }>("check_config", {
    changes,
    current: s.config,
  });
  if (!check.ok) {
    say("config-messages", check.messages, "error");
    return;
  }
  // The one-way change asks first, as `tinybms config` does.
  if (check.wire.read_only === "on") {
    const yes = window.confirm(
      "read_only=on makes the bridge refuse every write, its configuration too. The only ways " +
        "back: hold the board's BOOT button for 5 seconds while it runs, or erase its " +
        "configuration. Make the bridge read-only?",
    );
    if (!yes) {
      say("config-messages", ["nothing changed"], "ok");
      return;
    }
  }
  const lines = await s.link.request(
    { cmd: "set_config", fields: check.wire },
    (l) => l.type === "config_done",
    15000,
  );
  const err = errorOf(lines);
  const out: string[] = [];
  let failed = Boolean(err);
  if (err) out.push(err.startsWith("read_only") ? "the bridge is read-only: it refuses every write, its configuration too (hold BOOT for 5 s to allow changes)" : err);
  for (const l of lines.filter((l) => l.type === "config_outcome")) {
    switch (l.outcome) {
      case "applied":
        out.push(`${l.name} = ${l.value}: applied`);
        break;
      case "at_restart":
        out.push(`${l.name} = ${l.value}: stored, applies at the next restart`);
        break;
      case "unchanged":
        out.push(`${l.name} = ${l.value}: unchanged`);
        break;
      case "not_applied":
        out.push(`${l.name}: not applied (another field was refused)`);
        break;
      default:
        failed = true;
        out.push(`${l.name}: refused, ${l.error} (${l.detail ?? ""})${l.range ? "; it takes " + l.range : ""}`);
    }
  }
  const done = lines.find((l) => l.type === "config_done");
  if (done && done.saved === false) {
    failed = true;
    out.push(`NOT saved to flash: ${done.detail ?? "?"} (the change holds until the bridge restarts)`);
  } else if (done && !failed) {
    out.push("saved to the bridge's flash");
  }
  say("config-messages", out, failed ? "error" : "ok");
  for (const input of $("config").querySelectorAll<HTMLInputElement>("input")) input.value = "";
  await fetchConfig(s);
}

// ---------------------------------------------------------------- settings

function showSettings(lines: Line[]): void {
  const body = $("settings").querySelector("tbody")!;
  body.replaceChildren(
    ...lines.map((l) => {
      const tr = document.createElement("tr");
      tr.dataset.setting = l.name;
      const td = cell;
      const input = document.createElement("input");
      input.name = l.name;
      input.autocomplete = "off";
      const edit = document.createElement("td");
      edit.append(input);
      const unit = l.unit ? ` ${l.unit}` : "";
      const bms =
        l.bms_min !== null && l.bms_min !== undefined ? `; this BMS ${l.bms_min}..${l.bms_max}${unit}` : "";
      tr.append(
        td(l.name, "name"),
        td(`${l.value ?? l.raw}${unit}`, "current"),
        edit,
        td(l.min !== undefined && l.min !== null ? `allowed ${l.min}..${l.max}${unit}${bms}` : ""),
      );
      return tr;
    }),
  );
  $("settings-apply").hidden = lines.length === 0;
}

async function readSettings(quiet = false): Promise<void> {
  const s = session;
  if (!s) return;
  const lines = await s.link.request({ cmd: "get", what: "settings" }, (l) => l.type === "settings_end", 10000);
  const err = errorOf(lines);
  if (err) {
    say("settings-messages", [err.startsWith("not_ready") ? "the bridge has not read the BMS's settings yet: try again in a few seconds" : err], "error");
    return;
  }
  s.settings = lines.filter((l) => l.type === "setting");
  showSettings(s.settings);
  if (!quiet) say("settings-messages", [`${s.settings.length} settings read`], "ok");
}

async function applySettings(): Promise<void> {
  const s = session;
  if (!s) return;
  const changes: string[] = [];
  for (const input of $("settings").querySelectorAll<HTMLInputElement>("input")) {
    if (input.value.trim() !== "") changes.push(`${input.name}=${input.value.trim()}`);
  }
  const check = rules<{
    ok: boolean;
    messages: string[];
    values: Record<string, number>;
    chemistry: string | null;
  }>("check_settings", {
    changes,
    current: s.settings,
  });
  // As `tinybms set` says it: which chemistry the cell voltages are held to.
  const said = check.chemistry ? [check.chemistry] : [];
  if (!check.ok) {
    say("settings-messages", [...said, ...check.messages], "error");
    return;
  }
  const names = Object.keys(check.values);
  const seen = new Set<string>();
  const lines = await s.link.request(
    { cmd: "set", raw: check.values },
    (l) => {
      if (l.type === "outcome" && l.outcome !== "unconfirmed") seen.add(l.name);
      return names.every((n) => seen.has(n));
    },
    20000,
  );
  const err = errorOf(lines);
  const out: string[] = [...said, ...(err ? [err] : [])];
  let failed = Boolean(err);
  for (const l of lines.filter((l) => l.type === "outcome")) {
    const ok = l.outcome === "verified" || l.outcome === "unchanged";
    failed ||= !ok;
    out.push(`${l.name} = ${l.value}: ${l.outcome}${l.detail ? ` (${l.detail})` : ""}`);
  }
  say("settings-messages", out, failed ? "error" : "ok");
  for (const input of $("settings").querySelectorAll<HTMLInputElement>("input")) input.value = "";
  await readSettings(true);
}

// ------------------------------------------------------------------ session

function onLine(s: Session, l: Line): void {
  switch (l.type) {
    case "telemetry":
      s.telemetry = l;
      s.receivedAt = performance.now();
      showTelemetry(l);
      break;
    case "link": {
      const q = rules<{ text: string | null }>("link_quality", l);
      text("link-quality", q.text ?? "–");
      break;
    }
    case "event":
      prepend(
        $("events"),
        `${l.timestamp_s} s  ${l.name} (${l.severity})${l.history ? "" : " — new"}`,
        l.severity,
      );
      break;
    case "log":
      prepend($("log"), l.text, l.level);
      break;
    case "hello":
      s.hello = l;
      showIdentity(l);
      break;
  }
  // The newest lines, for the browser's developer tools.
  recent.push(l);
  if (recent.length > 100) recent.shift();
}

function showIdentity(h: Line, direct = session?.direct ?? false): void {
  if (direct) {
    text(
      "identity",
      "direct: a TinyBMS behind a USB-UART adapter, read by the bridge's own firmware running in this page " +
        `(firmware ${h.firmware}); no bridge configuration, no inverter output`,
    );
    return;
  }
  const parts = [
    `firmware ${h.firmware} (${h.build})`,
    `${h.board} (${h.chip})`,
    `built in: ${(h.features ?? []).join(", ") || "nothing listed"}`,
  ];
  if (h.wifi) parts.push(`Wi-Fi ${words(h.wifi.state)}${h.wifi.ip ? " " + h.wifi.ip : ""}`);
  if (h.mqtt) parts.push(`MQTT ${words(h.mqtt)}`);
  if (h.read_only) parts.push("read-only");
  if (h.rolled_back) parts.push(h.rolled_back);
  text("identity", parts.join(" · "));
}

async function connect(): Promise<void> {
  const error = $("connect-error");
  error.hidden = true;
  let port: SerialPort;
  try {
    port = await navigator.serial!.requestPort();
  } catch {
    return; // no port chosen
  }
  const link: Link = new HostLink(port);
  try {
    await link.open();
  } catch (e) {
    error.textContent = `cannot open the port: ${(e as Error).message} (another program using it? close it, or the desktop tool)`;
    error.hidden = false;
    return;
  }
  let hello: Line | undefined;
  let direct = false;
  let active: Link = link;
  try {
    hello = (await link.request({ cmd: "hello" }, (l) => l.type === "hello", 3000))[0];
  } catch {
    // No bridge: perhaps a TinyBMS behind a USB-UART adapter. The firmware's
    // station runs in the page then (direct mode), if the BMS answers it.
    await link.close();
    const d = new DirectLink(port, rules);
    const seen: Line[] = [];
    d.onLine = (l) => seen.push(l);
    try {
      await d.open();
      await until(() => seen.some((l) => l.type === "telemetry" && l.online === true), 8000);
      hello = seen.find((l) => l.type === "hello");
      direct = true;
      active = d;
    } catch {
      await d.close();
    }
  }
  if (!hello) {
    error.textContent =
      "nothing answered on this port: neither a bridge (no hello) nor a TinyBMS. An ESP32 board not " +
      "running this firmware yet (install it from the Install page), one still starting, or a " +
      "USB-UART adapter whose wires to the BMS are crossed or loose (TX to RX, RX to TX, GND).";
    error.hidden = false;
    return;
  }
  const about = rules<{ protocol: number }>("about");
  if (hello.protocol !== about.protocol) {
    error.textContent = `this bridge speaks host-link protocol ${hello.protocol}; this console speaks ${about.protocol}: update the one that is older`;
    error.hidden = false;
  }
  const s: Session = { link: active, direct, hello, receivedAt: performance.now(), config: [], settings: [] };
  session = s;
  active.onLine = (l) => onLine(s, l);
  active.onClose = (why) => {
    if (session === s) {
      session = undefined;
      disconnected(why);
    }
  };
  showIdentity(hello, direct);
  for (const id of ["live", "events-section", "log-section", "settings-section"]) $(id).hidden = false;
  $("connect").hidden = true;
  $("disconnect").hidden = false;
  timer = window.setInterval(tick, 250);
  tick();
  if (!direct) {
    $("update-section").hidden = false;
    try {
      await fetchConfig(s);
    } catch (e) {
      say("config-messages", [`the configuration: ${(e as Error).message}`], "error");
    }
  }
  await active.request({ cmd: "get", what: "link" }, (l) => l.type === "link").catch(() => []);
  await active.request({ cmd: "get", what: "events" }, (l) => l.type === "events_end", 8000).catch(() => []);
}

function disconnected(why: string): void {
  if (timer !== undefined) window.clearInterval(timer);
  timer = undefined;
  const pill = $("state");
  pill.textContent = "NOT CONNECTED";
  pill.className = "pill none";
  text("age", why);
  $("connect").hidden = false;
  $("disconnect").hidden = true;
}

async function disconnect(): Promise<void> {
  const s = session;
  session = undefined;
  if (s) await s.link.close();
  disconnected("disconnected");
}

async function main(): Promise<void> {
  if (!navigator.serial) {
    $("no-serial").hidden = false;
    $<HTMLButtonElement>("connect").disabled = true;
  }
  await loadRules();
  $("connect").addEventListener("click", () => void connect());
  $("disconnect").addEventListener("click", () => void disconnect());
  $("config-apply").addEventListener("click", () => void applyConfig().catch((e) => say("config-messages", [String(e.message ?? e)], "error")));
  $("update-send").addEventListener("click", () => void sendUpdate().catch((e) => say("update-messages", [String(e.message ?? e)], "error")));
  $("settings-read").addEventListener("click", () => void readSettings(false).catch((e) => say("settings-messages", [String(e.message ?? e)], "error")));
  $("settings-apply").addEventListener("click", () => void applySettings().catch((e) => say("settings-messages", [String(e.message ?? e)], "error")));
  document.body.dataset.ready = "true";
}

void main();
