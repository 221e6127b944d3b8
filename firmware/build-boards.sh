#!/usr/bin/env bash
# Builds the release firmware for every board and both log paths, and prints the
# size of each image (size-report.sh).
#
# Usage: ./build-boards.sh
# Boards: every `board-… = ["esp32c3"|"esp32c6"]` feature line of Cargo.toml (the host
# test host-tests/tests/boards.rs checks that those lines and firmware/src/boards.rs
# list the same boards). Log paths: log-rtt and log-uart. Every image has the full
# feature set (can, host-link), as the default build and the aliases — except a
# log-uart image of a board whose host link runs on UART0 (only `can`).
# Then every board once more with Wi-Fi and MQTT (feature `wifi`, log-rtt), held
# to size-report.sh's budget for Wi-Fi images (WIFI_FLASH_BUDGET_KIB, default 1024;
# WIFI_RAM_BUDGET_KIB, default 256: the radio's heap included; WIFI_RAM_BUDGET_C6_KIB, 280).
# Images are kept as target/boards/tinybms-firmware-<board>-<log>[-wifi].elf.
#
# BOARDS_IMAGES=DIR (CI): the log-rtt images, with and without Wi-Fi, are the
# ready-made images' ELFs make-images.sh built into DIR (tinybms-<board>.elf,
# tinybms-<board>-wifi.elf; the same features): sized, not built again. (A
# `cargo check` of a board instead of its link was tried: the check-mode
# build of the dependencies it needs costs more than the links, 12 s each.)
# BOARDS_VARIANTS="…": only those of the three (CI sizes the Wi-Fi images in a
# lane of their own). A CARGO_TARGET_DIR is where its builds are.
# Exit status: 0 = all built and within budget; 1 = some image over budget;
# anything else = a build or tool failure.
#
# Board features only change this crate, so after the first build per (chip, log
# path) each further board only recompiles and links tinybms-firmware.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")"

out=target/boards
mkdir -p "$out"

boards=$(sed -n 's/^\(board-[a-z0-9-]*\) = \["\(esp32c[36]\)"\]$/\1:\2/p' Cargo.toml)
if [[ -z $boards ]]; then
    echo "build-boards: no board features found in Cargo.toml" >&2
    exit 2
fi

# Boards whose host link runs on UART0 (boards.rs: `host: HostWire::Uart0`):
# their log-uart image leaves the host link out (defmt frames would share UART0).
uart0_host=$(awk '/feature: "board-/ { f = $2; gsub(/[",]/, "", f) } /host: HostWire::Uart0/ { print f }' src/boards.rs)

status=0
summary=()
for entry in $boards; do
    board=${entry%%:*}
    chip=${entry##*:}
    case $chip in
        esp32c3) target=riscv32imc-unknown-none-elf ;;
        esp32c6) target=riscv32imac-unknown-none-elf ;;
    esac
    for variant in ${BOARDS_VARIANTS:-log-rtt log-uart log-rtt,wifi}; do
        echo "== $board ($chip), $variant"
        rest=can,host-link
        if [[ $variant == log-uart ]] && grep -qx "$board" <<<"$uart0_host"; then
            rest=can
        fi
        elf="$out/tinybms-firmware-$board-${variant/,/-}.elf"
        features="$board,$variant,$rest"
        if [[ -n ${BOARDS_IMAGES:-} && $variant != log-uart ]]; then
            suffix=""
            [[ $variant != *wifi ]] || suffix=-wifi
            image="$BOARDS_IMAGES/tinybms-${board#board-}$suffix.elf"
            [[ -f $image ]] || { echo "build-boards: $image missing (make-images.sh first)" >&2; exit 2; }
            cp "$image" "$elf"
        else
            cargo build --release --quiet --no-default-features --features "$features" --target "$target"
            cp "${CARGO_TARGET_DIR:-target}/$target/release/tinybms-firmware" "$elf"
        fi
        if report=$(./size-report.sh "$elf"); then :; else
            rc=$?
            status=$(( rc > status ? rc : status ))
        fi
        echo "$report"
        summary+=("$(printf '%-22s %-14s %s' "$board" "$variant" "$(head -n1 <<<"$report")")")
    done
done

echo "== sizes (board, log path, chip: flash, static RAM)"
printf '%s\n' "${summary[@]}"
exit "$status"
