"""What the service takes from the autopilot's own figures: pose uncertainty, height, firmware."""

from __future__ import annotations

import math
from dataclasses import astuple

import numpy as np
import pytest

from companion.config import PoseConfig
from companion.drive import frame_observation, pose_sigma
from companion.vehicle.events import describe_event
from companion.vehicle.mavsdk_link import FlightMode, Status
from companion.vehicle.view import ACCURACY_FRESH_S, Accuracy, VehicleView, height_agl_m


class Clock:
    """A receive clock the test moves by hand."""

    def __init__(self) -> None:
        self.now_s = 100.0

    def __call__(self) -> float:
        return self.now_s


FLOORS = PoseConfig(horizontal_std_m=0.1, vertical_std_m=0.1, attitude_std_deg=0.5,
                    heading_std_deg=2.0, camera_rest_height_m=0.0, max_gap_s=0.5,
                    glitch_gate_m=8.0, glitch_accept_after_s=10.0)


def test_the_best_fresh_source_gives_each_figure() -> None:
    clock = Clock()
    view = VehicleView(clock)
    assert all(math.isnan(v) for v in astuple(view.accuracy()))
    view.on_accuracy("gps", 0.8, 1.2)
    view.on_accuracy("estimator", 0.3, 0.6)
    view.on_accuracy("odometry", 0.2, math.nan, 1.5, 4.0)  # no vertical figure: the next one's
    assert view.accuracy() == Accuracy(0.2, 0.6, 1.5, 4.0)
    clock.now_s += ACCURACY_FRESH_S + 1.0
    view.on_accuracy("gps", 0.8, 1.2)  # only GPS is fresh now
    assert view.accuracy() == Accuracy(0.8, 1.2, math.nan, math.nan)
    view.on_accuracy("gps", -1.0, 1.0)  # refused: a negative sigma
    view.on_accuracy("magic", 0.01, 0.01)  # refused: an unknown source
    assert view.accuracy() == Accuracy(0.8, 1.2, math.nan, math.nan)


def test_the_floors_hold_under_the_autopilots_figures() -> None:
    sigma = pose_sigma(FLOORS, Accuracy(0.05, 0.4, math.nan, 6.0))
    assert (sigma.horizontal_m, sigma.vertical_m, sigma.attitude_deg, sigma.heading_deg) == (
        0.1, 0.4, 0.5, 6.0)


def test_height_from_the_rangefinder_then_the_terrain_then_the_altitude() -> None:
    view = VehicleView(Clock())
    assert view.height_at(10.0, 7.75, 1.0, 0.25) == (8.0, "altitude")
    assert view.height_at(10.0, -0.3, 1.0, 0.1) == (0.0, "altitude")  # never underground
    view.on_terrain_height(10.1, 7.9)
    assert view.height_at(10.0, 7.75, 1.0, 0.25) == (7.9, "terrain")
    view.on_distance(10.05, 8.2, 0.1, 40.0)
    view.on_distance(10.0, 55.0, 0.1, 40.0)  # out of its range: says nothing
    height_m, source = view.height_at(10.0, 7.75, math.cos(math.radians(10.0)), 0.25)
    assert source == "rangefinder" and height_m == pytest.approx(8.2 * math.cos(math.radians(10)))
    assert view.height_at(11.0, 7.75, 1.0, 0.25) == (8.0, "altitude")  # too far in time


def test_resting_height_and_firmware() -> None:
    assert height_agl_m(8.0, -0.25) == 7.75 and height_agl_m(0.1, -0.25) == 0.0
    view = VehicleView(Clock())
    view.on_heartbeat(3)
    assert view.ardupilot
    view.on_heartbeat(12)
    assert not view.ardupilot


def test_frames_after_landing_are_blind_and_before_take_off_are_judged_by_height() -> None:
    """Once the landed state has said "in the air", its "on the ground" makes every frame
    blind, whatever height the altitude says (a baro's metre of drift on the ground)."""
    view = VehicleView(Clock())
    image = np.zeros((4, 4), dtype=np.uint8)
    for k in range(40):
        view.on_position(10.0 + 0.1 * k, 47.0, 8.0, 501.0, 1.02)
        view.on_attitude(10.0 + 0.1 * k, (1.0, 0.0, 0.0, 0.0))

    def status(in_air: bool) -> Status:
        return Status(FlightMode.LAND, True, in_air, True, True, 80.0)

    view.on_status(status(False))  # before any flight: the pose decides, as it did
    before = frame_observation(view, 12.0, image, FLOORS)
    assert before.blind is None and before.pose is not None
    view.on_status(status(True))
    assert frame_observation(view, 12.5, image, FLOORS).blind is None
    view.on_status(status(False))
    after = frame_observation(view, 13.0, image, FLOORS)
    assert after.blind == "on the ground" and after.pose is None


def test_px4_events_are_named_or_given_by_id() -> None:
    assert describe_event(0x0187D640) == (
        "autopilot: preflight: horizontal velocity unstable (arming refused for now)")
    assert describe_event(0x01ABCDEF) == "autopilot event 0x01abcdef"
