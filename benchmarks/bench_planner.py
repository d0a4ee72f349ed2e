"""Replan time of the search-and-track planner: median and p95 per call against the 20 ms goal.

    python -m benchmarks.bench_planner

Three cases: the paper's world (150 m square, 25 m view: 144 cells), the SITL walkers' field
(60 m x 40 m, the 1280x720 camera at 15 m), and the finest grid the planner builds (MAX_CELLS
cells); each with a full mixture (100 components, the filter's cap) and 30 confirmed tracks,
replanned 300 times from a robot that moves on between calls.
"""

from __future__ import annotations

import time

import numpy as np

from companion.plan.planners import move_towards
from companion.plan.search_track import SearchProgress, SearchTrackParams, make_search_track
from companion.plan.world import World
from companion.sat.mixture import Mixture, make_mixture
from companion.sat.motion import TargetMotion
from companion.sat.tracks import Tracks

GOAL_MS = 20.0
CALLS = 300


def _tracks(rng: np.random.Generator, world: World, n: int) -> tuple[Tracks, Mixture]:
    """n confirmed tracks at random, and a mixture of 100 components, n of them theirs."""
    empty = Tracks.empty(2, 30)
    ids = np.arange(n, dtype=np.int64)
    xy = rng.uniform(0, 1, (n, 2)) * [world.width_m, world.height_m]
    tracks = empty._replace(
        ids=ids, hits=np.full(n, 5), life=np.full(n, 5), confirmed=np.ones(n, bool),
        born_t_s=np.zeros(n), last_t_s=np.zeros(n), seen_t_s=rng.uniform(-300, 0, n),
        score=np.full(n, 8.0), alone=np.zeros(n, bool), means=xy,
        covs=np.broadcast_to(np.eye(2), (n, 2, 2)).copy(), win_t_s=np.zeros((n, 30)),
        win_xy=np.zeros((n, 30, 2)), win_count=np.zeros(n, np.int64), gp_mu=np.zeros((n, 2)),
        gp_beta=np.zeros((n, 30, 2)), gp_ky_inv=np.zeros((n, 30, 30)),
    )
    m = 100
    means = np.vstack([xy, rng.uniform(0, 1, (m - n, 2)) * [world.width_m, world.height_m]])
    mix = make_mixture(rng.uniform(0.01, 1.0, m), means, np.array([20.0 * np.eye(2)] * m))
    labels = np.concatenate([ids, np.full(m - n, -1)])
    return tracks, Mixture(mix.weights, mix.means, mix.covs, labels)


def bench(name: str, world: World, view_m: float) -> float:
    """Print one case's median and p95 replan time; return the median in ms."""
    rng = np.random.default_rng(1)
    planner = make_search_track(world, SearchTrackParams(
        view_radius_m=view_m, motion=TargetMotion(speed_m_s=0.5)))
    tracks, mix = _tracks(rng, world, 30)
    robot = np.array([world.width_m / 2, world.height_m / 2])
    progress: SearchProgress | int = 0
    times_ms = []
    for k in range(CALLS):
        started = time.perf_counter_ns()
        waypoint, progress = planner.next_waypoint(robot, mix, tracks, world, progress, float(k))
        times_ms.append((time.perf_counter_ns() - started) / 1e6)
        robot = move_towards(robot, waypoint, 1.0)
    median, p95 = float(np.median(times_ms)), float(np.percentile(times_ms, 95))
    print(f"{name}: {planner.cells_xy.shape[0]} cells, replan median {median:.2f} ms, "
          f"p95 {p95:.2f} ms (goal < {GOAL_MS:g} ms: {'met' if median < GOAL_MS else 'NOT met'})")
    return median


def main() -> None:
    """Run the three cases."""
    bench("paper world 150 m x 150 m, view 25 m", World(150.0, 150.0), 25.0)
    bench("walkers field 60 m x 40 m, 1280x720 camera at 15 m", World(60.0, 40.0), 4.0)
    bench("finest grid, 150 m x 150 m, view 1 m", World(150.0, 150.0), 1.0)


if __name__ == "__main__":
    main()
