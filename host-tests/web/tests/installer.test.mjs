// The installer page in Chromium: every board of the firmware's table, the
// manifests firmware/make-images.sh wrote (checked by check-images.py as
// served), and ESP Web Tools' Improv Wi-Fi against the firmware's own
// station (`sim --bridge-pty`, simulated networks).
import assert from "node:assert/strict";
import { spawnSync } from "node:child_process";
import { mkdtempSync, readFileSync, rmSync, statSync } from "node:fs";
import { tmpdir } from "node:os";
import { join } from "node:path";
import { after, before, test } from "node:test";

import { bridge, browser, dist, pageFor, root, serveSite, shotPath, until } from "./harness.mjs";

let site;
let chromium;
let index;

before(async () => {
  site = await serveSite();
  chromium = await browser();
  index = JSON.parse(readFileSync(join(dist, "firmware/index.json"), "utf8"));
});

after(async () => {
  await chromium?.close();
  await site?.close();
});

/** Board names of firmware/src/boards.rs, read from the table itself. */
function firmwareBoards() {
  const src = readFileSync(join(root, "firmware/src/boards.rs"), "utf8");
  return [...src.matchAll(/^\s*name: "([^"]+)",\s*\n\s*feature: "board-([a-z0-9-]+)"/gm)].map((m) => ({
    name: m[1],
    board: m[2],
  }));
}

test("every board is offered, and every manifest names the files make-images.sh made, at the offsets check-images.py checks", async () => {
  assert.ok(index.length > 0, "no images in the site: run firmware/make-images.sh before node build.mjs");
  // The served folder passes the same checks as the images themselves.
  const check = spawnSync("python3", [join(root, "firmware/check-images.py"), join(dist, "firmware")], {
    encoding: "utf8",
    timeout: 300000,
  });
  assert.equal(check.status, 0, check.stdout + check.stderr);
  const images = join(root, "firmware/target/images");
  const context = await chromium.newContext({ viewport: { width: 1100, height: 1400 } });
  const page = await context.newPage();
  const errors = [];
  page.on("pageerror", (e) => errors.push(e.message));
  try {
    await page.goto(site.url);
    await page.waitForSelector("body[data-ready=true]", { timeout: 15000 });
    const boards = firmwareBoards();
    assert.ok(boards.length >= 7, JSON.stringify(boards));
    for (const b of boards) {
      const radio = page.locator(`input[name=board][value="${b.board}"]`);
      assert.equal(await radio.count(), 1, b.board);
      assert.equal(await radio.isEnabled(), true, `${b.board} has images`);
    }
    for (const entry of index) {
      // The manifest as the browser fetches it.
      const m = await page.evaluate(async (p) => (await fetch(`firmware/${p}`)).json(), entry.manifest);
      assert.equal(m.name, "TinyBMS bridge");
      const parts = m.builds[0].parts;
      assert.deepEqual(
        parts.map((p) => p.offset),
        [0, 0x10000, 0x20000],
        entry.manifest,
      );
      for (const p of parts) {
        const size = await page.evaluate(async (f) => (await (await fetch(`firmware/${f}`)).arrayBuffer()).byteLength, p.path);
        assert.equal(size, statSync(join(images, p.path)).size, p.path);
      }
    }
    // Issue 42, item 2: the page ticked "With Wi-Fi" by default (the README's
    // default build has none), and both images of a board had one version, so
    // ESP Web Tools offered no update from one to the other.
    assert.equal(await page.isChecked("#wifi"), false, "With Wi-Fi is unticked at first");
    const versions = {};
    for (const entry of index) {
      const m = await page.evaluate(async (p) => (await fetch(`firmware/${p}`)).json(), entry.manifest);
      versions[entry.manifest] = m.version;
    }
    for (const [manifest, version] of Object.entries(versions)) {
      if (!manifest.endsWith("-wifi.json")) {
        assert.doesNotMatch(version, /\+wifi$/, manifest);
        const other = versions[manifest.replace(/\.json$/, "-wifi.json")];
        assert.equal(other, `${version}+wifi`, `${manifest}: the Wi-Fi image's version`);
      }
    }
    // Item 12: the downloads by board, one line each, its parts named.
    const downloads = await page.locator("#files li").allTextContents();
    assert.equal(downloads.length, boards.length, downloads.join("\n"));
    for (const line of downloads) {
      for (const part of [/without Wi-Fi merged/, /with Wi-Fi merged/, /boot \(0x0\)/, /otadata \(0x10000\)/, /app \(0x20000\)/, /update file/]) {
        assert.match(line, part, line);
      }
    }
    // Choosing a board points the install button at its manifest.
    await page.check('input[name=board][value="c3-supermini"]');
    await page.check("#wifi");
    assert.equal(await page.getAttribute("#install", "manifest"), "firmware/manifest-c3-supermini-wifi.json");
    await page.uncheck("#wifi");
    assert.equal(await page.getAttribute("#install", "manifest"), "firmware/manifest-c3-supermini.json");
    assert.match(await page.textContent("#chosen"), /ESP32-C3 SuperMini \(ESP32-C3\), without Wi-Fi/);
    await page.screenshot({ path: shotPath("installer.png"), fullPage: true });
    assert.deepEqual(errors, []);
  } finally {
    await context.close();
  }
});

test("a build without the WebAssembly says how to make it (a plain cargo build makes none)", () => {
  const out = mkdtempSync(join(tmpdir(), "tinybms-site-"));
  try {
    const r = spawnSync(
      process.execPath,
      [join(root, "host-tests/web/build.mjs"), "--wasm", join(out, "missing.wasm"), "--out", join(out, "dist")],
      { encoding: "utf8", timeout: 120000 },
    );
    assert.equal(r.status, 1, r.stdout + r.stderr);
    assert.match(r.stderr, /cargo rustc -p tinybms-web --release --target wasm32-unknown-unknown --crate-type cdylib/);
    assert.match(r.stderr, /a plain `cargo build -p tinybms-web` makes no \.wasm/);
  } finally {
    rmSync(out, { recursive: true, force: true });
  }
});

test("a page built without images says so, offers nothing to install and no dead checksum link", async () => {
  const context = await chromium.newContext({ viewport: { width: 1100, height: 1400 } });
  const page = await context.newPage();
  const errors = [];
  page.on("pageerror", (e) => errors.push(e.message));
  try {
    // The site as build.mjs makes it without images: an empty index.
    await page.route("**/firmware/index.json", (r) =>
      r.fulfill({ status: 200, contentType: "application/json", body: "[]" }),
    );
    await page.goto(site.url);
    await page.waitForSelector("body[data-ready=true]", { timeout: 15000 });
    assert.equal(await page.isVisible("#no-images"), true);
    assert.equal(await page.isDisabled("#install-button"), true);
    assert.equal(await page.isVisible("#downloads"), false);
    assert.deepEqual(errors, []);
  } finally {
    await context.close();
  }
});

/**
 * The installer page from `url`, the SuperMini chosen (with Wi-Fi or not),
 * the board's configuration partition marked when `nvs`, Install pressed.
 */
async function pressInstall(page, { url = site.url, wifi = true, nvs = false } = {}) {
  await page.goto(url);
  await page.waitForSelector("body[data-ready=true]", { timeout: 15000 });
  if (nvs) await markNvs(page);
  await page.check('input[name=board][value="c3-supermini"]');
  await (wifi ? page.check("#wifi") : page.uncheck("#wifi"));
  await page.click("#install-button");
}

/** ESP Web Tools' dialog for the chosen board, connected to the bridge. */
async function openDialog(page) {
  await pressInstall(page);
  await until("Improv answered", async () => (await page.getByText("Connected to").count()) > 0, 20000);
}

/** Confirms the install in the dialog and waits for its end. */
async function confirmAndWait(page) {
  await page.locator("ew-text-button", { hasText: "Install" }).last().click();
  await until(
    "installed",
    async () => (await page.locator('ewt-page-message[label="Installation complete!"]').count()) > 0,
    180000,
    500,
  );
  return page.evaluate(() => {
    const { erased, stub, writes, resets } = window.__fakeSerial.rom;
    return { erased, stub, writes, resets };
  });
}

test("Improv Wi-Fi through ESP Web Tools: a wrong passphrase is refused, the right one joins, the passphrase never comes back", async () => {
  const b = await bridge(["--wifi-network", "HomeNet:correct-horse-9:-48", "--wifi-network", "Cafe::-70"]);
  const { page, context, errors } = await pageFor(chromium, b, { width: 900, height: 900 });
  try {
    await openDialog(page);
    // Who the bridge said it is.
    assert.ok((await page.getByText(/TinyBMS bridge/).count()) > 0, "the bridge said who it is");
    await page.getByText("Connect to Wi-Fi", { exact: true }).click();
    // The scan: the networks in range, in the dialog's list.
    await until("networks", async () => (await page.locator("ew-select-option", { hasText: "HomeNet" }).count()) > 0, 20000);
    assert.ok((await page.locator("ew-select-option", { hasText: "Cafe" }).count()) > 0);
    const provision = async (ssid, pass) => {
      // The strongest network is chosen in the list; else the name is typed.
      const typed = page.locator("ew-filled-text-field[name=ssid] input");
      if (await typed.count()) await typed.fill(ssid);
      else assert.equal(await page.locator("ew-filled-select").evaluate((e) => e.value), ssid);
      await page.locator("ew-filled-text-field[name=password] input").fill(pass);
      await page.locator("ew-text-button", { hasText: "Connect" }).last().click();
    };
    await provision("HomeNet", "wrong-horse-1");
    await until("refused", async () => (await page.getByText("Unable to connect").count()) > 0, 40000);
    await page.screenshot({ path: shotPath("improv-refused.png") });
    await provision("HomeNet", "correct-horse-9");
    await until("joined", async () => (await page.locator('ewt-page-message[label="Device connected to the network!"]').count()) > 0, 40000);
    await page.screenshot({ path: shotPath("improv-joined.png") });
    const bytes = Buffer.from(await page.evaluate(() => window.__fakeSerial.received)).toString("latin1");
    assert.match(bytes, /Improv Wi-Fi: joined HomeNet, IP 192\.0\.2\.10; network stored/);
    assert.match(bytes, /Improv Wi-Fi: cannot join HomeNet: the passphrase was not accepted/);
    assert.ok(!bytes.includes("correct-horse-9") && !bytes.includes("wrong-horse-1"), "a passphrase came back");
    assert.deepEqual(errors, []);
  } finally {
    await context.close();
    await b.stop();
  }
});

test("a malformed Improv packet is refused and the port goes on as a host link", async () => {
  const b = await bridge();
  const { page, context } = await pageFor(chromium, b);
  try {
    await page.goto(site.url);
    await page.waitForSelector("body[data-ready=true]", { timeout: 15000 });
    const answer = await page.evaluate(async () => {
      const port = await navigator.serial.requestPort();
      await port.open({ baudRate: 115200 });
      const w = port.writable.getWriter();
      // "Request current state" with a checksum off by one, then a hello.
      const bad = [..."IMPROV"].map((c) => c.charCodeAt(0)).concat([1, 3, 2, 2, 0]);
      bad.push((bad.reduce((a, b) => a + b, 0) + 1) & 0xff, 10);
      await w.write(new Uint8Array(bad));
      await w.write(new TextEncoder().encode('{"cmd":"hello"}\n'));
      const r = port.readable.getReader();
      let got = [];
      const end = Date.now() + 8000;
      while (Date.now() < end) {
        const { value } = await Promise.race([
          r.read(),
          new Promise((res) => setTimeout(() => res({ value: undefined }), 500)),
        ]);
        if (value) got = got.concat([...value]);
        const text = String.fromCharCode(...got);
        if (text.includes('"type":"hello"') && text.includes("IMPROV")) break;
      }
      r.releaseLock();
      w.releaseLock();
      await port.close();
      return got;
    });
    const text = Buffer.from(answer).toString("latin1");
    const at = text.indexOf("IMPROV");
    assert.ok(at >= 0, text);
    const packet = Buffer.from(answer.slice(at, at + 11));
    assert.equal(packet[7], 0x02, "an error state packet");
    assert.equal(packet[9], 0x01, "invalid RPC packet");
    assert.match(text, /"type":"hello"/);
  } finally {
    await context.close();
    await b.stop();
  }
});

/** What the board's flash holds, from `offset`, `length` bytes. */
async function flashAt(page, offset, length) {
  return Buffer.from(
    await page.evaluate(([o, n]) => [...window.__fakeSerial.rom.flash.subarray(o, o + n)], [offset, length]),
  );
}

/** The configuration the bridge kept: the nvs partition, marked. */
async function markNvs(page) {
  await page.evaluate(() => {
    const f = new Uint8Array(4 * 1024 * 1024).fill(0xff);
    f.fill(0xa5, 0x9000, 0xf000);
    window.__fakeSerial.rom.flash = f;
  });
}

function part(name) {
  return readFileSync(join(dist, "firmware", name));
}

test("a first install: ESP Web Tools erases the board, writes each part where the manifest says, and the bridge it boots answers Improv", async () => {
  const b = await bridge(["--wifi-network", "HomeNet:correct-horse-9:-48"]);
  const { page, context, errors } = await pageFor(chromium, b, { width: 900, height: 900 }, { mode: "rom" });
  try {
    await pressInstall(page, { nvs: true });
    // A board in download mode does not answer Improv: a new install.
    await until("new install", async () => (await page.getByText("Install TinyBMS bridge").count()) > 0, 30000);
    await page.getByText("Install TinyBMS bridge").click();
    await until("confirm", async () => (await page.getByText("All data on the device will be erased").count()) > 0);
    const rom = await confirmAndWait(page);
    assert.equal(rom.stub, true, "esptool-js ran its flasher stub");
    assert.equal(rom.erased, true, "a first install erases");
    const boot = part("tinybms-c3-supermini-wifi-boot.bin");
    const app = part("tinybms-c3-supermini-wifi-app.bin");
    assert.deepEqual(
      rom.writes.map((w) => w.offset),
      [0, 0x10000, 0x20000],
    );
    assert.ok((await flashAt(page, 0, boot.length)).equals(boot), "the bootloader and partition table at 0x0");
    assert.ok((await flashAt(page, 0x10000, 0x2000)).every((x) => x === 0xff), "otadata erased: the bootloader boots ota_0");
    assert.ok((await flashAt(page, 0x20000, app.length)).equals(app), "the firmware in ota_0 at 0x20000");
    assert.ok((await flashAt(page, 0x9000, 0x6000)).every((x) => x === 0xff), "the old configuration is gone");
    // The board resets into the firmware it was given; the installer finds it
    // over Improv and asks for the network.
    assert.deepEqual(rom.resets.at(-1), "firmware");
    await page.getByText("Next").click();
    await until("the Wi-Fi form", async () => (await page.getByText("Connect your device to the network").count()) > 0, 30000);
    await page.screenshot({ path: shotPath("install-done.png") });
    assert.deepEqual(errors, []);
  } finally {
    await context.close();
    await b.stop();
  }
});

test("an update writes the new firmware and leaves the stored configuration alone", async () => {
  const newer = await serveSite({ manifestVersion: "9.9.9" });
  const b = await bridge();
  const { page, context, errors } = await pageFor(chromium, b, { width: 900, height: 900 });
  try {
    await pressInstall(page, { url: newer.url, wifi: false, nvs: true });
    await until("recognised", async () => (await page.getByText("Update TinyBMS bridge").count()) > 0, 30000);
    await page.screenshot({ path: shotPath("install-update.png") });
    await page.getByText("Update TinyBMS bridge").click();
    await until("confirm", async () => (await page.getByText("update to").count()) > 0);
    assert.equal(await page.getByText("All data on the device will be erased").count(), 0);
    const rom = await confirmAndWait(page);
    assert.equal(rom.erased, false, "an update erases nothing");
    assert.deepEqual(rom.resets.slice(0, 1), ["rom"], "esptool-js reset the board into its download mode");
    const boot = part("tinybms-c3-supermini-boot.bin");
    const app = part("tinybms-c3-supermini-app.bin");
    assert.ok((await flashAt(page, 0, boot.length)).equals(boot));
    assert.ok((await flashAt(page, 0x10000, 0x2000)).every((x) => x === 0xff), "otadata erased");
    assert.ok((await flashAt(page, 0x20000, app.length)).equals(app));
    assert.ok((await flashAt(page, 0x9000, 0x6000)).every((x) => x === 0xa5), "the configuration is kept");
    assert.deepEqual(errors, []);
  } finally {
    await context.close();
    await b.stop();
    await newer.close();
  }
});
