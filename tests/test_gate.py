"""The safety gate: geofence (non-convex too), altitude band, speed limits, refusals."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from companion.errors import InputError
from companion.plan.gate import (
    GateAction,
    GateLimits,
    GateResult,
    Setpoint,
    gate,
    inside_fence,
    nearest_inside_fence,
)

SQUARE = [[0.0, 0.0], [100.0, 0.0], [100.0, 100.0], [0.0, 100.0]]
# A U open to the north: arms east 0..10 and 20..30, notch north 10..30 x east 10..20.
U_SHAPE = [[0, 0], [30, 0], [30, 10], [10, 10], [10, 20], [30, 20], [30, 30], [0, 30]]


def limits(fence: object = SQUARE, **kw: float) -> GateLimits:
    args = {"min_alt_m": 2.0, "max_alt_m": 30.0, "max_speed_h_m_s": 3.0,
            "max_speed_v_m_s": 1.0} | kw
    return GateLimits(fence, **args)  # type: ignore[arg-type]  # lists are checked too


def sp(north_m: float, east_m: float, alt_m: float, yaw_deg: float = 0.0) -> Setpoint:
    return Setpoint(north_m, east_m, -alt_m, yaw_deg)


def far(result: GateResult) -> Setpoint:
    assert result.setpoint is not None
    return result.setpoint


@pytest.mark.parametrize(
    ("fence", "kw", "field"),
    [
        ([[0, 0], [1, 0]], {}, "fence_ne_m"),
        ([[0, 0], [1, 0], [2, 0]], {}, "fence_ne_m"),  # no area
        ([[0, 0], [1, 1], [1, 0], [0, 1]], {}, "fence_ne_m"),  # bow tie
        ([[0, 0], [1, 0], [1, 1], [1, 1], [0, 1]], {}, "fence_ne_m"),  # repeated vertex
        ([[0, 0], [2, 0], [1, 0], [1, 1]], {}, "fence_ne_m"),  # folds back
        ([[0, 0], [4, 0], [4, 4], [2, 0], [0, 4]], {}, "fence_ne_m"),  # vertex on an edge
        ([[0, 0], [1, math.nan], [1, 1]], {}, "fence_ne_m"),
        ([[0, 0], [1], [1, 1]], {}, "fence_ne_m"),  # ragged
        (SQUARE, {"min_alt_m": 0.0}, "min_alt_m"),
        (SQUARE, {"max_alt_m": 2.0}, "max_alt_m"),
        (SQUARE, {"max_alt_m": math.inf}, "max_alt_m"),
        (SQUARE, {"max_speed_h_m_s": 0.0}, "max_speed_h_m_s"),
        (SQUARE, {"max_speed_v_m_s": -1.0}, "max_speed_v_m_s"),
        (SQUARE, {"fence_margin_m": 0.0}, "fence_margin_m"),
    ],
)
def test_bad_limits_name_the_field(fence: object, kw: dict[str, float], field: str) -> None:
    with pytest.raises(InputError) as err:
        limits(fence, **kw)
    assert err.value.field == field and str(err.value).startswith(f"{field} ")


def test_closed_ring_and_point_in_non_convex_polygon() -> None:
    lim = limits([*U_SHAPE, U_SHAPE[0]])
    assert lim.fence_ne_m.shape == (8, 2) and not lim.fence_ne_m.flags.writeable
    assert inside_fence(lim, [20.0, 5.0]) and inside_fence(lim, [20.0, 25.0])
    assert not inside_fence(lim, [20.0, 15.0])  # the notch
    assert inside_fence(lim, [30.0, 5.0]) and inside_fence(lim, [10.0, 15.0])  # on the boundary
    assert not inside_fence(lim, [-1e-6, 5.0]) and not inside_fence(lim, [31.0, 5.0])


def test_a_safe_setpoint_passes_unchanged() -> None:
    target = sp(50.0, 50.0, 10.0, 45.0)
    result = gate(limits(), target, sp(50.5, 50.0, 10.2), np.array([50.0, 50.0, -10.0]), 0.5)
    assert result == GateResult(target, GateAction.PASS, ()) and result.setpoint is target


@pytest.mark.parametrize(
    ("target", "previous", "vehicle", "dt_s", "why"),
    [
        (sp(math.nan, 1.0, 10.0), None, [1.0, 1.0, -10.0], 0.1, "non-finite setpoint"),
        (sp(1.0, 1.0, 10.0, math.inf), None, [1.0, 1.0, -10.0], 0.1, "non-finite setpoint"),
        (sp(1, 1, 10), sp(1, math.nan, 10), [1.0, 1.0, -10.0], 0.1, "non-finite previous"),
        (sp(1.0, 1.0, 10.0), None, [1.0, math.inf, -10.0], 0.1, "non-finite vehicle"),
        (sp(1.0, 1.0, 10.0), None, [1.0, 1.0, -10.0], 0.0, "dt_s"),
        (sp(1.0, 1.0, 10.0), None, [1.0, 1.0, -10.0], math.nan, "dt_s"),
    ],
)
def test_non_finite_or_bad_dt_is_refused(
    target: Setpoint, previous: Setpoint | None, vehicle: list[float], dt_s: float, why: str
) -> None:
    result = gate(limits(), target, previous, np.array(vehicle), dt_s)
    assert result.setpoint is None and result.action == "refused"
    assert why in result.reasons[0]


@pytest.mark.parametrize(("alt_m", "expected_alt_m"), [(150.0, 30.0), (0.5, 2.0), (-3.0, 2.0)])
def test_altitude_is_clamped_into_the_band(alt_m: float, expected_alt_m: float) -> None:
    result = gate(limits(max_speed_v_m_s=1e3), sp(50, 50, alt_m), None, [50, 50, -10.0], 1.0)
    assert result.action == "clamped" and far(result).down_m == -expected_alt_m
    assert far(result).north_m == 50 and result.reasons[0].startswith("alt ")
    assert f"clamped by {abs(alt_m - expected_alt_m):.2f} m" in result.reasons[0]


def test_outside_target_goes_to_nearest_boundary_point_moved_inside() -> None:
    lim = limits(max_speed_h_m_s=1e3)
    side = far(gate(lim, sp(120, 50, 10), None, [50, 50, -10.0], 1.0))
    assert (side.north_m, side.east_m) == (99.5, 50.0)
    corner = gate(lim, sp(120, 130, 10), None, [50, 50, -10.0], 1.0)
    c = 100 - 0.5 / math.sqrt(2)  # on the corner's bisector
    np.testing.assert_allclose([far(corner).north_m, far(corner).east_m], [c, c])
    moved_m = math.hypot(120 - c, 130 - c)
    assert corner.reasons == (f"target outside geofence: moved {moved_m:.2f} m",)


def test_non_convex_notch_and_thin_corridor() -> None:
    lim = limits(U_SHAPE, max_speed_h_m_s=1e3)
    out = far(gate(lim, sp(25, 14, 10), None, [5, 5, -10.0], 1.0))  # nearest wall east = 10
    assert (out.north_m, out.east_m) == (25.0, 9.5) and inside_fence(lim, [25.0, 9.5])
    # A 0.4 m corridor: the 0.5 m margin would cross it, so it is halved to 0.25 m.
    thin = limits([[0, 0], [50, 0], [50, 0.4], [0, 0.4]], max_speed_h_m_s=1e3)
    moved = nearest_inside_fence(thin, [25.0, 5.0])
    assert moved is not None
    np.testing.assert_allclose(moved, [25.0, 0.15])


def test_speed_limits_the_step_along_its_direction() -> None:
    lim = limits([[-100, -100], [100, -100], [100, 100], [-100, 100]], max_speed_h_m_s=2.0)
    result = gate(lim, sp(30, 40, 20), sp(0, 0, 10), [5, 5, -12.0], 0.5)
    out = far(result)
    np.testing.assert_allclose([out.north_m, out.east_m, out.down_m], [0.6, 0.8, -10.5])
    assert len(result.reasons) == 2 and "horizontal step 50.00 m > 1.00 m" in result.reasons[0]
    # Without a previous setpoint the step is measured from the vehicle.
    out = far(gate(lim, sp(10, 0, 10), None, [0, 0, -10.0], 0.5))
    assert (out.north_m, out.east_m, out.down_m) == (1.0, 0.0, -10.0)


def test_containment_wins_over_speed() -> None:
    lim = limits(max_speed_h_m_s=1.0)
    # Vehicle 10 m outside: target becomes the nearest inside point; the 1 m step from the
    # vehicle would stay outside, so the setpoint goes inside at once.
    result = gate(lim, sp(50, 50, 10), None, [110, 50, -10.0], 1.0)
    assert (far(result).north_m, far(result).east_m) == (99.5, 50.0)
    assert result.reasons[0].startswith("vehicle 10.00 m outside geofence")
    assert result.reasons[-1].startswith("limited step left geofence")
    # Non-convex: the straight step from one arm of the U towards the other enters the notch.
    u_lim = limits(U_SHAPE, max_speed_h_m_s=8.0)
    out = far(gate(u_lim, sp(25, 25, 10), sp(25, 5, 10), [25, 5, -10.0], 1.0))
    assert (out.north_m, out.east_m) == (25.0, 9.5)
    # A vehicle on the ground: the first setpoint is raised into the band at once.
    assert far(gate(lim, sp(50, 50, 10), None, [50, 50, 0.0], 1.0)).down_m == -2.0


# ---------------------------------------------------------------------------------------------
# Properties over random polygons
# ---------------------------------------------------------------------------------------------

COORD = st.floats(-250.0, 250.0)


@st.composite
def star_polygons(draw: st.DrawFn, convex: bool = False) -> GateLimits:
    """Star-shaped (often non-convex) polygons about the origin, or points on a circle."""
    n = draw(st.integers(3, 12))
    angles = sorted(set(draw(st.lists(st.floats(0.0, 2 * math.pi, exclude_max=True),
                                      min_size=n, max_size=n))))
    radii = [100.0] * len(angles) if convex else draw(
        st.lists(st.floats(2.0, 150.0), min_size=len(angles), max_size=len(angles)))
    fence = [[r * math.cos(a), r * math.sin(a)] for a, r in zip(angles, radii, strict=True)]
    try:
        return limits(fence, max_speed_h_m_s=draw(st.floats(0.5, 20.0)),
                      max_speed_v_m_s=draw(st.floats(0.2, 5.0)))
    except InputError:
        assume(False)
        raise


SETPOINTS = st.builds(sp, COORD, COORD, st.floats(-50.0, 200.0), st.floats(-180.0, 180.0))
VEHICLES = st.tuples(COORD, COORD, st.floats(-200.0, 5.0))
DT = st.floats(0.01, 3.0)


def inside(lim: GateLimits, out: Setpoint) -> bool:
    return inside_fence(lim, [out.north_m, out.east_m]) and (
        lim.min_alt_m <= -out.down_m <= lim.max_alt_m)


@settings(deadline=None, max_examples=300, derandomize=True)
@given(star_polygons(), SETPOINTS, st.none() | SETPOINTS, VEHICLES, DT)
def test_output_is_always_inside_and_gating_it_again_passes(
    lim: GateLimits, target: Setpoint, previous: Setpoint | None,
    vehicle: tuple[float, float, float], dt_s: float,
) -> None:
    result = gate(lim, target, previous, np.array(vehicle), dt_s)
    assert result.action in ("pass", "clamped")
    out = far(result)
    assert inside(lim, out) and out.yaw_deg == target.yaw_deg
    assert (result.action == "pass") == (out == target) == (not result.reasons)
    again = gate(lim, out, out, np.array([out.north_m, out.east_m, out.down_m]), dt_s)
    assert again.action == "pass" and again.setpoint is out


@settings(deadline=None, max_examples=200, derandomize=True)
@given(star_polygons(convex=True), SETPOINTS, SETPOINTS, DT)
def test_in_a_convex_fence_the_step_from_an_inside_previous_respects_the_speed(
    lim: GateLimits, first: Setpoint, target: Setpoint, dt_s: float
) -> None:
    previous = far(gate(lim, first, None, np.zeros(3), 1e6))  # any point inside, no speed limit
    vehicle = np.array([previous.north_m, previous.east_m, previous.down_m])
    out = far(gate(lim, target, previous, vehicle, dt_s))
    step_h = math.hypot(out.north_m - previous.north_m, out.east_m - previous.east_m)
    assert step_h <= lim.max_speed_h_m_s * dt_s * (1 + 1e-9)
    assert abs(out.down_m - previous.down_m) <= lim.max_speed_v_m_s * dt_s * (1 + 1e-9)
    assert inside(lim, out)
