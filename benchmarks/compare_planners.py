"""The lawn mower and the search-and-track planner on the paper's scenarios, same seeds.

    python -m benchmarks.compare_planners [--seeds N] [--priors exact,under,over,empty,dynamic]

For each prior (the paper's 10 % clutter scenarios; empty = no initial components; dynamic = the
moving targets) and seed 1..N, runs the lawn mower as shipped and the search-track planner on the
same scenario, and prints per prior the medians of the time until every target is confirmed
(`t_all_confirmed_s`, its ratio search-track / lawn mower), the means of that time over the seeds
on which both planners confirmed every target and their ratio (as the study's planners.md), the
count at the end, the Mahalanobis distance to the closest track, OSPA and GOSPA over the last 20 %
of steps. `--stationary` tells the filter of the stationary scenarios that the targets do not
move (filter.target_speed = 0) in both planners' runs; without it the filter's default motion
class (0.3 m/s) is kept.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
from typing import Any

from companion.scenario_lookup import resolve_scenario
from companion.sim.run import simulate
from companion.sim.scenario import load_scenario, parse_scenario, scenario_to_dict

PRIORS = {
    "exact": ("paper-lawnmower-exact-c10", None),
    "under": ("paper-lawnmower-under-c10", None),
    "over": ("paper-lawnmower-over-c10", None),
    "empty": ("paper-lawnmower-exact-c10", {"kind": "empty", "count": 0}),
    "dynamic": ("paper-lawnmower-dynamic-c10", None),
}
KEYS = ("t_all_confirmed_s", "tracks_confirmed", "mahal_closest_mean", "ospa_tail_mean",
        "gospa_tail_mean")


def run(prior: str, planner: str, seed: int, stationary: bool) -> dict[str, Any]:
    """The simulate summary of one prior's scenario with that planner and seed."""
    name, belief = PRIORS[prior]
    s = load_scenario(resolve_scenario(name), seed=seed)
    data = scenario_to_dict(s)
    data["robot"]["planner"] = planner
    if belief is not None:
        data["belief"] = {**data["belief"], **belief}
    if stationary and prior != "dynamic":
        data["filter"]["target_speed"] = 0.0
    scenario = dataclasses.replace(parse_scenario(data, name=f"{name}-{planner}"), seed=seed)
    return simulate(scenario).summary()


def _median(rows: list[dict[str, Any]], key: str) -> float:
    values = [float("inf") if r[key] is None else float(r[key]) for r in rows]
    return statistics.median(values)


def _paired_means(mower: list[dict[str, Any]], search: list[dict[str, Any]]) -> dict[str, float]:
    """Mean t_all_confirmed_s of each planner over the seeds on which both confirmed every
    target, and how many seeds those are (nan means when none)."""
    both = [(a["t_all_confirmed_s"], b["t_all_confirmed_s"]) for a, b in zip(mower, search,
                                                                               strict=True)
            if a["t_all_confirmed_s"] is not None and b["t_all_confirmed_s"] is not None]
    if not both:
        return {"lawnmower": float("nan"), "search-track": float("nan"), "seeds": 0.0}
    return {"lawnmower": statistics.mean(a for a, _ in both),
            "search-track": statistics.mean(b for _, b in both), "seeds": float(len(both))}


def main() -> None:
    """Print the comparison table."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--priors", default="exact,under,over,empty,dynamic")
    ap.add_argument("--stationary", action="store_true")
    args = ap.parse_args()
    print("| prior | planner | t_all_confirmed_s | ratio | paired mean (ratio) | count (10) | "
          "mahal | ospa tail | gospa tail | all found |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for prior in args.priors.split(","):
        seeds = range(1, args.seeds + 1)
        rows = {p: [run(prior, p, seed, args.stationary) for seed in seeds]
                for p in ("lawnmower", "search-track")}
        base = _median(rows["lawnmower"], "t_all_confirmed_s")
        paired = _paired_means(rows["lawnmower"], rows["search-track"])
        for planner, got in rows.items():
            t = _median(got, "t_all_confirmed_s")
            mean = paired[planner]
            found = sum(r["t_all_confirmed_s"] is not None for r in got)
            near = sum(abs(r["tracks_confirmed"] - r["true_count"]) <= 1 for r in got)
            print(f"| {prior} | {planner} | {t:.0f} | {t / base:.2f} | "
                  f"{mean:.0f} ({mean / paired['lawnmower']:.2f}, {paired['seeds']:.0f} seeds) | "
                  f"{_median(got, 'tracks_confirmed'):g} (+-1 in {near}/{len(got)}) | "
                  f"{_median(got, 'mahal_closest_mean'):.3f} | "
                  f"{_median(got, 'ospa_tail_mean'):.2f} | {_median(got, 'gospa_tail_mean'):.2f} | "
                  f"{found}/{len(got)} |", flush=True)


if __name__ == "__main__":
    main()
