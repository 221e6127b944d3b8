"""Reads the doctor's fixtures (the bridge's CAN captures: candump logs with
the direction flag, T sent and R heard, and SocketCAN error frames) with
python-can and decodes every frame the bridge sent with cantools against its
dialect's DBC. Exits non-zero on a frame either tool cannot read, and when
the error frames are not the no-ack and bus-off fixtures' own.

    check_capture.py DIR     (DIR/expected.txt names each fixture's protocol)
"""
import os
import sys

import can
import cantools

d = sys.argv[1]
here = os.path.dirname(os.path.abspath(__file__))
dbcs = {}
total = errors = 0
for line in open(os.path.join(d, "expected.txt")):
    if line.startswith("#") or not line.strip():
        continue
    name, protocol = line.split()[:2]
    if protocol not in dbcs:
        dbcs[protocol] = cantools.database.load_file(os.path.join(here, f"tinybms-{protocol}.dbc"))
    db = dbcs[protocol]
    sent = 0
    for m in can.LogReader(os.path.join(d, name + ".log")):
        total += 1
        if m.is_error_frame:
            if "no-ack" not in name and "bus-off" not in name:
                sys.exit(f"{name}: an error frame at {m.timestamp}")
            errors += 1
            continue
        if m.is_extended_id:
            sys.exit(f"{name}: extended id {m.arbitration_id:X} at {m.timestamp}")
        if not m.is_rx:
            try:
                db.get_message_by_frame_id(m.arbitration_id)
            except KeyError:
                continue  # a frame the DBC does not describe
            db.decode_message(m.arbitration_id, m.data)
            sent += 1
    if sent == 0 and "no-ack" not in name and "bus-off" not in name:
        sys.exit(f"{name}: no frame of the bridge decoded")
print(f"{total} frames read ({errors} error frames), every sent frame decoded")
