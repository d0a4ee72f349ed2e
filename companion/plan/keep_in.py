"""A polygon the plan keeps a clearance inside: lawn-mower lanes cut to it, targets moved into it.

The service's geofence is the search area unless configured, so a plan over the area's bounding
box runs along (and, for a non-rectangular area, beyond) the fence; a real vehicle overshoots
a lane's end by a metre and its position estimate wanders. Planning `clearance_m` inside the
fence leaves the safety gate nothing to clamp in normal flight. Pure numpy, search-frame metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from companion.errors import InputError
from companion.plan.search_track import inside_polygon

__all__ = ["KeepIn", "clearance_m", "nearest_on_boundary"]

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

_STEP_M = 0.1  # lanes are cut to within this
_ATTEMPTS = 8  # moves towards the clearance before the best point found is kept


def nearest_on_boundary(
    xy: FloatArray, polygon_xy: FloatArray
) -> tuple[FloatArray, FloatArray, IntArray, FloatArray]:
    """For (m, 2) points: the (m, 2) nearest points on the polygon's boundary, their (m,)
    distances, the (m,) indices of the edges they lie on and their (m,) parameters along them."""
    a = polygon_xy
    edge = np.roll(a, -1, axis=0) - a
    t = np.clip(np.sum((xy[:, None, :] - a) * edge, axis=2) / np.sum(edge * edge, axis=1),
                0.0, 1.0)
    points = a + t[..., None] * edge  # (m, k, 2)
    dist = np.hypot(*(points - xy[:, None, :]).transpose(2, 0, 1))
    nearest = np.argmin(dist, axis=1)
    rows = np.arange(len(xy))
    return points[rows, nearest], dist[rows, nearest], nearest, t[rows, nearest]


def clearance_m(xy: FloatArray, polygon_xy: FloatArray) -> FloatArray:
    """(m,) distance of each point (m, 2) to the polygon's boundary, negative outside it."""
    points = np.atleast_2d(np.asarray(xy, dtype=np.float64))
    _, dist, _, _ = nearest_on_boundary(points, polygon_xy)
    out: FloatArray = np.where(inside_polygon(points, polygon_xy), dist, -dist)
    return out


@dataclass(frozen=True, slots=True, eq=False)
class KeepIn:
    """A simple polygon (k, 2) and the clearance (m) a plan keeps inside its boundary."""

    polygon_xy: FloatArray
    clearance_m: float

    def __post_init__(self) -> None:
        """InputError unless the polygon is (k >= 3, 2) and the clearance finite and >= 0."""
        polygon = np.asarray(self.polygon_xy, dtype=np.float64)
        if polygon.ndim != 2 or polygon.shape[1] != 2 or len(polygon) < 3:
            raise InputError(f"keep-in polygon: expected (k >= 3, 2), got shape {polygon.shape}")
        if not (np.isfinite(self.clearance_m) and self.clearance_m >= 0.0):
            raise InputError(f"clearance_m must be finite and >= 0, got {self.clearance_m!r}")
        object.__setattr__(self, "polygon_xy", polygon)

    def lane_runs(self, x_m: float) -> list[tuple[float, float]]:
        """The (y_from, y_to) stretches of the north-south line x = x_m, south to north, whose
        points all keep the clearance (to within 0.1 m; none where the line keeps none)."""
        low, high = self.polygon_xy[:, 1].min(), self.polygon_xy[:, 1].max()
        ys = np.linspace(low, high, max(int(np.ceil((high - low) / _STEP_M)), 1) + 1)
        ok = clearance_m(np.column_stack([np.full(ys.size, x_m), ys]),
                         self.polygon_xy) >= self.clearance_m
        edges = np.diff(np.concatenate([[0], ok.astype(np.int8), [0]]))
        starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1) - 1
        return [(float(ys[s]), float(ys[e])) for s, e in zip(starts, ends, strict=True)]

    def x_range(self) -> tuple[float, float]:
        """The polygon's east-west extent less the clearance on both sides (its middle when
        narrower than twice the clearance)."""
        low, high = self.polygon_xy[:, 0].min(), self.polygon_xy[:, 0].max()
        if high - low < 2.0 * self.clearance_m:
            middle = float(low + high) / 2.0
            return middle, middle
        return float(low + self.clearance_m), float(high - self.clearance_m)

    def longest_lane_x(self, x_m: float, towards_x_m: float) -> float:
        """The x from x_m up to towards_x_m (0.1 m steps) whose lane keeps the clearance along
        the most length, the nearest to x_m of those within 0.2 m of it (a side of the polygon
        not quite north-south leaves the outermost lanes short)."""
        xs = np.linspace(x_m, towards_x_m, max(int(abs(towards_x_m - x_m) / _STEP_M), 0) + 1)
        lengths = np.array([sum(b - a for a, b in self.lane_runs(float(x))) for x in xs])
        return float(xs[np.argmax(lengths >= lengths.max() - 2.0 * _STEP_M)])

    def nearest(self, xy: FloatArray) -> FloatArray:
        """The point itself if it keeps the clearance, else a point near it that does: moved
        away from the nearest boundary point, a few times at a corner (where the polygon has no
        such point, the one of the attempts with the most clearance)."""
        point = np.asarray(xy, dtype=np.float64)
        best, best_m = point, float(clearance_m(point, self.polygon_xy)[0])
        for _ in range(_ATTEMPTS):
            if best_m >= self.clearance_m - 1e-9:
                return best
            near, dist, _, _ = nearest_on_boundary(point[None, :], self.polygon_xy)
            inside = bool(inside_polygon(point[None, :], self.polygon_xy)[0])
            if dist[0] > 1e-9:
                inward = (point - near[0]) / dist[0] * (1.0 if inside else -1.0)
            else:  # on the boundary: towards the polygon's centroid
                towards = self.polygon_xy.mean(axis=0) - point
                inward = towards / max(float(np.hypot(*towards)), 1e-12)
            point = near[0] + self.clearance_m * inward
            margin_m = float(clearance_m(point, self.polygon_xy)[0])
            if margin_m > best_m:
                best, best_m = point, margin_m
        return best
