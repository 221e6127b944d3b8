#!/usr/bin/env bash
# On-target cost benchmark: builds bench-rv32 for RV32IMC (the firmware's release
# settings), runs it under qemu-riscv32 (user mode) with qemu's execution log
# (-d in_asm,exec,nochain: every translated block's instructions, then every
# block executed) streamed through a pipe, and counts the instructions executed
# between the program's bench_mark() calls. Prints instructions per snapshot for
# each layer of the receive path, and per byte for the decoder.
#
# Needs: qemu-riscv32 (Debian/Ubuntu: apt-get install qemu-user), awk.
# Exit status 1 when the replay of the recorded trace diverged from the host's.
set -euo pipefail
cd "$(dirname "$0")"
# BENCH_FEATURES=handle-rx: replay through the copying receive (older trees).
cargo build --release --quiet ${BENCH_FEATURES:+--features "$BENCH_FEATURES"}
elf=target/riscv32imc-unknown-none-elf/release/bench-rv32
command -v qemu-riscv32 >/dev/null || { echo "run.sh: qemu-riscv32 not found (apt-get install qemu-user)" >&2; exit 2; }

tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
mkfifo "$tmp/log"
# Count while qemu runs: blocks -> instructions per block, executions -> sums.
awk '
    /^IN: / { inblock = 1; first = ""; n = 0; mark = ($2 == "bench_mark"); next }
    inblock && /^0x[0-9a-f]+:/ { if (first == "") first = substr($1, 3, length($1) - 3); n++; next }
    inblock { if (first != "") { len[first] = n; if (mark) markpc = first }; inblock = 0 }
    /^Trace / {
        split($0, f, "/"); pc = f[2]
        if (pc == markpc) phase++
        count[phase] += len[pc]
    }
    END { for (p = 0; p <= phase; p++) printf "phase%d %d\n", p, count[p] }
' "$tmp/log" > "$tmp/counts" &
counter=$!
qemu-riscv32 -d in_asm,exec,nochain -D "$tmp/log" "$elf" > "$tmp/out"
wait "$counter"

get() { awk -v k="$1" '$1 == k { print $2 }' "$tmp/out" "$tmp/counts"; }
reps=$(get reps); bytes=$(get reply_bytes); snaps=$(get snapshots); mism=$(get mismatches)
[ -n "$reps" ] && [ -n "$snaps" ] || { echo "run.sh: the benchmark printed nothing" >&2; cat "$tmp/out" >&2; exit 1; }
per() { echo $(( ($(get "phase$1") + $2 / 2) / $2 )); }

echo "RV32IMC instructions (qemu-riscv32, firmware release profile):"
printf '  %-52s %7s\n' "CRC-16 of the $((bytes - 2)) checked bytes of a live reply" "$(per 1 "$reps")"
dec=$(per 2 "$reps")
printf '  %-52s %7s  (%s per byte)\n' "decoder, one $bytes-byte 0x03 live reply" "$dec" "$(awk -v d="$dec" -v b="$bytes" 'BEGIN { printf "%.1f", d / b }')"
printf '  %-52s %7s\n' "+ Response::decode + LiveSnapshot view" "$(per 3 "$reps")"
printf '  %-52s %7s\n' "+ the snapshot summary line" "$(per 4 "$reps")"
bridge=$(( $(get phase5) - $(get phase6) ))
printf '  %-52s %7s  (%s snapshots, %s calls; the replay'"'"'s own work, %s per snapshot, measured apart and subtracted)\n' \
    "whole Bridge on the recorded 40 s trace, per snapshot" "$(( (bridge + snaps / 2) / snaps ))" "$snaps" \
    "$(( $(get polls) + $(get rx_calls) ))" "$(per 6 "$snaps")"
printf '  %-52s %7s  (soft float; once a second, with a node number)\n' \
    "the packs' shares, one battery step with 8 packs" "$(per 8 "$(get share_updates)")"
[ "$(get shares_learnt)" = 1 ] || { echo "run.sh: the shares' benchmark learnt nothing (it measured the wrong path)" >&2; exit 1; }
psk=$(get phase9)
printf '  %-52s %7s  (the whole key: %s in %s steps, one per station poll)\n' \
    "Improv: one step of the WPA2 key (16 PBKDF2 rounds)" "$(per 9 "$(get psk_steps)")" "$psk" "$(get psk_steps)"
[ "$(get psk_ok)" = 1 ] || { echo "run.sh: the WPA2 key is not IEEE 802.11i's (it measured the wrong path)" >&2; exit 1; }
echo "  sizes (bytes): Bridge $(get bridge_bytes), Response $(get response_bytes), Frame $(get frame_bytes), link Completion $(get completion_bytes), Action $(get action_bytes), Step $(get step_bytes)"
echo "  replay mismatches: $mism"
[ "$mism" = 0 ] || { echo "run.sh: the replay diverged from the recorded trace" >&2; exit 1; }
[ "$(get walk_mismatches)" = 0 ] || { echo "run.sh: the stand-in replay diverged (the subtracted figure is wrong)" >&2; exit 1; }
grep -q '^decoded_ok' "$tmp/out" && [ "$(get decoded_ok)" = $((3 * reps)) ] || { echo "run.sh: a reply did not decode" >&2; exit 1; }
