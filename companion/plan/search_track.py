"""The search-and-track planner: where to look next, from what the estimator says is not yet known.

Pure: a function of (robot position, mixture, tracks, world, progress, time) -> (waypoint,
progress), with no clock, no randomness and no I/O. The search area is covered by a grid of
cells, each holding the expected number of targets on it that no scan has found yet:
`unseen_targets` spread evenly over the area (or, if more, the density of the confirmed tracks
beyond the initial belief's count over the ground seen, times the area), plus each initial
component's weight that no confirmed track or component near it holds any more, spread as that
component was, times (1 - p_D) for each look at the cell (a look: the cell enters the sensor's
sure view, or stays in it for another `look_s` seconds). The goals are

- search: the mixture's components that support no confirmed track (the PHD mass no detection
  has explained), valued by their weight, and the nearest point of a sweep over unseen ground
  (points along lanes as wide as the sure view; the nearest next makes a lawn mower that skips
  what was seen and resumes where the robot is; once every cell was looked at, another pass over
  the cells out of view whose unseen mass would keep the search going were every cell like them),
  valued by the unseen mass that the next few sweep points would look at;
- track: each confirmed track, valued (while the search lasts, at TRACK_WEIGHT_SEARCHING: re-finding
  a counted target is worth less than finding a new one; at nothing once every cell has been
  looked at and only unexplained components keep the search going, so that the robot looks at
  them and the search can end) by the probability that its target has moved farther than
  half the view from the track's mean (from its honest covariance, grown with the time unseen),
  times the probability that a look at its mean still sees it, times its existence;

all in one unit, expected targets. The plan is the order of the best `goals` goals that maximises
the sum of value x exp(-distance flown to it / horizon) (every order tried), and the waypoint is
its first goal. A goal, the sweep's next point too, is flown to until it is reached, gone (a sweep
point whose cells have all been looked at), or worth less than half what it was planned at,
unless a goal worth much more turns up, so that the robot neither dithers between goals whose
values change as it flies nor nibbles at small near goals for ever (a sweep point replanned at
every call let the robot hover between a far sweep point and the tracks near it). Components whose
2-sigma disk the sure view holds now are not goals: the sensor is looking at them.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from companion.errors import InputError
from companion.plan.world import World
from companion.sat.mixture import Mixture
from companion.sat.motion import TargetMotion
from companion.sat.tracks import Tracks, grown_covs

__all__ = ["MAX_CELLS", "SearchProgress", "SearchTrack", "SearchTrackParams", "best_order",
           "inscribed_radius_m", "inside_polygon", "make_search_track"]

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

REACHED_M = 1.0  # a goal this close is reached: plan again
TRACK_WEIGHT_SEARCHING = 0.25  # while searching, re-finding a counted target is worth this much
# of finding a new one; once the search has ended, as much
COMMIT_GOALS = 1  # goals of a tour flown before the next plan (receding horizon)
INTERRUPT_VALUE = 0.3  # a new goal worth this much, and INTERRUPT_RATIO times the most the
INTERRUPT_RATIO = 3.0  # tour being flown holds, makes the planner plan a new tour at once
MIN_SEEN_SHARE = 0.25  # the density of found targets is trusted once this much was seen
HALF_VALUE_LOOKS = 12.0  # a minute in view at look_s = 5 s halves a whole target's value
LOST_SIGMAS = 3.0  # a track or component this many sigmas from an initial component holds its mass
LOST_SPREAD = 2.0  # a target its initial component lost is looked for this many times as wide
MAX_CELLS = 2500  # the grid is made coarser than view/2 if the area would need more cells


@dataclass(frozen=True, slots=True)
class SearchTrackParams:
    """What the planner knows of the sensor, the targets and when to stop searching."""

    view_radius_m: float  # radius of the disk around the robot that the sensor surely sees
    p_detect: float = 0.98  # p(D|F) inside that disk
    unseen_targets: float = 1.0  # expected targets beside the initial belief, spread evenly
    stop_below: float = 0.05  # the search ends when fewer targets than this are left to find
    motion: TargetMotion = field(default_factory=lambda: TargetMotion(speed_m_s=0.0))
    area_xy: FloatArray | None = None  # (k, 2) search-area polygon; None: the world
    goals: int = 5  # goals ordered in one plan (all orders are tried: keep it small)
    horizon_m: float | None = None  # distance at which a goal's value falls by 1/e; None: world
    look_s: float = 5.0  # a cell that stays in view is looked at again after this long

    def __post_init__(self) -> None:
        _positive("view_radius_m", self.view_radius_m)
        if not (math.isfinite(self.p_detect) and 0.0 < self.p_detect <= 1.0):
            raise InputError(f"p_detect: must be in (0, 1], got {self.p_detect!r}",
                             reason=f"must be in (0, 1], got {self.p_detect!r}")
        _non_negative("unseen_targets", self.unseen_targets)
        _non_negative("stop_below", self.stop_below)
        if not 1 <= self.goals <= 7:
            raise InputError(f"goals: must be 1 to 7, got {self.goals!r}",
                             reason=f"must be 1 to 7, got {self.goals!r}")
        if self.horizon_m is not None:
            _positive("horizon_m", self.horizon_m)
        _positive("look_s", self.look_s)


def _positive(name: str, value: float) -> None:
    """InputError naming the parameter unless value is finite and > 0."""
    if not (math.isfinite(value) and value > 0.0):
        raise InputError(f"{name}: must be > 0, got {value!r}",
                         reason=f"must be > 0, got {value!r}")


def _non_negative(name: str, value: float) -> None:
    """InputError naming the parameter unless value is finite and >= 0."""
    if not (math.isfinite(value) and value >= 0.0):
        raise InputError(f"{name}: must be >= 0, got {value!r}",
                         reason=f"must be >= 0, got {value!r}")


@dataclass(frozen=True, slots=True)
class SearchProgress:
    """The planner's memory: looks per cell, which cells were in view, when, and the mass left."""

    looks: IntArray  # (n,) looks at each cell so far
    in_view: BoolArray  # (n,) cells in view at the last call
    looked_t_s: FloatArray  # (n,) time of each cell's last look
    t_s: float  # time of the last call
    left: float  # expected targets left to find after the last call
    searched: bool  # the stop rule has held once: the search is over
    goal_xy: FloatArray | None = None  # the goal flown to now: the tour's first
    tour_xy: FloatArray = field(default_factory=lambda: np.zeros((0, 2)))  # (m, 2) goals left
    tour_values: FloatArray = field(default_factory=lambda: np.zeros(0))  # their planned values
    prior: Mixture = field(default_factory=Mixture.empty)  # the mixture at the first call
    prior_share: FloatArray = field(default_factory=lambda: np.zeros((0, 0)))  # (n, m) its
    # components' shares on each cell


@dataclass(frozen=True, slots=True, eq=False)
class SearchTrack:
    """The search-and-track planner over a fixed grid (see the module docstring)."""

    params: SearchTrackParams
    cells_xy: FloatArray  # (n, 2) centres of the cells inside the area
    cell_m: float  # side of a cell
    seen_m: float  # a cell whose centre is this close to the robot is wholly in view
    sweep_xy: FloatArray  # (s, 2) sweep points in lawn-mower order
    sweep_of_pair: IntArray  # (p,) sweep point of each (sweep point, cell it looks at) pair
    cell_of_pair: IntArray  # (p,) cell of each pair
    cell_at: IntArray  # (nx, ny) the cell of each square of the full grid, -1 outside the area
    horizon_m: float
    area_xy: FloatArray  # (k, 2) the search area's polygon

    def start(self, belief: Mixture | None = None) -> SearchProgress:
        """The memory before the first call from the initial belief (None: empty): nothing looked
        at, everything left to find."""
        n = self.cells_xy.shape[0]
        prior = belief if belief is not None else Mixture.empty()
        share = self._shares_on_cells(prior._replace(covs=prior.covs * LOST_SPREAD**2))
        return SearchProgress(np.zeros(n, dtype=np.int64), np.zeros(n, dtype=bool),
                              np.full(n, -math.inf), -math.inf, math.inf, False,
                              prior=prior, prior_share=share)

    def _shares_on_cells(self, mixture: Mixture) -> FloatArray:
        """(n, m) each component's share of its position mass on each cell (its density at the
        cell's centre times the cell's area, normalised over the cells)."""
        n, m = self.cells_xy.shape[0], mixture.size
        if n == 0 or m == 0:
            return np.zeros((n, m))
        density = np.exp(-0.5 * _mahalanobis2(self.cells_xy, mixture))
        share: FloatArray = density / np.maximum(density.sum(axis=0), 1e-300)
        return share

    def next_waypoint(
        self, robot_xy: FloatArray, mixture: Mixture, tracks: Tracks, world: World,
        progress: SearchProgress | int, t_s: float = 0.0,
    ) -> tuple[FloatArray | None, SearchProgress]:
        """The first goal of the best plan from here (None: nothing worth flying to) and the
        memory after looking from robot_xy at t_s; progress 0 starts afresh."""
        memory = self.start(mixture) if isinstance(progress, int) else progress
        memory = self._look(robot_xy, memory, t_s)
        found = _found_ids(tracks)
        comp_xy, comp_value, comp_sd = self._component_goals(mixture, found, memory)
        unseen, lost_xy, lost_value = self._unseen_mass(memory, tracks, mixture)
        left = float(unseen.sum() + comp_value.sum())
        # A component whose 2-sigma disk the sensor surely sees is being looked at: no need to fly
        # to it; one wider is flown to until it is that well in view (or its mean reached).
        sure_m = np.clip(self.params.view_radius_m - 2.0 * comp_sd, REACHED_M, self.seen_m)
        away = np.hypot(*(comp_xy - robot_xy).T) > sure_m
        comp_xy, comp_value = comp_xy[away], comp_value[away]
        searched = memory.searched or left < self.params.stop_below
        memory = replace(memory, left=left, searched=searched)
        sweep_xy, sweep_value = (np.zeros((0, 2)), np.zeros(0)) if searched else (
            self._sweep_goals(robot_xy, memory, unseen))
        track_xy, track_value = self._track_goals(tracks, t_s)
        # Searching with every cell looked at: only the unexplained components are left to look
        # at, and the search ends once they are; revisiting tracks would hold it off for ever.
        weight = 1.0 if searched else TRACK_WEIGHT_SEARCHING if sweep_value.size else 0.0
        track_value = track_value * weight
        memory = self._choose(robot_xy, np.vstack([comp_xy, lost_xy, track_xy]),
                              np.concatenate([comp_value, lost_value, track_value]), sweep_xy,
                              sweep_value, memory)
        waypoint = memory.goal_xy
        return (None if waypoint is None else world.clip(waypoint)), memory

    def finished(self, progress: SearchProgress | int) -> bool:
        """True once the expected number of targets left to find has fallen below stop_below."""
        return not isinstance(progress, int) and progress.searched

    def _look(self, robot_xy: FloatArray, memory: SearchProgress, t_s: float) -> SearchProgress:
        """The memory after the sensor looked from robot_xy at t_s."""
        dist = np.hypot(*(self.cells_xy - robot_xy).T)
        in_view = dist <= self.seen_m
        again = in_view & memory.in_view & (t_s - memory.looked_t_s >= self.params.look_s)
        look = (in_view & ~memory.in_view) | again
        looks = memory.looks + look
        looked_t_s = np.where(look, t_s, memory.looked_t_s)
        return replace(memory, looks=looks, in_view=in_view, looked_t_s=looked_t_s, t_s=t_s)

    def _unseen_mass(self, memory: SearchProgress, tracks: Tracks,
                     mixture: Mixture) -> tuple[FloatArray, FloatArray, FloatArray]:
        """(n,) expected targets on each cell that no look has found: unseen_targets spread evenly
        (or more where the targets found so far on the ground seen say the area holds more), and
        each initial component's mass that no confirmed track or component near it holds any more,
        spread as that component was; with the goals of that lost mass: for each initial component
        that lost some, the centroid of its part no look has found yet (its heaviest cell when
        the centroid lies on ground looked at), worth that part."""
        n = self.cells_xy.shape[0]
        found = int(tracks.confirmed.sum())
        seen = float((memory.looks > 0).mean()) if n else 1.0
        beyond = max(found - memory.prior.total_weight, 0.0)  # beyond what the first belief held
        total = max(self.params.unseen_targets, beyond / max(seen, MIN_SEEN_SHARE))
        missed = (1.0 - self.params.p_detect) ** memory.looks
        miss: FloatArray = np.full(n, total / max(n, 1)) * missed
        if not memory.prior.size:
            return miss, np.zeros((0, 2)), np.zeros(0)
        lost_share = memory.prior_share * missed[:, None] * _lost(memory.prior, tracks, mixture)
        miss += lost_share.sum(axis=1)
        lost_value = lost_share.sum(axis=0)
        some = lost_value > 1e-6
        share = lost_share[:, some]
        lost_xy = (share.T @ self.cells_xy) / lost_value[some, None]
        # A centroid on ground already looked at lies between parts left on either side of it
        # (the robot would hover there): the goal is then the part's heaviest cell.
        on_seen = memory.looks[self._cell_of(lost_xy)] > 0
        lost_xy[on_seen] = self.cells_xy[np.argmax(share[:, on_seen], axis=0)]
        return miss, lost_xy, lost_value[some]

    def _cell_of(self, xy: FloatArray) -> IntArray:
        """(m,) the cell each point lies on, or the nearest cell for a point on none."""
        if xy.shape[0] == 0 or self.cells_xy.shape[0] == 0:
            return np.zeros(xy.shape[0], dtype=np.int64)
        nx, ny = self.cell_at.shape
        ix = np.clip(np.floor(xy[:, 0] / self.cell_m), 0, nx - 1).astype(np.int64)
        iy = np.clip(np.floor(xy[:, 1] / self.cell_m), 0, ny - 1).astype(np.int64)
        cell = self.cell_at[ix, iy]
        off = np.flatnonzero(cell < 0)
        if off.size:
            d2 = ((xy[off, None, :] - self.cells_xy[None, :, :]) ** 2).sum(axis=2)
            cell[off] = np.argmin(d2, axis=1)
        return cell

    def _component_goals(
        self, mixture: Mixture, found: IntArray, memory: SearchProgress
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Means, values and position standard deviations (larger axis) of the components that
        support no confirmed track: their weight, halved for every HALF_VALUE_LOOKS x weight (at
        most 1) looks already spent on the cell under them, so that a component the filter does
        not explain cannot hold the robot, and a faint one holds it least."""
        unfound = ~np.isin(mixture.labels, found)
        xy = mixture.means[unfound, :2]
        weights = mixture.weights[unfound]
        covs = mixture.covs[unfound, :2, :2]
        inside = self._inside(xy)
        xy, weights, covs = xy[inside], weights[inside], covs[inside]
        sd: FloatArray = np.sqrt(np.linalg.eigvalsh(covs)[:, -1]) if covs.size else np.zeros(0)
        looks = memory.looks[self._cell_of(xy)] if self.cells_xy.shape[0] else np.zeros(0)
        patience = HALF_VALUE_LOOKS * np.clip(weights, 0.05, 1.0)
        value: FloatArray = weights * 0.5 ** (np.maximum(looks - 1, 0) / patience)
        return xy, value, sd

    def _into_area(self, xy: FloatArray) -> FloatArray:
        """The points, each outside the area replaced by the nearest cell centre (inside)."""
        if xy.shape[0] == 0 or self.cells_xy.shape[0] == 0:
            return xy
        outside = ~inside_polygon(xy, self.area_xy)
        out = xy.copy()
        out[outside] = self.cells_xy[self._cell_of(xy[outside])]
        return out

    def _inside(self, xy: FloatArray) -> BoolArray:
        """Whether each point is within one cell of the area's cells (a goal worth flying to)."""
        if xy.shape[0] == 0 or self.cells_xy.shape[0] == 0:
            return np.zeros(xy.shape[0], dtype=bool)
        d2 = ((xy - self.cells_xy[self._cell_of(xy)]) ** 2).sum(axis=1)
        near: BoolArray = d2 <= 2.0 * self.cell_m**2
        return near

    def _sweep_goals(
        self, robot_xy: FloatArray, memory: SearchProgress, unseen: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        """The nearest sweep point with a fresh cell (the first in lawn-mower order among equally
        near ones; the one being flown to while it has such a cell), valued by the unseen mass that
        it and the `goals` - 1 next nearest such points would look at (what going on with the
        sweep finds). A cell is fresh while no look has reached it; once every cell was looked
        at, while out of view and holding enough unseen mass to keep the search going were every
        cell like it (another pass: p_D or the targets expected may call for more than one)."""
        fresh_cell = memory.looks == 0
        if not fresh_cell.any():
            enough = self.params.stop_below / max(self.cells_xy.shape[0], 1)
            fresh_cell = (unseen > enough) & ~memory.in_view
        fresh = fresh_cell[self.cell_of_pair]
        n = self.sweep_xy.shape[0]
        count = np.bincount(self.sweep_of_pair[fresh], minlength=n)
        value: FloatArray = np.bincount(
            self.sweep_of_pair[fresh], weights=unseen[self.cell_of_pair[fresh]], minlength=n
        ).astype(np.float64)
        fresh_points = np.flatnonzero(count > 0)
        if fresh_points.size == 0:
            return np.zeros((0, 2)), np.zeros(0)
        dist = np.hypot(*(self.sweep_xy[fresh_points] - robot_xy).T)
        if memory.goal_xy is not None:  # the sweep point being flown to, while it is fresh
            dist[np.hypot(*(self.sweep_xy[fresh_points] - memory.goal_xy).T) < 1e-9] = -1.0
        nxt = fresh_points[np.argsort(dist, kind="stable")[: self.params.goals]]
        return self.sweep_xy[nxt[:1]], np.array([float(value[nxt].sum())])

    def _track_goals(self, tracks: Tracks, t_s: float) -> tuple[FloatArray, FloatArray]:
        """Means and values of the confirmed tracks: existence x P(moved beyond half the view) x
    P(still in the view centred on the mean), from the track's honest covariance."""
        conf = tracks.confirmed
        if not conf.any():
            return np.zeros((0, 2)), np.zeros(0)
        covs = grown_covs(tracks, max(t_s, float(tracks.last_t_s.max())), self.params.motion)
        var_m2 = np.maximum(0.5 * (covs[conf, 0, 0] + covs[conf, 1, 1]), 1e-9)
        r2 = self.params.view_radius_m**2
        lost = np.exp(-0.25 * r2 / (2.0 * var_m2))  # farther than half the view from its mean
        in_view = 1.0 - np.exp(-r2 / (2.0 * var_m2))  # inside the view centred on its mean
        value: FloatArray = tracks.existence[conf] * lost * in_view
        return tracks.means[conf, :2], value

    def _choose(self, robot_xy: FloatArray, goals_xy: FloatArray, values: FloatArray,
                sweep_xy: FloatArray, sweep_value: FloatArray,
                memory: SearchProgress) -> SearchProgress:
        """The memory with the goal to fly to: the one being flown to, unless it is done or a goal
        worth much more has turned up; else the first of the best order over the goals and the
        sweep's next point."""
        worth = values > 1e-6
        goals_xy, values = self._into_area(goals_xy[worth]), values[worth]
        cand_xy = np.vstack([goals_xy, sweep_xy])
        cand_values = np.concatenate([values, sweep_value])
        tour_xy, tour_values = self._follow(robot_xy, cand_xy, cand_values, memory)
        stale = values.size and values.max() > max(INTERRUPT_VALUE,
                                                   INTERRUPT_RATIO * tour_values.max(initial=0.0))
        if tour_xy.shape[0] and not stale:
            return replace(memory, goal_xy=tour_xy[0], tour_xy=tour_xy, tour_values=tour_values)
        if cand_values.size == 0:
            return replace(memory, goal_xy=None, tour_xy=np.zeros((0, 2)), tour_values=np.zeros(0))
        near = cand_values * np.exp(-np.hypot(*(cand_xy - robot_xy).T) / self.horizon_m)
        top = np.argsort(-near, kind="stable")[: self.params.goals]
        order = top[best_order(robot_xy, cand_xy[top], cand_values[top], self.horizon_m)]
        keep = order[:COMMIT_GOALS]
        return replace(memory, goal_xy=cand_xy[keep[0]], tour_xy=cand_xy[keep],
                       tour_values=cand_values[keep])

    def _follow(self, robot_xy: FloatArray, goals_xy: FloatArray, values: FloatArray,
                memory: SearchProgress) -> tuple[FloatArray, FloatArray]:
        """The rest of the tour being flown: each goal moved to the candidate within a cell of it
        (so that it follows a moving track), and dropped once gone, worth less than half its
        planned value, or reached (the first)."""
        keep_xy: list[FloatArray] = []
        keep_values: list[float] = []
        for xy, planned in zip(memory.tour_xy, memory.tour_values, strict=True):
            if values.size == 0:
                break
            same = np.hypot(*(goals_xy - xy).T) <= self.cell_m
            if not same.any():
                continue
            best = int(np.argmax(np.where(same, values, -1.0)))
            reached = np.hypot(*(goals_xy[best] - robot_xy)) <= REACHED_M
            if values[best] < 0.5 * planned or (not keep_xy and reached):
                continue
            keep_xy.append(goals_xy[best])
            keep_values.append(float(planned))
        if not keep_xy:
            return np.zeros((0, 2)), np.zeros(0)
        return np.array(keep_xy), np.array(keep_values)


def best_order(robot_xy: FloatArray, goals_xy: FloatArray, values: FloatArray,
               horizon_m: float) -> IntArray:
    """The order of the goals (indices) maximising sum(value exp(-distance flown / horizon)),
    every order tried."""
    k = goals_xy.shape[0]
    if k <= 1:
        return np.arange(k, dtype=np.int64)
    orders = np.array(list(itertools.permutations(range(k))), dtype=np.int64)  # (k!, k)
    points = np.vstack([robot_xy[None, :], goals_xy])
    hop = np.hypot(*(points[:, None, :] - points[None, :, :]).transpose(2, 0, 1))
    path = np.column_stack([np.zeros(len(orders), dtype=np.int64), orders + 1])
    flown = np.cumsum(hop[path[:, :-1], path[:, 1:]], axis=1)
    score = (values[orders] * np.exp(-flown / horizon_m)).sum(axis=1)
    best: IntArray = orders[int(np.argmax(score))]
    return best


def _lost(prior: Mixture, tracks: Tracks, mixture: Mixture) -> FloatArray:
    """(m,) each initial component's weight that neither a confirmed track (a whole target each)
    nor the unexplained weight of the components now near it (within LOST_SIGMAS of it, nearest
    to it of all the initial components) accounts for."""
    found = tracks.confirmed
    unexplained = ~np.isin(mixture.labels, tracks.ids[found])
    held = np.concatenate([np.ones(int(found.sum())), mixture.weights[unexplained]])
    xy = np.vstack([tracks.means[found, :2], mixture.means[unexplained, :2]])
    maha = _mahalanobis2(xy, prior)
    lost = prior.weights.copy()
    if xy.shape[0]:
        nearest = np.argmin(maha, axis=1)
        near = maha[np.arange(xy.shape[0]), nearest] <= LOST_SIGMAS**2
        lost -= np.bincount(nearest[near], weights=held[near], minlength=prior.size)
    out: FloatArray = np.maximum(lost, 0.0)
    return out


def _mahalanobis2(xy: FloatArray, mixture: Mixture) -> FloatArray:
    """(k, m) the squared Mahalanobis distance of each point to each component's position."""
    d = xy[:, None, :] - mixture.means[None, :, :2]
    maha: FloatArray = np.einsum("kmi,mij,kmj->km", d, np.linalg.inv(mixture.covs[:, :2, :2]), d)
    return maha


def _found_ids(tracks: Tracks) -> IntArray:
    """Ids of the confirmed tracks."""
    ids: IntArray = tracks.ids[tracks.confirmed]
    return ids


def make_search_track(world: World, params: SearchTrackParams) -> SearchTrack:
    """The planner over the world (or the params' convex area inside it), cells of about half the
    view radius, and sweep lanes as wide as the sure view."""
    area_xy = _area_xy(world, params.area_xy)
    cell_m = max(params.view_radius_m / 2.0,
                 math.sqrt(world.width_m * world.height_m / MAX_CELLS))
    seen_m = max(params.view_radius_m - cell_m / math.sqrt(2.0), 0.5 * cell_m)
    cells_xy = _cells(world, cell_m, area_xy)
    sweep_xy = _sweep_points(world, cell_m, seen_m, area_xy)
    near = np.hypot(*(sweep_xy[:, None, :] - cells_xy[None, :, :]).transpose(2, 0, 1)) <= seen_m
    sweep_of_pair, cell_of_pair = (a.astype(np.int64) for a in np.nonzero(near))
    horizon_m = params.horizon_m or max(world.width_m, world.height_m)
    return SearchTrack(params, cells_xy, cell_m, seen_m, sweep_xy, sweep_of_pair, cell_of_pair,
                       _cell_at(world, cell_m, cells_xy), horizon_m, area_xy)


def _area_xy(world: World, area_xy: FloatArray | None) -> FloatArray:
    """The search area's polygon (the world's rectangle when none is given)."""
    if area_xy is None:
        w, h = world.width_m, world.height_m
        return np.array([[0.0, 0.0], [w, 0.0], [w, h], [0.0, h]])
    polygon = np.asarray(area_xy, dtype=np.float64)
    if polygon.ndim != 2 or polygon.shape[0] < 3 or polygon.shape[1] != 2:
        raise InputError(f"area_xy: expected a (k >= 3, 2) polygon, got shape {polygon.shape}",
                         reason="expected a polygon of at least 3 points")
    return polygon


def inside_polygon(xy: FloatArray, polygon_xy: FloatArray) -> BoolArray:
    """Whether each point (m, 2) lies inside the polygon (k, 2) (even-odd rule, any shape)."""
    a, b = polygon_xy, np.roll(polygon_xy, -1, axis=0)
    x, y = xy[:, 0:1], xy[:, 1:2]
    crosses = (a[:, 1] > y) != (b[:, 1] > y)
    dy = np.where(b[:, 1] == a[:, 1], 1.0, b[:, 1] - a[:, 1])
    x_at = a[:, 0] + (y - a[:, 1]) * (b[:, 0] - a[:, 0]) / dy
    inside: BoolArray = (np.sum(crosses & (x < x_at), axis=1) % 2) == 1
    return inside


def _cells(world: World, cell_m: float, area_xy: FloatArray) -> FloatArray:
    """Centres of the grid's cells that lie inside the area."""
    xs = np.arange(cell_m / 2.0, world.width_m, cell_m)
    ys = np.arange(cell_m / 2.0, world.height_m, cell_m)
    grid = np.array(np.meshgrid(xs, ys, indexing="ij")).reshape(2, -1).T
    inside: FloatArray = grid[inside_polygon(grid, area_xy)] if grid.size else np.zeros((0, 2))
    return inside


def _sweep_points(
    world: World, cell_m: float, seen_m: float, area_xy: FloatArray
) -> FloatArray:
    """Lawn-mower points inside the area: north-south lanes as wide as the sure view (2 seen_m),
    one point per cell along each lane, alternating direction."""
    lane_m = max(2.0 * seen_m, cell_m)
    lanes_x = np.arange(min(seen_m, world.width_m / 2.0), world.width_m, lane_m)
    if lanes_x.size and world.width_m - lanes_x[-1] > seen_m:
        lanes_x = np.append(lanes_x, world.width_m - min(seen_m, world.width_m / 2.0))
    ys = np.arange(cell_m / 2.0, world.height_m, cell_m)
    points = [np.zeros((0, 2))]
    for lane, x in enumerate(lanes_x):
        along = ys if lane % 2 == 0 else ys[::-1]
        lane_points = np.column_stack([np.full(along.size, x), along])
        points.append(lane_points[inside_polygon(lane_points, area_xy)])
    return np.concatenate(points)


def _cell_at(world: World, cell_m: float, cells_xy: FloatArray) -> IntArray:
    """(nx, ny) the index of the cell on each square of the full grid, -1 where none is."""
    nx = max(int(np.ceil(world.width_m / cell_m - 1e-9)), 1)
    ny = max(int(np.ceil(world.height_m / cell_m - 1e-9)), 1)
    table = np.full((nx, ny), -1, dtype=np.int64)
    ix = np.clip(np.floor(cells_xy[:, 0] / cell_m), 0, nx - 1).astype(np.int64)
    iy = np.clip(np.floor(cells_xy[:, 1] / cell_m), 0, ny - 1).astype(np.int64)
    table[ix, iy] = np.arange(cells_xy.shape[0])
    return table


def inscribed_radius_m(polygon_xy: FloatArray) -> float:
    """Radius of the largest disk around the origin inside a convex polygon around it (0 when the
    origin is outside)."""
    p = np.asarray(polygon_xy, dtype=np.float64)
    a, b = p, np.roll(p, -1, axis=0)
    edge = b - a
    length = np.hypot(*edge.T)
    # Signed distance of the origin from each edge's line, positive on the polygon's side.
    cross = (edge[:, 0] * -a[:, 1] - edge[:, 1] * -a[:, 0]) / np.maximum(length, 1e-12)
    sign = 1.0 if float(np.sum(a[:, 0] * b[:, 1] - b[:, 0] * a[:, 1])) > 0 else -1.0
    return max(float(np.min(sign * cross)), 0.0)
