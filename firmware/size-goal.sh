#!/usr/bin/env bash
# Flash / static RAM of the firmware as it was when the size goal was set (issue 10:
# "C3 <= 84 KiB flash and <= 16 KiB static RAM for today's features"), with the
# goal's measures applied: the panic handler of today's src/chip/panic.rs (it does not read
# PanicInfo, so core::fmt is not linked) and esp-hal's switch tables in flash.
#
# Usage: firmware/size-goal.sh [COMMIT]   (default: 82114d9, main on the day)
# Builds that tree for the ESP32-C3 (and the C6 with C6=1) in a temporary git
# worktree with its own target directory (about a minute per chip on two cores),
# prints size-report.sh's figures, removes the worktree.
#   FEATURES=a,b      build the C3 with --no-default-features --features a,b (e.g. the
#                     bridge alone on later trees: board-c3-devkitm-1,log-rtt)
#   C6_FEATURES=a,b   the same for the C6 (needed with C6=1 when FEATURES is set)
#   FLASH_BUDGET_KIB, RAM_BUDGET_KIB   passed to size-report.sh (CI: 84 and 16)
# Exit status: size-report.sh's (1 = over budget), 2 if the tree does not have the
# expected shape or a usage error, cargo's if a build fails.
set -euo pipefail

commit=${1:-82114d9}
if [[ ${C6:-0} == 1 && -n ${FEATURES:-} && -z ${C6_FEATURES:-} ]]; then
    echo "size-goal: with FEATURES, C6=1 needs C6_FEATURES (the C6 board's features)" >&2
    exit 2
fi
here=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
repo=$(git -C "$here" rev-parse --show-toplevel)
work=$(mktemp -d)
target=${SIZE_FILING_TARGET:-$work/target}
cleanup() {
    git -C "$repo" worktree remove --force "$work/tree" >/dev/null 2>&1 || true
    rm -rf "$work"
    git -C "$repo" worktree prune >/dev/null 2>&1 || true
}
trap cleanup EXIT

git -C "$repo" worktree add --detach "$work/tree" "$commit" >/dev/null 2>&1 || {
    echo "size-goal: cannot check out $commit (a full clone is needed)" >&2; exit 2; }
fw=$work/tree/firmware

# Today's panic handler, taken from this checkout's src/chip/panic.rs (attribute to closing brace).
handler=$(awk '/^#\[panic_handler\]/{p=1} p{print} p&&/^}/{exit}' "$here/src/chip/panic.rs")
[[ -n $handler ]] || { echo "size-goal: no panic handler in $here/src/chip/panic.rs" >&2; exit 2; }

if ! HANDLER=$handler python3 - "$fw" <<'EOF'

import os, re, sys
fw = sys.argv[1]
def edit(path, old, new):
    p = os.path.join(fw, path)
    s = open(p).read()
    if old not in s:
        sys.exit(f"size-goal: {path}: expected text not found: {old!r}")
    open(p, "w").write(s.replace(old, new, 1))
handler = os.environ["HANDLER"]
main = os.path.join(fw, "src/main.rs")
s = open(main).read()
if "const PANIC_RESET_DELAY_US" not in s:
    handler = handler.replace("PANIC_RESET_DELAY_US", "1_000_000")
if "#[panic_handler]" in s:
    # An own handler already (later trees): today's instead.
    s, n = re.subn(r"#\[panic_handler\]\n.*?\n}\n", lambda _: handler + "\n", s, count=1, flags=re.S)
    if n != 1:
        sys.exit("size-goal: src/main.rs: the panic handler could not be replaced")
else:
    # esp-backtrace's formatting handler out, today's in.
    s, n = re.subn(r"use esp_backtrace as _;[^\n]*\n", lambda _: handler + "\n", s, count=1)
    if n != 1:
        sys.exit("size-goal: src/main.rs: no panic handler found")
open(main, "w").write(s)
cargo = os.path.join(fw, "Cargo.toml")
c = open(cargo).read()
c = re.sub(r'"panic-handler", |, "custom-halt"', "", c)
open(cargo, "w").write(c)
config = os.path.join(fw, ".cargo/config.toml")
c = open(config).read()
if "ESP_HAL_CONFIG_PLACE_SWITCH_TABLES_IN_RAM" not in c:
    edit(".cargo/config.toml", 'DEFMT_LOG = "info"\n',
         'DEFMT_LOG = "info"\nESP_HAL_CONFIG_PLACE_SWITCH_TABLES_IN_RAM = "false"\n')
EOF
then
    exit 2
fi

elfs=()
(cd "$fw" && CARGO_TARGET_DIR=$target cargo build --release --quiet \
    ${FEATURES:+--no-default-features --features "$FEATURES"})
elfs+=("$target/riscv32imc-unknown-none-elf/release/tinybms-firmware")
if [[ ${C6:-0} == 1 ]]; then
    if [[ -n ${C6_FEATURES:-} ]]; then
        (cd "$fw" && CARGO_TARGET_DIR=$target cargo build --release --quiet \
            --target riscv32imac-unknown-none-elf --no-default-features --features "$C6_FEATURES")
    else
        (cd "$fw" && CARGO_TARGET_DIR=$target cargo build-c6 --quiet)
    fi
    elfs+=("$target/riscv32imac-unknown-none-elf/release/tinybms-firmware")
fi
echo "tree $(git -C "$work/tree" log -1 --format='%h %ad' --date=short) with today's panic handler, switch tables in flash:"
"$here/size-report.sh" "${elfs[@]}"
