"""Small writers of flight logs for tests: .tlog with pymavlink's encoder, and ArduPilot
DataFlash .bin and PX4 .ulg after the formats' specifications (pymavlink and pyulog only read
those). Each keeps the offset where every record ends, to cut files mid-record."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from pymavlink.dialects.v20 import ardupilotmega as mavlink

FloatArray = NDArray[np.float64]
Built = tuple[bytes, list[int]]  # a log's bytes and the offset where each record ends
T0_US = 1_700_000_000_000_000


class Tlog:
    def __init__(self) -> None:
        self.data = bytearray()
        self.ends: list[int] = []
        self._senders: dict[tuple[int, int], mavlink.MAVLink] = {}

    def add(self, system: int, component: int, message: mavlink.MAVLink_message) -> None:
        sender = self._senders.setdefault((system, component), mavlink.MAVLink(
            None, srcSystem=system, srcComponent=component))
        self.data += struct.pack(">Q", T0_US + 20_000 * len(self.ends)) + message.pack(sender)
        self.ends.append(len(self.data))

    def built(self) -> Built:
        return bytes(self.data), self.ends



# --- .bin: ArduPilot DataFlash (FMT records, then records of the formats they define) ------

_DF_STRUCT = {"Q": "Q", "q": "q", "L": "i", "i": "i", "I": "I", "f": "f", "c": "h", "C": "H",
              "e": "i", "E": "I", "h": "h", "H": "H", "b": "b", "B": "B", "n": "4s",
              "N": "16s", "Z": "64s"}
_FMT_ID = 0x80


class DataFlash:
    def __init__(self) -> None:
        self.data = bytearray()
        self.ends: list[int] = []
        self.formats: dict[str, tuple[int, str]] = {}
        self._record(_FMT_ID, "BBnNZ", _FMT_ID, 89, b"FMT", b"BBnNZ",
                     b"Type,Length,Name,Format,Columns")

    def _record(self, type_id: int, fmt: str, *values: object) -> None:
        body = struct.pack("<" + "".join(_DF_STRUCT[c] for c in fmt), *values)
        self.data += bytes((0xA3, 0x95, type_id)) + body
        self.ends.append(len(self.data))

    def define(self, type_id: int, name: str, fmt: str, columns: str) -> None:
        length = 3 + struct.calcsize("<" + "".join(_DF_STRUCT[c] for c in fmt))
        self._record(_FMT_ID, "BBnNZ", type_id, length, name.encode(), fmt.encode(),
                     columns.encode())
        self.formats[name] = (type_id, fmt)

    def add(self, name: str, *values: object) -> None:
        type_id, fmt = self.formats[name]
        self._record(type_id, fmt, *values)

    def built(self) -> Built:
        return bytes(self.data), self.ends



# --- .ulg: PX4 ULog (header, definitions F/I, then A subscriptions and D data) -------------

_ULOG_TYPES = {"uint64_t": "Q", "double": "d", "float": "f", "bool": "B", "uint8_t": "B"}


class ULog:
    def __init__(self, topics: dict[str, str]) -> None:
        self.data = bytearray(b"ULog\x01\x12\x35\x01" + struct.pack("<Q", 112_500_176))
        self.ends: list[int] = []
        self._message("B", bytes(16) + bytes(24))  # flag bits: no appended data
        self._message("I", bytes([16]) + b"char[3] sys_name" + b"PX4")
        self.layout: dict[str, tuple[int, str]] = {}
        for name, fields in topics.items():
            self._message("F", f"{name}:{fields}".encode())
        for msg_id, (name, fields) in enumerate(topics.items()):
            self._message("A", struct.pack("<BH", 0, msg_id) + name.encode())
            codes = ""
            for item in filter(None, fields.split(";")):
                kind, _ = item.split(" ")
                base, _, count = kind.partition("[")
                codes += _ULOG_TYPES[base] * (int(count[:-1]) if count else 1)
            self.layout[name] = (msg_id, "<" + codes)

    def _message(self, kind: str, payload: bytes) -> None:
        self.data += struct.pack("<HB", len(payload), ord(kind)) + payload
        self.ends.append(len(self.data))

    def add(self, name: str, *values: float) -> None:
        msg_id, codes = self.layout[name]
        self._message("D", struct.pack("<H", msg_id) + struct.pack(codes, *values))

    def built(self) -> Built:
        return bytes(self.data), self.ends




def write_bin(path: Path, positions: FloatArray, attitudes: FloatArray) -> Path:
    """A .bin of POS and ATT (float degrees) records from FlightLog-style rows."""
    log = DataFlash()
    log.define(64, "POS", "QLLfff", "TimeUS,Lat,Lng,Alt,RelHomeAlt,RelOriginAlt")
    log.define(65, "ATT", "Qffffff", "TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw")
    rows = [(round(p[0] * 1e6), 0, p) for p in positions]
    rows += [(round(a[0] * 1e6), 1, a) for a in attitudes]
    for t_us, kind, row in sorted(rows, key=lambda r: (r[0], r[1])):
        if kind == 0:
            log.add("POS", t_us, round(row[1] * 1e7), round(row[2] * 1e7), row[3], row[4],
                    row[4])
        else:
            w, x, y, z = row[1:]
            roll = np.degrees(np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y)))
            pitch = np.degrees(np.arcsin(np.clip(2 * (w * y - z * x), -1.0, 1.0)))
            yaw = np.degrees(np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z)))
            log.add("ATT", t_us, 0.0, roll, 0.0, pitch, 0.0, yaw)
    path.write_bytes(log.built()[0])
    return path


def write_ulg(path: Path, positions: FloatArray, attitudes: FloatArray) -> Path:
    """A .ulg of vehicle_global_position, vehicle_local_position (its reference altitude) and
    vehicle_attitude from FlightLog-style rows."""
    log = ULog({"vehicle_attitude": "uint64_t timestamp;float[4] q;",
                "vehicle_global_position": "uint64_t timestamp;double lat;double lon;float alt;",
                "vehicle_local_position": "uint64_t timestamp;double ref_lat;double ref_lon;"
                                          "float x;float y;float z;float ref_alt;bool xy_valid;"
                                          "bool z_valid;"})
    ref_alt_m = float(positions[0, 3] - positions[0, 4])
    rows = [(round(p[0] * 1e6), 0, p) for p in positions]
    rows += [(round(a[0] * 1e6), 1, a) for a in attitudes]
    for t_us, kind, row in sorted(rows, key=lambda r: (r[0], r[1])):
        if kind == 0:
            log.add("vehicle_global_position", t_us, row[1], row[2], row[3])
            log.add("vehicle_local_position", t_us, positions[0, 1], positions[0, 2], 0.0, 0.0,
                    -row[4], ref_alt_m, False, True)
        else:
            log.add("vehicle_attitude", t_us, *row[1:])
    path.write_bytes(log.built()[0])
    return path
