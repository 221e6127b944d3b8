// Builds the site into dist/: the installer page and the console bundled by
// esbuild (ESP Web Tools and its esptool-js and Improv SDK from
// node_modules, locked by package-lock.json: no script from a CDN), the
// firmware's rules compiled to WebAssembly, and the ready-made images with
// the manifests firmware/make-images.sh wrote beside them.
//
//   node build.mjs [--images DIR] [--wasm FILE] [--require-images] [--out DIR]
//
// DIR defaults to ../../firmware/target/images, FILE to the release build of
// host-tests/web/wasm for wasm32-unknown-unknown, --out to dist/.
import { build } from "esbuild";
import { copyFileSync, existsSync, mkdirSync, readdirSync, readFileSync, rmSync, writeFileSync } from "node:fs";
import { dirname, join } from "node:path";
import { fileURLToPath } from "node:url";

const here = dirname(fileURLToPath(import.meta.url));
const arg = (name, fallback) => {
  const i = process.argv.indexOf(name);
  return i >= 0 ? process.argv[i + 1] : fallback;
};
const images = arg("--images", join(here, "../../firmware/target/images"));
const wasm = arg("--wasm", join(here, "../../target/wasm32-unknown-unknown/release/tinybms_web.wasm"));
const out = arg("--out", join(here, "dist"));

rmSync(out, { recursive: true, force: true });
mkdirSync(join(out, "firmware"), { recursive: true });

await build({
  entryPoints: [join(here, "src/install.ts"), join(here, "src/console.ts")],
  bundle: true,
  splitting: true,
  format: "esm",
  target: "chrome100",
  minify: true,
  sourcemap: true,
  outdir: out,
  logLevel: "warning",
});
for (const f of ["index.html", "console.html", "style.css"]) copyFileSync(join(here, "src", f), join(out, f));
if (!existsSync(wasm)) {
  console.error(
    `build: ${wasm} missing: make it with\n  cargo rustc -p tinybms-web --release --target wasm32-unknown-unknown --crate-type cdylib\n` +
      "(a plain `cargo build -p tinybms-web` makes no .wasm)",
  );
  process.exit(1);
}
copyFileSync(wasm, join(out, "tinybms_web.wasm"));

const index = [];
if (existsSync(images)) {
  for (const m of readdirSync(images).filter((n) => /^manifest-.*\.json$/.test(n)).sort()) {
    const manifest = JSON.parse(readFileSync(join(images, m), "utf8"));
    const parts = manifest.builds.flatMap((b) => b.parts.map((p) => p.path));
    const merged = parts[0].replace(/-boot\.bin$/, ".bin");
    // The signed update file beside them (`tinybms update`), when there is one.
    const update = merged.replace(/\.bin$/, ".tbu");
    const files = [merged, ...parts, ...(existsSync(join(images, update)) ? [update] : [])];
    for (const f of [m, ...files]) copyFileSync(join(images, f), join(out, "firmware", f));
    index.push({ manifest: m, board: manifest.board, wifi: manifest.wifi, version: manifest.version, files });
  }
  if (existsSync(join(images, "SHA256SUMS"))) copyFileSync(join(images, "SHA256SUMS"), join(out, "firmware/SHA256SUMS"));
  // The public key the images trust for updates (the update files' check).
  if (existsSync(join(images, "update-key.pub"))) copyFileSync(join(images, "update-key.pub"), join(out, "firmware/update-key.pub"));
}
if (!index.length) {
  const say = `build: no manifests in ${images} (firmware/make-images.sh writes them)`;
  if (process.argv.includes("--require-images")) {
    console.error(say);
    process.exit(1);
  }
  console.warn(`${say}: the installer page will offer no board`);
}
writeFileSync(join(out, "firmware/index.json"), JSON.stringify(index, null, 1));
console.log(`site in ${out}: ${index.length} manifests`);
