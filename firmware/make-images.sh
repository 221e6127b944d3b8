#!/usr/bin/env bash
# Ready-made flash images, one set per board, into one folder with their
# checksums — for owners who flash without a Rust toolchain (docs/flashing.md).
#
# Usage: ./make-images.sh [OUT_DIR]            (default: target/images)
# Needs: the firmware's toolchain. The images are packed by
# host-tests/pack-images (espflash's library: byte for byte what
# `espflash save-image` writes), built here unless PACK_IMAGES names it;
# PACK_IMAGES_CROSSCHECK=espflash also runs the espflash command (4.7.0) on
# every ELF and fails unless its images are the same bytes (the release does).
# Environment: IMAGE_FEATURES — extra cargo features for every image, and
# IMAGE_SUFFIX — a name part for them (e.g. IMAGE_FEATURES=wifi IMAGE_SUFFIX=-wifi).
#
# Per board (the `board-…` features of Cargo.toml), built like its alias
# `cargo build-<board>` in .cargo/config.toml (the log path that needs only the
# board's own USB connector, the inverter output and the host link), with the
# partition table of partitions.csv (nvs, otadata, two app slots):
#   tinybms-<board>.bin         bootloader + partition table + app, written at
#                               0x0: a first install (it also erases the stored
#                               configuration and otadata: it covers both)
#   tinybms-<board>-app.bin     the app alone, for ota_0 at 0x20000
#   tinybms-<board>-otadata.bin otadata erased (8 KiB of FF), for 0x10000: with
#                               the app, a reinstall by cable that keeps the
#                               configuration and boots ota_0
#   tinybms-<board>-boot.bin    the merged image's first 0x9000 bytes
#                               (bootloader and partition table, up to the nvs
#                               partition)
#   tinybms-<board>.tbu         the update file: the app signed (docs/updates.md),
#                               what `tinybms update` sends over USB or Wi-Fi
#   manifest-<board>.json       the ESP Web Tools manifest of the browser
#                               installer: boot.bin at 0x0, otadata.bin at
#                               0x10000 and app.bin at 0x20000, so an update
#                               leaves the nvs partition (the configuration) alone
# and SHA256SUMS over all of them. check-images.py checks their layout and
# the update files' signatures.
# The signing key: TINYBMS_SIGNING_KEY_FILE (64 hex digits, `tinybms keygen`;
# the release workflow's secret); its public key is built into every image
# (TINYBMS_UPDATE_KEY). Without one, a throwaway key is made once in the
# target folder (openssl): those images trust it and no other bridge does.
# The update files are signed by `tinybms sign` (TINYBMS names the tool, else
# it is built from this repository).
# TINYBMS_VERSION (the release tag without its `v`; else the package's
# version) is the version the images report and the manifests carry.
# MAKE_IMAGES_STEP: `build` builds every board's ELF into OUT_DIR, `pack` makes
# the images, manifests and SHA256SUMS from those ELFs, `all` (the default)
# both.
# IMAGE_LINT_BOARDS="board …": those boards' builds are also clippy's runs over
# the firmware crate (-D warnings; CI).
# Every image names what it was built from (`hello`'s `build`, `tinybms version`,
# its first log line, Home Assistant's device info): TINYBMS_BUILD if set (a
# release's name), else `git describe --always --dirty --tags`, else `unknown`
# (a copy outside git) — never the `dev` of a local build.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")"

if [[ -z ${TINYBMS_BUILD:-} ]]; then
    TINYBMS_BUILD=$(git describe --always --dirty --tags 2>/dev/null) || TINYBMS_BUILD=unknown
    [[ -n $TINYBMS_BUILD ]] || TINYBMS_BUILD=unknown
fi
export TINYBMS_BUILD
echo "== build $TINYBMS_BUILD"

out=${1:-target/images}
mkdir -p "$out"
phase=${MAKE_IMAGES_STEP:-all}
case $phase in build | pack | all) ;; *) echo "make-images: MAKE_IMAGES_STEP is build, pack or all" >&2; exit 2 ;; esac
if [[ $phase != build ]]; then
    if [[ -z ${PACK_IMAGES:-} ]]; then
        # Its own workspace, built from its folder (this folder's cargo
        # configuration would build it for the chip).
        (cd ../host-tests/pack-images && cargo build -q --locked)
        PACK_IMAGES=$PWD/../host-tests/pack-images/target/debug/pack-images
    fi
    [[ -x $PACK_IMAGES ]] || { echo "make-images: $PACK_IMAGES is not a program" >&2; exit 2; }
    if [[ -z ${TINYBMS:-} ]]; then
        (cd .. && cargo build -q --locked -p tinybms)
        TINYBMS=$PWD/../target/debug/tinybms
    fi
    [[ -x $TINYBMS ]] || { echo "make-images: $TINYBMS is not a program" >&2; exit 2; }
    if [[ -n ${PACK_IMAGES_CROSSCHECK:-} ]]; then
        "$PACK_IMAGES_CROSSCHECK" --version | grep -qx 'espflash 4.7.0' \
            || { echo "make-images: the cross-check needs espflash 4.7.0" >&2; exit 2; }
    fi
fi

# The signing key and its public key (built into every image).
key_file=${TINYBMS_SIGNING_KEY_FILE:-}
if [[ -z $key_file ]]; then
    key_file=target/update-signing-key.hex
    if [[ ! -s $key_file ]]; then
        mkdir -p "$(dirname "$key_file")"
        (umask 077 && openssl rand -hex 32 > "$key_file")
    fi
    echo "== a throwaway signing key ($key_file): these images trust it, no other bridge does"
fi
[[ -s $key_file ]] || { echo "make-images: no signing key in $key_file" >&2; exit 2; }
# Ed25519's public key of the seed, through openssl (a DER private key is a
# fixed prefix and the 32-byte seed; the public key's DER ends in its 32 bytes).
TINYBMS_UPDATE_KEY=$(python3 - "$key_file" <<'PY'
import subprocess, sys
seed = bytes.fromhex(open(sys.argv[1]).read().strip())
assert len(seed) == 32, "the signing key is not 64 hex digits"
der = bytes.fromhex("302e020100300506032b657004220420") + seed
pub = subprocess.run(["openssl", "pkey", "-inform", "DER", "-pubout", "-outform", "DER"],
                     input=der, capture_output=True, check=True).stdout
print(pub[-32:].hex())
PY
) || { echo "make-images: cannot read the signing key" >&2; exit 2; }
export TINYBMS_UPDATE_KEY
echo "== images trust the update key $TINYBMS_UPDATE_KEY"

version=${TINYBMS_VERSION:-$(sed -n 's/^version = "\(.*\)"$/\1/p' Cargo.toml | head -n 1)}
export TINYBMS_VERSION=$version
# The name the firmware gives the installer (Improv's device info): the
# manifests must carry the same, so an installed bridge is recognised.
product=$(sed -n 's/^pub const PRODUCT: &str = "\(.*\)";$/\1/p' src/improv/mod.rs)
[[ -n $product ]] || { echo "make-images: no PRODUCT in src/improv/mod.rs" >&2; exit 2; }

boards=$(sed -n 's/^board-\([a-z0-9-]*\) = \["\(esp32c[36]\)"\]$/\1:\2/p' Cargo.toml)
[[ -n $boards ]] || { echo "make-images: no board features in Cargo.toml" >&2; exit 2; }

for entry in $boards; do
    board=${entry%%:*}
    chip=${entry##*:}
    alias_line=$(sed -n "s/^build-$board = \"\(.*\)\"$/\1/p" .cargo/config.toml)
    [[ -n $alias_line ]] || { echo "make-images: no alias build-$board in .cargo/config.toml" >&2; exit 2; }
    case $chip in
        esp32c3) target=riscv32imc-unknown-none-elf ;;
        esp32c6) target=riscv32imac-unknown-none-elf ;;
    esac
    # The alias's arguments, with the extra features added to its --features.
    read -r -a args <<<"$alias_line"
    if [[ -n ${IMAGE_FEATURES:-} ]]; then
        for i in "${!args[@]}"; do
            if [[ ${args[$i]} == --features ]]; then
                args[$((i + 1))]="${args[$((i + 1))]},$IMAGE_FEATURES"
            fi
        done
    fi
    name="tinybms-$board${IMAGE_SUFFIX:-}"
    if [[ $phase != pack ]]; then
        echo "== $board ($chip): cargo ${args[*]}"
        if [[ " ${IMAGE_LINT_BOARDS:-} " == *" $board "* ]]; then
            # clippy over the firmware crate as part of this build (CI).
            RUSTC_WORKSPACE_WRAPPER=$(command -v clippy-driver) CLIPPY_ARGS=-Dwarnings \
                cargo "${args[@]}" --quiet
        else
            cargo "${args[@]}" --quiet
        fi
        cp "${CARGO_TARGET_DIR:-target}/$target/release/tinybms-firmware" "$out/$name.elf"
    fi
    [[ $phase != build ]] || continue
    [[ -f $out/$name.elf ]] || { echo "make-images: $out/$name.elf missing (MAKE_IMAGES_STEP=build first)" >&2; exit 2; }
    "$PACK_IMAGES" "$chip" "$out/$name.elf" "$out/$name.bin" "$out/$name-app.bin" partitions.csv >/dev/null
    if [[ -n ${PACK_IMAGES_CROSSCHECK:-} ]]; then
        x=$(mktemp -d)
        "$PACK_IMAGES_CROSSCHECK" save-image --chip "$chip" --merge --skip-padding --partition-table partitions.csv "$out/$name.elf" "$x/m.bin" >/dev/null
        "$PACK_IMAGES_CROSSCHECK" save-image --chip "$chip" --partition-table partitions.csv "$out/$name.elf" "$x/a.bin" >/dev/null
        cmp "$x/m.bin" "$out/$name.bin" && cmp "$x/a.bin" "$out/$name-app.bin" \
            || { echo "make-images: $name: not espflash's bytes" >&2; exit 1; }
        rm -rf "$x"
        echo "== $name: the same bytes as espflash save-image"
    fi
    head -c $((0x9000)) "$out/$name.bin" > "$out/$name-boot.bin"
    head -c $((0x2000)) /dev/zero | tr '\0' '\377' > "$out/$name-otadata.bin"
    # What the image has built in, as its hello names it.
    features=can,host-link
    [[ ,${IMAGE_FEATURES:-}, == *,wifi,* ]] && features+=,wifi
    features+=,store
    "$TINYBMS" sign --key "$key_file" --chip "$chip" --board "$board" --version "$version" \
        --features "$features" --build "$TINYBMS_BUILD" "$out/$name-app.bin" -o "$out/$name.tbu" >/dev/null
    case $chip in
        esp32c3) family=ESP32-C3 ;;
        esp32c6) family=ESP32-C6 ;;
    esac
    cat > "$out/manifest-$board${IMAGE_SUFFIX:-}.json" <<MANIFEST
{
  "name": "$product",
  "version": "$version$([[ ,${IMAGE_FEATURES:-}, == *,wifi,* ]] && echo +wifi)",
  "board": "$board",
  "wifi": $([[ ,${IMAGE_FEATURES:-}, == *,wifi,* ]] && echo true || echo false),
  "new_install_prompt_erase": false,
  "new_install_improv_wait_time": 15,
  "builds": [
    {
      "chipFamily": "$family",
      "parts": [
        { "path": "$name-boot.bin", "offset": 0 },
        { "path": "$name-otadata.bin", "offset": 65536 },
        { "path": "$name-app.bin", "offset": 131072 }
      ]
    }
  ]
}
MANIFEST
done

if [[ $phase == build ]]; then
    echo "== ELFs in $out"
    exit 0
fi
(cd "$out" && sha256sum -- *.bin *.tbu > SHA256SUMS)
echo "$TINYBMS_UPDATE_KEY" > "$out/update-key.pub"
echo "== images in $out"
(cd "$out" && ls -l -- *.bin *.tbu && cat SHA256SUMS)
