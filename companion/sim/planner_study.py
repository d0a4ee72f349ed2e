"""The study's planners side by side: the paper's lawn-mower experiments flown by each planner.

Each lawn-mower experiment of the study is run again with `robot.planner` set to every other
planner asked for, over the same seeds; the lawn mower's own runs are the study's. From those
results `planners_table` builds one row per (experiment, planner): the time until every target
is confirmed (`t_all_confirmed_s`), its ratio to the lawn mower's, GOSPA and OSPA over the last
20 % of steps, the count at the end and the Mahalanobis distance; `write_planner_outputs` writes
it as `planners.md` with, per experiment, the flown paths of seed 1 (`paths-<scenario>.png`)
and GOSPA over time, mean ± std over seeds (`gospa-<scenario>.png`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from companion.errors import ConfigError
from companion.plan.planners import PlannerKind

__all__ = [
    "BASELINE",
    "PLANNERS",
    "is_lawnmower_experiment",
    "parse_planners",
    "planner_rows",
    "planners_table",
    "write_planner_outputs",
]

FloatArray = NDArray[np.float64]
Result = dict[str, Any]
# Results of every run by (scenario, planner), in seed order; the baseline's are the study's own.
PlannerResults = Mapping[tuple[str, str], Sequence[Result]]

PLANNERS = tuple(p.value for p in PlannerKind)
BASELINE = PlannerKind.LAWNMOWER.value
LAWNMOWER_PREFIX = "paper-lawnmower-"
OPTION = "--planners"

HEADER = (
    "scenario", "planner", "every target confirmed at (s)", "never all confirmed",
    "time / lawn mower", "GOSPA last 20 % (m)", "count = truth at the end",
    "count within ±1", "Mahalanobis to closest", "OSPA last 20 % (m)",
)


def parse_planners(text: str) -> list[str]:
    """The planner names of a comma-separated value, in order, once each; ConfigError naming
    --planners for an empty or unknown name."""
    names = [part.strip() for part in text.split(",")]
    for name in names:
        if not name:
            raise ConfigError(OPTION, f"an empty name in {text!r}")
        if name not in PLANNERS:
            raise ConfigError(OPTION, f"unknown planner {name!r} (known: {', '.join(PLANNERS)})")
    return list(dict.fromkeys(names))


def is_lawnmower_experiment(scenario: str) -> bool:
    """Whether a study scenario is one of the paper's lawn-mower experiments."""
    return scenario.startswith(LAWNMOWER_PREFIX)


def _values(results: Sequence[Result], key: str) -> FloatArray:
    """One summary value over the seeds (None becomes nan)."""
    return np.array([math.nan if r["summary"][key] is None else float(r["summary"][key])
                     for r in results], dtype=np.float64)


def _mean_sd(values: FloatArray, digits: int = 2) -> str:
    """mean ± population sd of the finite values; n/a when there are none."""
    finite = values[np.isfinite(values)]
    if finite.size == 0:
        return "n/a"
    return f"{finite.mean():.{digits}f} ± {finite.std():.{digits}f}"


def time_ratio(times: FloatArray, baseline: FloatArray) -> str:
    """Mean time over the mean lawn-mower time, on the seeds where both confirmed every target
    (paired); how many seeds that is when not all; n/a when none."""
    both = np.isfinite(times) & np.isfinite(baseline) & (baseline > 0)
    if not both.any():
        return "n/a"
    text = f"{times[both].sum() / baseline[both].sum():.2f}"
    if both.sum() < times.size:
        text += f" ({int(both.sum())} paired seeds)"
    return text


def _share(hits: NDArray[np.bool_]) -> str:
    return f"{int(hits.sum())}/{hits.size}"


def planner_rows(
    results: PlannerResults, scenarios: Sequence[str], planners: Sequence[str]
) -> list[list[str]]:
    """One row per (scenario, planner) in that order, cells as HEADER names them; the ratio is
    to the BASELINE runs of the same scenario (which results must hold)."""
    rows = []
    for scenario in scenarios:
        base = _values(results[(scenario, BASELINE)], "t_all_confirmed_s")
        for planner in planners:
            runs = results[(scenario, planner)]
            t_all = _values(runs, "t_all_confirmed_s")
            error = _values(runs, "tracks_confirmed") - _values(runs, "true_count")
            rows.append([
                scenario, planner, _mean_sd(t_all, 0), _share(~np.isfinite(t_all)),
                time_ratio(t_all, base), _mean_sd(_values(runs, "gospa_tail_mean")),
                _share(error == 0), _share(np.abs(error) <= 1),
                _mean_sd(_values(runs, "mahal_closest_mean")),
                _mean_sd(_values(runs, "ospa_tail_mean")),
            ])
    return rows


def planners_table(
    results: PlannerResults, scenarios: Sequence[str], planners: Sequence[str], seeds: int,
    steps: int | None = None,
) -> str:
    """The Markdown of planners.md: a title, what the cells are, and the rows."""
    shortened = "" if steps is None else f", every run cut to {steps} steps (a quick look)"
    lines = [
        f"### Planners side by side on the paper's lawn-mower experiments, the same {seeds} "
        f"seeds{shortened}", "",
        "mean ± sd over seeds (the time over the seeds that confirmed every target); time / "
        "lawn mower: the mean time over the lawn mower's on the seeds where both confirmed "
        "every target", "",
        "| " + " | ".join(HEADER) + " |", "|" + "|".join("---" for _ in HEADER) + "|",
    ]
    lines += ["| " + " | ".join(row) + " |"
              for row in planner_rows(results, scenarios, planners)]
    return "\n".join(lines) + "\n"


def _safe(name: str) -> str:
    return "".join(c if c.isalnum() or c in "._-" else "_" for c in name)


def write_planner_outputs(
    results: PlannerResults, scenarios: Sequence[str], planners: Sequence[str], seeds: int,
    out_dir: Path, steps: int | None = None,
) -> tuple[str, list[Path]]:
    """Write planners.md and, when matplotlib is there, the per-scenario figures (the paths of
    the first seed, whose results carry a "path"; GOSPA over time) in out_dir; the Markdown and
    the figures' paths."""
    import importlib.util  # noqa: PLC0415

    out_dir.mkdir(parents=True, exist_ok=True)
    markdown = planners_table(results, scenarios, planners, seeds, steps)
    (out_dir / "planners.md").write_text(markdown)
    if importlib.util.find_spec("matplotlib") is None:
        return markdown, []
    from companion.sim.path_plots import plot_paths  # noqa: PLC0415
    from companion.sim.plots import aggregate, plot_bands  # noqa: PLC0415

    figures = []
    for scenario in scenarios:
        paths = [results[(scenario, p)][0]["path"] for p in planners
                 if "path" in results[(scenario, p)][0]]
        if paths:
            seed = results[(scenario, planners[0])][0]["summary"]["seed"]
            figures.append(plot_paths(paths, f"{scenario}: flown paths, seed {seed}",
                                      out_dir / f"paths-{_safe(scenario)}.png"))
        bands = []
        for planner in planners:
            runs = results[(scenario, planner)]
            length = min(r["t_s"].size for r in runs)
            bands.append(aggregate(planner, runs[0]["t_s"][:length].astype(np.float64),
                                   [r["series"]["gospa"][:length].astype(np.float64)
                                    for r in runs]))
        figures.append(plot_bands(bands, f"{scenario}: GOSPA over time, mean ± sd over {seeds} "
                                  "seeds", "GOSPA (m)", out_dir / f"gospa-{_safe(scenario)}.png"))
    return markdown, figures
