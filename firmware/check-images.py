#!/usr/bin/env python3
"""Checks the ready-made images of make-images.sh, so that what an owner writes
to a board is what it should be.

Usage: check-images.py [DIR]   (default: target/images)

For every tinybms-<board>[-suffix].bin (merged) and its -app.bin:
  * the bootloader at 0x0 and the app in ota_0 are ESP images of the board's
    chip whose checksum and SHA-256 esptool finds valid (`esptool image-info`);
  * the partition table at 0x8000 is partitions.csv's: nvs (data/nvs) at
    0x9000, 0x6000 bytes — the partition the configuration store uses, where
    it has always been —, otadata at 0x10000 (0x2000 bytes), the app slots
    ota_0 at 0x20000 and ota_1 at 0x1d0000 (0x1b0000 bytes, 1728 KiB, each),
    the history partition (data, subtype undefined 0x06, label history: the
    bridge's event log and daily records) at 0x380000 (0x80000 bytes, to the
    end of the 4 MiB), and nothing else;
  * the app fits a slot: the merged image's app, the -app.bin and the update
    file's image are each at most 0x1b0000 bytes;
  * the -app.bin is byte for byte the app inside the merged image, the
    -boot.bin its first 0x9000 bytes (bootloader and partition table, ending
    where the nvs partition starts), and the -otadata.bin 0x2000 bytes of FF;
  * the update file tinybms-<board>[-suffix].tbu: its header names the chip,
    the board, the version of the manifest and the features of the image
    (wifi with -wifi), its image is the -app.bin, its SHA-256 the one signed,
    and its Ed25519 signature verifies with the key in update-key.pub (the one
    built into the images; openssl checks it);
  * SHA256SUMS lists every image and update file with its right checksum;
  * every manifest-<board>[-suffix].json (ESP Web Tools, the browser
    installer) names the firmware as the firmware names itself (PRODUCT in
    src/improv/mod.rs), the chip family of the board's chip, and exactly three
    parts: the -boot.bin at 0, the -otadata.bin at 0x10000 and the -app.bin
    at ota_0's offset, all present here — so the installer writes what these
    checks checked, boots ota_0, and never touches the nvs partition (the
    stored configuration).
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
OTADATA = (0x10000, 0x2000)
OTA_0 = (0x20000, 0x1B0000)
OTA_1 = (0x1D0000, 0x1B0000)
# The history partition: data (1), subtype undefined (0x06), label history.
HISTORY = (0x380000, 0x80000)
HISTORY_TYPE = (1, 0x06)
# Every partition of the table, no more.
LABELS = ["nvs", "phy_init", "otadata", "ota_0", "ota_1", "history"]
HEADER = 256
SIGNED = 192


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
    want = [(f"tinybms-{stem}-boot.bin", 0), (f"tinybms-{stem}-otadata.bin", OTADATA[0]),
            (f"tinybms-{stem}-app.bin", app_offset)]
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
        print(f"{what}: {family}, boot at 0x0 + otadata erased + app at {app_offset:#x}, "
              f"nvs untouched: ok")


def text_field(header, start, end):
    raw = header[start:end]
    return raw.split(b"\0", 1)[0].decode("ascii", "replace")


def verify_ed25519(public_hex, message, signature):
    """True when openssl verifies the Ed25519 `signature` of `message`."""
    import tempfile
    der = bytes.fromhex("302a300506032b6570032100") + bytes.fromhex(public_hex)
    with tempfile.TemporaryDirectory() as d:
        paths = {n: os.path.join(d, n) for n in ("pub.der", "msg", "sig")}
        for n, data in (("pub.der", der), ("msg", message), ("sig", signature)):
            with open(paths[n], "wb") as f:
                f.write(data)
        r = subprocess.run(["openssl", "pkeyutl", "-verify", "-pubin", "-keyform", "DER",
                            "-inkey", paths["pub.der"], "-rawin", "-in", paths["msg"],
                            "-sigfile", paths["sig"]], capture_output=True, text=True)
        return r.returncode == 0


def check_update(dirname, n, chip, app, problems):
    """The signed update file of the merged image `n`."""
    stem = n[len("tinybms-"):-len(".bin")]
    path = os.path.join(dirname, f"tinybms-{stem}.tbu")
    what = os.path.basename(path)
    if not os.path.exists(path):
        problems.append(f"{n}: {what} missing")
        return
    data = open(path, "rb").read()
    header, image = data[:HEADER], data[HEADER:]
    board = stem[:-len("-wifi")] if stem.endswith("-wifi") else stem
    if header[:8] != b"TBMSUPD1":
        problems.append(f"{what}: no TBMSUPD1 header")
        return
    length = struct.unpack("<I", header[8:12])[0]
    if length != len(image):
        problems.append(f"{what}: the header says {length} bytes of image, {len(image)} follow")
    if image != app:
        problems.append(f"{what}: its image is not the -app.bin")
    if len(image) > min(OTA_0[1], OTA_1[1]):
        problems.append(f"{what}: its image ({len(image)} bytes) is larger than a slot "
                        f"({min(OTA_0[1], OTA_1[1])} bytes): no bridge could take it")
    if header[12:44] != hashlib.sha256(image).digest():
        problems.append(f"{what}: the image's SHA-256 is not the signed one")
    fields = {"chip": text_field(header, 44, 60), "board": text_field(header, 60, 84),
              "features": text_field(header, 84, 124), "version": text_field(header, 124, 148)}
    if fields["chip"] != chip or fields["board"] != board:
        problems.append(f"{what}: for {fields['chip']} {fields['board']}, not {chip} {board}")
    features = fields["features"].split(",")
    if ("wifi" in features) != stem.endswith("-wifi") or "host-link" not in features:
        problems.append(f"{what}: features {fields['features']!r} are not the image's")
    # The header says what the image itself says: its descriptor's version
    # (bytes 48..80) and build (80..112), the features it names in its bytes.
    desc_version = app[48:80].split(b"\0")[0].decode("ascii", "replace")
    desc_build = app[80:112].split(b"\0")[0].decode("ascii", "replace")
    build = text_field(header, 148, 180)
    if fields["version"] != desc_version or build != desc_build:
        problems.append(f"{what}: header {fields['version']!r} built from {build!r}, the image "
                        f"says {desc_version!r} built from {desc_build!r}")
    mark = b"tinybms-features="
    at = app.find(mark)
    named = app[at + len(mark):].split(b"\0")[0].decode("ascii", "replace") if at >= 0 else None
    if named != fields["features"]:
        problems.append(f"{what}: header features {fields['features']!r}, the image names {named!r}")
    manifest = os.path.join(dirname, f"manifest-{stem}.json")
    if os.path.exists(manifest):
        want = json.load(open(manifest)).get("version", "").split("+")[0]
        if fields["version"] != want:
            problems.append(f"{what}: version {fields['version']!r}, the manifest says {want!r}")
    pub_path = os.path.join(dirname, "update-key.pub")
    if not os.path.exists(pub_path):
        problems.append("update-key.pub missing: no key to check the signatures with")
    elif not verify_ed25519(open(pub_path).read().strip(), header[:SIGNED], header[SIGNED:HEADER]):
        problems.append(f"{what}: the signature does not verify with update-key.pub")
    if not [p for p in problems if p.startswith(what)]:
        print(f"{what}: {chip} {board} {fields['version']} ({fields['features']}), "
              f"{len(image)} bytes, SHA-256 and Ed25519 signature verified: ok")


def check(dirname):
    problems = []
    names = sorted(n for n in os.listdir(dirname) if n.endswith(".bin") or n.endswith(".tbu"))
    parts_of = ("-app.bin", "-boot.bin", "-otadata.bin")
    merged = [n for n in names if n.endswith(".bin") and not n.endswith(parts_of)]
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
        otadata = [p for p in parts if p[0] == 1 and p[1] == 0]
        slots = [[p for p in parts if p[0] == 0 and p[1] == 0x10 + i] for i in (0, 1)]
        if not otadata or (otadata[0][2], otadata[0][3]) != OTADATA:
            problems.append(f"{n}: no otadata at 0x10000 of 0x2000 bytes: {parts}")
        for i, want in ((0, OTA_0), (1, OTA_1)):
            if not slots[i] or (slots[i][0][2], slots[i][0][3]) != want:
                problems.append(f"{n}: no ota_{i} at {want[0]:#x} of {want[1]:#x} bytes: {parts}")
        history = [p for p in parts if (p[0], p[1]) == HISTORY_TYPE and p[4] == "history"]
        if not history or (history[0][2], history[0][3]) != HISTORY:
            problems.append(f"{n}: no history partition (data, undefined) at 0x380000 of "
                            f"0x80000 bytes: {parts}")
        if [p for p in parts if p[0] == 0 and p[1] == 0]:
            problems.append(f"{n}: a factory app besides the two slots: {parts}")
        if sorted(p[4] for p in parts) != sorted(LABELS):
            problems.append(f"{n}: the partitions are not {LABELS}: {parts}")
        ends = sorted((p[2], p[2] + p[3], p[4]) for p in parts)
        for (a0, a1, la), (b0, b1, lb) in zip(ends, ends[1:]):
            if a1 > b0:
                problems.append(f"{n}: {la} overlaps {lb}")
        if ends and ends[-1][1] > 0x400000:
            problems.append(f"{n}: {ends[-1][2]} reaches past 4 MiB")
        app = image[OTA_0[0]:]
        if image[OTADATA[0]:OTADATA[0] + OTADATA[1]].strip(b"\xff"):
            problems.append(f"{n}: otadata is not erased in the merged image")
        if not app or app[0] != 0xE9:
            problems.append(f"{n}: no app image at {OTA_0[0]:#x}")
            continue
        if struct.unpack("<H", app[12:14])[0] != chip_id:
            problems.append(f"{n}: the app is not for {chip}")
        if len(app) > OTA_0[1]:
            problems.append(f"{n}: the app ({len(app)} bytes) does not fit its slot "
                            f"({OTA_0[1]} bytes)")
        info = image_info(chip, app, f"{n} app", problems) or ""
        app_path = os.path.join(dirname, n[:-len(".bin")] + "-app.bin")
        if not os.path.exists(app_path):
            problems.append(f"{n}: {os.path.basename(app_path)} missing")
        elif open(app_path, "rb").read() != app:
            problems.append(f"{os.path.basename(app_path)}: differs from the app in {n}")
        elif os.path.getsize(app_path) > min(OTA_0[1], OTA_1[1]):
            problems.append(f"{os.path.basename(app_path)}: larger than a slot "
                            f"({min(OTA_0[1], OTA_1[1])} bytes)")
        boot_path = os.path.join(dirname, n[:-len(".bin")] + "-boot.bin")
        if not os.path.exists(boot_path):
            problems.append(f"{n}: {os.path.basename(boot_path)} missing")
        elif open(boot_path, "rb").read() != image[:NVS[0]]:
            problems.append(f"{os.path.basename(boot_path)}: not the first 0x9000 bytes of {n}")
        ota_path = os.path.join(dirname, n[:-len(".bin")] + "-otadata.bin")
        if not os.path.exists(ota_path):
            problems.append(f"{n}: {os.path.basename(ota_path)} missing")
        elif open(ota_path, "rb").read() != b"\xff" * OTADATA[1]:
            problems.append(f"{os.path.basename(ota_path)}: not 0x2000 bytes of FF")
        check_manifest(dirname, n, chip, OTA_0[0], problems)
        check_update(dirname, n, chip, app, problems)
        size = re.search(r"Image size: (\d+)", info)
        print(f"{n}: {chip}, bootloader + partition table (nvs 0x9000+0x6000, otadata "
              f"0x10000, ota_0 0x20000, ota_1 0x1d0000, 0x1b0000 each, history 0x380000) "
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
