"""Bad telemetry never gets in: GPS glitches refused by the position gate, malformed values
(latitude 200, NaN attitude, a quaternion that is not a rotation) refused and counted; a frozen
frame is a blind step; a checkpoint carries the estimate over a restart."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from companion.config import load_config
from companion.errors import ConfigError
from companion.pipeline import Pipeline, camera_model
from companion.record.checkpoint import CHECKPOINT_NAME, latest_checkpoint, save_checkpoint
from companion.vehicle.mavsdk_link import FlightMode, Status
from companion.vehicle.plausibility import PositionGate
from companion.vehicle.view import VehicleView
from companion.vision.projection import GeoPose

ROOT = Path(__file__).resolve().parent.parent
LAT0, LON0 = 47.397742, 8.545594
M_PER_DEG = 111_320.0


def _latlon(north_m: float, east_m: float) -> tuple[float, float]:
    return (LAT0 + north_m / M_PER_DEG,
            LON0 + east_m / (M_PER_DEG * math.cos(math.radians(LAT0))))


def _flight(gate: PositionGate, glitch: tuple[float, float, float], speed_m_s: float = 5.0,
            seconds: float = 30.0) -> list[bool]:
    """10 Hz positions for seconds of a vehicle flying east and turning north at 10 s, with a
    jump of glitch = (north_m, start_s, duration_s) added; each sample's verdict."""
    verdicts = []
    for k in range(round(10 * seconds)):
        t_s = 0.1 * k
        if t_s < 10.0:
            north, east, vel = 0.0, speed_m_s * t_s, (0.0, speed_m_s)
        else:
            north, east, vel = speed_m_s * (t_s - 10.0), 10.0 * speed_m_s, (speed_m_s, 0.0)
        jump_m, start_s, duration_s = glitch
        if start_s <= t_s < start_s + duration_s:
            north += jump_m
        verdicts.append(gate.check(t_s, *_latlon(north, east), vel))
    return verdicts


def test_a_20_m_jump_for_3_s_is_refused_and_the_return_accepted() -> None:
    gate = PositionGate(gate_m=8.0, accept_after_s=10.0)
    verdicts = np.array(_flight(gate, (20.0, 8.0, 3.0)))  # across the turn at 10 s
    t_s = 0.1 * np.arange(verdicts.size)
    glitch = (t_s >= 8.0 - 1e-9) & (t_s < 11.0 - 1e-9)
    assert not verdicts[glitch].any() and verdicts[~glitch].all()
    assert gate.refused == int(glitch.sum()) and gate.accepted_jumps == 0
    # judged at any later time, by the samples around it: from the last plausible one (7.9 s)
    # to the first plausible again (11.0 s)
    assert [gate.refused_around(t) for t in (7.9, 7.95, 9.0, 10.99, 11.0, 12.0)] == [
        False, True, True, True, False, False]


def test_a_glitch_still_refused_covers_every_time_since_its_start() -> None:
    gate = PositionGate(gate_m=8.0, accept_after_s=10.0)
    _flight(gate, (20.0, 8.0, 30.0), seconds=9.0)
    assert gate.refusing_since_s is not None
    assert not gate.refused_around(7.5) and gate.refused_around(8.5) and gate.refused_around(20.0)
    gate.reset()
    assert not gate.refused_around(8.5)


def test_a_clean_flight_is_never_refused_and_a_jump_that_stays_is_believed() -> None:
    gate = PositionGate()
    assert all(_flight(gate, (0.0, 0.0, 0.0), speed_m_s=12.0))
    gate = PositionGate(gate_m=8.0, accept_after_s=10.0)
    verdicts = np.array(_flight(gate, (30.0, 5.0, 100.0)))
    first_back = 50 + 100  # refused from 5 s, believed 10 s later
    assert not verdicts[50:first_back].any() and verdicts[first_back:].all()
    assert gate.accepted_jumps == 1
    with pytest.raises(ConfigError, match=r"pose\.glitch_gate_m"):
        PositionGate(gate_m=0.0)


def test_the_view_refuses_and_counts_malformed_and_implausible_telemetry() -> None:
    view = VehicleView(lambda: 100.0)
    view.on_position(10.0, LAT0, LON0, 500.0, 8.0, (0.0, 0.0))
    view.on_position(10.1, 200.0, LON0, 500.0, 8.0, (0.0, 0.0))  # latitude 200
    view.on_position(10.2, LAT0, math.nan, 500.0, 8.0, (0.0, 0.0))
    view.on_position(10.3, 0.0, 0.0, 500.0, 8.0, (0.0, 0.0))  # no fix
    view.on_position(10.4, *_latlon(20.0, 0.0), 500.0, 8.0, (0.0, 0.0))  # a 20 m jump
    view.on_attitude(10.0, (1.0, 0.0, 0.0, 0.0))
    view.on_attitude(10.1, (math.nan, 0.0, 0.0, 0.0))
    view.on_attitude(10.2, (2.0, 0.0, 0.0, 0.0))  # not a rotation
    view.on_local_position(10.0, math.inf, 0.0, 0.0)
    assert view.rejected == {"position": 3, "local_position": 1, "attitude": 2,
                             "implausible": 1}
    assert view.poses.position_count == 1 and view.poses.attitude_count == 1
    assert view.gate.refusing_since_s == pytest.approx(10.4)


def test_the_view_signals_a_change_of_mode_or_arming_and_nothing_else() -> None:
    view = VehicleView(lambda: 100.0)
    calls: list[Status | None] = []
    view.on_mode_change = lambda: calls.append(view.status)
    status = Status(FlightMode.OFFBOARD, armed=True, in_air=True, position_ok=True,
                    armable=True, battery_percent=80.0)
    changes = [status, dataclasses.replace(status, battery_percent=79.0),
               dataclasses.replace(status, in_air=False, position_ok=False),
               dataclasses.replace(status, flight_mode=FlightMode.POSCTL),
               dataclasses.replace(status, flight_mode=FlightMode.POSCTL, armed=False)]
    for s in changes:
        view.on_status(s)
    assert calls == [changes[0], changes[3], changes[4]]


def _pipeline() -> Pipeline:
    config = load_config(ROOT / "sitl" / "service.toml")
    return Pipeline(config, camera_model(config.camera))


def test_a_frozen_frame_is_a_blind_step() -> None:
    pipeline = _pipeline()
    area = pipeline.config.search.area_latlon.mean(axis=0)
    image = np.random.default_rng(0).integers(0, 255, (480, 640), dtype=np.uint8)
    pose = GeoPose(10.0, float(area[0]), float(area[1]), 500.0, 8.0, (1.0, 0.0, 0.0, 0.0))
    assert pipeline.step(image, pose).blind is None
    again = GeoPose(10.5, pose.lat_deg, pose.lon_deg, pose.alt_amsl_m, pose.height_agl_m,
                    pose.q_wxyz)
    assert pipeline.step(image.copy(), again).blind == "frozen frame"
    image[0, 0] ^= 1  # one pixel differs: a new picture
    later = GeoPose(11.0, pose.lat_deg, pose.lon_deg, pose.alt_amsl_m, pose.height_agl_m,
                    pose.q_wxyz)
    assert pipeline.step(image, later).blind is None


def test_a_checkpoint_carries_the_estimate_over_a_restart(tmp_path: Path) -> None:
    first = _pipeline()
    for k in range(5):
        first.blind(10.0 + k, "no frame")
    old = tmp_path / "run-20261122T080000Z"
    old.mkdir()
    save_checkpoint(old, first.checkpoint())
    new = tmp_path / "run-20261122T080500Z"
    new.mkdir()
    found = latest_checkpoint(tmp_path, exclude=new, max_age_s=600.0,
                              now_wall_s=(old / CHECKPOINT_NAME).stat().st_mtime + 1.0)
    assert found is not None and found[0] == old / CHECKPOINT_NAME
    second = _pipeline()
    assert second.restore(found[1]) is None
    assert second.state is not None and first.state is not None
    assert second.state.t_s == first.state.t_s
    assert second.blind(15.0, "no frame").t_s == 15.0  # its clock carries on
    assert latest_checkpoint(tmp_path, exclude=new, max_age_s=600.0,
                             now_wall_s=(old / CHECKPOINT_NAME).stat().st_mtime + 601.0) is None
    other = dict(found[1], area_latlon=[[0.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    assert _pipeline().restore(other) == "is of another search area"
    assert _pipeline().restore(dict(found[1], state="a string")) == "holds no estimator state"
    tracks = first.state.tracks
    older = first.state._replace(tracks=tracks._replace(gp_mu=tracks.gp_mu[:, :-1]))
    kept = second.state
    assert second.restore(dict(found[1], state=older)) == (
        "was written by another version of the estimator")
    assert second.state is kept
    (old / CHECKPOINT_NAME).write_bytes(b"torn")
    said: list[str] = []
    assert latest_checkpoint(tmp_path, exclude=new, max_age_s=600.0,
                             now_wall_s=(old / CHECKPOINT_NAME).stat().st_mtime,
                             log=said.append) is None
    assert said and "is unreadable" in said[0]
