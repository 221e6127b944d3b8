#!/usr/bin/env bash
# Ready-made flash images, one set per board, into one folder with their
# checksums — for owners who flash without a Rust toolchain (docs/flashing.md).
#
# Usage: ./make-images.sh [OUT_DIR]            (default: target/images)
# Needs: espflash (cargo install espflash --locked), the firmware's toolchain.
# Environment: IMAGE_FEATURES — extra cargo features for every image, and
# IMAGE_SUFFIX — a name part for them (e.g. IMAGE_FEATURES=wifi IMAGE_SUFFIX=-wifi).
#
# Per board (the `board-…` features of Cargo.toml), built like its alias
# `cargo build-<board>` in .cargo/config.toml (the log path that needs only the
# board's own USB connector, the inverter output and the host link):
#   tinybms-<board>.bin       bootloader + partition table + app, written at 0x0:
#                             a first install (it also erases the stored
#                             configuration: it covers the nvs partition)
#   tinybms-<board>-app.bin   the app alone, written at 0x10000: an update that
#                             keeps the configuration
# and SHA256SUMS over all of them. check-images.py checks their layout.
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
espflash=${ESPFLASH:-espflash}
command -v "$espflash" >/dev/null || { echo "make-images: espflash not found (cargo install espflash --locked)" >&2; exit 2; }

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
    echo "== $board ($chip): cargo ${args[*]}"
    cargo "${args[@]}" --quiet
    elf="target/$target/release/tinybms-firmware"
    name="tinybms-$board${IMAGE_SUFFIX:-}"
    "$espflash" save-image --chip "$chip" --merge --skip-padding "$elf" "$out/$name.bin" >/dev/null
    "$espflash" save-image --chip "$chip" "$elf" "$out/$name-app.bin" >/dev/null
    cp "$elf" "$out/$name.elf"
done

(cd "$out" && sha256sum -- *.bin > SHA256SUMS)
echo "== images in $out"
(cd "$out" && ls -l -- *.bin && cat SHA256SUMS)
