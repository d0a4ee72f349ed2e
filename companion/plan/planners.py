"""The planners: the paper's lawn mower, nearest-Gaussian and largest-Gaussian (Section
Planning), and the search-and-track planner (companion.plan.search_track).

Each planner is a pure function of (robot position, mixture, tracks, world, progress, time) that
returns the next waypoint (or None: stay) and its new progress. The paper's planners ignore the
time and count progress in an int (only the lawn mower uses it); the search-and-track planner
keeps its memory of where it has looked in a SearchProgress, and starts one from progress 0.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from companion.errors import InputError
from companion.plan.keep_in import KeepIn
from companion.plan.search_track import SearchTrackParams, make_search_track
from companion.plan.world import World
from companion.sat.mixture import Mixture
from companion.sat.tracks import Tracks

FloatArray = NDArray[np.float64]


class PlannerKind(StrEnum):
    """The configured planner, by its TOML name."""

    LAWNMOWER = "lawnmower"
    NEAREST_GAUSSIAN = "nearest-gaussian"
    LARGEST_GAUSSIAN = "largest-gaussian"
    SEARCH_TRACK = "search-track"


PlanProgress = Any
"""A planner's progress: an int for the paper's planners, a SearchProgress for search-track;
every planner starts from 0."""


class Planner(Protocol):
    """next waypoint = planner(robot, mixture, tracks, world, progress, t_s)."""

    def next_waypoint(
        self, robot_xy: FloatArray, mixture: Mixture, tracks: Tracks, world: World,
        progress: PlanProgress, t_s: float = 0.0,
    ) -> tuple[FloatArray | None, PlanProgress]:
        """The waypoint to fly to now (None: hold) and the planner's new progress; t_s is the
        estimator's time."""
        ...

    def finished(self, progress: PlanProgress) -> bool:
        """Whether the plan has nothing left to do."""
        ...


def lawnmower_path(
    world: World, start_xy: FloatArray, lane_spacing_m: float, sweeps: int,
    keep_in: KeepIn | None = None,
) -> FloatArray:
    """Waypoints of `sweeps` boustrophedon passes over the world, each returning to start.

    Lanes run north-south at x = s/2, 3s/2, ... (s = lane spacing) so that a sensor that sees
    s/2 to each side covers the whole width; the last lane is moved inside the world if needed.
    With `keep_in`, lanes are moved into its east-west range (the outermost up to half a spacing
    further, to where they keep its clearance longest) and cut to the stretches inside the world
    that keep it (a lane keeping none is left out); the start is the nearest point keeping it.
    """
    if lane_spacing_m <= 0:
        raise InputError(f"lane spacing must be > 0, got {lane_spacing_m!r}",
                         reason=f"must be > 0, got {lane_spacing_m!r}")
    lanes = np.arange(lane_spacing_m / 2.0, world.width_m, lane_spacing_m)
    if lanes.size == 0:
        lanes = np.array([world.width_m / 2.0])
    runs = [[(0.0, world.height_m)] for _ in lanes]
    if keep_in is not None:
        lanes = np.unique(np.clip(lanes, *keep_in.x_range()))
        if lanes.size > 1:  # the outermost lanes, up to half a spacing inwards
            lanes[0] = keep_in.longest_lane_x(lanes[0], lanes[0] + lane_spacing_m / 2.0)
            lanes[-1] = keep_in.longest_lane_x(lanes[-1], lanes[-1] - lane_spacing_m / 2.0)
        runs = [[(max(a, 0.0), min(b, world.height_m)) for a, b in keep_in.lane_runs(float(x))
                 if a <= world.height_m and b >= 0.0] for x in lanes]
        start_xy = keep_in.nearest(start_xy)
    one_sweep: list[list[float]] = []
    flown = [(float(x), lane) for x, lane in zip(lanes, runs, strict=True) if lane]
    for i, (x, lane) in enumerate(flown):
        for y_from, y_to in (lane if i % 2 == 0 else [(b, a) for a, b in lane[::-1]]):
            one_sweep += [[x, y_from], [x, y_to]]
    points = [*one_sweep, [float(start_xy[0]), float(start_xy[1])]] * sweeps
    return np.asarray(points, dtype=np.float64)


@dataclass(frozen=True, slots=True)
class LawnMower:
    """Fly the precomputed lawn-mower waypoints in order; progress is the next waypoint's index."""

    path_xy: FloatArray
    reached_m: float = 1e-6

    def next_waypoint(
        self, robot_xy: FloatArray, mixture: Mixture, tracks: Tracks, world: World, progress: int,
        t_s: float = 0.0,
    ) -> tuple[FloatArray | None, int]:
        """The current waypoint, advancing past those already reached."""
        while progress < len(self.path_xy) and (
            np.hypot(*(self.path_xy[progress] - robot_xy)) <= self.reached_m
        ):
            progress += 1
        if progress >= len(self.path_xy):
            return None, progress
        return self.path_xy[progress], progress

    def finished(self, progress: int) -> bool:
        """True once every waypoint has been reached."""
        return progress >= len(self.path_xy)


@dataclass(frozen=True, slots=True)
class NearestGaussian:
    """Drive to the mean of the nearest component of the mixture."""

    def next_waypoint(
        self, robot_xy: FloatArray, mixture: Mixture, tracks: Tracks, world: World, progress: int,
        t_s: float = 0.0,
    ) -> tuple[FloatArray | None, int]:
        """The nearest component mean inside the world, or None for an empty mixture."""
        if mixture.size == 0:
            return None, progress
        dist = np.hypot(*(mixture.means[:, :2] - robot_xy).T)
        return world.clip(mixture.means[int(np.argmin(dist)), :2]), progress

    def finished(self, progress: int) -> bool:
        """Never: it tracks for as long as it runs."""
        return False


@dataclass(frozen=True, slots=True)
class LargestGaussian:
    """Drive to the mean of the component with the largest covariance (largest ellipse area)."""

    def next_waypoint(
        self, robot_xy: FloatArray, mixture: Mixture, tracks: Tracks, world: World, progress: int,
        t_s: float = 0.0,
    ) -> tuple[FloatArray | None, int]:
        """The mean of the component whose position covariance has the largest determinant."""
        if mixture.size == 0:
            return None, progress
        pos = mixture.covs[:, :2, :2]
        area = pos[:, 0, 0] * pos[:, 1, 1] - pos[:, 0, 1] * pos[:, 1, 0]
        return world.clip(mixture.means[int(np.argmax(area)), :2]), progress

    def finished(self, progress: int) -> bool:
        """Never: it searches for as long as it runs."""
        return False


def move_towards(
    robot_xy: FloatArray, waypoint_xy: FloatArray | None, max_step_m: float
) -> FloatArray:
    """The robot's next position: up to max_step_m straight towards the waypoint."""
    if waypoint_xy is None:
        return robot_xy
    delta = waypoint_xy - robot_xy
    dist = float(np.hypot(*delta))
    if dist <= max_step_m:
        return np.array(waypoint_xy, dtype=np.float64)
    return robot_xy + delta * (max_step_m / dist)


def make_planner(
    kind: PlannerKind, world: World, start_xy: FloatArray, lane_spacing_m: float, sweeps: int,
    search: SearchTrackParams | None = None, keep_in: KeepIn | None = None,
) -> Planner:
    """The planner of that kind; a lawn mower's `sweeps` passes each end at start_xy, inside
    `keep_in` if given; the search-and-track planner needs `search` (InputError without it)."""
    if kind == PlannerKind.LAWNMOWER:
        return LawnMower(lawnmower_path(world, start_xy, lane_spacing_m, sweeps, keep_in))
    if kind == PlannerKind.NEAREST_GAUSSIAN:
        return NearestGaussian()
    if kind == PlannerKind.LARGEST_GAUSSIAN:
        return LargestGaussian()
    if kind == PlannerKind.SEARCH_TRACK:
        if search is None:
            raise InputError("the search-track planner needs its sensor and stop parameters")
        return make_search_track(world, search)
    raise InputError(f"unknown planner {kind!r}")
