"""The vehicle's pose history from another tool's flight log, for replay against video frames.

`read_flight_log(path)` reads a MAVLink telemetry log (.tlog), an ArduPilot DataFlash log (.bin)
or a PX4 ULog (.ulg), chosen by the suffix (any case), into a `FlightLog`: positions (t_s,
lat_deg, lon_deg, alt_amsl_m, alt_rel_m) and attitudes (t_s, qw, qx, qy, qz: body FRD -> NED,
unit norm), each sorted by t_s, strictly increasing, on the autopilot's boot clock in seconds.

Where the poses come from:
- .tlog: GLOBAL_POSITION_INT and ATTITUDE_QUATERNION (or, if the log has none, ATTITUDE's ZYX
  Euler angles) from the autopilot only: the system and component of the first HEARTBEAT
  whose autopilot is not MAV_AUTOPILOT_INVALID (a GCS's is ignored).
- .bin: POS (or GPS instance 0, altitude above its first fix) and ATT (ZYX Euler, degrees).
- .ulg: vehicle_global_position, alt_rel_m above vehicle_local_position's origin (the EKF's:
  alt - ref_alt, which is PX4's -z); without it, vehicle_local_position x, y, z about its
  reference (PX4's own azimuthal equidistant projection on a sphere); vehicle_attitude q.

Samples that are not finite, out of range (|lat| > 90, |lon| > 180, not a unit quaternion) or
have no fix (lat = lon = 0) are dropped; of samples sharing a time the last in the file is kept;
each is counted in a warning (bare copies of a sample are not). A file cut at an arbitrary byte
gives what it holds and a warning.
Every other problem (missing, unreadable, empty, unknown suffix, not the format, no position or
no attitude) is an InputError naming the file; no exception of the libraries gets out.
"""

from __future__ import annotations

import contextlib
import io
import os
import struct
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pymavlink import DFReader, mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink
from pyproj import Proj
from pyulog import ULog

from companion.errors import InputError
from companion.rotation import quaternions_from_euler

__all__ = ["FlightLog", "read_flight_log"]

FloatArray = NDArray[np.float64]

_FORMATS = {".tlog": "tlog", ".bin": "bin", ".ulg": "ulg"}
_UNIT_TOLERANCE = 1e-2  # |q| - 1 beyond this is not an attitude; within it, q is normalized
_REBOOT_JUMP_S = 1.0  # the boot clock going back by more: a restart (or corrupt times)
_PX4_EARTH_RADIUS_M = 6371000.0  # PX4's CONSTANTS_RADIUS_OF_EARTH (lib/geo map projection)
_DATAFLASH_HEADER = b"\xa3\x95"
_DATAFLASH_SLACK_BYTES = 528  # pymavlink's allowance for the garbage ArduPilot leaves at the end


@dataclass(frozen=True)
class FlightLog:
    """Pose history from a flight log: positions and attitudes on the autopilot's boot clock."""

    path: Path
    format: str            # "tlog" | "bin" | "ulg"
    positions: FloatArray  # (n, 5): t_s, lat_deg, lon_deg, alt_amsl_m, alt_rel_m
    attitudes: FloatArray  # (m, 5): t_s, qw, qx, qy, qz (body FRD -> NED, unit norm)
    warnings: list[str]    # e.g. "x.ulg: the file ends mid-record (truncated?): read up to ..."


@dataclass
class _Raw:
    """What a format's reader found, before cleaning: rows in file order."""

    positions: FloatArray
    attitudes: FloatArray
    looked_for_positions: str
    looked_for_attitudes: str
    notes: list[str] = field(default_factory=list)
    truncated: bool = False
    hint: str = ""  # why nothing was found, when the file does not look like the format


def _rows(values: list[tuple[float, ...]] | FloatArray) -> FloatArray:
    """Rows as a (k, 5) float64 array, (0, 5) if there are none."""
    array = np.asarray(values, dtype=np.float64)
    return array.reshape(-1, 5) if array.size else np.empty((0, 5))


class _Discard(io.TextIOBase):
    """A text stream that drops what is written to it."""

    def write(self, s: str) -> int:
        """Drop s."""
        return len(s)


@contextlib.contextmanager
def _quiet(c_stderr: bool = False) -> Iterator[None]:
    """Silence the libraries' prints; with c_stderr, also C code's (file descriptor 2)."""
    saved: int | None = None
    if c_stderr:
        sys.stderr.flush()
        with contextlib.suppress(OSError):  # no file descriptor 2 (a daemon): nothing to hide
            saved = os.dup(2)
            null = os.open(os.devnull, os.O_WRONLY)
            os.dup2(null, 2)
            os.close(null)
    try:
        with contextlib.redirect_stdout(_Discard()), contextlib.redirect_stderr(_Discard()):
            yield
    finally:
        if saved is not None:
            os.dup2(saved, 2)
            os.close(saved)


# --- .tlog ---------------------------------------------------------------------------------

_TLOG_TYPES = ["HEARTBEAT", "GLOBAL_POSITION_INT", "ATTITUDE_QUATERNION", "ATTITUDE"]


def _tlog_tail_is_whole(tail: bytes) -> bool:
    """Whether bytes that start at a record of a .tlog end exactly at a record's end."""
    pos, n = 0, len(tail)
    while pos < n:
        if pos + 10 > n:
            return False
        magic, payload = tail[pos + 8], tail[pos + 9]
        if magic == mavlink.PROTOCOL_MARKER_V1:
            pos += 8 + mavlink.HEADER_LEN_V1 + payload + 2
        elif magic == mavlink.PROTOCOL_MARKER_V2:
            if pos + 11 > n:
                return False
            signed = tail[pos + 10] & mavlink.MAVLINK_IFLAG_SIGNED
            pos += 8 + mavlink.HEADER_LEN_V2 + payload + 2 + (
                mavlink.MAVLINK_SIGNATURE_BLOCK_LEN if signed else 0)
        else:
            return False
    return pos == n


def _read_tlog(path: Path) -> _Raw:
    """GLOBAL_POSITION_INT and ATTITUDE_QUATERNION / ATTITUDE of the autopilot in a .tlog."""
    # mavutil.mavlink_connection would return this reader too, but it runs a log whose path
    # contains "/bin/" as a program; the dialect is pymavlink's global choice either way.
    mavutil.set_dialect("ardupilotmega")
    log = mavutil.mavmmaplog(str(path))
    autopilot: tuple[int, int] | None = None
    streams: dict[str, list[tuple[tuple[int, int], tuple[float, ...]]]] = {
        name: [] for name in _TLOG_TYPES[1:]}
    decoded = 0
    try:
        while (msg := log.recv_match(type=_TLOG_TYPES)) is not None:
            kind = msg.get_type()
            source = (int(msg.get_srcSystem()), int(msg.get_srcComponent()))
            decoded += 1
            if kind == "HEARTBEAT":
                if autopilot is None and msg.autopilot != mavlink.MAV_AUTOPILOT_INVALID \
                        and msg.type != mavlink.MAV_TYPE_GCS:
                    autopilot = source
            elif kind == "GLOBAL_POSITION_INT":
                streams[kind].append((source, (msg.time_boot_ms / 1e3, msg.lat / 1e7,
                                               msg.lon / 1e7, msg.alt / 1e3,
                                               msg.relative_alt / 1e3)))
            elif kind == "ATTITUDE_QUATERNION":
                streams[kind].append((source, (msg.time_boot_ms / 1e3, msg.q1, msg.q2,
                                               msg.q3, msg.q4)))
            elif kind == "ATTITUDE":
                streams[kind].append((source, (msg.time_boot_ms / 1e3, msg.roll, msg.pitch,
                                               msg.yaw)))
        offsets: dict[int, list[int]] = getattr(log, "offsets", {})
        last_record = max((found[-1] for found in offsets.values() if found), default=0)
    finally:
        log.close()
    with path.open("rb") as fh:
        fh.seek(last_record)
        truncated = not _tlog_tail_is_whole(fh.read())

    notes: list[str] = []
    if autopilot is None:
        first = [rows[0][0] for rows in streams.values() if rows]
        if first:
            autopilot = first[0]
            notes.append(f"no autopilot HEARTBEAT: took the poses of system {autopilot[0]} "
                         f"component {autopilot[1]}")
    others = sorted({src for rows in streams.values() for src, _ in rows if src != autopilot})
    if others:
        ignored = sum(src != autopilot for rows in streams.values() for src, _ in rows)
        notes.append(f"ignored {ignored} position/attitude messages from other systems "
                     f"(system/component {', '.join(f'{s}/{c}' for s, c in others)})")

    def mine(kind: str) -> list[tuple[float, ...]]:
        return [row for src, row in streams[kind] if src == autopilot]

    positions = _rows(mine("GLOBAL_POSITION_INT"))
    attitudes = _rows(mine("ATTITUDE_QUATERNION"))
    euler = np.asarray(mine("ATTITUDE"), dtype=np.float64).reshape(-1, 4)
    if len(attitudes) == 0 and len(euler):  # ArduPilot streams ATTITUDE only, by default
        attitudes = np.column_stack([euler[:, 0], quaternions_from_euler(
            euler[:, 1], euler[:, 2], euler[:, 3])])
    sender = "" if autopilot is None else f" of system {autopilot[0]} component {autopilot[1]}"
    return _Raw(positions, attitudes, f"GLOBAL_POSITION_INT{sender}",
                f"ATTITUDE_QUATERNION or ATTITUDE{sender}", notes, truncated,
                "" if decoded else "not one valid MAVLink message of those types: not a .tlog?")


# --- .bin (ArduPilot DataFlash) ------------------------------------------------------------

_NUMPY_OF_STRUCT = {"b": "<i1", "B": "<u1", "h": "<i2", "H": "<u2", "i": "<i4", "I": "<u4",
                    "q": "<i8", "Q": "<u8", "f": "<f4", "d": "<f8", "e": "<f2"}


class _DataFlashIndex(DFReader.DFReader_binary):  # type: ignore[misc]
    """pymavlink's DataFlash index (record offsets by type, formats) without its wall clock.

    The clock (GPS week and time) is not needed for TimeUS, and looking for it parses every
    record of a log that has no GPS time.
    """

    def init_clock(self) -> None:
        """Leave the clock unset: records keep their boot-time TimeUS."""
        self.clock = None


def _dataflash_columns(data: NDArray[np.uint8], index: _DataFlashIndex, name: str,
                       columns: tuple[str, ...]) -> dict[str, FloatArray] | None:
    """A record type's columns (format letters' scaling applied, as DFReader does), or None."""
    type_id = index.name_to_id.get(name)
    if type_id is None or type_id not in index.formats:
        return None
    fmt = index.formats[type_id]
    if not set(columns) <= set(fmt.columns) or len(fmt.format) != len(fmt.columns):
        return None
    starts = np.asarray(index.offsets[type_id], dtype=np.int64)
    starts = starts[starts + fmt.len <= len(data)]  # a torn last record is not read
    out: dict[str, FloatArray] = {}
    offset = 3
    for letter, column in zip(fmt.format, fmt.columns, strict=True):
        code, multiplier, _ = DFReader.FORMAT_TO_STRUCT[letter]
        size = struct.calcsize("<" + code)
        if column in columns:
            if code not in _NUMPY_OF_STRUCT:
                return None
            raw = data[starts[:, None] + offset + np.arange(size)]
            values = np.ascontiguousarray(raw).view(_NUMPY_OF_STRUCT[code])[:, 0]
            value = values.astype(np.float64)
            if multiplier is not None:  # DFReader divides by 1e7 rather than times 1e-7
                value = value / round(1.0 / multiplier) if 0.0 < multiplier < 1.0 \
                    else value * multiplier
            out[column] = value
        offset += size
    return out


def _read_bin(path: Path) -> _Raw:
    """POS (or GPS) and ATT records of an ArduPilot DataFlash log."""
    with _quiet(c_stderr=True):  # pymavlink's C indexer prints each bad byte
        index = _DataFlashIndex(str(path))
    try:
        data = np.frombuffer(path.read_bytes(), dtype=np.uint8)
        size = len(data)
        ends = [(found[-1] + index.formats[t].len, t) for t, found in enumerate(index.offsets)
                if found and t in index.formats]
        last_end = max(ends, default=(0, 0))[0]
        tail = data[last_end:].tobytes()
        truncated = last_end > size or (
            0 < len(tail) <= 3 and _DATAFLASH_HEADER.startswith(tail[:2]))  # a torn header
        covered = sum(len(found) * index.formats[t].len for t, found in enumerate(index.offsets)
                      if found and t in index.formats) - max(last_end - size, 0)
        notes: list[str] = []
        if (between := min(last_end, size) - covered) > 0:
            notes.append(f"skipped {between} bytes between records (a corrupt log?)")
        if len(tail) > 3 and tail.startswith(_DATAFLASH_HEADER):
            notes.append(f"stopped at byte {last_end} of {size}, a record of no known format "
                         f"(a corrupt log?): the {len(tail)} bytes after it are not read")
        elif len(tail) > _DATAFLASH_SLACK_BYTES:
            notes.append(f"the last {len(tail)} bytes are not records (ignored)")

        pos = _dataflash_columns(data, index, "POS", ("TimeUS", "Lat", "Lng", "Alt"))
        positions = np.empty((0, 5))
        looked_for_positions = "POS or GPS records"
        if pos is not None and len(pos["TimeUS"]):
            rel = _dataflash_columns(data, index, "POS", ("RelHomeAlt",))
            alt_rel = rel["RelHomeAlt"] if rel is not None \
                else pos["Alt"] - _first_finite(pos["Alt"])
            if rel is None:
                notes.append("POS has no RelHomeAlt: alt_rel_m is above the first POS altitude")
            positions = np.column_stack([pos["TimeUS"] / 1e6, pos["Lat"], pos["Lng"],
                                         pos["Alt"], alt_rel])
        else:
            gps = _dataflash_columns(data, index, "GPS", ("TimeUS", "Lat", "Lng", "Alt"))
            if gps is not None and len(gps["TimeUS"]):
                instance = _dataflash_columns(data, index, "GPS", ("I",))
                keep = np.ones(len(gps["TimeUS"]), dtype=bool) if instance is None \
                    else instance["I"] == 0
                fix = (gps["Lat"] != 0.0) | (gps["Lng"] != 0.0)
                alt0 = _first_finite(gps["Alt"][keep & fix])
                notes.append("no POS records: positions from GPS, alt_rel_m above the first "
                             "GPS fix's altitude")
                positions = np.column_stack([gps["TimeUS"] / 1e6, gps["Lat"], gps["Lng"],
                                             gps["Alt"], gps["Alt"] - alt0])[keep]

        att = _dataflash_columns(data, index, "ATT", ("TimeUS", "Roll", "Pitch", "Yaw"))
        attitudes = np.empty((0, 5))
        if att is not None and len(att["TimeUS"]):
            q = quaternions_from_euler(*(np.radians(att[c]) for c in ("Roll", "Pitch", "Yaw")))
            attitudes = np.column_stack([att["TimeUS"] / 1e6, q])
        return _Raw(positions, attitudes, looked_for_positions, "ATT records (Roll, Pitch, Yaw)",
                    notes, truncated,
                    "" if covered else "not one DataFlash record: not an ArduPilot .bin log?")
    finally:
        index.close()


def _first_finite(values: FloatArray) -> float:
    """The first finite value, nan if there is none."""
    finite = values[np.isfinite(values)]
    return float(finite[0]) if len(finite) else float("nan")


# --- .ulg (PX4 ULog) -----------------------------------------------------------------------

_ULOG_TOPICS = ["vehicle_global_position", "vehicle_local_position", "vehicle_attitude"]


class _EndWatcher(io.BufferedReader):
    """A file pyulog reads: remembers its last read, to tell a clean end from a torn record.

    pyulog stops quietly at a record cut short; at a clean end its last read is a header (3
    bytes) that found nothing.
    """

    last_read: tuple[int | None, int] = (None, 0)

    def read(self, size: int | None = -1, /) -> bytes:
        """Read, noting how much was asked for and got."""
        data = super().read(size)
        self.last_read = (size, len(data))
        return data


def _ulog_topic(ulog: Any, name: str, fields: tuple[str, ...]) -> dict[str, FloatArray] | None:
    """A topic's fields (lowest instance) as float64 arrays, or None without them."""
    found = sorted((d for d in ulog.data_list if d.name == name), key=lambda d: d.multi_id)
    if not found or not set(fields) <= set(found[0].data):
        return None
    return {f: np.asarray(found[0].data[f], dtype=np.float64) for f in fields}


def _px4_reproject(north_m: FloatArray, east_m: FloatArray, ref_lat_deg: FloatArray,
                   ref_lon_deg: FloatArray) -> tuple[FloatArray, FloatArray]:
    """(lat_deg, lon_deg) of local positions as PX4 computes them: azimuthal equidistant on a
    sphere about each row's reference."""
    lat, lon = np.full(len(north_m), np.nan), np.full(len(north_m), np.nan)
    refs = np.column_stack([ref_lat_deg, ref_lon_deg])
    for ref_lat, ref_lon in np.unique(refs, axis=0):
        rows = (refs[:, 0] == ref_lat) & (refs[:, 1] == ref_lon)
        projection = Proj(f"+proj=aeqd +lat_0={float(ref_lat)!r} +lon_0={float(ref_lon)!r} "
                          f"+R={_PX4_EARTH_RADIUS_M!r} +x_0=0 +y_0=0")
        lon[rows], lat[rows] = projection(east_m[rows], north_m[rows], inverse=True)
    return lat, lon


def _read_ulg(path: Path) -> _Raw:
    """vehicle_global_position (or vehicle_local_position) and vehicle_attitude of a ULog."""
    with _quiet():
        fh = _EndWatcher(io.FileIO(path, "rb"))
        try:
            ulog = ULog(fh, _ULOG_TOPICS, disable_str_exceptions=True)
        finally:
            fh.close()
    notes: list[str] = []
    if ulog.file_corruption:
        notes.append("pyulog found corrupt data and skipped it")
    truncated = fh.last_read != (3, 0)

    gpos = _ulog_topic(ulog, "vehicle_global_position", ("timestamp", "lat", "lon", "alt"))
    lpos = _ulog_topic(ulog, "vehicle_local_position", ("timestamp", "x", "y", "z"))
    ref = _ulog_topic(ulog, "vehicle_local_position", ("ref_lat", "ref_lon", "ref_alt"))
    positions = np.empty((0, 5))
    hint = "" if ulog.message_formats else "no message formats: not a PX4 ULog?"
    if gpos is not None:
        t_s = gpos["timestamp"] / 1e6
        origin_alt = None if lpos is None or ref is None \
            else _origin_alt_m(ulog, lpos, ref, t_s)
        if origin_alt is None:
            notes.append("no vehicle_local_position reference altitude: alt_rel_m is above the "
                         "first vehicle_global_position altitude")
            origin_alt = np.full(len(t_s), _first_finite(gpos["alt"]))
        alt_rel = gpos["alt"] - origin_alt  # PX4: alt = ref_alt - z, so this is -z
        positions = np.column_stack([t_s, gpos["lat"], gpos["lon"], gpos["alt"], alt_rel])
    elif lpos is not None and ref is not None:
        usable = (_ulog_valid(ulog, lpos, "xy_valid") & _ulog_valid(ulog, lpos, "z_valid")
                  & _has_reference(ref))
        rows = {k: v[usable] for k, v in (lpos | ref).items()}
        lat, lon = _px4_reproject(rows["x"], rows["y"], rows["ref_lat"], rows["ref_lon"])
        positions = np.column_stack([rows["timestamp"] / 1e6, lat, lon,
                                     rows["ref_alt"] - rows["z"], -rows["z"]])
        valid = f"{int(usable.sum())} of its {len(usable)} samples valid with a reference"
        notes.append(f"no vehicle_global_position: positions from vehicle_local_position "
                     f"({valid})")
        hint = f"vehicle_local_position has {valid}"

    att = _ulog_topic(ulog, "vehicle_attitude", ("timestamp", "q[0]", "q[1]", "q[2]", "q[3]"))
    attitudes = np.empty((0, 5)) if att is None else np.column_stack(
        [att["timestamp"] / 1e6] + [att[f"q[{i}]"] for i in range(4)])
    return _Raw(positions, attitudes,
                "vehicle_global_position, or vehicle_local_position valid with a reference",
                "vehicle_attitude (q)", notes, truncated, hint)


def _has_reference(ref: dict[str, FloatArray]) -> NDArray[np.bool_]:
    """Rows of vehicle_local_position whose reference (origin) is set: finite, in range, not 0."""
    lat, lon = ref["ref_lat"], ref["ref_lon"]
    usable: NDArray[np.bool_] = (
        np.isfinite(lat) & np.isfinite(lon) & np.isfinite(ref["ref_alt"])
        & (np.abs(lat) <= 90.0) & (np.abs(lon) <= 180.0) & ((lat != 0.0) | (lon != 0.0)))
    return usable


def _origin_alt_m(ulog: Any, lpos: dict[str, FloatArray], ref: dict[str, FloatArray],
                  t_s: FloatArray) -> FloatArray | None:
    """The altitude of vehicle_local_position's origin at each t_s (the latest set before it,
    else the first), None if it is never set."""
    valid = _ulog_valid(ulog, lpos, "z_global") & _has_reference(ref)
    if not valid.any():
        return None
    ref_t_s, ref_alt_m = lpos["timestamp"][valid] / 1e6, ref["ref_alt"][valid]
    order = np.argsort(ref_t_s, kind="stable")
    latest = np.searchsorted(ref_t_s[order], t_s, side="right") - 1
    return ref_alt_m[order][np.maximum(latest, 0)]


def _ulog_valid(ulog: Any, topic: dict[str, FloatArray], flag: str) -> NDArray[np.bool_]:
    """A vehicle_local_position validity flag per row (all valid if the log has no such field)."""
    flags = _ulog_topic(ulog, "vehicle_local_position", (flag,))
    return np.ones(len(topic["timestamp"]), dtype=bool) if flags is None else flags[flag] != 0


# --- cleaning and the entry point ----------------------------------------------------------

def _clean(rows: FloatArray, usable: NDArray[np.bool_], what: str,
           notes: list[str]) -> FloatArray:
    """Usable rows sorted by time, the last of each time kept; drops and repeats noted."""
    if (dropped := int(len(rows) - usable.sum())) > 0:
        notes.append(f"dropped {dropped} of {len(rows)} {what} samples (not finite, out of "
                     f"range{' or no fix' if what == 'position' else ''})")
    rows = rows[usable]
    if (jumps := int(np.sum(np.diff(rows[:, 0]) < -_REBOOT_JUMP_S))) > 0:
        notes.append(f"the {what} times jump back by more than {_REBOOT_JUMP_S:g} s {jumps} "
                     "time(s) (an autopilot reboot, or corrupt times?): sorted by time anyway")
    rows = rows[np.argsort(rows[:, 0], kind="stable")]
    last = np.append(rows[1:, 0] != rows[:-1, 0], True) if len(rows) else np.ones(0, bool)
    kept = np.flatnonzero(last)
    its_kept = kept[np.searchsorted(kept, np.arange(len(rows)))]  # the last row of each time
    if (conflicts := int(np.sum(np.any(rows != rows[its_kept], axis=1)))) > 0:  # not copies
        notes.append(f"{conflicts} {what} samples shared a time with a later, different one: "
                     "kept the last")
    return np.ascontiguousarray(rows[last])


def _clean_positions(rows: FloatArray, notes: list[str]) -> FloatArray:
    """Positions with a fix, finite and in range."""
    usable = (np.all(np.isfinite(rows), axis=1) & (np.abs(rows[:, 1]) <= 90.0)
              & (np.abs(rows[:, 2]) <= 180.0) & ((rows[:, 1] != 0.0) | (rows[:, 2] != 0.0)))
    return _clean(rows, usable, "position", notes)


def _clean_attitudes(rows: FloatArray, notes: list[str]) -> FloatArray:
    """Attitudes with a finite, (nearly) unit quaternion, normalized."""
    finite = np.all(np.isfinite(rows), axis=1)
    norm = np.ones(len(rows))
    norm[finite] = np.linalg.norm(rows[finite, 1:], axis=1)
    usable = finite & (np.abs(norm - 1.0) <= _UNIT_TOLERANCE)
    rows = rows.copy()
    rows[usable, 1:] /= norm[usable, None]
    return _clean(rows, usable, "attitude", notes)


_READERS: dict[str, Callable[[Path], _Raw]] = {"tlog": _read_tlog, "bin": _read_bin,
                                               "ulg": _read_ulg}


def read_flight_log(path: Path) -> FlightLog:
    """The poses in a .tlog, ArduPilot DataFlash .bin or PX4 .ulg file (by suffix, any case)."""
    path = Path(path)
    kind = _FORMATS.get(path.suffix.lower())
    if kind is None:
        raise InputError(f"{path}: not a flight log this reads (suffix {path.suffix!r}); "
                         f"accepted: {', '.join(_FORMATS)} (any case)")
    try:
        with path.open("rb") as fh:
            empty = not fh.read(1)
    except OSError as exc:
        raise InputError(f"{path}: cannot read the flight log: {exc.strerror or exc}") from exc
    if empty:
        raise InputError(f"{path}: the flight log is empty")
    try:
        raw = _READERS[kind](path)
    except InputError:
        raise
    except Exception as exc:  # the libraries raise anything on a file that is not the format
        problem = " ".join(str(exc).split()) or "no details"
        raise InputError(f"{path}: not a readable .{kind} flight log "
                         f"({type(exc).__name__}: {problem})") from exc
    notes = list(raw.notes)
    positions = _clean_positions(raw.positions, notes)
    attitudes = _clean_attitudes(raw.attitudes, notes)
    for rows, what, looked_for, found in (
            (positions, "position", raw.looked_for_positions, raw.positions),
            (attitudes, "attitude", raw.looked_for_attitudes, raw.attitudes)):
        if len(rows) == 0:
            detail = f"all {len(found)} found were unusable: not finite, out of range" \
                f"{' or no fix' if what == 'position' else ''}" if len(found) else \
                f"looked for {looked_for}"
            if raw.hint:
                detail += f"; {raw.hint}"
            if raw.truncated:
                detail += "; the file ends mid-record (truncated?)"
            raise InputError(f"{path}: no {what} samples ({detail})")
    warnings = [f"{path.name}: {note}" for note in notes]
    if raw.truncated:
        end_s = max(positions[-1, 0], attitudes[-1, 0])
        warnings.append(f"{path.name}: the file ends mid-record (truncated?): read up to "
                        f"t={end_s:.1f} s")
    return FlightLog(path, kind, positions, attitudes, warnings)
