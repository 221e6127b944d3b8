"""Decodes a candump log written by `sim --can-log` with python-can and cantools
against the DBC files: the frames a user's own tools read must be the ones the
encoder meant. Exits non-zero on any mismatch.

    check_with_cantools.py LOG DBC [DBC...]

The limits (0x351; Growatt's 0x311) are held to 16 cells within [2.5, 3.65] V
and non-negative currents. Every frame of the DBC the bridge sends must be in
the log; the inverter's own frames need not be.

With the pack summaries' DBC (a log of `sim --packs N`), every summary is
checked too: SOC and SOH within 0-100 %, lowest cell at most the highest,
conditions 0-2, and the four frames of one summary with one sequence number."""
import sys

import can
import cantools

log, dbc_paths = sys.argv[1], sys.argv[2:]
db = cantools.database.Database()
for p in dbc_paths:
    db.add_dbc_file(p)
counts = {}
summaries = 0
pending = {}
for m in can.LogReader(log):
    if m.is_extended_id:
        sys.exit(f"extended id {m.arbitration_id:X} in {log}")
    d = db.decode_message(m.arbitration_id, m.data)
    counts[m.arbitration_id] = counts.get(m.arbitration_id, 0) + 1
    # The limits: Victron, SMA and the Pylontech family's 0x351, Growatt's
    # 0x311 (big-endian).
    growatt = m.arbitration_id == 0x311 and "ChargeVoltageLimit" in d
    if m.arbitration_id == 0x351 or growatt:
        cvl = d["ChargeVoltageLimit"]
        if not (16 * 2.5 - 0.05 <= cvl <= 16 * 3.65 + 0.05):
            sys.exit(f"CVL {cvl} V out of 16 x [2.5, 3.65] at {m.timestamp}")
        if d["ChargeCurrentLimit"] < 0 or d["DischargeCurrentLimit"] < 0:
            sys.exit(f"negative current limit at {m.timestamp}: {d}")
    if 0x6A0 <= m.arbitration_id <= 0x6BF:
        node, k = divmod(m.arbitration_id - 0x6A0, 4)
        for name, v in d.items():
            if name in ("StateOfCharge", "StateOfHealth") and not 0 <= v <= 100:
                sys.exit(f"pack {node + 1}: {name} {v} at {m.timestamp}")
            if name in (
                "HighVoltage", "LowVoltage", "HighTemperature", "LowTemperature",
                "HighTemperatureCharge", "LowTemperatureCharge", "HighDischargeCurrent",
                "HighChargeCurrent", "BmsInternal", "CellImbalance") and v > 2:
                sys.exit(f"pack {node + 1}: condition {name} = {v} at {m.timestamp}")
        if k == 1 and d["MinCellVoltage"] > d["MaxCellVoltage"]:
            sys.exit(f"pack {node + 1}: lowest cell above the highest at {m.timestamp}")
        seq = d["Sequence"]
        if k == 0:
            pending[node] = seq
        elif pending.get(node) != seq:
            sys.exit(f"pack {node + 1}: frame {k} with sequence {seq} after {pending.get(node)}")
        elif k == 3:
            summaries += 1
# Every frame the bridge sends must be in the log; the inverter's own
# (0x305, 0x307, 0x300, 0x301: sender INVERTER) only when the simulated one
# sends it.
missing = [f"{i.frame_id:03X}" for i in db.messages
           if i.frame_id not in counts and "INVERTER" not in i.senders]
if missing:
    sys.exit(f"frames of the DBC never seen in the log: {missing}")
print("cantools/python-can decoded", sum(counts.values()), "frames:",
      ", ".join(f"{k:03X} x{v}" for k, v in sorted(counts.items())))
if summaries:
    print("pack summaries complete and in order:", summaries)
