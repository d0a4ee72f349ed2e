"""Speed of the labeled multi-Bernoulli filter (filter.kind = "lmb") beside the GM-PHD.

Run: python benchmarks/bench_lmb.py [--scenario NAME] [--seed S] [--walkers N] [--steps N]

1. The paper's 10-target lawn-mower scenario, as `companion simulate` runs it, with each kind:
   filter time per step (median, p95) and for the whole run.
2. N walkers (50) inside one footprint: a disk of 30 m radius over a hovering sensor, targets
   walking at 0.3 m/s inside it, p_D 0.98, 0.1 false positives per scan, 1 m noise; the LMB's
   step once every walker has a confirmed track (median, p95 over the last half of the steps).
Then the issue's targets, each met or NOT met. The machine may be shared: compare the two kinds
within one run rather than single figures across runs.
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np

from companion.sat.filter import FilterKind, SatParams, Scan, initial_state, step
from companion.sat.fov import Disk
from companion.sat.gp import GpPredictor
from companion.sat.mixture import Mixture
from companion.sat.motion import TargetMotion
from companion.sat.tracks import TrackParams
from companion.scenario_lookup import resolve_scenario
from companion.sim.run import simulate
from companion.sim.scenario import load_scenario

TARGET_MEDIAN_MS = 1.0
TARGET_P95_MS = 3.0
TARGET_RUN_S = 5.0
TARGET_CROWD_MEDIAN_MS = 5.0
RADIUS_M = 30.0


def _verdict(ok: bool) -> str:
    return "met" if ok else "NOT met"


def bench_paper(scenario: str, seed: int) -> dict[str, tuple[float, float, float]]:
    """(median ms, p95 ms, run s) of the filter step per kind on a shipped scenario."""
    base = load_scenario(resolve_scenario(scenario), seed=seed)
    figures = {}
    for kind in FilterKind:
        s = dataclasses.replace(base, filter=dataclasses.replace(base.filter, kind=kind))
        summary = simulate(s).summary()
        figures[kind.value] = (summary["step_ms_median"], summary["step_ms_p95"],
                               summary["filter_s"])
        print(f"1. {s.name}, seed {seed}, {summary['steps']} steps, {kind.value}: step median "
              f"{summary['step_ms_median']:.3f} ms, p95 {summary['step_ms_p95']:.3f} ms, run "
              f"{summary['filter_s']:.2f} s; {summary['tracks_confirmed']} confirmed of "
              f"{summary['true_count']}")
    return figures


def bench_crowd(walkers: int, steps: int, seed: int) -> tuple[float, float, int]:
    """(median ms, p95 ms, confirmed tracks at the end) of LMB steps over a crowd in view."""
    rng = np.random.default_rng(seed)
    region = Disk(np.zeros(2), RADIUS_M)
    r_cov = np.eye(2)
    params = SatParams(kind=FilterKind.LMB, p_detect=0.98, clutter_per_scan=0.1,
                       q_m2_per_s=0.045, tracks=TrackParams(motion=TargetMotion(0.3, 200.0)))
    gp = GpPredictor(params.gp)
    angle = rng.uniform(0.0, 2.0 * np.pi, walkers)
    xy = RADIUS_M * 0.8 * np.sqrt(rng.uniform(0.0, 1.0, walkers))[:, None] * np.column_stack(
        [np.cos(angle), np.sin(angle)])
    heading = rng.uniform(0.0, 2.0 * np.pi, walkers)
    state = initial_state(Mixture.empty(2), 0.0, params)
    times_ms = []
    for k in range(1, steps + 1):
        heading += rng.normal(0.0, 0.1, walkers)
        xy += 0.3 * np.column_stack([np.cos(heading), np.sin(heading)])
        outside = np.hypot(*xy.T) > RADIUS_M * 0.8  # walkers turn back at the edge
        heading[outside] += np.pi
        seen = xy[rng.random(walkers) < 0.98]
        z = np.vstack([seen + rng.normal(size=seen.shape),
                       region.sample_uniform(rng, int(rng.poisson(0.1)))])
        scan = Scan(float(k), region, z, r_cov, np.zeros(2))
        t0 = time.perf_counter_ns()
        state, _ = step(state, scan, params, gp)
        times_ms.append((time.perf_counter_ns() - t0) / 1e6)
    tail = np.array(times_ms[steps // 2:])
    confirmed = int(state.tracks.confirmed.sum())
    print(f"2. {walkers} walkers in one {RADIUS_M:.0f} m footprint, {steps} steps: LMB step "
          f"median {np.median(tail):.2f} ms, p95 {np.percentile(tail, 95):.2f} ms over the last "
          f"half; {confirmed} confirmed tracks at the end")
    return float(np.median(tail)), float(np.percentile(tail, 95)), confirmed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="paper-lawnmower-exact-c10")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--walkers", type=int, default=50)
    parser.add_argument("--steps", type=int, default=400)
    args = parser.parse_args()
    paper = bench_paper(args.scenario, args.seed)
    crowd_median, _, _ = bench_crowd(args.walkers, args.steps, args.seed)
    median, p95, run = paper["lmb"]
    gm_median = paper["gmphd"][0]
    print("targets:")
    print(f"  LMB step median {median:.3f} ms < {TARGET_MEDIAN_MS} ms: "
          f"{_verdict(median < TARGET_MEDIAN_MS)} (GM-PHD {gm_median:.3f} ms, ratio "
          f"{median / gm_median:.2f})")
    print(f"  LMB step p95 {p95:.3f} ms < {TARGET_P95_MS} ms: {_verdict(p95 < TARGET_P95_MS)}")
    print(f"  LMB whole run {run:.2f} s < {TARGET_RUN_S} s: {_verdict(run < TARGET_RUN_S)}")
    print(f"  LMB step median with {args.walkers} in view {crowd_median:.2f} ms < "
          f"{TARGET_CROWD_MEDIAN_MS} ms: {_verdict(crowd_median < TARGET_CROWD_MEDIAN_MS)}")


if __name__ == "__main__":
    main()
