// The installer page: the board table is the firmware's own (compiled to
// WebAssembly with the console's rules), the manifests are those
// firmware/make-images.sh wrote beside the images (firmware/index.json
// lists them), and ESP Web Tools does the flashing and Improv Wi-Fi.

// ESP Web Tools as its package ships it for the web (self-contained; the
// locked package, bundled here: no script from a CDN).
import "esp-web-tools/dist/web/install-button.js";
import { loadRules, rules } from "./wasm";

interface Board {
  name: string;
  board: string;
  chip_family: string;
  host: string;
  labels: string[];
  bms_tx: number;
  bms_rx: number;
  can_tx: number;
  can_rx: number;
}

interface Image {
  manifest: string;
  board: string;
  wifi: boolean;
  version: string;
  files: string[];
}

const $ = (id: string) => document.getElementById(id)!;

function choose(boards: Board[], images: Image[]): void {
  const picked = document.querySelector<HTMLInputElement>("input[name=board]:checked");
  const wifi = (document.getElementById("wifi") as HTMLInputElement).checked;
  const board = boards.find((b) => b.board === picked?.value);
  const image = images.find((i) => i.board === board?.board && i.wifi === wifi);
  const button = $("install");
  if (!board || !image) {
    button.removeAttribute("manifest");
    $("chosen").textContent = board ? "no image of this board here" : "choose a board first";
    ($("install-button") as HTMLButtonElement).disabled = true;
    return;
  }
  button.setAttribute("manifest", `firmware/${image.manifest}`);
  ($("install-button") as HTMLButtonElement).disabled = false;
  $("chosen").textContent =
    `${board.name} (${board.chip_family}), ${wifi ? "with" : "without"} Wi-Fi, version ${image.version}: ` +
    `BMS on GPIO${board.bms_tx} (TX) / GPIO${board.bms_rx} (RX), CAN on GPIO${board.can_tx} / GPIO${board.can_rx}.`;
}

async function main(): Promise<void> {
  if (!("serial" in navigator)) $("no-serial").hidden = false;
  await loadRules();
  const boards = rules<Board[]>("boards");
  let images: Image[] = [];
  try {
    const r = await fetch("firmware/index.json");
    if (r.ok) images = await r.json();
  } catch {
    /* no images on this copy of the page */
  }
  const box = $("boards");
  const families = [...new Set(boards.map((b) => b.chip_family))];
  for (const family of families) {
    const group = document.createElement("fieldset");
    const legend = document.createElement("legend");
    const same = boards.filter((b) => b.chip_family === family);
    legend.textContent = `${family}${same.length > 1 ? ` (${same.length} boards share this chip)` : ""}`;
    group.append(legend);
    for (const b of same) {
      const label = document.createElement("label");
      label.className = "board";
      const input = document.createElement("input");
      input.type = "radio";
      input.name = "board";
      input.value = b.board;
      input.addEventListener("change", () => choose(boards, images));
      const has = images.some((i) => i.board === b.board);
      input.disabled = !has;
      label.append(input, ` ${b.name}${has ? "" : " (no image here)"}`);
      group.append(label);
    }
    box.append(group);
  }
  ($("wifi") as HTMLInputElement).addEventListener("change", () => choose(boards, images));
  if (!images.length) {
    // A copy of the page built without images: say so, offer nothing to
    // install or download (no dead checksum link either).
    $("no-images").hidden = false;
    $("downloads").hidden = true;
    ($("install-button") as HTMLButtonElement).disabled = true;
  }
  // Downloads by board: its images with and without Wi-Fi, each with the
  // parts the installer writes.
  const files = $("files");
  for (const b of boards) {
    const mine = images.filter((i) => i.board === b.board);
    if (!mine.length) continue;
    const li = document.createElement("li");
    li.append(`${b.name}: `);
    mine.forEach((i, k) => {
      if (k > 0) li.append(" · ");
      li.append(i.wifi ? "with Wi-Fi " : "without Wi-Fi ");
      i.files.forEach((f, n) => {
        const a = document.createElement("a");
        a.href = `firmware/${f}`;
        a.textContent =
          n === 0
            ? "merged (0x0)"
            : f.endsWith("-boot.bin")
              ? "boot (0x0)"
              : f.endsWith("-otadata.bin")
                ? "otadata (0x10000)"
                : f.endsWith(".tbu")
                  ? "update file"
                  : "app (0x20000)";
        a.title = f;
        li.append(n > 0 ? ", " : "", a);
      });
    });
    files.append(li);
  }
  choose(boards, images);
  document.body.dataset.ready = "true";
}

void main();
