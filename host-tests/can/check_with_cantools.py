"""Decodes a candump log written by `sim --can-log` with python-can and cantools
against the DBC files: the frames a user's own tools read must be the ones the
encoder meant. Exits non-zero on any mismatch."""
import sys

import can
import cantools

log, dbc_path = sys.argv[1], sys.argv[2]
db = cantools.database.load_file(dbc_path)
counts = {}
for m in can.LogReader(log):
    if m.is_extended_id:
        sys.exit(f"extended id {m.arbitration_id:X} in {log}")
    d = db.decode_message(m.arbitration_id, m.data)
    counts[m.arbitration_id] = counts.get(m.arbitration_id, 0) + 1
    if m.arbitration_id == 0x351:
        cvl = d["ChargeVoltageLimit"]
        if not (16 * 2.5 - 0.05 <= cvl <= 16 * 3.65 + 0.05):
            sys.exit(f"CVL {cvl} V out of 16 x [2.5, 3.65] at {m.timestamp}")
        if d["ChargeCurrentLimit"] < 0 or d["DischargeCurrentLimit"] < 0:
            sys.exit(f"negative current limit at {m.timestamp}: {d}")
missing = [f"{i.frame_id:03X}" for i in db.messages if i.frame_id not in counts]
if missing:
    sys.exit(f"frames of the DBC never seen in the log: {missing}")
print("cantools/python-can decoded", sum(counts.values()), "frames:",
      ", ".join(f"{k:03X} x{v}" for k, v in sorted(counts.items())))
