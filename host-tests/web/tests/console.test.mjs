// The console in Chromium against `sim --bridge-pty` (the firmware's own
// station and a simulated TinyBMS), through `serial-ws` standing in for the
// browser's serial port. What an owner sees must be what the bridge sent;
// what an owner types is refused as `tinybms` refuses it.
import assert from "node:assert/strict";
import { mkdtempSync, readFileSync, writeFileSync } from "node:fs";
import { tmpdir } from "node:os";
import { join } from "node:path";
import { after, before, test } from "node:test";

import { adapter, bridge, browser, pageFor, receivedLines, repoint, serveSite, shotPath, tinybms, until } from "./harness.mjs";

let site;
let chromium;

before(async () => {
  site = await serveSite();
  chromium = await browser();
});

after(async () => {
  await chromium?.close();
  await site?.close();
});

async function connect(page) {
  await page.goto(site.url + "console.html");
  await page.waitForSelector("body[data-ready=true]", { timeout: 15000 });
  await page.click("#connect");
  await until("LIVE", async () => (await page.textContent("#state")) === "LIVE", 30000);
}

/** The newest telemetry line the page got whose values are on screen. */
async function shownTelemetry(page) {
  const lines = (await receivedLines(page)).filter((l) => l.type === "telemetry");
  return lines.at(-1);
}

const fix = (v, d, unit) => `${v.toFixed(d)} ${unit}`;

test("live values are the ones the bridge sent, and a configuration change survives a restart", async () => {
  const dir = mkdtempSync(join(tmpdir(), "tinybms-console-"));
  const flash = join(dir, "flash.bin");
  let b = await bridge(["--flash", flash]);
  const { page, context, errors } = await pageFor(chromium, b);
  try {
    await connect(page);
    assert.match(await page.textContent("#identity"), /firmware .* \(dev|firmware /);
    // The values on screen equal the latest telemetry line, digit for digit.
    await until("cells drawn", async () => (await page.$$("#cells .cell")).length === 16);
    const check = async () => {
      const t = await shownTelemetry(page);
      const [v, a, soc, min, max, cells] = await Promise.all([
        page.textContent("#pack-voltage"),
        page.textContent("#pack-current"),
        page.textContent("#soc"),
        page.textContent("#cell-min"),
        page.textContent("#cell-max"),
        page.$$eval("#cells .cell-value", (e) => e.map((x) => x.textContent)),
      ]);
      const latest = await shownTelemetry(page);
      if (latest.seq !== t.seq) return false; // a new line came meanwhile: again
      assert.equal(v, fix(t.pack_voltage_v, 2, "V"));
      assert.equal(a, fix(t.pack_current_a, 2, "A"));
      assert.equal(soc, fix(t.soc_percent, 1, "%"));
      assert.equal(min, fix(t.min_cell_voltage_v, 3, "V"));
      assert.equal(max, fix(t.max_cell_voltage_v, 3, "V"));
      assert.deepEqual(
        cells,
        t.cell_voltages_v.map((c) => fix(c, 3, "V")),
      );
      return true;
    };
    await until("values equal to the telemetry", check, 10000, 50);
    assert.match(await page.textContent("#temp-ext2"), /not connected|°C/);
    assert.match(await page.textContent("#inverter"), /CVL .* V, CCL .* A, DCL .* A/);
    await until("link quality", async () => /% ok/.test(await page.textContent("#link-quality")));
    await page.screenshot({ path: shotPath("console-live.png"), fullPage: false });

    // A configuration change, applied and saved...
    await page.fill('#config tr[data-field="charge_current_cap"] input', "42A");
    await page.click("#config-apply");
    await until("applied", async () => /saved to the bridge's flash/.test(await page.textContent("#config-messages")));
    assert.match(await page.textContent("#config-messages"), /charge_current_cap = 42(\.0)? A: applied/);
    // Issue 42, item 12: the fields by group, not one flat form.
    const groups = await page.locator("#config tbody th").allTextContents();
    for (const g of ["Inverter (CAN)", "Charge control", "Host link (USB)", "Network"]) {
      assert.ok(
        groups.some((t) => t.startsWith(g)),
        `${g}: ${groups.join(" | ")}`,
      );
    }
    await page.locator("#config-section").screenshot({ path: shotPath("console-config.png") });
    // ...survives a restart of the bridge (the same flash file).
    await page.click("#disconnect");
    await b.stop();
    b = await bridge(["--flash", flash]);
    await repoint(page, b);
    await page.click("#connect");
    await until("LIVE again", async () => (await page.textContent("#state")) === "LIVE", 30000);
    await until("the stored cap", async () =>
      /^42(\.0)? A/.test((await page.textContent('#config tr[data-field="charge_current_cap"] td.current')) ?? ""),
    );
    assert.deepEqual(errors, []);
  } finally {
    await context.close();
    await b.stop();
  }
});

test("a value the firmware refuses is refused before anything is sent, with the tool's own words", async () => {
  const b = await bridge();
  const other = await bridge();
  const { page, context } = await pageFor(chromium, b);
  try {
    await connect(page);
    // What the desktop tool says to the same change (its dry run, on a bridge of its own).
    const tool = await tinybms(["config", other.pty, "charge_current_cap=0", "--dry-run"]);
    assert.notEqual(tool.code, 0, tool.out);
    const before = (await receivedLines(page)).filter((l) => l.type === "config_outcome").length;
    await page.fill('#config tr[data-field="charge_current_cap"] input', "0");
    await page.click("#config-apply");
    const said = await until("refused", async () => {
      const t = (await page.textContent("#config-messages")).trim();
      return t.length ? t : false;
    });
    assert.ok(tool.out.includes(said), `the console says:\n${said}\nthe tool says:\n${tool.out}`);
    assert.match(said, /charge_current_cap = 0: /);
    // Nothing went to the bridge.
    await new Promise((r) => setTimeout(r, 500));
    const outcomes = (await receivedLines(page)).filter((l) => l.type === "config_outcome").length;
    assert.equal(outcomes, before);

    // A BMS setting that contradicts another: the tool's words, nothing written.
    await page.click("#settings-read");
    await until("settings", async () => (await page.$$("#settings tbody tr")).length > 20, 30000);
    const tool2 = await tinybms(["set", other.pty, "over_voltage_cutoff=2.4V", "--dry-run"]);
    assert.notEqual(tool2.code, 0, tool2.out);
    await page.fill('#settings tr[data-setting="over_voltage_cutoff"] input', "2.4V");
    await page.click("#settings-apply");
    const said2 = await until("refused", async () => {
      const t = (await page.innerText("#settings-messages")).trim();
      return /refused/.test(t) ? t : false;
    });
    for (const line of said2.split("\n").map((l) => l.trim()).filter(Boolean)) {
      assert.ok(tool2.out.includes(line), `console: ${line}\ntool: ${tool2.out}`);
    }
    // A value plainly wrong for the pack's chemistry (4.2 V on LiFePO4): the
    // tool's words again, the chemistry said first.
    await page.fill('#settings tr[data-setting="over_voltage_cutoff"] input', "");
    const tool3 = await tinybms([
      "set",
      other.pty,
      "over_voltage_cutoff=4.25V",
      "fully_charged_voltage=4.2V",
      "--dry-run",
    ]);
    assert.notEqual(tool3.code, 0, tool3.out);
    await page.fill('#settings tr[data-setting="over_voltage_cutoff"] input', "4.25V");
    await page.fill('#settings tr[data-setting="fully_charged_voltage"] input', "4.2V");
    await page.click("#settings-apply");
    const said3 = await until("refused for the chemistry", async () => {
      const t = (await page.innerText("#settings-messages")).trim();
      return /plainly wrong for a LiFePO4 pack/.test(t) ? t : false;
    });
    for (const line of said3.split("\n").map((l) => l.trim()).filter(Boolean)) {
      assert.ok(tool3.out.includes(line), `console: ${line}\ntool: ${tool3.out}`);
    }
    assert.match(said3, /^chemistry: LiFePO4/);
    // A good change is written and read back (the refused ones taken back).
    await page.fill('#settings tr[data-setting="over_voltage_cutoff"] input', "");
    await page.fill('#settings tr[data-setting="fully_charged_voltage"] input', "");
    await page.fill('#settings tr[data-setting="charger_startup_delay"] input', "25");
    await page.click("#settings-apply");
    let seen = "";
    await until(
      "verified",
      async () => /charger_startup_delay = 25(\.0)?: verified/.test((seen = await page.textContent("#settings-messages"))),
      30000,
    ).catch((e) => assert.fail(`${e.message}: ${seen}`));
    await page.locator("#settings-section").screenshot({ path: shotPath("console-settings.png") });
  } finally {
    await context.close();
    await b.stop();
    await other.stop();
  }
});

test("a BMS that falls silent is OFFLINE within 10 s; a bridge that freezes is NO DATA within 7 s", async () => {
  // The BMS stops answering 12 s after the start; the bridge reports it offline.
  const b = await bridge(["--bms-silent", "12s+60s"]);
  const { page, context } = await pageFor(chromium, b);
  try {
    await connect(page);
    // The simulated BMS falls silent 12 s after the bridge started.
    const silent = b.startedAt + 12000;
    await until("the silence", async () => Date.now() >= silent, 30000, 100);
    assert.equal(await page.textContent("#state"), "LIVE", "live up to the silence");
    const shown = await until(
      "OFFLINE",
      async () => (await page.textContent("#state")) === "OFFLINE" && Date.now(),
      15000,
      100,
    );
    const after = (shown - silent) / 1000;
    assert.ok(after <= 10, `OFFLINE ${after.toFixed(1)} s after the BMS fell silent`);
    console.log(`OFFLINE ${after.toFixed(1)} s after the BMS fell silent`);
    await page.locator("#connection").screenshot({ path: shotPath("console-offline.png") });
  } finally {
    await context.close();
    await b.stop();
  }
  const f = await bridge(["--freeze", "12s+40s"]);
  const p2 = await pageFor(chromium, f);
  try {
    await connect(p2.page);
    // The last line before the freeze, then NO DATA at the freshness limit.
    let last = Date.now();
    let count = 0;
    await until("the bridge froze", async () => {
      const n = (await receivedLines(p2.page)).length;
      if (n !== count) {
        count = n;
        last = Date.now();
      }
      return Date.now() - last > 1500;
    }, 40000, 100);
    const shown = await until("NO DATA", async () => (await p2.page.textContent("#state")) === "NO DATA" && Date.now(), 10000, 100);
    const after = (shown - last) / 1000;
    assert.ok(after <= 7, `NO DATA ${after.toFixed(1)} s after the last line`);
    console.log(`NO DATA ${after.toFixed(1)} s after the bridge's last line`);
    assert.match(await p2.page.textContent("#age"), /NO DATA: nothing new from the port/);
  } finally {
    await p2.context.close();
    await f.stop();
  }
});

test("a TinyBMS behind a USB-UART adapter: the firmware's station runs in the page (direct mode)", async () => {
  const a = await adapter();
  const { page, context, errors } = await pageFor(chromium, a);
  try {
    await connect(page);
    assert.match(await page.textContent("#identity"), /^direct: a TinyBMS behind a USB-UART adapter/);
    // The values on screen are the station's telemetry, made in the page from
    // the BMS's own replies.
    await until("cells", async () => (await page.$$("#cells .cell")).length === 16);
    await until(
      "values equal to the station's telemetry",
      async () => {
        const t = await page.evaluate(() => window.tinybms.recent.filter((l) => l.type === "telemetry").at(-1));
        const [v, cells] = await Promise.all([
          page.textContent("#pack-voltage"),
          page.$$eval("#cells .cell-value", (e) => e.map((x) => x.textContent)),
        ]);
        const again = await page.evaluate(() => window.tinybms.recent.filter((l) => l.type === "telemetry").at(-1));
        if (again.seq !== t.seq) return false;
        assert.equal(v, fix(t.pack_voltage_v, 2, "V"));
        assert.deepEqual(cells, t.cell_voltages_v.map((c) => fix(c, 3, "V")));
        return true;
      },
      10000,
      50,
    );
    // What went over the wire is the TinyBMS protocol, not the host link.
    const raw = Buffer.from(await page.evaluate(() => window.__fakeSerial.received));
    assert.ok(raw.includes(0xaa), "replies of the BMS (0xAA)");
    assert.ok(!raw.toString("latin1").includes('"type":"hello"'), "no bridge on the wire");
    // The BMS's settings, through the station in the page.
    assert.equal(await page.isHidden("#config-section"), true, "no bridge configuration in direct mode");
    await page.click("#settings-read");
    await until("settings", async () => (await page.$$("#settings tbody tr")).length > 20, 30000);
    await page.screenshot({ path: shotPath("console-direct.png") });
    assert.deepEqual(errors, []);
  } finally {
    await context.close();
    await a.stop();
  }
});

/** An app image as the bridge checks its start (ESP32-C3, version `v`), naming
 * its features in its bytes as a real image does (what `sign` reads). */
function appImage(len, v) {
  const b = Buffer.alloc(len);
  for (let i = 0; i < len; i++) b[i] = (i * 13 + (i >> 8)) & 0xff;
  b[0] = 0xe9;
  b.writeUInt16LE(5, 12);
  b.writeUInt32LE(0xabcd5432, 32);
  b.fill(0, 48, 112);
  b.write(v, 48, "latin1");
  b.write("tinybms-firmware", 80, "latin1");
  b.write("tinybms-features=can,host-link,wifi,store\0", 5000, "latin1");
  return b;
}

test("a firmware update from the page: refused with the bridge's reason, then sent and installed", async () => {
  const dir = mkdtempSync(join(tmpdir(), "tinybms-update-"));
  const key = join(dir, "k");
  const stranger = join(dir, "s");
  for (const k of [key, stranger]) assert.equal((await tinybms(["keygen", k])).code, 0);
  // The .pub file: `#` lines saying what it is, then the key's 64 hex digits.
  const pub = readFileSync(`${key}.pub`, "utf8").split("\n").find((l) => /^[0-9a-f]{64}$/.test(l.trim())).trim();
  const app = join(dir, "app.bin");
  writeFileSync(app, appImage(12000, "0.9.0"));
  const sign = async (k, out) => {
    const r = await tinybms(["sign", "--key", k, "--chip", "esp32c3", "--board", "c3-supermini", "--version", "0.9.0", app, "-o", out]);
    assert.equal(r.code, 0, r.out);
  };
  await sign(key, join(dir, "good.tbu"));
  await sign(stranger, join(dir, "stranger.tbu"));
  const b = await bridge(["--board", "c3-supermini", "--config", `update_key=${pub}`]);
  const { page, context, errors } = await pageFor(chromium, b);
  try {
    await connect(page);
    assert.equal(await page.isHidden("#update-section"), false);
    await page.setInputFiles("#update-file", join(dir, "stranger.tbu"));
    await page.click("#update-send");
    await until("refused", async () => /not from a key this bridge trusts/.test(await page.textContent("#update-messages")), 30000);
    await page.setInputFiles("#update-file", join(dir, "good.tbu"));
    await page.click("#update-send");
    await until("installed", async () => /installed 0\.9\.0: the bridge restarts into it on trial/.test(await page.textContent("#update-messages")), 120000);
    await page.screenshot({ path: shotPath("console-update.png") });
    assert.deepEqual(errors, []);
  } finally {
    await context.close();
    await b.stop();
  }
});
