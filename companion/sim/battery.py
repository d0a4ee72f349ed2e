"""The scenario battery: families of generated scenarios, run over seeds and estimator variants.

A family is a named generator `seed -> Scenario`: it writes the scenario as TOML data and reads
it through the scenario parser, so every rule and default of a scenario file applies. Every
family flies the lawn mower at 1 m/s over a 100 m x 100 m world with 5-10 targets drawn from the
seed; the [filter] table is left at its defaults but for the sensor's own model (which the
simulation passes from [sensor]) and the hint `target_speed` (the family's target speed). A
variant is a named set of [filter] overrides on top of that, and may fly another planner
(`PLANNER_OF`: the variant "search-track" is the defaults with the search-and-track planner), so
that `--variants defaults,search-track` puts the two planners side by side on the same seeds.

`run_battery` runs families x variants x seeds 1..N on the execution engine (local processes or a
dask cluster), prints one Markdown table per family with the variants side by side, and writes
`battery.md`, `results.csv` (one row per run, sorted, so that two engines give the same file up
to the timing columns) and a plot per family.
"""

from __future__ import annotations

import csv
import importlib.util
import math
import sys
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from functools import cache, partial
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from companion.errors import ConfigError
from companion.progress import progress_bar
from companion.sim.engine import check_scheduler_address, run_tasks
from companion.sim.footprint import camera_footprint_xy
from companion.sim.scenario import Scenario, parse_scenario

__all__ = [
    "FAMILIES",
    "TIMING_COLUMNS",
    "VARIANTS",
    "Family",
    "family_scenario",
    "format_family_list",
    "parse_names",
    "run_battery",
    "run_task",
]

FloatArray = NDArray[np.float64]
ScenarioData = dict[str, Any]

# Overrides of [filter] per variant, applied on top of every family's scenario.
VARIANTS: dict[str, dict[str, Any]] = {
    "defaults": {},
    # The previous release's estimator: no motion class (a track's uncertainty saturates with
    # the GP's), confirmation by detections alone and no ending by evidence.
    "round-1": {"target_speed": 0.0, "confirm_existence": 1e-6, "drop_existence": 1e-6},
    # The labeled multi-Bernoulli filter at its defaults, beside the GM-PHD.
    "lmb": {"kind": "lmb"},
    "search-track": {},  # the defaults, flown by the search-and-track planner (PLANNER_OF)
}
# The planner a variant flies instead of the families' lawn mower.
PLANNER_OF: dict[str, str] = {"search-track": "search-track"}
TIMING_COLUMNS = ("wall_s", "filter_s", "step_ms_median", "step_ms_p95")
ID_COLUMNS = ("family", "seed", "variant", "filter_kind", "planner")

WORLD_M = 100.0
ROBOT_SPEED_M_S = 1.0
SWEEPS = 2
LANE_FRACTION = 0.8  # lane spacing at most this share of the FOV's width across the lanes
TARGETS_MIN, TARGETS_MAX = 5, 10
MARGIN_M = 5.0  # generated targets keep this far from the world's edge
BASE_CLUTTER_RATE = 0.1  # false positives per scan where a family does not vary it
CAMERA_ALTITUDE_M = 20.0  # the camera family: a level 90-degree 4:3 camera at this height
WRONG_PRIOR_DISTANCE_M = 20.0  # the wrong prior's components keep this far from every target
_SEED_TAG = 0xBA77E  # separates the families' draws from the simulation's own (same seed)


# ---------------------------------------------------------------------------------------------
# Families
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Family:
    """A named generator of scenarios: `build(seed)` is the scenario's TOML data."""

    name: str
    description: str
    target_speed_m_s: float
    build: Callable[[int], ScenarioData]


def _draws(seed: int) -> tuple[np.random.Generator, np.random.Generator]:
    """The seed's two generators: target layout, and events (appearances, wrong priors)."""
    layout, events = np.random.SeedSequence([_SEED_TAG, seed]).spawn(2)
    return np.random.default_rng(layout), np.random.default_rng(events)


def _positions(rng: np.random.Generator, n: int) -> FloatArray:
    """n positions uniform in the world, MARGIN_M inside its edges."""
    return rng.uniform(MARGIN_M, WORLD_M - MARGIN_M, size=(n, 2))


def _layout(seed: int) -> FloatArray:
    """The seed's targets: 5-10 uniform positions (the same for every family but pairs)."""
    rng, _ = _draws(seed)
    return _positions(rng, int(rng.integers(TARGETS_MIN, TARGETS_MAX + 1)))


def _pairs(seed: int, gap_m: tuple[float, float] = (2.0, 6.0)) -> FloatArray:
    """The seed's close pairs: 2-5 pairs of targets gap_m apart, in random directions."""
    rng, _ = _draws(seed)
    n_pairs = int(rng.integers(TARGETS_MIN, TARGETS_MAX + 1)) // 2
    half = gap_m[1] / 2.0
    centres = rng.uniform(MARGIN_M + half, WORLD_M - MARGIN_M - half, size=(n_pairs, 2))
    gaps = rng.uniform(*gap_m, size=n_pairs)
    angles = rng.uniform(0.0, math.pi, size=n_pairs)
    offsets = 0.5 * gaps[:, None] * np.column_stack([np.cos(angles), np.sin(angles)])
    return np.vstack([centres - offsets, centres + offsets])


def lane_spacing_m(fov_width_m: float) -> float:
    """The world's width over the fewest lanes that are at most LANE_FRACTION * fov_width apart."""
    lanes = math.ceil(WORLD_M / (LANE_FRACTION * fov_width_m) - 1e-9)
    return WORLD_M / lanes


def _scenario_data(
    seed: int,
    positions_xy: FloatArray,
    targets: Mapping[str, Any] | None = None,
    sensor: Mapping[str, Any] | None = None,
    belief: Mapping[str, Any] | None = None,
    fov_width_m: float = 50.0,
) -> ScenarioData:
    """A battery scenario: the common set-up with a family's [targets], [sensor], [belief]."""
    return {
        "seed": seed,
        "dt": 1.0,
        "steps": 0,
        "world": {"size": [WORLD_M, WORLD_M]},
        "targets": {"positions": positions_xy.tolist(), **(targets or {})},
        "sensor": {"fov": "disk", "fov_radius": 25.0, "p_detect": 0.98, "noise_std": 1.0,
                   "clutter_prob": 0.0, "clutter_rate": BASE_CLUTTER_RATE, **(sensor or {})},
        "robot": {"start": [0.0, 0.0], "speed": ROBOT_SPEED_M_S, "planner": "lawnmower",
                  "lane_spacing": lane_spacing_m(fov_width_m), "sweeps": SWEEPS},
        "belief": {"kind": "exact", **(belief or {})},
        "filter": {},
    }


def _stationary(seed: int, sensor: Mapping[str, Any] | None = None) -> ScenarioData:
    """Stationary targets of the seed's layout, the sensor changed as given."""
    return _scenario_data(seed, _layout(seed), sensor=sensor)


def _moving(seed: int, speed_m_s: float, turn_every_steps: int) -> ScenarioData:
    """The seed's layout moving at speed_m_s, a new random heading every turn_every_steps."""
    return _scenario_data(seed, _layout(seed),
                          targets={"speed": speed_m_s, "turn_every": turn_every_steps})


def _lawnmower_steps(data: ScenarioData) -> int:
    """How many steps the scenario's lawn mower flies."""
    from companion.plan.world import World  # noqa: PLC0415  (kept off the --list path)
    from companion.sim.run import planned_steps  # noqa: PLC0415

    s = parse_scenario(data)
    return planned_steps(s, World(*s.world.size_m))


def _turnover(seed: int, speed_m_s: float = 0.3, turn_every_steps: int = 200) -> ScenarioData:
    """Walking targets of which 2-3 leave and 2-4 new ones enter, at steps drawn from the seed."""
    positions = _layout(seed)
    data = _moving(seed, speed_m_s, turn_every_steps)
    horizon = _lawnmower_steps(data)
    _, rng = _draws(seed)
    n_new = int(rng.integers(2, 5))
    appear_steps = rng.integers(int(0.1 * horizon), int(0.6 * horizon), size=n_new)
    appear_xy = _positions(rng, n_new)
    n_gone = int(rng.integers(2, 4))
    gone = rng.choice(positions.shape[0], size=n_gone, replace=False)
    gone_steps = rng.integers(int(0.2 * horizon), int(0.7 * horizon), size=n_gone)
    data["targets"]["appear"] = [[int(k), float(x), float(y)]
                                 for k, (x, y) in zip(appear_steps, appear_xy, strict=True)]
    data["targets"]["disappear"] = [[int(k), int(i)]
                                    for k, i in sorted(zip(gone_steps, gone, strict=True))]
    return data


def _close_pairs(seed: int) -> ScenarioData:
    """Stationary pairs of targets 2-6 m apart."""
    return _scenario_data(seed, _pairs(seed))


def _prior(seed: int, kind: str) -> ScenarioData:
    """The seed's stationary layout with an initial belief of the given kind."""
    positions = _layout(seed)
    n = positions.shape[0]
    belief: dict[str, Any] = {"kind": kind}
    if kind == "under":
        belief["count"] = n - 2
    elif kind == "over":
        belief["count"] = n + 3
    elif kind == "wrong":
        belief = {"kind": "explicit", "components": _wrong_components(seed, positions)}
    return _scenario_data(seed, positions, belief=belief)


def _wrong_components(seed: int, targets_xy: FloatArray) -> list[dict[str, Any]]:
    """One unit-weight component per target, each far from every target (the farthest
    candidates when too few keep WRONG_PRIOR_DISTANCE_M)."""
    _, rng = _draws(seed)
    candidates = rng.uniform(0.0, WORLD_M, size=(4000, 2))
    distance = np.min(np.hypot(*(candidates[:, None, :] - targets_xy[None, :, :]).T), axis=0)
    n = targets_xy.shape[0]
    far = candidates[distance > WRONG_PRIOR_DISTANCE_M]
    chosen = far[:n] if far.shape[0] >= n else candidates[np.argsort(-distance)[:n]]
    return [{"weight": 1.0, "mean": [float(x), float(y)]} for x, y in chosen]


def _disk_fov(seed: int, radius_m: float) -> ScenarioData:
    """The seed's stationary layout seen through a disk of radius_m."""
    data = _scenario_data(seed, _layout(seed), sensor={"fov_radius": radius_m},
                          fov_width_m=2.0 * radius_m)
    return data


@cache
def _camera_polygon_xy() -> FloatArray:
    """The ground footprint of the default camera, level at CAMERA_ALTITUDE_M, heading north."""
    camera = parse_scenario({}).camera
    return camera_footprint_xy(camera, CAMERA_ALTITUDE_M, 0.0)


def _camera_fov(seed: int) -> ScenarioData:
    """The seed's stationary layout seen through a camera footprint (a fixed polygon)."""
    polygon = _camera_polygon_xy()
    width_m = float(np.ptp(polygon[:, 0]))
    return _scenario_data(seed, _layout(seed),
                          sensor={"fov": "polygon", "fov_polygon": polygon.tolist()},
                          fov_width_m=width_m)


def _families() -> tuple[Family, ...]:
    out: list[Family] = []
    for rate in (0.0, 0.5, 1.0, 2.0):
        out.append(Family(f"clutter-{rate:g}",
                          f"stationary targets, clutter rate {rate:g} per scan (Poisson false "
                          "positives)", 0.0, partial(_stationary, sensor={"clutter_rate": rate})))
    for p_d in (0.8, 0.9, 0.98):
        out.append(Family(f"pd-{p_d:g}", f"stationary targets, p_D = {p_d:g}", 0.0,
                          partial(_stationary, sensor={"p_detect": p_d})))
    for noise_m in (0.5, 1.0, 2.0):
        out.append(Family(f"noise-{noise_m:g}",
                          f"stationary targets, measurement noise {noise_m:g} m per axis", 0.0,
                          partial(_stationary, sensor={"noise_std": noise_m})))
    for name, speed, turn in (("slow", 0.05, 400), ("walk", 0.3, 200), ("fast", 1.0, 60)):
        out.append(Family(f"moving-{name}",
                          f"targets at {speed:g} m/s, a new heading every {turn} s", speed,
                          partial(_moving, speed_m_s=speed, turn_every_steps=turn)))
    out.append(Family("turnover", "targets walking at 0.3 m/s; 2-3 leave, 2-4 enter later", 0.3,
                      _turnover))
    out.append(Family("close-pairs", "stationary pairs of targets 2-6 m apart", 0.0,
                      _close_pairs))
    for kind, text in (("exact", "one component near each target"),
                       ("under", "two components fewer than targets"),
                       ("over", "three components more than targets"),
                       ("empty", "no component"),
                       ("wrong", "one component per target, each far from every target")):
        out.append(Family(f"prior-{kind}", f"stationary targets, initial belief: {text}", 0.0,
                          partial(_prior, kind=kind)))
    for radius_m in (10.0, 25.0, 40.0):
        out.append(Family(f"fov-{radius_m:g}", f"stationary targets, disk FOV of {radius_m:g} m",
                          0.0, partial(_disk_fov, radius_m=radius_m)))
    out.append(Family("fov-camera",
                      f"stationary targets, the footprint of a level 90-degree camera at "
                      f"{CAMERA_ALTITUDE_M:g} m (40 m x 30 m)", 0.0, _camera_fov))
    return tuple(out)


FAMILIES: dict[str, Family] = {f.name: f for f in _families()}


def format_family_list() -> str:
    """One line per family: its name and what it varies."""
    width = max(map(len, FAMILIES))
    return "".join(f"{f.name:<{width}}  {f.description}\n" for f in FAMILIES.values())


def family_scenario(family: str, seed: int, variant: str = "defaults") -> Scenario:
    """The family's scenario for a seed with a variant's [filter] overrides; ConfigError if bad."""
    fam = _known(family, FAMILIES, "--families")
    overrides = _known(variant, VARIANTS, "--variants")
    data = fam.build(seed)
    data["filter"] = {**data["filter"], "target_speed": fam.target_speed_m_s, **overrides}
    if variant in PLANNER_OF:
        data["robot"] = {**data["robot"], "planner": PLANNER_OF[variant]}
    return parse_scenario(data, name=fam.name)


def _known(name: str, table: Mapping[str, Any], option: str) -> Any:
    if name not in table:
        raise ConfigError(option, f"unknown name {name!r} (known: {', '.join(table)})")
    return table[name]


def parse_names(text: str | None, known: Sequence[str], option: str) -> list[str]:
    """Comma-separated names, each one of `known` (None: all of them); ConfigError naming the
    first unknown or empty name."""
    if text is None:
        return list(known)
    names = [part.strip() for part in text.split(",")]
    for name in names:
        if not name:
            raise ConfigError(option, f"an empty name in {text!r}")
        if name not in known:
            raise ConfigError(option, f"unknown name {name!r} (known: {', '.join(known)})")
    return list(dict.fromkeys(names))


# ---------------------------------------------------------------------------------------------
# Runs
# ---------------------------------------------------------------------------------------------


def _simulate(family: str, seed: int, variant: str, steps: int | None) -> tuple[Scenario, Any]:
    from companion.sim.run import simulate  # noqa: PLC0415  (workers import it when they run)

    s = family_scenario(family, seed, variant)
    s = s if steps is None else replace(s, steps=steps)
    return s, simulate(s)


def _row(family: str, seed: int, variant: str, s: Scenario, result: Any) -> dict[str, Any]:
    """The flat row of one run: who ran, then every summary key, then the component peak."""
    kind = getattr(s.filter, "kind", None)
    row: dict[str, Any] = {
        "family": family, "seed": seed, "variant": variant,
        "filter_kind": "gmphd" if kind is None else str(kind), "planner": str(s.robot.planner),
    }
    row.update((key, value) for key, value in result.summary().items() if key not in row)
    row["components_peak"] = int(np.max(result.components))
    row["max_components"] = int(s.filter.max_components)
    return row


def run_task(family: str, seed: int, variant: str, steps: int | None = None) -> dict[str, Any]:
    """One run of a family's scenario: family, seed, variant, filter_kind, planner and its summary.

    `steps` cuts the run to that many steps (a quick look).
    """
    s, result = _simulate(family, seed, variant, steps)
    return _row(family, seed, variant, s, result)


def run_task_series(
    family: str, seed: int, variant: str, steps: int | None = None
) -> dict[str, Any]:
    """`run_task`'s row with the run's OSPA and count-error time series (for the plots)."""
    s, result = _simulate(family, seed, variant, steps)
    return {
        "row": _row(family, seed, variant, s, result),
        "t_s": result.t_s.astype(np.float32),
        "ospa": result.ospa.astype(np.float32),
        "count_error": (result.tracks_confirmed - result.true_count).astype(np.float32),
    }


# ---------------------------------------------------------------------------------------------
# Report
# ---------------------------------------------------------------------------------------------


def _values(rows: Sequence[Mapping[str, Any]], key: str) -> FloatArray:
    return np.array([math.nan if r.get(key) is None else float(r[key]) for r in rows])


def _mean_std(values: FloatArray, digits: int = 2) -> str:
    """mean ± std over the defined values, with how many were undefined."""
    finite = values[np.isfinite(values)]
    if finite.size == 0:
        return f"n/a ({values.size} undefined)"
    text = f"{finite.mean():.{digits}f} ± {finite.std():.{digits}f}"
    if finite.size < values.size:
        text += f" ({values.size - finite.size} undefined)"
    return text


def _share(hits: NDArray[np.bool_]) -> str:
    return f"{int(hits.sum())}/{hits.size} ({100.0 * hits.mean():.0f} %)"


def _count_error(rows: Sequence[Mapping[str, Any]]) -> FloatArray:
    return _values(rows, "tracks_confirmed") - _values(rows, "true_count")


def _components(rows: Sequence[Mapping[str, Any]]) -> str:
    peak = _values(rows, "components_peak")
    hit = peak >= _values(rows, "max_components")
    return f"{int(peak.max())}; hit max_components in {_share(hit)}"


MetricRow = tuple[str, Callable[[Sequence[Mapping[str, Any]]], str]]

# Shown when some run of the family has the key.
_OPTIONAL = (
    ("GOSPA at the end (m)", "gospa_final"),
    ("GOSPA missed at the end", "gospa_missed_final"),
    ("GOSPA false at the end", "gospa_false_final"),
    ("GOSPA localisation at the end (m)", "gospa_localisation_final"),
)
_OPTIONAL_TAIL = (
    ("NEES mean (2 = calibrated)", "nees_mean"),
    ("time until all confirmed (s)", "t_all_confirmed_s"),
)


def _metric_rows(keys: set[str]) -> list[MetricRow]:
    """The table's rows for a family whose runs have these keys."""

    def mean_of(key: str) -> Callable[[Sequence[Mapping[str, Any]]], str]:
        return lambda rows: _mean_std(_values(rows, key))

    out: list[MetricRow] = [(label, mean_of(key)) for label, key in _OPTIONAL if key in keys]
    out += [
        ("count error (tracks - truth)", lambda rows: _mean_std(_count_error(rows))),
        ("count exact", lambda rows: _share(_count_error(rows) == 0)),
        ("count within ±1", lambda rows: _share(np.abs(_count_error(rows)) <= 1)),
    ]
    out += [(label, mean_of(key)) for label, key in _OPTIONAL_TAIL if key in keys]
    out += [
        ("OSPA last 20 % (m)", mean_of("ospa_tail_mean")),
        ("components: peak; runs at the cap", _components),
        ("filter time per run (s)", mean_of("filter_s")),
    ]
    return out


def family_table(family: str, variants: Sequence[str], rows: Sequence[Mapping[str, Any]]) -> str:
    """The Markdown table of one family: one row per metric, one column per variant."""
    mine = [r for r in rows if r["family"] == family]
    by_variant = {v: [r for r in mine if r["variant"] == v] for v in variants}
    seeds = len(by_variant[variants[0]])
    truth = _values(by_variant[variants[0]], "true_count")
    metrics = _metric_rows({key for r in mine for key in r})
    lines = [f"### {family}: {FAMILIES[family].description}", "",
             f"{seeds} seeds, mean ± std over seeds; true targets at the end "
             f"{_mean_std(truth, 1)}", "",
             "| | " + " | ".join(variants) + " |", "|---" * (len(variants) + 1) + "|"]
    lines += ["| " + " | ".join([label, *(fn(by_variant[v]) for v in variants)]) + " |"
              for label, fn in metrics]
    return "\n".join(lines) + "\n"


def _sorted_rows(rows: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    return sorted(rows, key=lambda r: (str(r["family"]), str(r["variant"]), int(r["seed"])))


def write_results_csv(rows: Sequence[dict[str, Any]], path: Path) -> None:
    """One row per run, sorted by family, variant and seed; None is an empty cell."""
    columns = list(dict.fromkeys(key for r in rows for key in r))
    with path.open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=columns, restval="")
        writer.writeheader()
        writer.writerows({k: ("" if v is None else v) for k, v in r.items()}
                         for r in _sorted_rows(rows))


def _plot_family(
    family: str, variants: Sequence[str], runs: Sequence[Mapping[str, Any]], plots: Path
) -> list[Path]:
    """OSPA and count error over time, mean ± std over seeds per variant."""
    from companion.sim.plots import aggregate, plot_bands  # noqa: PLC0415  (matplotlib: optional)

    def band(variant: str, key: str) -> Any:
        mine = [r for r in runs if r["row"]["family"] == family and r["row"]["variant"] == variant]
        length = min(r["t_s"].size for r in mine)
        return aggregate(variant, mine[0]["t_s"][:length].astype(np.float64),
                         [r[key][:length].astype(np.float64) for r in mine])

    return [
        plot_bands([band(v, "ospa") for v in variants], f"{family}: OSPA (m)", "OSPA (m)",
                   plots / f"{family}-ospa.png"),
        plot_bands([band(v, "count_error") for v in variants],
                   f"{family}: confirmed tracks minus true targets", "count error",
                   plots / f"{family}-count.png", hline=0.0),
    ]


def run_battery(
    families: Sequence[str],
    seeds: int,
    out_dir: Path,
    variants: Sequence[str] = ("defaults",),
    jobs: int = 1,
    scheduler: str | None = None,
    steps: int | None = None,
) -> list[dict[str, Any]]:
    """Run families x variants x seeds 1..seeds; print the tables, write the outputs; the rows.

    ConfigError (naming the option or key) for an unknown family or variant, a variant's bad
    [filter] key, seeds, jobs or steps below 1, or a malformed scheduler address; all are
    checked before anything runs.
    """
    for name in families:
        _known(name, FAMILIES, "--families")
    for name in variants:
        _known(name, VARIANTS, "--variants")
    for option, value in (("--seeds", seeds), ("--jobs", jobs), ("--steps", steps)):
        if value is not None and value < 1:
            raise ConfigError(option, f"must be >= 1, got {value}")
    if not families or not variants:
        raise ConfigError("--families" if not families else "--variants", "names nothing")
    if scheduler is not None:
        check_scheduler_address(scheduler)
    for f in families:  # a variant's bad [filter] key is named here, not in a worker
        for v in variants:
            family_scenario(f, 1, v)
    tasks = [(f, seed, v, steps) for f in families for v in variants
             for seed in range(1, seeds + 1)]
    with progress_bar("battery", "run") as bar:
        runs = run_tasks(run_task_series, tasks, jobs, scheduler, bar.update_to)
    rows = _sorted_rows([r["row"] for r in runs])
    shortened = "" if steps is None else f", every run cut to {steps} steps"
    markdown = (f"# Scenario battery: {len(families)} families, {seeds} seeds, variants "
                f"{', '.join(variants)}{shortened}\n\n"
                + "\n".join(family_table(f, variants, rows) for f in families))
    print(markdown)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "battery.md").write_text(markdown)
    write_results_csv(rows, out_dir / "results.csv")
    wrote = f"wrote {out_dir / 'battery.md'}, {out_dir / 'results.csv'}"
    if importlib.util.find_spec("matplotlib") is not None:
        plots = out_dir / "plots"
        plots.mkdir(exist_ok=True)
        for f in families:
            _plot_family(f, variants, runs, plots)
        wrote += f" and plots under {plots}"
    else:
        wrote += " (no plots: matplotlib, the `plots` extra, is not installed)"
    print(wrote, file=sys.stderr)
    return rows
