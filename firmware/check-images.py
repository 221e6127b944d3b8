#!/usr/bin/env python3
"""Checks the ready-made images of make-images.sh, so that what an owner writes
to a board is what it should be.

Usage: check-images.py [DIR]   (default: target/images)

For every tinybms-<board>[-suffix].bin (merged) and its -app.bin:
  * the bootloader at 0x0 and the app at the factory partition are ESP images of
    the board's chip whose checksum and SHA-256 esptool finds valid
    (`esptool image-info`);
  * the partition table at 0x8000 is espflash's default: nvs (data/nvs) at 0x9000,
    0x6000 bytes — the partition the configuration store uses — and the factory
    app at 0x10000;
  * the app fits its partition;
  * the -app.bin is byte for byte the app inside the merged image, and the
    -boot.bin its first 0x9000 bytes (bootloader and partition table, ending
    where the nvs partition starts);
  * SHA256SUMS lists every image with its right checksum;
  * every manifest-<board>[-suffix].json (ESP Web Tools, the browser
    installer) names the firmware as the firmware names itself (PRODUCT in
    src/improv/mod.rs), the chip family of the board's chip, and exactly two
    parts: the -boot.bin at 0 and the -app.bin at the factory partition's
    offset, both files present here — so the installer writes what these
    checks checked and never the nvs partition (the stored configuration).
Exit status 0 when all hold; 1 otherwise (each problem printed).
"""
import hashlib
import json
import os
import re
import struct
import subprocess
import sys

PARTITION_TABLE = 0x8000
NVS = (0x9000, 0x6000)
FACTORY = 0x10000


def chip_of(board):
    """(esptool chip name, image chip id) of a board name."""
    if "c6" in board:
        return ("esp32c6", 13)
    return ("esp32c3", 5)


def partitions(image):
    out = []
    table = image[PARTITION_TABLE:PARTITION_TABLE + 0xC00]
    for i in range(0, len(table), 32):
        magic, ptype, subtype, offset, size = struct.unpack("<HBBII", table[i:i + 12])
        if magic != 0x50AA:
            break
        label = table[i + 12:i + 28].rstrip(b"\0").decode("ascii", "replace")
        out.append((ptype, subtype, offset, size, label))
    return out


def image_info(chip, data, what, problems):
    """Runs esptool image-info on `data`; checks the checksum and hash are valid."""
    path = f"/tmp/check-images-{os.getpid()}.bin"
    with open(path, "wb") as f:
        f.write(data)
    try:
        r = subprocess.run(
            [sys.executable, "-m", "esptool", "--chip", chip, "image-info", path],
            capture_output=True, text=True, timeout=120,
        )
    finally:
        os.unlink(path)
    text = r.stdout + r.stderr
    if r.returncode != 0:
        problems.append(f"{what}: esptool image-info failed: {text.strip()[-300:]}")
        return
    if not re.search(r"Checksum: 0x[0-9a-f]+ \(valid\)", text):
        problems.append(f"{what}: checksum not valid")
    if not re.search(r"Validation hash: [0-9a-f]+ \(valid\)", text):
        problems.append(f"{what}: validation hash not valid")
    return text


def product_name():
    """The name the firmware gives the installer (Improv's device info)."""
    src = os.path.join(os.path.dirname(os.path.abspath(__file__)), "src", "improv", "mod.rs")
    m = re.search(r'^pub const PRODUCT: &str = "(.*)";$', open(src).read(), re.M)
    return m.group(1) if m else None


def check_manifest(dirname, merged_name, chip, app_offset, problems):
    """The ESP Web Tools manifest of one merged image."""
    stem = merged_name[len("tinybms-"):-len(".bin")]
    path = os.path.join(dirname, f"manifest-{stem}.json")
    what = os.path.basename(path)
    if not os.path.exists(path):
        problems.append(f"{merged_name}: {what} missing")
        return
    try:
        m = json.load(open(path))
    except ValueError as e:
        problems.append(f"{what}: not JSON: {e}")
        return
    if m.get("name") != product_name():
        problems.append(f"{what}: name {m.get('name')!r}, the firmware says {product_name()!r}")
    if not m.get("version"):
        problems.append(f"{what}: no version")
    # An image with Wi-Fi says `VERSION+wifi` (its Improv device info says the
    # same): the installer then offers the switch between the two as an update.
    elif m["version"].endswith("+wifi") != stem.endswith("-wifi") \
            or m.get("wifi") is not stem.endswith("-wifi"):
        problems.append(f"{what}: version {m['version']!r} / wifi {m.get('wifi')!r} "
                        f"do not say whether the image has Wi-Fi")
    if m.get("new_install_prompt_erase") is not False:
        problems.append(f"{what}: a first install must erase (new_install_prompt_erase false)")
    family = {"esp32c3": "ESP32-C3", "esp32c6": "ESP32-C6"}[chip]
    builds = m.get("builds") or []
    if len(builds) != 1 or builds[0].get("chipFamily") != family:
        problems.append(f"{what}: want one build for {family}: {builds}")
        return
    parts = builds[0].get("parts") or []
    want = [(f"tinybms-{stem}-boot.bin", 0), (f"tinybms-{stem}-app.bin", app_offset)]
    got = [(p.get("path"), p.get("offset")) for p in parts]
    if got != want:
        problems.append(f"{what}: parts {got}, want {want}")
    for p, _ in got:
        if p and not os.path.exists(os.path.join(dirname, p)):
            problems.append(f"{what}: {p} is not here")
    boot = os.path.join(dirname, f"tinybms-{stem}-boot.bin")
    if os.path.exists(boot) and os.path.getsize(boot) > NVS[0]:
        problems.append(f"{what}: the part at 0 reaches into the nvs partition")
    if not [x for x in problems if x.startswith(what)]:
        print(f"{what}: {family}, boot at 0x0 + app at {app_offset:#x}, nvs untouched: ok")


def check(dirname):
    problems = []
    names = sorted(n for n in os.listdir(dirname) if n.endswith(".bin"))
    merged = [n for n in names if not n.endswith("-app.bin") and not n.endswith("-boot.bin")]
    if not merged:
        return [f"{dirname}: no images"]
    sums = {}
    sums_path = os.path.join(dirname, "SHA256SUMS")
    if os.path.exists(sums_path):
        for line in open(sums_path):
            digest, name = line.split()
            sums[name.lstrip("*")] = digest
    else:
        problems.append("SHA256SUMS missing")
    for n in names:
        data = open(os.path.join(dirname, n), "rb").read()
        if sums.get(n) != hashlib.sha256(data).hexdigest():
            problems.append(f"{n}: not in SHA256SUMS with its checksum")
    for n in merged:
        board = n[len("tinybms-"):-len(".bin")]
        chip, chip_id = chip_of(board)
        image = open(os.path.join(dirname, n), "rb").read()
        if image[0] != 0xE9:
            problems.append(f"{n}: no bootloader image at 0x0")
        elif struct.unpack("<H", image[12:14])[0] != chip_id:
            problems.append(f"{n}: the bootloader is not for {chip}")
        image_info(chip, image[:PARTITION_TABLE], f"{n} bootloader", problems)
        parts = partitions(image)
        nvs = [p for p in parts if p[0] == 1 and p[1] == 2 and p[4] == "nvs"]
        if not nvs or (nvs[0][2], nvs[0][3]) != NVS:
            problems.append(f"{n}: no nvs partition at 0x9000 of 0x6000 bytes: {parts}")
        factory = [p for p in parts if p[0] == 0 and p[1] == 0]
        if not factory or factory[0][2] != FACTORY:
            problems.append(f"{n}: no factory app at 0x10000: {parts}")
        app = image[FACTORY:]
        if not app or app[0] != 0xE9:
            problems.append(f"{n}: no app image at 0x10000")
            continue
        if struct.unpack("<H", app[12:14])[0] != chip_id:
            problems.append(f"{n}: the app is not for {chip}")
        if factory and len(app) > factory[0][3]:
            problems.append(f"{n}: the app ({len(app)} bytes) does not fit the factory "
                            f"partition ({factory[0][3]} bytes)")
        info = image_info(chip, app, f"{n} app", problems) or ""
        app_path = os.path.join(dirname, n[:-len(".bin")] + "-app.bin")
        if not os.path.exists(app_path):
            problems.append(f"{n}: {os.path.basename(app_path)} missing")
        elif open(app_path, "rb").read() != app:
            problems.append(f"{os.path.basename(app_path)}: differs from the app in {n}")
        boot_path = os.path.join(dirname, n[:-len(".bin")] + "-boot.bin")
        if not os.path.exists(boot_path):
            problems.append(f"{n}: {os.path.basename(boot_path)} missing")
        elif open(boot_path, "rb").read() != image[:NVS[0]]:
            problems.append(f"{os.path.basename(boot_path)}: not the first 0x9000 bytes of {n}")
        check_manifest(dirname, n, chip, factory[0][2] if factory else FACTORY, problems)
        size = re.search(r"Image size: (\d+)", info)
        print(f"{n}: {chip}, bootloader + partition table (nvs 0x9000+0x6000, factory 0x10000) "
              f"+ app of {size.group(1) if size else '?'} bytes: ok"
              if not [p for p in problems if p.startswith(n)] else f"{n}: PROBLEMS")
    return problems


def main():
    dirname = sys.argv[1] if len(sys.argv) > 1 else "target/images"
    problems = check(dirname)
    for p in problems:
        print("FAIL:", p)
    sys.exit(1 if problems else 0)


if __name__ == "__main__":
    main()
