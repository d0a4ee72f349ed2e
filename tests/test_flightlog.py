"""Flight logs of other tools: poses of known trajectories come back from a .tlog (pymavlink's
encoder), an ArduPilot .bin and a PX4 .ulg (small writers here, after the formats' specs);
foreign senders are ignored, bad samples dropped, torn files read up to the tear, and
garbage, empty or unknown files are an InputError."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from numpy.typing import NDArray
from pymavlink.dialects.v20 import ardupilotmega as mavlink
from pymavlink.quaternion import Quaternion

from companion.errors import InputError
from companion.flightlog import FlightLog, read_flight_log
from tests.logwriters import Built, DataFlash, Tlog, ULog

FloatArray = NDArray[np.float64]
R_PX4_M = 6371000.0


def _check_contract(log: FlightLog) -> None:
    for rows in (log.positions, log.attitudes):
        assert rows.dtype == np.float64 and rows.ndim == 2 and rows.shape[1] == 5
        assert len(rows) >= 1 and np.all(np.diff(rows[:, 0]) > 0.0)
        assert np.all(np.isfinite(rows))
    assert np.allclose(np.linalg.norm(log.attitudes[:, 1:], axis=1), 1.0, atol=1e-12)


def _written_and_read(path: Path, data: bytes) -> FlightLog:
    """The flight log read back from data written at path, its contract checked."""
    path.write_bytes(data)
    log = read_flight_log(path)
    _check_contract(log)
    return log


def _same_rotation(q: FloatArray, expected: FloatArray, atol: float) -> None:
    """Rows of q equal expected's, up to the sign of each quaternion (q and -q are one)."""
    sign = np.where(np.sum(q * expected, axis=1) < 0.0, -1.0, 1.0)
    np.testing.assert_allclose(q * sign[:, None], expected, atol=atol)


def _unit_quaternions(n: int, seed: int) -> FloatArray:
    q = np.random.default_rng(seed).normal(size=(n, 4))
    unit: FloatArray = q / np.linalg.norm(q, axis=1, keepdims=True)
    return unit


# --- .tlog: pymavlink's own encoder, 8-byte big-endian µs timestamps -----------------------

def _heartbeat(kind: int, autopilot: int) -> mavlink.MAVLink_message:
    return mavlink.MAVLink_heartbeat_message(kind, autopilot, 0, 0, 4, 3)


def _tlog_trajectory(n: int, euler: bool = False) -> tuple[Built, FloatArray, FloatArray]:
    """A GCS, a gimbal and an autopilot; the autopilot's poses at 10 Hz (expected rows)."""
    log = Tlog()
    log.add(255, 190, _heartbeat(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID))
    log.add(1, 154, _heartbeat(mavlink.MAV_TYPE_GIMBAL, mavlink.MAV_AUTOPILOT_INVALID))
    log.add(1, 1, _heartbeat(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA))
    quaternions = _unit_quaternions(n, seed=3)
    positions, attitudes = [], []
    for k in range(n):
        t_ms = 5000 + 100 * k
        lat, lon, alt, rel = 473977420 + 37 * k, 85455940 - 11 * k, 488000 + 250 * k, 250 * k
        log.add(1, 1, mavlink.MAVLink_global_position_int_message(
            t_ms, lat, lon, alt, rel, 100, -20, 0, 9000))
        positions.append((t_ms / 1e3, lat / 1e7, lon / 1e7, alt / 1e3, rel / 1e3))
        q = quaternions[k].astype(np.float32).astype(np.float64)
        if euler:
            roll, pitch, yaw = (float(v) for v in Quaternion(q).euler)
            log.add(1, 1, mavlink.MAVLink_attitude_message(t_ms + 3, roll, pitch, yaw, 0, 0, 0))
            q = np.asarray(Quaternion([np.float32(roll), np.float32(pitch),
                                       np.float32(yaw)]).q, dtype=np.float64)
        else:
            log.add(1, 1, mavlink.MAVLink_attitude_quaternion_message(
                t_ms + 3, *q.tolist(), 0, 0, 0, [0.0] * 4))
        attitudes.append(((t_ms + 3) / 1e3, *(q / np.linalg.norm(q))))
        if k % 5 == 0:  # the GCS (or a second vehicle) says something else entirely
            log.add(255, 190, mavlink.MAVLink_global_position_int_message(
                t_ms + 1, -335000000, 1510000000, 0, 0, 0, 0, 0, 0))
            log.add(255, 190, mavlink.MAVLink_attitude_quaternion_message(
                t_ms + 1, 0.0, 1.0, 0.0, 0.0, 0, 0, 0, [0.0] * 4))
        if k % 7 == 0:
            log.add(1, 1, mavlink.MAVLink_vfr_hud_message(5.0, 5.0, 90, 50, 4.0, 0.1))
    return log.built(), np.asarray(positions), np.asarray(attitudes)


def test_tlog_poses_of_the_autopilot_come_back(tmp_path: Path) -> None:
    (data, _), positions, attitudes = _tlog_trajectory(40)
    path = tmp_path / "flight.TLOG"
    log = _written_and_read(path, data)
    assert log.format == "tlog" and log.path == path
    np.testing.assert_allclose(log.positions, positions, rtol=0.0, atol=1e-9)
    np.testing.assert_allclose(log.attitudes, attitudes, rtol=0.0, atol=1e-12)
    assert any("ignored 16 position/attitude messages" in w and "255/190" in w
               for w in log.warnings)


def test_tlog_attitudes_from_euler_angles_without_attitude_quaternion(tmp_path: Path) -> None:
    (data, _), positions, attitudes = _tlog_trajectory(30, euler=True)
    path = tmp_path / "flight.tlog"
    log = _written_and_read(path, data)
    np.testing.assert_allclose(log.positions, positions, atol=1e-9)
    np.testing.assert_allclose(log.attitudes[:, 0], attitudes[:, 0])
    _same_rotation(log.attitudes[:, 1:], attitudes[:, 1:], atol=1e-6)
    assert [w for w in log.warnings if "ignored" not in w] == []


def test_tlog_bad_samples_are_dropped_and_a_repeated_time_keeps_the_last(tmp_path: Path) -> None:
    log = Tlog()
    log.add(1, 1, _heartbeat(mavlink.MAV_TYPE_FIXED_WING, mavlink.MAV_AUTOPILOT_PX4))
    for t_ms, lat in ((1000, 0), (1100, 0), (1200, 473977420), (1300, 473977430),
                      (1300, 473977440), (1400, 473977450)):  # no fix yet, then a repeat
        log.add(1, 1, mavlink.MAVLink_global_position_int_message(
            t_ms, lat, 0 if lat == 0 else 85455940, 488000, 0, 0, 0, 0, 0))
    for t_ms, q in ((1000, (math.nan, 0.0, 0.0, 0.0)), (1100, (0.0, 0.0, 0.0, 0.0)),
                    (1200, (1.0, 0.0, 0.0, 0.0)), (1300, (0.0, 0.0, 0.0, 1.0005)),
                    (1300, (0.0, 0.0, 0.0, 1.0005))):  # a copy, as a second link gives
        log.add(1, 1, mavlink.MAVLink_attitude_quaternion_message(
            t_ms, *q, 0, 0, 0, [0.0] * 4))
    path = tmp_path / "flight.tlog"
    path.write_bytes(log.built()[0])
    result = read_flight_log(path)
    _check_contract(result)
    np.testing.assert_allclose(result.positions[:, 0], [1.2, 1.3, 1.4])
    np.testing.assert_allclose(result.positions[:, 1], [47.397742, 47.397744, 47.397745])
    np.testing.assert_allclose(result.attitudes[:, 1:], [[1, 0, 0, 0], [0, 0, 0, 1]])
    text = "\n".join(result.warnings)
    assert "flight.tlog: dropped 2 of 6 position samples" in text
    assert "dropped 2 of 5 attitude samples" in text
    assert "1 position samples shared a time with a later, different one: kept the last" in text
    assert "attitude samples shared" not in text  # the repeated attitude was a copy


def test_tlog_without_an_autopilot_says_what_it_looked_for(tmp_path: Path) -> None:
    log = Tlog()
    log.add(1, 1, _heartbeat(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA))
    log.add(1, 1, mavlink.MAVLink_attitude_message(1000, 0.1, 0.2, 0.3, 0, 0, 0))
    log.add(2, 1, mavlink.MAVLink_global_position_int_message(
        1000, 473977420, 85455940, 488000, 0, 0, 0, 0, 0))  # another vehicle's
    path = tmp_path / "flight.tlog"
    path.write_bytes(log.built()[0])
    with pytest.raises(InputError, match=r"flight\.tlog: no position samples \(looked for "
                                         r"GLOBAL_POSITION_INT of system 1 component 1\)"):
        read_flight_log(path)


# --- .bin: ArduPilot DataFlash (FMT records, then records of the formats they define) ------

def _bin_trajectory(n: int, att_format: str) -> tuple[Built, FloatArray, FloatArray]:
    """POS at 10 Hz and ATT at 20 Hz (ATT in centidegrees or float degrees), plus noise."""
    log = DataFlash()
    log.define(129, "PARM", "QNf", "TimeUS,Name,Value")
    log.define(64, "POS", "QLLfff", "TimeUS,Lat,Lng,Alt,RelHomeAlt,RelOriginAlt")
    log.define(65, "ATT", att_format, "TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw")
    log.add("PARM", 1000, b"LOG_BITMASK", 176126.0)
    positions, attitudes = [], []
    for k in range(2 * n):
        t_us = 3_000_000 + 50_000 * k + 7
        roll, pitch, yaw = 15.0 * math.sin(k / 5.0), -8.0 + 0.37 * k, (23.0 * k) % 360.0
        if att_format.endswith("C"):  # roll, pitch int16 and yaw uint16, all in centidegrees
            raw = (round(roll * 100), round(pitch * 100), round(yaw * 100))
            roll, pitch, yaw = raw[0] / 100, raw[1] / 100, raw[2] / 100
            log.add("ATT", t_us, 0, raw[0], 0, raw[1], 0, raw[2])
        else:
            raw32 = tuple(float(np.float32(v)) for v in (roll, pitch, yaw))
            roll, pitch, yaw = raw32
            log.add("ATT", t_us, 0.0, roll, 0.0, pitch, 0.0, yaw)
        attitudes.append((t_us / 1e6, *Quaternion(np.radians([roll, pitch, yaw])).q))
        if k % 2 == 0:
            lat, lng = -353632620 + 91 * k, 1491652370 + 45 * k
            alt, rel = float(np.float32(584.25 + 0.5 * k)), float(np.float32(0.5 * k))
            log.add("POS", t_us + 1000, lat, lng, alt, rel, rel + 0.1)
            positions.append(((t_us + 1000) / 1e6, lat / 1e7, lng / 1e7, alt, rel))
    return log.built(), np.asarray(positions), np.asarray(attitudes)


@pytest.mark.parametrize("att_format", ["QccccCC", "Qffffff"])
def test_bin_poses_come_back_in_degrees_and_metres(tmp_path: Path, att_format: str) -> None:
    (data, _), positions, attitudes = _bin_trajectory(30, att_format)
    path = tmp_path / "00000042.BIN"
    log = _written_and_read(path, data)
    assert log.format == "bin" and log.warnings == []
    np.testing.assert_allclose(log.positions, positions, rtol=0.0, atol=1e-9)
    np.testing.assert_allclose(log.attitudes[:, 0], attitudes[:, 0])
    _same_rotation(log.attitudes[:, 1:], attitudes[:, 1:], atol=1e-6)


def test_bin_without_pos_takes_gps_instance_0(tmp_path: Path) -> None:
    log = DataFlash()
    log.define(66, "GPS", "QBBIHBcLLeffffB",
               "TimeUS,I,Status,GMS,GWk,NSats,HDop,Lat,Lng,Alt,Spd,GCrs,VZ,Yaw,U")
    log.define(65, "ATT", "QccccCC", "TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw")
    expected = []
    for k in range(12):
        t_us = 10_000_000 + 200_000 * k
        fix = k >= 2
        lat, lng, alt_cm = (515000000 + 10 * k, -1000000 - 5 * k, 4000 + 30 * k) if fix \
            else (0, 0, 0)
        log.add("GPS", t_us, 0, 3 if fix else 1, 1000 * k, 2300 if fix else 0, 9, 80,
                lat, lng, alt_cm, 0.0, 0.0, 0.0, 0.0, 1)
        log.add("GPS", t_us + 10, 1, 3, 1000 * k, 2300, 9, 80, lat + 500, lng, alt_cm + 900,
                0.0, 0.0, 0.0, 0.0, 1)  # a second receiver: not used
        log.add("ATT", t_us + 20, 0, 0, 0, 0, 0, 9000)
        if fix:
            expected.append((t_us / 1e6, lat / 1e7, lng / 1e7, alt_cm / 100,
                             (alt_cm - 4060) / 100))
    path = tmp_path / "gps.bin"
    path.write_bytes(log.built()[0])
    result = read_flight_log(path)
    _check_contract(result)
    np.testing.assert_allclose(result.positions, np.asarray(expected), atol=1e-9)
    _same_rotation(result.attitudes[:, 1:], np.tile([math.sqrt(0.5), 0, 0, math.sqrt(0.5)],
                                                    (12, 1)), atol=1e-12)
    text = "\n".join(result.warnings)
    assert "positions from GPS" in text and "dropped 2 of 12 position samples" in text


def test_bin_without_att_says_what_it_looked_for(tmp_path: Path) -> None:
    (data, _), _, _ = _bin_trajectory(5, "QccccCC")
    path = tmp_path / "no-att.bin"
    path.write_bytes(data.replace(b"ATT\x00", b"XYZ\x00"))
    with pytest.raises(InputError, match=r"no-att\.bin: no attitude samples \(looked for ATT"):
        read_flight_log(path)


# --- .ulg: PX4 ULog (header, definitions F/I, then A subscriptions and D data) -------------

_GPOS = "uint64_t timestamp;double lat;double lon;float alt;"
_LPOS = ("uint64_t timestamp;double ref_lat;double ref_lon;float x;float y;float z;"
         "float ref_alt;bool xy_valid;bool z_valid;")
_ATT = "uint64_t timestamp;float[4] q;"
_OTHER = "uint64_t timestamp;float voltage_v;uint8_t cell_count;"


def _ulog_flight(n: int, with_global: bool) -> tuple[Built, FloatArray, FloatArray]:
    """Attitude at 50 Hz, local position at 10 Hz and global position at 5 Hz (expected)."""
    topics = {"battery_status": _OTHER, "vehicle_attitude": _ATT,
              "vehicle_local_position": _LPOS}
    if with_global:
        topics["vehicle_global_position"] = _GPOS
    log = ULog(topics)
    ref_lat, ref_lon, ref_alt = 47.3977418, 8.5455939, float(np.float32(487.95694))
    quaternions = _unit_quaternions(n * 5, seed=7).astype(np.float32)
    positions, attitudes = [], []
    for k in range(n * 5):
        t_us = 113_000_000 + 20_000 * k
        log.add("vehicle_attitude", t_us, *quaternions[k].tolist())
        q = quaternions[k].astype(np.float64)
        attitudes.append((t_us / 1e6, *(q / np.linalg.norm(q))))
        if k % 5 == 0:
            log.add("battery_status", t_us + 1, 15.8, 4)
        if k % 5 == 1:  # 10 Hz
            j = k // 5
            valid = j >= 3
            north, east = float(np.float32(40.0 * j)), float(np.float32(-25.0 * j + 3.0))
            down = float(np.float32(-1.5 * j))
            log.add("vehicle_local_position", t_us, ref_lat if valid else 0.0,
                    ref_lon if valid else 0.0, north, east, down, ref_alt if valid else 0.0,
                    valid, True)
            if valid and not with_global:
                positions.append((t_us / 1e6, north, east, ref_alt - down, -down))
        if k % 10 == 3 and with_global:  # 5 Hz, between local positions
            lat, lon = 47.39 + 1e-6 * k, 8.54 - 2e-6 * k
            alt = float(np.float32(ref_alt + 1.5 * (k - 1) / 5))  # PX4: ref_alt - z
            log.add("vehicle_global_position", t_us, lat, lon, alt)
            positions.append((t_us / 1e6, lat, lon, alt, alt - ref_alt))
    return log.built(), np.asarray(positions), np.asarray(attitudes)


def test_ulg_global_position_with_height_from_local_position(tmp_path: Path) -> None:
    (data, _), positions, attitudes = _ulog_flight(20, with_global=True)
    path = tmp_path / "log_12.ulg"
    log = _written_and_read(path, data)
    assert log.format == "ulg" and log.warnings == []
    np.testing.assert_allclose(log.positions, positions, rtol=0.0, atol=1e-9)
    np.testing.assert_allclose(log.attitudes, attitudes, rtol=0.0, atol=1e-12)


def test_ulg_local_position_about_its_reference_without_global(tmp_path: Path) -> None:
    (data, _), local, _ = _ulog_flight(20, with_global=False)
    path = tmp_path / "log_13.ULG"
    log = _written_and_read(path, data)
    p = log.positions
    np.testing.assert_allclose(p[:, [0, 3, 4]], local[:, [0, 3, 4]], atol=1e-9)
    # Azimuthal equidistant on PX4's sphere: distance and bearing from the reference are kept.
    lat0, lon0 = math.radians(47.3977418), math.radians(8.5455939)
    lat, dlon = np.radians(p[:, 1]), np.radians(p[:, 2]) - lon0
    arc = np.arccos(np.clip(math.sin(lat0) * np.sin(lat) + math.cos(lat0) * np.cos(lat)
                            * np.cos(dlon), -1.0, 1.0))
    bearing = np.arctan2(np.sin(dlon) * np.cos(lat), math.cos(lat0) * np.sin(lat)
                         - math.sin(lat0) * np.cos(lat) * np.cos(dlon))
    np.testing.assert_allclose(arc * R_PX4_M, np.hypot(local[:, 1], local[:, 2]), atol=1e-3)
    np.testing.assert_allclose(bearing, np.arctan2(local[:, 2], local[:, 1]), atol=1e-8)
    assert any("positions from vehicle_local_position (17 of its 20 samples valid" in w
               for w in log.warnings)


# --- torn files: what is there, and a warning --------------------------------------------

def _built(kind: str) -> Built:
    if kind == "tlog":
        return _tlog_trajectory(40)[0]
    if kind == "bin":
        return _bin_trajectory(30, "QccccCC")[0]
    return _ulog_flight(20, with_global=True)[0]


@pytest.mark.parametrize("kind", ["tlog", "bin", "ulg"])
def test_a_file_cut_at_any_byte_gives_the_poses_before_the_cut(tmp_path: Path,
                                                                 kind: str) -> None:
    data, ends = _built(kind)
    whole_path = tmp_path / f"whole.{kind}"
    whole_path.write_bytes(data)
    whole = read_flight_log(whole_path)
    records = len(ends)
    for k in (records // 2, 2 * records // 3, 3 * records // 4, records - 3):
        size = ends[k] - ends[k - 1]
        for into in (1, 2, 3, size // 2, size - 1):  # a torn header, and a torn body
            path = tmp_path / f"cut.{kind}"
            path.write_bytes(data[: ends[k - 1] + into])
            log = read_flight_log(path)
            _check_contract(log)
            n, m = len(log.positions), len(log.attitudes)
            np.testing.assert_array_equal(log.positions, whole.positions[:n])
            np.testing.assert_array_equal(log.attitudes, whole.attitudes[:m])
            torn = [w for w in log.warnings if "the file ends mid-record (truncated?)" in w]
            end_s = max(log.positions[-1, 0], log.attitudes[-1, 0])
            assert torn == [f"cut.{kind}: the file ends mid-record (truncated?): read up to "
                            f"t={end_s:.1f} s"], (k, into, log.warnings)
        path.write_bytes(data[: ends[k]])  # cut at a record's end: a shorter, whole log
        assert not any("truncated" in w for w in read_flight_log(path).warnings)


# --- not a flight log ----------------------------------------------------------------------

@pytest.mark.parametrize("suffix", [".tlog", ".bin", ".ulg"])
def test_garbage_empty_and_foreign_files_are_input_errors(tmp_path: Path, suffix: str) -> None:
    rng = np.random.default_rng(11)
    path = tmp_path / f"noise{suffix}"
    for size in (1, 7, 100, 5000, 70_000):
        path.write_bytes(rng.bytes(size))
        with pytest.raises(InputError, match=rf"noise\{suffix}: "):
            read_flight_log(path)
    path.write_bytes(b"")
    with pytest.raises(InputError, match=r"noise.*: the flight log is empty"):
        read_flight_log(path)
    for kind in ("tlog", "bin", "ulg"):  # another format's bytes under this suffix
        if f".{kind}" != suffix:
            path.write_bytes(_built(kind)[0])
            with pytest.raises(InputError, match=r"no (position|attitude) samples|not a "):
                read_flight_log(path)
    ulog_then_noise = _built("ulg")[0][:16] + rng.bytes(3000)
    path.write_bytes(ulog_then_noise)
    with pytest.raises(InputError):
        read_flight_log(path)


@pytest.mark.parametrize("name, message", [
    ("flight.csv", r"flight\.csv: not a flight log this reads \(suffix '\.csv'\); "
                   r"accepted: \.tlog, \.bin, \.ulg \(any case\)$"),
    ("missing.tlog", r"missing\.tlog: cannot read the flight log: No such file"),
    ("folder.ulg", r"folder\.ulg: cannot read the flight log: Is a directory"),
])
def test_unknown_missing_and_unreadable_paths_are_input_errors(tmp_path: Path, name: str,
                                                               message: str) -> None:
    (tmp_path / "flight.csv").write_text("t_s,lat,lon\n")
    (tmp_path / "folder.ulg").mkdir()
    with pytest.raises(InputError, match=message):
        read_flight_log(tmp_path / name)


def test_ulg_without_a_valid_reference_has_no_positions(tmp_path: Path) -> None:
    log = ULog({"vehicle_attitude": _ATT, "vehicle_local_position": _LPOS})
    for k in range(20):  # on the bench: no GPS, so no reference for the local position
        log.add("vehicle_attitude", 1_000_000 + 10_000 * k, 1.0, 0.0, 0.0, 0.0)
        log.add("vehicle_local_position", 1_000_000 + 10_000 * k, 0.0, 0.0, 0.0, 0.0, -0.1,
                0.0, False, True)
    path = tmp_path / "bench.ulg"
    path.write_bytes(log.built()[0])
    with pytest.raises(InputError, match=r"bench\.ulg: no position samples \(looked for "
                                         r"vehicle_global_position.*; vehicle_local_position "
                                         r"has 0 of its 20 samples valid with a reference\)"):
        read_flight_log(path)
