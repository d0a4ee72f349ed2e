"""The paper's simulation study: every experiment, Monte Carlo over seeds, beside the paper.

`run_study` runs each shipped `paper-*` scenario for seeds 1..N on worker processes (one per core
by default), prints the paper's tables with our mean and spread over seeds next to the paper's
numbers, and writes them (Markdown and CSV) with the plots under the output directory. With
planners named, it also flies the lawn-mower experiments with each of them on the same seeds
and writes planners.md with its figures (`companion.sim.planner_study`).
"""

from __future__ import annotations

import csv
import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from companion.errors import CompanionError, ConfigError
from companion.progress import progress_bar
from companion.sat.filter import FilterKind
from companion.scenario_lookup import resolve_scenario
from companion.sim.engine import run_tasks

FloatArray = NDArray[np.float64]

SERIES = ("tracks_confirmed", "weight_sum", "components", "ospa", "mahal_closest_mean",
          "max_track_var_m2", "gospa")


@dataclass(frozen=True, slots=True)
class Experiment:
    """One row/column of the paper's tables: a shipped scenario and its label."""

    scenario: str
    label: str


CLUTTER = (
    Experiment("paper-lawnmower-exact-c0", "0 %"),
    Experiment("paper-lawnmower-exact-c10", "10 %"),
    Experiment("paper-lawnmower-exact-c20", "20 %"),
)
ESTIMATE = (
    Experiment("paper-lawnmower-under-c10", "under"),
    Experiment("paper-lawnmower-exact-c10", "exact"),
    Experiment("paper-lawnmower-over-c10", "over"),
)
LARGEST = (
    Experiment("paper-largest-under-c10", "under"),
    Experiment("paper-largest-exact-c10", "exact"),
    Experiment("paper-largest-over-c10", "over"),
)
# The limited-FOV rule: as exact no-detection moments (ours), as the paper's Eq. push, and off;
# with the learned GP hyperparameters and with the untuned defaults.
FOV_RULE = {
    "learned GP": (
        Experiment("paper-lawnmower-exact-c10", "moment rule"),
        Experiment("paper-lawnmower-exact-c10-paperpush", "paper's Eq. push"),
        Experiment("paper-lawnmower-exact-c10-nopush", "off"),
    ),
    "untuned GP": (
        Experiment("paper-lawnmower-exact-c10-untuned", "moment rule"),
        Experiment("paper-lawnmower-exact-c10-untuned-paperpush", "paper's Eq. push"),
        Experiment("paper-lawnmower-exact-c10-untuned-nopush", "off"),
    ),
}
DYNAMIC = Experiment("paper-lawnmower-dynamic-c10", "dynamic")
ALL = (
    *CLUTTER, *ESTIMATE[::2], *FOV_RULE["learned GP"][1:], *FOV_RULE["untuned GP"], DYNAMIC,
    *LARGEST,
)
LAWNMOWER_GOAL_RUNS = (*CLUTTER, *ESTIMATE[::2])

# The paper's numbers (paper-study.md).
PAPER_CLUTTER = {
    "mahal_closest_mean": (3.0311, 2.3603, 2.5529),
    "mahal_closest_std": (2.6494, 1.9604, 2.6242),
    "mahal_second_mean": (8.2450, 7.0569, 7.0451),
}
PAPER_ESTIMATE = {
    "mahal_closest_mean": (3.0930, 2.3603, 3.3152),
    "mahal_closest_std": (2.5537, 1.9604, 2.2353),
    "mahal_second_mean": (7.3006, 7.0569, 7.5527),
}
PAPER_DYNAMIC_CLOSEST = 3.1570
PAPER_COUNT = {
    ("tracks_confirmed", "lawnmower"): (10, 7, 8),
    ("tracks_confirmed", "largest"): (3, 7, 5),
    ("weight_sum", "lawnmower"): (13.3769, 18.8052, 19.6354),
    ("weight_sum", "largest"): (11.3125, 14.1745, 13.0396),
}
GOALS = {"mahal_closest_mean": 1.0, "ospa_tail_mean": 3.0}
STONE_SOUP_OSPA_TAIL = 48.6


def run_one(
    scenario: str, seed: int, plot_dir: Path | None, steps: int | None = None,
    kind: str = "gmphd", planner: str | None = None, keep_path: bool = False,
) -> dict[str, Any]:
    """Simulate one shipped scenario with one seed, estimator kind and planner; its summary and
    time series, and its flown path when asked (a worker task).

    `steps` shortens every run to that many steps (a quick look, not the study's figures).
    `planner` replaces the scenario's robot.planner (the run is then named
    `<scenario>-<planner>`); `keep_path` adds "path", the run's `FlownPath`.
    """
    from companion.plan.planners import PlannerKind
    from companion.sim.run import simulate
    from companion.sim.scenario import load_scenario

    loaded = load_scenario(resolve_scenario(scenario), seed=seed)
    loaded = replace(loaded, filter=replace(loaded.filter, kind=FilterKind(kind)))
    if planner is not None:
        loaded = replace(loaded, name=f"{loaded.name}-{planner}",
                         robot=replace(loaded.robot, planner=PlannerKind(planner)))
    result = simulate(loaded if steps is None else replace(loaded, steps=steps))
    if plot_dir is not None:
        from companion.sim.plots import plot_run

        plot_run(result, plot_dir)
    series = {name: np.asarray(getattr(result, name), dtype=np.float32) for name in SERIES}
    summary = result.summary()
    out = {"summary": summary, "series": series, "t_s": result.t_s.astype(np.float32)}
    if keep_path:
        from companion.sim.path_plots import flown_path

        t_all = summary["t_all_confirmed_s"]
        found = "never all confirmed" if t_all is None else f"all confirmed at {t_all:.0f} s"
        out["path"] = flown_path(result, f"{loaded.robot.planner}: {found}\n"
                                         f"{summary['tracks_confirmed']} tracks, "
                                         f"{summary['true_count']} targets at the end")
    return out


@dataclass(frozen=True, slots=True)
class Runs:
    """Every run of the study, by scenario name, in seed order."""

    by_scenario: dict[str, list[dict[str, Any]]]

    def values(self, scenario: str, key: str) -> FloatArray:
        """One summary value over the seeds (None becomes nan)."""
        return np.array(
            [math.nan if r["summary"][key] is None else r["summary"][key]
             for r in self.by_scenario[scenario]],
            dtype=np.float64,
        )


def _fmt(values: FloatArray, digits: int = 2) -> str:
    """mean ± std over seeds, with the count of undefined values if any."""
    finite = values[np.isfinite(values)]
    if finite.size == 0:
        return "n/a"
    text = f"{finite.mean():.{digits}f} ± {finite.std():.{digits}f}"
    if finite.size < values.size:
        text += f" ({values.size - finite.size} undefined)"
    return text


def _table(title: str, header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    lines = [f"### {title}", "", "| " + " | ".join(header) + " |",
             "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines) + "\n"


def build_tables(runs: Runs) -> list[tuple[str, list[str], list[list[str]]]]:
    """The paper's tables with our mean ± std over seeds beside the paper's numbers."""
    tables: list[tuple[str, list[str], list[list[str]]]] = []
    names = {"mahal_closest_mean": "mean to closest", "mahal_closest_std": "std to closest",
             "mahal_second_mean": "mean to second closest"}
    for title, exps, paper in (
        ("Mahalanobis distance of the true targets to confirmed tracks vs clutter (lawn mower)",
         CLUTTER, PAPER_CLUTTER),
        ("Mahalanobis distance vs initial estimate (lawn mower, 10 % clutter)", ESTIMATE,
         PAPER_ESTIMATE),
    ):
        header = ["", *[f"{e.label} (ours)" for e in exps], *[f"{e.label} (paper)" for e in exps]]
        rows = [[names[key], *[_fmt(runs.values(e.scenario, key)) for e in exps],
                 *[f"{v:.2f}" for v in paper[key]]] for key in names]
        tables.append((title, header, rows))
    tables.append((
        "Dynamic targets (lawn mower, exact, 10 % clutter)",
        ["", "ours", "paper"],
        [["mean to closest", _fmt(runs.values(DYNAMIC.scenario, "mahal_closest_mean")),
          f"{PAPER_DYNAMIC_CLOSEST:.2f}"],
         ["mean to second closest", _fmt(runs.values(DYNAMIC.scenario, "mahal_second_mean")), ""],
         ["confirmed tracks at the end (truth 10)",
          _fmt(runs.values(DYNAMIC.scenario, "tracks_confirmed")), ""],
         ["OSPA, last 20 % of steps (m)",
          _fmt(runs.values(DYNAMIC.scenario, "ospa_tail_mean")), ""],
         *[[what, _fmt(runs.values(DYNAMIC.scenario, key)), ""] for key, what in (
             ("gospa_final", "GOSPA at the end (m; c = 10, p = 2)"),
             ("gospa_missed_final", "GOSPA missed targets at the end"),
             ("gospa_false_final", "GOSPA false tracks at the end"),
             ("nees_mean", "NEES to the GOSPA-assigned track (2 = calibrated)"))]],
    ))
    header = ["", *[f"{e.label} (ours)" for e in ESTIMATE],
              *[f"{e.label} (paper)" for e in ESTIMATE]]
    rows = []
    for key, what in (("tracks_confirmed", "tracks"), ("weight_sum", "sum of weights")):
        for planner, exps in (("lawnmower", ESTIMATE), ("largest", LARGEST)):
            rows.append([f"{what}, {planner}", *[_fmt(runs.values(e.scenario, key)) for e in exps],
                         *[f"{v:g}" for v in PAPER_COUNT[(key, planner)]]])
    tables.append(("Estimated number at the end, lawn mower vs largest-Gaussian (truth 10)",
                   header, rows))
    rows = []
    for setting, exps in FOV_RULE.items():
        for e in exps:
            count_ok = runs.values(e.scenario, "tracks_confirmed") == runs.values(
                e.scenario, "true_count")
            rows.append([setting, e.label, _fmt(runs.values(e.scenario, "ospa_mean")),
                         _fmt(runs.values(e.scenario, "ospa_tail_mean")),
                         f"{int(count_ok.sum())}/{count_ok.size}",
                         _fmt(runs.values(e.scenario, "mahal_closest_mean")),
                         _fmt(runs.values(e.scenario, "nees_mean"))])
    tables.append(("The limited-FOV update rule (lawn mower, exact, 10 % clutter; OSPA c = 100, "
                   "p = 2)", ["GP", "rule", "OSPA mean (m)", "OSPA last 20 % (m)",
                              "count = truth at the end", "Mahalanobis to closest",
                              "NEES (2 = calibrated)"], rows))
    rows = []
    for e in LAWNMOWER_GOAL_RUNS:
        count_ok = runs.values(e.scenario, "tracks_confirmed") == runs.values(
            e.scenario, "true_count")
        mahal = runs.values(e.scenario, "mahal_closest_mean")
        tail = runs.values(e.scenario, "ospa_tail_mean")
        rows.append([e.scenario, f"{int(count_ok.sum())}/{count_ok.size}", _fmt(mahal),
                     _fmt(tail), _verdict(count_ok.all() and _below(mahal, 1.0)
                                          and _below(tail, 3.0))])
    tables.append(("Goals over the lawn-mower runs of stationary targets: count = truth at the "
                   "end, mean Mahalanobis to closest < 1.0 (paper 2.36), OSPA last 20 % < 3 m "
                   f"(Stone Soup GM-PHD {STONE_SOUP_OSPA_TAIL} m)",
                   ["scenario", "count = truth", "Mahalanobis to closest", "OSPA last 20 % (m)",
                    "goals met"], rows))
    rows = []
    for e in (*ESTIMATE, *LARGEST):
        weights = runs.values(e.scenario, "weight_sum")
        tracks = runs.values(e.scenario, "tracks_confirmed")
        comps = runs.values(e.scenario, "components")
        worst = np.array([_finite_mean(r["series"]["max_track_var_m2"])
                          for r in runs.by_scenario[e.scenario]], dtype=np.float64)
        rows.append([e.scenario, _fmt(tracks), _fmt(weights), _fmt(comps), _fmt(worst, 3)])
    tables.append(("Qualitative findings: the sum of weights and the component count over-estimate "
                   "the number (truth 10) that confirmed tracks give; largest-Gaussian keeps the "
                   "worst track variance smaller than the lawn mower",
                   ["scenario", "confirmed tracks", "sum of weights", "components",
                    "largest track variance, run mean (m²)"], rows))
    rows = [[e.scenario, _fmt(runs.values(e.scenario, "step_ms_median"), 3),
             _fmt(runs.values(e.scenario, "step_ms_p95"), 3),
             _fmt(runs.values(e.scenario, "filter_s"), 2),
             _fmt(runs.values(e.scenario, "steps"), 0)] for e in ALL]
    tables.append(("Filter time on this machine (per run; workers share the cores)",
                   ["scenario", "step median (ms)", "step p95 (ms)", "filter time (s)", "steps"],
                   rows))
    return tables


def _finite_mean(values: FloatArray) -> float:
    """Mean of the finite entries; nan when there are none."""
    finite = values[np.isfinite(values)]
    return float(finite.mean()) if finite.size else math.nan


def _below(values: FloatArray, limit: float) -> bool:
    return bool(np.all(np.isfinite(values)) and values.mean() < limit)


def _verdict(ok: bool) -> str:
    return "yes" if ok else "NO"


def _write_outputs(runs: Runs, out_dir: Path, seeds: int, steps: int | None) -> str:
    """Tables (Markdown, CSV), per-run CSV and the aggregated plots; returns the Markdown."""
    from companion.sim.plots import aggregate, plot_bands

    out_dir.mkdir(parents=True, exist_ok=True)
    tables = build_tables(runs)
    shortened = "" if steps is None else f", every run cut to {steps} steps (a quick look)"
    markdown = f"# The paper's study, {seeds} seeds per experiment{shortened}\n\n" + "\n".join(
        _table(title, header, rows) for title, header, rows in tables)
    (out_dir / "tables.md").write_text(markdown)
    for i, (title, header, rows) in enumerate(tables, start=1):
        with (out_dir / f"table{i}.csv").open("w", newline="") as fh:
            writer = csv.writer(fh)
            writer.writerow([title])
            writer.writerow(header)
            writer.writerows(rows)
    with (out_dir / "runs.csv").open("w", newline="") as fh:
        first = next(iter(runs.by_scenario.values()))[0]["summary"]
        summaries = csv.DictWriter(fh, fieldnames=list(first))
        summaries.writeheader()
        for results in runs.by_scenario.values():
            summaries.writerows(r["summary"] for r in results)

    def band(e: Experiment, key: str, label: str | None = None) -> Any:
        results = runs.by_scenario[e.scenario]
        length = min(r["t_s"].size for r in results)
        return aggregate(label or e.label, results[0]["t_s"][:length].astype(np.float64),
                         [r["series"][key][:length].astype(np.float64) for r in results])

    plots = out_dir / "plots"
    plots.mkdir(exist_ok=True)
    for exps, what in ((CLUTTER, "clutter"), (ESTIMATE, "estimate"), (LARGEST, "largest")):
        plot_bands([band(e, "tracks_confirmed") for e in exps],
                   f"Confirmed tracks over time ({what}), mean ± std over {seeds} seeds",
                   "confirmed tracks", plots / f"count-tracks-{what}.png", hline=10.0)
        plot_bands([band(e, "weight_sum") for e in exps],
                   f"Sum of weights over time ({what})", "sum of weights",
                   plots / f"count-weights-{what}.png", hline=10.0)
    for setting, exps in FOV_RULE.items():
        plot_bands([band(e, "ospa") for e in exps],
                   f"OSPA (c = 100, p = 2) with and without the limited-FOV rule ({setting})",
                   "OSPA (m)", plots / f"ospa-fov-rule-{setting.split()[0]}.png", hline=3.0)
    plot_bands([band(ESTIMATE[1], "mahal_closest_mean", "lawn mower, static"),
                band(DYNAMIC, "mahal_closest_mean", "lawn mower, dynamic")],
               "Mean Mahalanobis distance to the closest confirmed track", "distance",
               plots / "mahalanobis-dynamic.png", hline=1.0)
    plot_bands([band(e, "max_track_var_m2", f"{e.label}, lawn mower") for e in ESTIMATE]
               + [band(e, "max_track_var_m2", f"{e.label}, largest-Gaussian") for e in LARGEST],
               "Largest position variance among confirmed tracks", "variance (m²)",
               plots / "largest-variance.png", logy=True)
    return markdown


KIND_ROWS = (
    ("count = truth at the end", None),
    ("confirmed tracks at the end", "tracks_confirmed"),
    ("Mahalanobis to closest", "mahal_closest_mean"),
    ("NEES (2 = calibrated)", "nees_mean"),
    ("OSPA last 20 % (m)", "ospa_tail_mean"),
    ("GOSPA last 20 % (m)", "gospa_tail_mean"),
    ("GOSPA missed + false at the end", None),
    ("every target confirmed at (s)", "t_all_confirmed_s"),
    ("step median (ms)", "step_ms_median"),
    ("step p95 (ms)", "step_ms_p95"),
)


def kinds_table(by_kind: dict[str, Runs]) -> str:
    """The estimator kinds side by side: one row per experiment and measure, a column each."""
    kinds = list(by_kind)
    first = by_kind[kinds[0]]
    header = ["scenario", "measure", *kinds]
    rows = []
    for scenario in first.by_scenario:
        for label, key in KIND_ROWS:
            cells = []
            for kind in kinds:
                runs = by_kind[kind]
                if key is not None:
                    cells.append(_fmt(runs.values(scenario, key), 3 if "ms" in key else 2))
                elif label.startswith("count"):
                    ok = runs.values(scenario, "tracks_confirmed") == runs.values(
                        scenario, "true_count")
                    cells.append(f"{int(ok.sum())}/{ok.size}")
                else:
                    cells.append(_fmt(runs.values(scenario, "gospa_missed_final")
                                      + runs.values(scenario, "gospa_false_final")))
            rows.append([scenario, label, *cells])
    return _table("Estimators side by side (filter.kind), the same seeds", header, rows)


def run_study(
    seeds: int,
    out_dir: Path,
    jobs: int,
    only: str | None = None,
    steps: int | None = None,
    scheduler: str | None = None,
    kinds: Sequence[str] = ("gmphd",),
    planners: Sequence[str] = (),
) -> dict[str, Runs]:
    """Run every experiment for seeds 1..seeds with each estimator kind, print and write the
    tables and plots (under out_dir/KIND when there are several kinds, with kinds.md beside).

    With `planners`, each lawn-mower experiment is also flown by every other planner named, on
    the same seeds, and planners.md with its figures is written beside each kind's tables
    (`companion.sim.planner_study`). The runs go to `jobs` local worker processes, or to the
    dask scheduler at `scheduler`.
    """
    from companion.sim.planner_study import (
        BASELINE,
        is_lawnmower_experiment,
        parse_planners,
        write_planner_outputs,
    )

    experiments = [e for e in ALL if only is None or only in e.scenario]
    if not experiments:
        raise CompanionError(f"--only {only!r} matches no experiment")
    planners = parse_planners(",".join(planners)) if planners else []
    flown = [e.scenario for e in experiments if is_lawnmower_experiment(e.scenario)]
    if planners and not flown:
        raise ConfigError("--planners", f"--only {only!r} selects no lawn-mower experiment to "
                          "fly with other planners")
    several = len(kinds) > 1
    tasks: list[tuple[str, int, str, str | None]] = [
        (e.scenario, seed, kind, None) for kind in kinds for e in experiments
        for seed in range(1, seeds + 1)]
    tasks += [(name, seed, kind, planner) for kind in kinds for planner in planners
              if planner != BASELINE for name in flown for seed in range(1, seeds + 1)]
    dirs = {kind: out_dir / kind if several else out_dir for kind in kinds}
    for path in dirs.values():
        (path / "runs").mkdir(parents=True, exist_ok=True)
    with progress_bar("study", "run") as bar:
        outputs = run_tasks(
            run_one,
            [(name, seed, dirs[kind] / "runs" if seed == 1 else None, steps, kind, planner,
              bool(planners) and seed == 1 and name in flown)
             for name, seed, kind, planner in tasks],
            jobs, scheduler, bar.update_to,
        )
    results = dict(zip(tasks, outputs, strict=True))
    by_kind = {
        kind: Runs({e.scenario: [results[(e.scenario, s, kind, None)]
                                 for s in range(1, seeds + 1)]
                    for e in experiments})
        for kind in kinds
    }
    for kind, runs in by_kind.items():
        if several:
            print(f"## filter.kind = {kind}\n")
        if len(experiments) == len(ALL):
            print(_write_outputs(runs, dirs[kind], seeds, steps))
            print(f"wrote {dirs[kind] / 'tables.md'}, CSV tables and plots under {dirs[kind]}",
                  file=sys.stderr)
        else:
            for e in experiments:
                print(f"{e.scenario}: " + ", ".join(
                    f"{key}={_fmt(runs.values(e.scenario, key))}"
                    for key in ("tracks_confirmed", "mahal_closest_mean", "ospa_tail_mean")))
        if planners:
            by_planner = {
                (name, planner): [results[(name, s, kind, None if planner == BASELINE
                                           else planner)] for s in range(1, seeds + 1)]
                for name in flown for planner in (BASELINE, *planners)
            }
            markdown, figures = write_planner_outputs(by_planner, flown, planners, seeds,
                                                      dirs[kind], steps)
            print(markdown)
            print(f"wrote {dirs[kind] / 'planners.md'} and {len(figures)} figures beside it",
                  file=sys.stderr)
    if several:
        side_by_side = kinds_table(by_kind)
        print(side_by_side)
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / "kinds.md").write_text(side_by_side)
    return by_kind
