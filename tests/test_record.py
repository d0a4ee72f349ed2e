"""Recording: the .tlog the service writes is standard, and a torn last record is harmless."""

from __future__ import annotations

import os
from pathlib import Path

os.environ.setdefault("MAVLINK20", "1")  # before mavutil is imported: MAVLink 2 dialect
from pymavlink import mavutil

from companion.record.tlog import TlogWriter


def _read(path: Path) -> list[tuple[float, str, int, int, dict[str, object]]]:
    log = mavutil.mavlink_connection(str(path))
    out = []
    while (msg := log.recv_match()) is not None:
        if msg.get_type() != "BAD_DATA":
            out.append((msg._timestamp, msg.get_type(), msg.get_srcSystem(),
                         msg.get_srcComponent(), msg.to_dict()))
    log.close()
    return out


def test_messages_round_trip_through_pymavlink(tmp_path: Path) -> None:
    path = tmp_path / "flight.tlog"
    writer = TlogWriter(path)
    writer.write(1_700_000_000.25, 1, 1, "GLOBAL_POSITION_INT",
                 {"time_boot_ms": 1200, "lat": 473977420, "lon": 85455940, "alt": 488000,
                  "relative_alt": 8000, "vx": 1, "vy": -2, "vz": 0, "hdg": 9000})
    writer.write(1_700_000_000.5, 1, 195, "STATUSTEXT",
                 {"severity": 5, "text": "target 3: 47.397751 8.545632", "id": 0,
                  "chunk_seq": 0})
    writer.write(1_700_000_000.75, 1, 1, "PARAM_VALUE",  # an array field out of wire order
                 {"param_id": "MIS_TAKEOFF_ALT", "param_value": 8.0, "param_type": 9,
                  "param_count": 2, "param_index": 0})
    writer.write(1_700_000_001.0, 1, 1, "NO_SUCH_MESSAGE", {})
    writer.close()
    assert (writer.written, writer.skipped) == (3, 1)
    (t0, kind0, sys0, comp0, gpi), (_, kind1, _, comp1, text), (_, _, _, _, param) = _read(path)
    assert (t0, kind0, sys0, comp0) == (1_700_000_000.25, "GLOBAL_POSITION_INT", 1, 1)
    assert gpi["lat"] == 473977420 and gpi["relative_alt"] == 8000 and gpi["vy"] == -2
    assert (kind1, comp1, text["text"]) == ("STATUSTEXT", 195, "target 3: 47.397751 8.545632")
    assert param["param_id"] == "MIS_TAKEOFF_ALT" and param["param_value"] == 8.0


def test_a_torn_last_record_leaves_the_rest_readable(tmp_path: Path) -> None:
    path = tmp_path / "flight.tlog"
    writer = TlogWriter(path)
    for k in range(20):
        writer.write(1_700_000_000.0 + k, 1, 1, "HEARTBEAT",
                     {"type": 2, "autopilot": 12, "base_mode": 129, "custom_mode": k,
                      "system_status": 4, "mavlink_version": 3})
    writer.close()
    data = path.read_bytes()
    path.write_bytes(data[: len(data) - 7])  # power cut in the middle of the last packet
    records = _read(path)
    assert [r[4]["custom_mode"] for r in records] == list(range(19))
