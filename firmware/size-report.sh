#!/usr/bin/env bash
# Flash / static-RAM usage report for esp-hal ELF images (ESP32-C3 / ESP32-C6).
#
# Usage: ./size-report.sh [-v] [ELF ...]
#   Without ELF arguments, reports the release ELFs of both chips (if built):
#     target/riscv32imc-unknown-none-elf/release/tinybms-firmware   (esp32c3)
#     target/riscv32imac-unknown-none-elf/release/tinybms-firmware  (esp32c6)
#   -v  also list every counted section.
# The bridge alone (without the features `can` and `host-link`):
#   cargo build --release --no-default-features --features board-c3-devkitm-1,log-rtt
#   cargo build --release --no-default-features --features board-c6-devkitc-1,log-rtt \
#       --target riscv32imac-unknown-none-elf
#   ./size-report.sh
# Figures (flash / static RAM, bytes): default C3 (SuperMini) 282,504 / 39,448, C6
# (DevKitC-1) 285,420 / 40,556; bridge only C3 112,828 / 19,028, C6 113,996 / 19,356.
# The tree the 84 KiB /
# 16 KiB goal was set on, with the goal's measures: ./size-goal.sh (C3 81,150 /
# 15,692). docs/performance.md: what makes them up.
# With Wi-Fi and MQTT (feature `wifi`; held to 1024 / 256 KiB, below):
# C3 855,682 / 210,556, C6 936,574 / 238,204 (a 100 KiB heap included in
# the RAM; by crate: the radio's C blobs about 320 KiB, rust-mqtt 58 KiB, smoltcp
# 18 KiB, esp-radio 12 KiB).
# Budgets (KiB) can be overridden: FLASH_BUDGET_KIB (default 448), RAM_BUDGET_KIB (default 64).
# The flash budget went from 416 to 448 KiB with the history in flash (issue
# 55: the ring of fixed slots and its CRC-32, the events and what the station
# records, the day book and the capacity estimate, the `get history` listing,
# `set_time`, the aging in the MQTT state: SuperMini 394.6 -> 418.7 KiB of
# flash, 56.6 -> 59.3 KiB of static RAM on the desk's build; 12 records of
# 117 bytes wait in RAM at most).
# They went from 384 / 48 to 416 / 64 KiB with the doctor of the inverter's
# wire (issue 54: the CAN capture, 512 entries of 14 bytes = 7 KiB of RAM; the
# host link's line from 1600 to 2112 bytes for the limits' reasons, the
# heartbeat and the verdicts, +2.5 KiB of RAM in its buffer and pipes; the
# reasons, the doctor's rules and their words, the `get can` listing, the BMS
# wire's verdict and adaptive reads: SuperMini 375.5 -> 397.6 KiB of flash,
# 46.3 -> 56.6 KiB of static RAM). The C3 has 320 KiB of data RAM; what static
# RAM leaves is the stack.
# An image with Wi-Fi (it holds esp-radio's symbols) has a budget of its own:
# WIFI_FLASH_BUDGET_KIB (default 1024), WIFI_RAM_BUDGET_KIB (default 256: the
# 100 KiB heap included), WIFI_RAM_BUDGET_C6_KIB (default 280: the C6's radio
# libraries keep 21.1 KiB more of their code in RAM than the C3's, .rwtext.wifi
# 55,168 B against 33,528 B; the C6 has 512 KiB of SRAM and keeps 248 KiB for
# the stack). The C6's went from 256 to 280 KiB when the inverter's safety by
# default (issue 50) took it to 256.9 KiB; the C3's, the same code, is 229.9.
# WIFI_FLASH_BUDGET_C6_KIB (default 1120; 1088 until the history in flash,
# issue 55, took its image to 1079 KiB on the desk): the C6's radio libraries take
# 79 KiB more flash than the C3's for the same Rust code (1022.8 against
# 943.7 KiB before issue 53); the end of a charge (issue 53: the balance hold,
# the step into float, the stage in words in the log, the host link and
# MQTT) took the C6's to 1026.5 KiB, past the 1024 both chips shared. An app
# slot was 1984 KiB then; 1728 KiB since the history partition (issue 55).
# The flash budget went from 320 to 384 KiB with updates without a cable (issue
# 41: the update file's Ed25519 signature check — curve25519-dalek's field and
# scalar arithmetic —, SHA-512 and SHA-256 in their compact form, the transfer,
# otadata and the trial boot, the update commands: supermini log-rtt 297.3 ->
# 346.3 KiB of flash; static RAM 44.6 KiB with the 4 KiB sector buffer; an app
# slot became 1984 KiB).
# It went from 288 to 320 KiB with the 48 V hybrid inverters (issue
# 40: the Pylontech family's and Growatt's frames, what must stop and its words,
# Growatt's answer: about 10.5 KiB of flash, 0.2 KiB of static RAM).
# It went from 256 to 288 KiB with packs in parallel (issue 20: the
# summaries between bridges, the election of one speaker, the battery's sums and
# limits in the CAN task, the host link's battery and pack lines, the battery's
# Home Assistant device: about 22 KiB of flash, 2 KiB of static RAM; docs/performance.md).
# It went from 224 to 256 KiB with the bridge's own configuration
# (issue 17: the record, its field table and text values, the flash store on
# sequential-storage and esp-storage, the host link's config commands: about
# 54 KiB of flash, 5 KiB of static RAM; docs/performance.md).
# It went from 160 to 224 KiB with the host link (JSON Lines on USB:
# about 71 KiB, of which serde-json-core 9.3 KiB, core's f64 parsing it calls about
# 16 KiB, the derived serializers and the parser/dispatch inlined into the bridge
# task about 28 KiB; docs/host-link.md, docs/performance.md). It was 128 KiB until the inverter output (charge control, CAN
# frames, TWAI task: about 20 KiB) came on top of the trust work (checks, reads in
# pieces, event scan: about 14 KiB). The hard limit is the app slot (1728 KiB,
# partitions.csv: 1.5 x 1152 KiB, the C6 Wi-Fi budget with 64 KiB more); the
# budget is there to make growth visible.
# Exit status: 0 = all within budget, 1 = some image over budget, 2 = usage/tool error.
#
# How sections are classified (from esp-hal's ld/<chip>/memory.x and the ELF section headers):
#   flash      = every allocated PROGBITS section: code/rodata in the cached flash windows
#                (C3: IROM 0x4200_0000.., DROM 0x3C00_0000..; C6: 0x4200_0000..) plus the
#                load images of RAM-resident sections (.trap/.rwtext/.data, .rtc_fast.*) that the
#                bootloader copies out of flash. Image headers / 64 KiB alignment padding of the
#                .bin are not counted.
#   static RAM = every allocated section in internal SRAM (C3: DRAM 0x3FC8_0000.., IRAM
#                0x4037_C000..; C6: HP SRAM 0x4080_0000..): .trap/.rwtext (code in IRAM),
#                .data, .bss, .noinit, ...
#   not counted: NOBITS placeholders that only reserve address space -- .rotext_dummy /
#                .rwdata_dummy (C3: the I-bus and D-bus views of the same SRAM/flash are
#                aliased, the dummy mirrors what the other view uses) and .text_gap (C6);
#                .stack, which is simply all RAM left over (reported as "stack").
#   RTC/LP RAM (0x5000_0000..) is reported separately, not in the static RAM figure.
set -euo pipefail

FLASH_BUDGET_KIB=${FLASH_BUDGET_KIB:-448}
RAM_BUDGET_KIB=${RAM_BUDGET_KIB:-64}
WIFI_FLASH_BUDGET_KIB=${WIFI_FLASH_BUDGET_KIB:-1024}
WIFI_RAM_BUDGET_KIB=${WIFI_RAM_BUDGET_KIB:-256}
WIFI_RAM_BUDGET_C6_KIB=${WIFI_RAM_BUDGET_C6_KIB:-280}
WIFI_FLASH_BUDGET_C6_KIB=${WIFI_FLASH_BUDGET_C6_KIB:-1120}

verbose=0
if [[ ${1:-} == -v ]]; then verbose=1; shift; fi

script_dir=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
if [[ $# -eq 0 ]]; then
    for t in riscv32imc-unknown-none-elf riscv32imac-unknown-none-elf; do
        f="$script_dir/target/$t/release/tinybms-firmware"
        [[ -f $f ]] && set -- "$@" "$f"
    done
    if [[ $# -eq 0 ]]; then
        echo "size-report: no ELF given and none built (cargo build --release / cargo build-c6)" >&2
        exit 2
    fi
fi

# --- locate tools: rustup llvm-tools first (rustup component add llvm-tools), then PATH ---
llvm_bin=""
if command -v rustc >/dev/null 2>&1; then
    llvm_bin="$(rustc --print sysroot)/lib/rustlib/$(rustc -vV | sed -n 's/^host: //p')/bin"
fi
find_tool() { # name [fallback...]
    local n
    for n in "$@"; do
        if [[ -n $llvm_bin && -x $llvm_bin/$n ]]; then echo "$llvm_bin/$n"; return; fi
        if command -v "$n" >/dev/null 2>&1; then command -v "$n"; return; fi
    done
    return 1
}
READOBJ=$(find_tool llvm-readobj) || { echo "size-report: need llvm-readobj (rustup component add llvm-tools)" >&2; exit 2; }
NM=$(find_tool llvm-nm nm) || true
OBJCOPY=$(find_tool llvm-objcopy objcopy) || true

# --- chip detection: esp-hal's `build_info.CHIP_NAME` in .espressif.metadata, else addresses ---
detect_chip() { # elf
    local elf=$1 tmp off size
    if [[ -n $NM && -n $OBJCOPY ]]; then
        read -r off size < <("$NM" -S "$elf" 2>/dev/null | awk '$4=="build_info.CHIP_NAME"{print $1, $2}') || true
        if [[ -n ${off:-} ]]; then
            tmp=$(mktemp)
            if "$OBJCOPY" --dump-section ".espressif.metadata=$tmp" "$elf" /dev/null 2>/dev/null; then
                dd if="$tmp" bs=1 skip=$((16#$off)) count=$((16#$size)) status=none
                rm -f "$tmp"
                return
            fi
            rm -f "$tmp"
        fi
    fi
    # Fallback: HP SRAM at 0x408xxxxx => C6; DRAM at 0x3FCxxxxx => C3.
    "$READOBJ" --elf-output-style=GNU -S "$elf" | awk '
        /\] / { sub(/^ *\[ *[0-9]+\] */, ""); a = tolower($3)
                if (a ~ /^408/) { print "esp32c6"; exit } if (a ~ /^3fc/) { print "esp32c3"; exit } }'
}

# --- flash by crate: the ELF's symbols in flash (code, read-only data, and the
# load images of RAM code/data), summed by the crate their demangled name starts
# with (for `<T as Trait>::f`, T's crate, or the trait's when T is a primitive).
# The firmware's async tasks are inlined into embassy-executor's
# `TaskStorage<F>::poll`: counted as "tinybms_firmware (tasks)". Unnamed
# constants (.Lanon.*: strings, tables, switch tables) are counted apart.
by_crate() { # elf ranges
    "$NM" -C -S --defined-only "$1" 2>/dev/null | awk -v ranges="$2" -v top="${SIZE_TOP_CRATES:-12}" '
    function hex(s,   i, c, v) { v = 0; s = tolower(s)
        for (i = 1; i <= length(s); i++) { c = index("0123456789abcdef", substr(s, i, 1)); v = v * 16 + c - 1 }
        return v }
    BEGIN { nr = split(ranges, tmp, " ")
        for (i = 1; i <= nr; i++) { split(tmp[i], p, ":"); rn[i] = p[1]; rs[i] = hex(p[2]); re[i] = hex(p[3]) } }
    NF >= 4 && $3 ~ /^[tTrRdD]$/ {
        addr = hex($1); reg = ""
        for (i = 1; i <= nr; i++) if (addr >= rs[i] && addr < re[i]) reg = rn[i]
        if (reg == "rtc") next
        n = $4; for (i = 5; i <= NF; i++) n = n " " $i
        gsub(/\$LT\$/, "<", n); gsub(/\$GT\$/, ">", n); gsub(/\$u20\$/, " ", n); gsub(/\$RF\$/, "\\&", n); gsub(/\.\./, "::", n)
        sub(/^_</, "<", n)
        if (n ~ /TaskStorage/) c = "tinybms_firmware (tasks)"
        else if (n ~ /^\.L/) c = "(unnamed constants)"
        else {
            sub(/^<+/, "", n); sub(/^&(mut )?/, "", n); sub(/^[\[(*]+/, "", n)
            if (match(n, / as /) && index(substr(n, 1, RSTART), "::") == 0) n = substr(n, RSTART + 4)
            if (index(n, "::") == 0) c = "(no crate: " n ")"; else { split(n, q, "::"); c = q[1] }
            sub(/^(mut |dyn |const )/, "", c); sub(/>+$/, "", c)
            if (c ~ /^(char|str|bool|[iuf](8|16|32|64|128|size))$/) c = "core"
        }
        sz[c] += hex($2); total += hex($2)
    }
    END {
        printf("  flash by crate (symbols: %.1f KiB):\n", total / 1024)
        while (shown < top) { best = ""; for (c in sz) if (best == "" || sz[c] > sz[best]) best = c
            if (best == "") break; printf("    %7d B  %s\n", sz[best], best); rest -= sz[best]; delete sz[best]; shown++ }
        o = 0; for (c in sz) o += sz[c]; if (o) printf("    %7d B  (%d others)\n", o, length(sz))
    }'
}

status=0
for elf in "$@"; do
    if [[ ! -f $elf ]]; then echo "size-report: $elf: not found" >&2; status=2; continue; fi
    chip=$(detect_chip "$elf")
    case $chip in
        esp32c3) # name:start:end (hex, end exclusive), per esptool / esp-hal memory.x
            ranges="flash:3C000000:3C800000 flash:42000000:42800000 ram:3FC80000:3FD00000 ram:4037C000:403E0000 rtc:50000000:50002000" ;;
        esp32c6)
            ranges="flash:42000000:43000000 ram:40800000:40880000 rtc:50000000:50004000" ;;
        *) echo "size-report: $elf: unsupported/unknown chip '${chip}'" >&2; status=2; continue ;;
    esac

    fbud=$FLASH_BUDGET_KIB rbud=$RAM_BUDGET_KIB
    if [[ -n $NM ]] && "$NM" "$elf" 2>/dev/null | grep -c 'esp_radio' >/dev/null; then
        fbud=$WIFI_FLASH_BUDGET_KIB rbud=$WIFI_RAM_BUDGET_KIB chip_note=" with Wi-Fi"
        [[ $chip == esp32c6 ]] && rbud=$WIFI_RAM_BUDGET_C6_KIB fbud=$WIFI_FLASH_BUDGET_C6_KIB
    else
        chip_note=""
    fi
    "$READOBJ" --elf-output-style=GNU -S "$elf" | awk \
        -v chip="$chip$chip_note" -v ranges="$ranges" -v verbose="$verbose" \
        -v fbud="$fbud" -v rbud="$rbud" '
    function hex(s,   i, c, v) { v = 0; s = tolower(s)
        for (i = 1; i <= length(s); i++) { c = index("0123456789abcdef", substr(s, i, 1)); v = v * 16 + c - 1 }
        return v }
    function region(addr,   i) { for (i = 1; i <= nr; i++) if (addr >= rs[i] && addr < re[i]) return rn[i]; return "" }
    function kib(b) { return sprintf("%.1f KiB", b / 1024) }
    BEGIN { nr = split(ranges, tmp, " ")
        for (i = 1; i <= nr; i++) { split(tmp[i], p, ":"); rn[i] = p[1]; rs[i] = hex(p[2]); re[i] = hex(p[3]) } }
    /^ *\[ *[0-9]+\] / {
        sub(/^ *\[ *[0-9]+\] */, "")
        name = $1; type = $2; addr = hex($3); size = hex($5); flags = (NF >= 10) ? $7 : ""
        if (index(flags, "A") == 0 || size == 0) next           # not loaded / empty
        reg = region(addr)
        if (type == "NOBITS" && (name ~ /dummy/ || name == ".text_gap")) next   # address-space reservations
        if (name == ".stack") { stack += size; next }
        if (type == "PROGBITS") {
            flash += size
            if (reg == "flash") { if (index(flags, "X")) ftext += size; else frodata += size }
            else fload += size
            if (reg == "") printf("  warning: %s at 0x%08x is outside the known memory map (counted as flash)\n", name, addr)
        }
        if (reg == "ram") { ram += size; if (type == "NOBITS") rbss += size; else if (index(flags, "X")) riram += size; else rdata += size }
        if (reg == "rtc") rtc += size
        if (verbose) printf("    %-24s %-8s 0x%08x %8d  %s\n", name, type, addr, size, (reg == "" ? "?" : reg))
    }
    END {
        over = (flash > fbud * 1024) || (ram > rbud * 1024)
        printf("%s: flash %d B = %s (budget %d KiB), static RAM %d B = %s (budget %d KiB)%s\n",
               chip, flash, kib(flash), fbud, ram, kib(ram), rbud, over ? "  ** OVER BUDGET **" : "")
        printf("  flash = text %s + rodata %s + RAM load images %s; RAM = code(IRAM) %s + data %s + bss/noinit %s; stack (rest of RAM) %s%s\n",
               kib(ftext), kib(frodata), kib(fload), kib(riram), kib(rdata), kib(rbss), kib(stack),
               rtc ? "; RTC RAM " kib(rtc) : "")
        exit over ? 1 : 0
    }' || status=$(( status > 1 ? status : 1 ))
    if [[ -n $NM ]]; then by_crate "$elf" "$ranges"; fi
done
exit "$status"
