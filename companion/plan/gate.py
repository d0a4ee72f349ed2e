"""The safety gate every setpoint passes just before it leaves the process.

Everything is in the autopilot's local NED frame, metres; the geofence is a simple polygon
(possibly non-convex) of [north, east] vertices, converted from lat/lon once by the caller.
Containment wins over the speed limit: when the reference (previous setpoint or vehicle) lies
outside the fence or the altitude band, the output is put back inside even if that step is longer.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum

import numpy as np
from numpy.typing import ArrayLike, NDArray

from companion.errors import InputError, field_error
from companion.plan.keep_in import nearest_on_boundary

FloatArray = NDArray[np.float64]

_ON_EDGE_M = 1e-9  # a point this close to the boundary counts as inside
_MIN_MARGIN_M = 1e-3  # the inward margin is halved down to this before giving up
_MIN_EDGE_M = 1e-6  # shorter fence edges are taken for repeated vertices


class GateAction(StrEnum):
    """What the gate did to a setpoint; the value is the word the logs and counters write."""

    PASS = "pass"
    CLAMPED = "clamped"
    REFUSED = "refused"


@dataclass(frozen=True, slots=True)
class Setpoint:
    """A position setpoint in local NED metres and a yaw in degrees (0 north, clockwise)."""

    north_m: float
    east_m: float
    down_m: float
    yaw_deg: float


@dataclass(frozen=True, slots=True)
class GateResult:
    """The setpoint to send (None when refused), what the gate did and why (for the logs)."""

    setpoint: Setpoint | None
    action: GateAction
    reasons: tuple[str, ...]


def _positive(field: str, value: object) -> float:
    number = float(value) if isinstance(value, int | float | np.number) else math.nan
    if isinstance(value, bool) or not (math.isfinite(number) and number > 0):
        raise field_error(field, f"must be a finite number > 0, got {value!r}")
    return number


@dataclass(frozen=True, slots=True, eq=False)
class GateLimits:
    """Geofence polygon (k, 2) [north, east] m, altitude band above the origin, speed limits."""

    fence_ne_m: FloatArray
    min_alt_m: float
    max_alt_m: float
    max_speed_h_m_s: float
    max_speed_v_m_s: float
    fence_margin_m: float = 0.5

    def __post_init__(self) -> None:
        """Check every limit once; a closing vertex equal to the first is dropped."""
        try:
            fence = np.array(self.fence_ne_m, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise field_error("fence_ne_m", f"is not an array of [north, east]: {exc}") from exc
        if fence.ndim == 2 and len(fence) > 3 and np.array_equal(fence[0], fence[-1]):
            fence = fence[:-1]
        if fence.ndim != 2 or fence.shape[1] != 2 or len(fence) < 3:
            raise field_error("fence_ne_m", f"needs >= 3 [north, east] vertices, got shape "
                                            f"{fence.shape}")
        if not np.all(np.isfinite(fence)):
            raise field_error("fence_ne_m", "has non-finite coordinates")
        problem = _polygon_problem(fence)
        if problem:
            raise field_error("fence_ne_m", problem)
        fence.flags.writeable = False
        object.__setattr__(self, "fence_ne_m", fence)
        low = _positive("min_alt_m", self.min_alt_m)
        if _positive("max_alt_m", self.max_alt_m) <= low:
            raise field_error("max_alt_m", f"must be above min_alt_m ({low!r}), "
                                           f"got {self.max_alt_m!r}")
        _positive("max_speed_h_m_s", self.max_speed_h_m_s)
        _positive("max_speed_v_m_s", self.max_speed_v_m_s)
        if _positive("fence_margin_m", self.fence_margin_m) < _MIN_MARGIN_M:
            raise field_error("fence_margin_m", f"must be >= {_MIN_MARGIN_M} m")


# ---------------------------------------------------------------------------------------------
# Polygon geometry (numpy only)
# ---------------------------------------------------------------------------------------------


def _orient(p: FloatArray, q: FloatArray, r: FloatArray) -> FloatArray:
    out: FloatArray = (q[..., 0] - p[..., 0]) * (r[..., 1] - p[..., 1]) - (
        q[..., 1] - p[..., 1]
    ) * (r[..., 0] - p[..., 0])
    return out


def _within_box(p: FloatArray, q: FloatArray, r: FloatArray) -> NDArray[np.bool_]:
    inside: NDArray[np.bool_] = np.all(
        (np.minimum(p, q) <= r) & (r <= np.maximum(p, q)), axis=-1
    )
    return inside


def _signed_area(fence: FloatArray) -> float:
    nxt = np.roll(fence, -1, axis=0)
    return 0.5 * float(np.sum(fence[:, 0] * nxt[:, 1] - nxt[:, 0] * fence[:, 1]))


def _polygon_problem(fence: FloatArray) -> str | None:
    """Why the polygon is not a simple polygon with an area, or None."""
    nxt = np.roll(fence, -1, axis=0)
    edge = nxt - fence
    length = np.hypot(edge[:, 0], edge[:, 1])
    if np.any(length < _MIN_EDGE_M):
        return f"vertices {int(np.argmin(length))} and the next are closer than {_MIN_EDGE_M} m"
    if abs(_signed_area(fence)) <= 1e-9 * float(np.sum(length)) ** 2:
        return "has no area (all vertices on a line)"
    k = len(fence)
    turn = _orient(np.zeros(2), edge, np.roll(edge, -1, axis=0))  # edge i x edge i+1
    dot = np.sum(edge * np.roll(edge, -1, axis=0), axis=1)
    if np.any((turn == 0.0) & (dot < 0.0)):
        return f"folds back on itself at vertex {(int(np.argmax((turn == 0) & (dot < 0))) + 1) % k}"
    a, b, c, d = fence[:, None], nxt[:, None], fence[None], nxt[None]
    d1, d2, d3, d4 = _orient(c, d, a), _orient(c, d, b), _orient(a, b, c), _orient(a, b, d)
    touch = ((d1 * d2 < 0) & (d3 * d4 < 0)) | (
        ((d1 == 0) & _within_box(c, d, a)) | ((d2 == 0) & _within_box(c, d, b))
        | ((d3 == 0) & _within_box(a, b, c)) | ((d4 == 0) & _within_box(a, b, d))
    )
    i, j = np.triu_indices(k, 2)
    non_adjacent = ~((i == 0) & (j == k - 1))
    crossing = touch[i, j] & non_adjacent
    if np.any(crossing):
        n = int(np.argmax(crossing))
        return f"is not simple: edges {int(i[n])} and {int(j[n])} meet"
    return None


def _nearest_on_boundary(fence: FloatArray, ne: FloatArray) -> tuple[FloatArray, float, int, float]:
    """Nearest boundary point, its distance, its edge index and parameter along that edge."""
    points, dist, edge, t = nearest_on_boundary(ne[None, :], fence)
    return points[0], float(dist[0]), int(edge[0]), float(t[0])


def inside_fence(limits: GateLimits, north_east_m: ArrayLike) -> bool:
    """Whether a [north, east] point lies in the fence (within 1e-9 m of the boundary counts)."""
    fence = limits.fence_ne_m
    ne = np.asarray(north_east_m, dtype=np.float64)
    if _nearest_on_boundary(fence, ne)[1] <= _ON_EDGE_M:
        return True
    nxt = np.roll(fence, -1, axis=0)
    crosses = (fence[:, 1] > ne[1]) != (nxt[:, 1] > ne[1])  # edges straddling the ray's line
    dy = np.where(crosses, nxt[:, 1] - fence[:, 1], 1.0)
    north_at = fence[:, 0] + (ne[1] - fence[:, 1]) * (nxt[:, 0] - fence[:, 0]) / dy
    return int(np.count_nonzero(crosses & (ne[0] < north_at))) % 2 == 1


def nearest_inside_fence(limits: GateLimits, north_east_m: ArrayLike) -> FloatArray:
    """The point itself if inside, else the nearest boundary point moved inward by the margin.

    The margin is halved (down to 1 mm) until the moved point is verified inside (thin parts of
    a non-convex fence); if none is, the boundary point itself (which counts as inside).
    """
    fence = limits.fence_ne_m
    ne = np.asarray(north_east_m, dtype=np.float64)
    if inside_fence(limits, ne):
        return ne
    near, _, i, t = _nearest_on_boundary(fence, ne)
    edge = np.roll(fence, -1, axis=0) - fence
    inward = math.copysign(1.0, _signed_area(fence)) * np.stack([-edge[:, 1], edge[:, 0]], axis=1)
    inward /= np.hypot(inward[:, 0], inward[:, 1])[:, None]
    k = len(fence)
    if t <= 1e-12:  # at vertex i: bisect the inward normals of its two edges
        direction = inward[i - 1] + inward[i]
    elif t >= 1.0 - 1e-12:  # at vertex i + 1
        direction = inward[i] + inward[(i + 1) % k]
    else:
        direction = inward[i]
    norm = float(np.hypot(direction[0], direction[1]))
    direction = direction / norm if norm > 1e-12 else inward[i]
    margin_m = limits.fence_margin_m
    while margin_m >= _MIN_MARGIN_M:
        candidate: FloatArray = near + margin_m * direction
        if inside_fence(limits, candidate):
            return candidate
        margin_m /= 2.0
    return near


# ---------------------------------------------------------------------------------------------
# The gate
# ---------------------------------------------------------------------------------------------


def _refused(reason: str) -> GateResult:
    return GateResult(None, GateAction.REFUSED, (reason,))


def gate(
    limits: GateLimits,
    setpoint: Setpoint,
    previous: Setpoint | None,
    vehicle_ned_m: ArrayLike,
    dt_s: float,
) -> GateResult:
    """The setpoint made safe: inside fence and altitude band, its step speed-limited.

    Non-finite inputs are refused. The step is measured from `previous` (the last setpoint
    sent) or, without one, from the vehicle; a vehicle outside the fence is brought back to the
    nearest inside point whatever the target. A setpoint needing no change passes unchanged.
    """
    vehicle = np.asarray(vehicle_ned_m, dtype=np.float64)
    if vehicle.shape != (3,):
        raise InputError(f"vehicle_ned_m must have shape (3,), got {vehicle.shape}")
    checks = [("setpoint", setpoint), ("previous setpoint", previous)]
    for name, value in checks:
        if value is not None and not all(
            math.isfinite(v) for v in (value.north_m, value.east_m, value.down_m, value.yaw_deg)
        ):
            return _refused(f"non-finite {name}")
    if not np.all(np.isfinite(vehicle)):
        return _refused("non-finite vehicle position")
    if not (math.isfinite(dt_s) and dt_s > 0):
        return _refused(f"dt_s must be finite and > 0, got {dt_s!r}")

    reasons: list[str] = []
    ne = np.array([setpoint.north_m, setpoint.east_m])
    alt_m = -setpoint.down_m
    low, high = limits.min_alt_m, limits.max_alt_m
    if not low <= alt_m <= high:
        clamped = min(max(alt_m, low), high)
        reasons.append(f"alt {alt_m:.2f} m outside [{low:g}, {high:g}] m: "
                       f"clamped by {abs(clamped - alt_m):.2f} m")
        alt_m = clamped

    if not inside_fence(limits, vehicle[:2]):
        back = nearest_inside_fence(limits, vehicle[:2])
        if not np.array_equal(back, ne):
            away = _nearest_on_boundary(limits.fence_ne_m, vehicle[:2])[1]
            reasons.append(f"vehicle {away:.2f} m outside geofence: target = nearest inside")
            ne = back
    elif not inside_fence(limits, ne):
        inside = nearest_inside_fence(limits, ne)
        reasons.append(f"target outside geofence: moved {float(np.hypot(*(ne - inside))):.2f} m")
        ne = inside

    ref = vehicle if previous is None else np.array(
        [previous.north_m, previous.east_m, previous.down_m])
    step_h = ne - ref[:2]
    length_h, limit_h = float(np.hypot(*step_h)), limits.max_speed_h_m_s * dt_s
    if length_h > limit_h:
        ne = ref[:2] + step_h * (limit_h / length_h)
        reasons.append(f"horizontal step {length_h:.2f} m > {limit_h:.2f} m "
                       f"({limits.max_speed_h_m_s:g} m/s): shortened")
    step_v, limit_v = alt_m - (-ref[2]), limits.max_speed_v_m_s * dt_s
    if abs(step_v) > limit_v:
        alt_m = -ref[2] + math.copysign(limit_v, step_v)
        reasons.append(f"vertical step {abs(step_v):.2f} m > {limit_v:.2f} m "
                       f"({limits.max_speed_v_m_s:g} m/s): shortened")

    if not inside_fence(limits, ne):  # the reference was outside, or the fence is non-convex
        inside = nearest_inside_fence(limits, ne)
        reasons.append(f"limited step left geofence: moved "
                       f"{float(np.hypot(*(ne - inside))):.2f} m inside")
        ne = inside
    if not low <= alt_m <= high:  # the reference was outside the band
        clamped = min(max(alt_m, low), high)
        reasons.append(f"limited step left altitude band: clamped by "
                       f"{abs(clamped - alt_m):.2f} m")
        alt_m = clamped

    if not reasons:
        return GateResult(setpoint, GateAction.PASS, ())
    out = Setpoint(float(ne[0]), float(ne[1]), -float(alt_m), setpoint.yaw_deg)
    return GateResult(out, GateAction.CLAMPED, tuple(reasons))
