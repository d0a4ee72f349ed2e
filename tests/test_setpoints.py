"""Setpoint geometry: the tilt of a quaternion, the safety limits in the local frame, the carrot
moving at the search speed and a lawn mower's waypoint counted once reached; the flight-mode
names the mission gets."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion import mission as ms
from companion.config import SafetyConfig
from companion.geo import LocalNed
from companion.plan.gate import GateAction, GateLimits, Setpoint, gate
from companion.plan.planners import LawnMower
from companion.plan.setpoints import (
    REACHED_M,
    Carrot,
    gate_limits,
    hold_setpoint,
    ramp,
    tilt_cos,
)
from companion.plan.world import World
from companion.sat.mixture import Mixture
from companion.sat.tracks import Tracks
from companion.vehicle.mavsdk_link import FlightMode, Status
from companion.vehicle.modes import mission_mode

WORLD = World(100.0, 100.0)


def test_tilt_cos_is_one_level_and_the_cosine_of_a_roll() -> None:
    assert tilt_cos((1.0, 0.0, 0.0, 0.0)) == 1.0
    half = math.radians(30.0) / 2.0
    assert tilt_cos((math.cos(half), math.sin(half), 0.0, 0.0)) == pytest.approx(
        math.cos(math.radians(30.0)))


def test_gate_limits_count_altitudes_above_home() -> None:
    origin = LocalNed(47.0, 8.0, 500.0)
    fence = np.array([[47.0, 8.0], [47.001, 8.0], [47.001, 8.001], [47.0, 8.001]])
    limits = gate_limits(SafetyConfig(fence, 2.0, 30.0, 5.0, 2.0), origin, home_amsl_m=510.0)
    assert (limits.min_alt_m, limits.max_alt_m) == pytest.approx((12.0, 40.0))
    assert np.allclose(limits.fence_ne_m[0], [0.0, 0.0], atol=1e-6)
    assert limits.fence_ne_m[1, 0] == pytest.approx(111.2, abs=0.5)


def test_hold_is_where_the_vehicle_is() -> None:
    sp = hold_setpoint(np.array([1.0, 2.0, -3.0]), 90.0)
    assert (sp.north_m, sp.east_m, sp.down_m, sp.yaw_deg) == (1.0, 2.0, -3.0, 90.0)


def test_a_ramped_setpoint_is_one_the_gate_passes() -> None:
    """A jump is cut to just under the gate's speed limits from the last setpoint, each axis
    group on its own; a step within them is left as it is."""
    limits = GateLimits(np.array([[-50.0, -50.0], [50.0, -50.0], [50.0, 50.0], [-50.0, 50.0]]),
                        2.0, 30.0, max_speed_h_m_s=4.0, max_speed_v_m_s=1.0)
    last = Setpoint(0.0, 0.0, -8.0, 0.0)
    here = np.array([0.0, 0.0, -8.0])
    near = Setpoint(0.2, 0.1, -8.05, 0.0)
    assert ramp(near, here, limits, 0.1) is near
    far = ramp(Setpoint(3.0, 4.0, -10.0, 90.0), here, limits, 0.1)
    assert math.hypot(far.north_m, far.east_m) == pytest.approx(0.99 * 0.4)
    assert far.north_m / far.east_m == pytest.approx(0.75) and far.yaw_deg == 90.0
    assert far.down_m == pytest.approx(-8.0 - 0.99 * 0.1)
    assert gate(limits, far, last, here, 0.1).action is GateAction.PASS
    assert gate(limits, Setpoint(3.0, 4.0, -10.0, 90.0), last, here, 0.1).action is (
        GateAction.CLAMPED)
    climb = ramp(Setpoint(0.0, 0.0, -12.0, 0.0), here, limits, 0.1)
    assert (climb.north_m, climb.east_m) == (0.0, 0.0) and climb.down_m < -8.0


def test_the_carrot_moves_at_the_search_speed_and_a_reached_waypoint_counts() -> None:
    planner = LawnMower(np.array([[10.0, 0.0], [10.0, 10.0]]))
    mixture, tracks = Mixture.empty(2), Tracks.empty(2, 5)
    target, carrot = Carrot().advance(planner, np.zeros(2), mixture, tracks, WORLD, 2.0, 0.5)
    assert np.allclose(target, [1.0, 0.0]) and carrot.progress == 0
    near = np.array([10.0 - 0.5 * REACHED_M, 0.0])  # the vehicle lags the carrot a little
    at_waypoint = Carrot(np.array([9.5, 0.0]), 0)
    target, carrot = at_waypoint.advance(planner, near, mixture, tracks, WORLD, 2.0, 0.5)
    assert np.allclose(target, [10.0, 0.0]) and carrot.progress == 1
    far = Carrot(np.array([9.5, 0.0]), 0).advance(planner, np.zeros(2), mixture, tracks, WORLD,
                                                  2.0, 0.5)[1]
    assert far.progress == 0  # the carrot is there, the vehicle is not


def test_a_finished_plan_leaves_the_carrot_where_it_is() -> None:
    planner = LawnMower(np.array([[0.0, 0.0]]))
    carrot = Carrot(None, 1)
    target, after = carrot.advance(planner, np.array([3.0, 4.0]), Mixture.empty(2),
                                   Tracks.empty(2, 5), WORLD, 2.0, 0.5)
    assert np.allclose(target, [3.0, 4.0]) and after.xy_m is None and after.progress == 1


def test_flight_modes_in_the_missions_terms() -> None:
    def status(mode: FlightMode) -> Status:
        return Status(mode, False, False, True, True, 80.0)

    assert mission_mode(None) is ms.FlightMode.UNKNOWN
    assert mission_mode(status(FlightMode.OFFBOARD)) is ms.FlightMode.OFFBOARD
    assert mission_mode(status(FlightMode.STABILIZED)) is ms.FlightMode.MANUAL
    assert mission_mode(status(FlightMode.RETURN_TO_LAUNCH)) is ms.FlightMode.RTL
    assert mission_mode(status(FlightMode.FOLLOW_ME)) is ms.FlightMode.OTHER
