"""The scenario battery: its families, variants, command line and outputs, on the local engine."""

from __future__ import annotations

import csv
import math
import operator
from pathlib import Path

import numpy as np
import pytest

from companion.cli import main
from companion.errors import ConfigError
from companion.plan.world import World
from companion.sat.params import FILTER_KEYS
from companion.sim import battery
from companion.sim.battery import (
    FAMILIES,
    ID_COLUMNS,
    family_scenario,
    lane_spacing_m,
    parse_names,
    run_task,
)
from companion.sim.engine import check_scheduler_address, run_tasks
from companion.sim.run import planned_steps

SEEDS = (1, 2, 3, 7)
MAX_STEPS = 2500


@pytest.mark.parametrize("name", list(FAMILIES))
def test_every_family_builds_a_valid_short_scenario_per_seed(name: str) -> None:
    scenarios = [family_scenario(name, seed) for seed in SEEDS]
    for seed, s in zip(SEEDS, scenarios, strict=True):
        assert s.name == name and s.seed == seed
        assert s.world.size_m == (100.0, 100.0)
        assert 4 <= s.targets.count <= 10
        assert s.robot.speed_m_s == 1.0 and str(s.robot.planner) == "lawnmower"
        assert planned_steps(s, World(*s.world.size_m)) <= MAX_STEPS
        assert family_scenario(name, seed) == s  # a pure function of the seed
    layouts = {s.targets.positions_xy.tobytes() for s in scenarios}
    assert len(layouts) == len(SEEDS)


def test_the_filter_is_told_only_the_target_speed() -> None:
    defaults = family_scenario("clutter-0", 1, "defaults").filter
    fast = family_scenario("moving-fast", 1, "defaults").filter
    if "target_speed" in {k.leaf for k in FILTER_KEYS}:
        assert getattr(fast, "target_speed") == 1.0  # noqa: B009  (a key being added)
        assert getattr(defaults, "target_speed") == 0.0  # noqa: B009
    else:
        assert fast == defaults


def test_families_vary_what_they_say() -> None:
    assert [family_scenario(f"clutter-{r}", 2).sensor.clutter_rate
            for r in ("0", "0.5", "1", "2")] == [0.0, 0.5, 1.0, 2.0]
    assert family_scenario("clutter-2", 2).sensor.clutter_prob == 0.0
    assert family_scenario("pd-0.8", 2).sensor.p_detect == 0.8
    assert family_scenario("noise-2", 2).sensor.noise_std_m == 2.0
    fast = family_scenario("moving-fast", 2).targets
    assert (fast.speed_m_s, fast.turn_every_steps) == (1.0, 60)
    # One seed: one layout, whatever the family varies.
    np.testing.assert_array_equal(family_scenario("pd-0.9", 3).targets.positions_xy,
                                  family_scenario("noise-0.5", 3).targets.positions_xy)


@pytest.mark.parametrize("seed", SEEDS)
def test_close_pairs_are_2_to_6_m_apart(seed: int) -> None:
    xy = family_scenario("close-pairs", seed).targets.positions_xy
    half = xy.shape[0] // 2
    gaps = np.hypot(*(xy[:half] - xy[half:]).T)
    assert np.all((gaps >= 2.0) & (gaps <= 6.0))


@pytest.mark.parametrize("seed", SEEDS)
def test_turnover_has_targets_entering_and_leaving(seed: int) -> None:
    t = family_scenario("turnover", seed).targets
    assert 2 <= len(t.appear) <= 4 and 2 <= len(t.disappear) <= 3
    assert all(index < t.count for _, index in t.disappear)
    assert t.speed_m_s == 0.3


@pytest.mark.parametrize("seed", SEEDS)
def test_the_wrong_prior_is_far_from_every_target(seed: int) -> None:
    s = family_scenario("prior-wrong", seed)
    means = np.array([c.mean_xy for c in s.belief.components])
    assert s.belief.kind == "explicit" and means.shape[0] == s.targets.count
    distance = np.hypot(*(means[:, None, :] - s.targets.positions_xy[None, :, :]).T)
    assert distance.min() > battery.WRONG_PRIOR_DISTANCE_M


def test_priors_and_fovs() -> None:
    n = family_scenario("prior-exact", 4).targets.count
    assert family_scenario("prior-under", 4).belief.count < n
    assert family_scenario("prior-over", 4).belief.count > n
    assert family_scenario("prior-empty", 4).belief.kind == "empty"
    for radius in (10.0, 25.0, 40.0):
        s = family_scenario(f"fov-{radius:g}", 4)
        assert s.sensor.fov_radius_m == radius
        assert s.robot.lane_spacing_m <= 0.8 * 2.0 * radius
    camera = family_scenario("fov-camera", 4).sensor
    assert camera.fov == "polygon" and camera.fov_polygon_xy.shape[0] >= 4
    assert lane_spacing_m(50.0) == pytest.approx(100.0 / 3.0)


def test_variants_override_the_filter(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(battery.VARIANTS, "fewer", {"max_components": 50})
    assert family_scenario("pd-0.9", 1, "fewer").filter.max_components == 50
    monkeypatch.setitem(battery.VARIANTS, "typo", {"max_component": 50})
    with pytest.raises(ConfigError, match=r"filter\.max_component"):
        family_scenario("pd-0.9", 1, "typo")
    assert battery.VARIANTS["defaults"] == {} and "round-1" in battery.VARIANTS


def test_parse_names() -> None:
    assert parse_names(None, ["a", "b"], "--x") == ["a", "b"]
    assert parse_names(" b,a,b", ["a", "b"], "--x") == ["b", "a"]
    with pytest.raises(ConfigError, match=r"--x: unknown name 'c'"):
        parse_names("a,c", ["a", "b"], "--x")
    with pytest.raises(ConfigError, match="--x: an empty name"):
        parse_names("a,", ["a", "b"], "--x")


def test_run_task_is_one_flat_row() -> None:
    row = run_task("prior-exact", 1, "defaults", steps=20)
    assert list(row)[:5] == list(ID_COLUMNS)
    assert (row["family"], row["seed"], row["variant"], row["steps"]) == ("prior-exact", 1,
                                                                           "defaults", 20)
    assert row["filter_kind"] == "gmphd" and row["planner"] == "lawnmower"
    for key in ("tracks_confirmed", "true_count", "ospa_tail_mean", "components",
                "components_peak", "max_components", "wall_s"):
        assert key in row
    assert all(not isinstance(v, float) or math.isfinite(v) for v in row.values())


def test_local_engine_keeps_task_order() -> None:
    tasks = [(i, 10 * i) for i in range(7)]
    seen: list[tuple[int, int]] = []
    assert run_tasks(operator.add, tasks, 2, progress=lambda d, t: seen.append((d, t))) == [
        11 * i for i in range(7)]
    assert seen[-1] == (7, 7)
    assert run_tasks(operator.add, tasks, 1) == [11 * i for i in range(7)]


@pytest.mark.parametrize("address", ["tcp://127.0.0.1:8786", "tls://scheduler.local:1"])
def test_scheduler_addresses_accepted(address: str) -> None:
    assert check_scheduler_address(address) == address


@pytest.mark.parametrize("address", ["127.0.0.1:8786", "tcp://127.0.0.1", "tcp://:8786",
                                     "http://127.0.0.1:8786", "tcp://127.0.0.1:99999",
                                     "tcp://127.0.0.1:80/x"])
def test_bad_scheduler_addresses_name_the_option(address: str) -> None:
    with pytest.raises(ConfigError, match="--scheduler: expected tcp://HOST:PORT"):
        check_scheduler_address(address)


def test_list_prints_every_family_with_a_line(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["battery", "--list"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert [line.split()[0] for line in lines] == list(FAMILIES)
    assert all(len(line.split()) > 2 for line in lines)


@pytest.mark.parametrize(("args", "named"), [
    (["--families", "clutter-1,nope"], "--families: unknown name 'nope'"),
    (["--variants", "defaults,round-9"], "--variants: unknown name 'round-9'"),
    (["--seeds", "0"], "--seeds: must be >= 1, got 0"),
    (["--jobs", "0"], "--jobs: must be >= 1, got 0"),
    (["--steps", "-3"], "--steps: must be >= 1, got -3"),
    (["--scheduler", "localhost"], "--scheduler: expected tcp://HOST:PORT"),
])
def test_bad_arguments_exit_2_with_one_named_line(
    args: list[str], named: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out_dir = tmp_path / "battery"
    assert main(["battery", *args, "--out", str(out_dir)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and named in err and "Traceback" not in err
    assert not out_dir.exists()


def test_a_bad_variant_key_is_named_before_anything_runs(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setitem(battery.VARIANTS, "round-1", {"merge_distanse": 4.0})
    args = ["battery", "--families", "pd-0.9", "--variants", "defaults,round-1", "--out",
            str(tmp_path / "battery")]
    assert main(args) == 2
    assert "filter.merge_distanse: unknown key" in capsys.readouterr().err
    assert not (tmp_path / "battery").exists()


def test_study_rejects_a_bad_scheduler_address(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["study", "--scheduler", "nowhere"]) == 2
    assert "--scheduler: expected tcp://HOST:PORT" in capsys.readouterr().err


def test_a_tiny_battery_writes_tables_rows_and_plots(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out_dir = tmp_path / "battery"
    args = ["battery", "--families", "turnover,clutter-1", "--seeds", "2", "--steps", "40",
            "--jobs", "1", "--variants", "defaults,round-1", "--out", str(out_dir)]
    assert main(args) == 0
    stdout = capsys.readouterr().out
    assert "### turnover:" in stdout and "### clutter-1:" in stdout
    assert "| | defaults | round-1 |" in stdout and "count within ±1" in stdout
    assert (out_dir / "battery.md").read_text() in stdout
    with (out_dir / "results.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert [(r["family"], r["variant"], r["seed"]) for r in rows] == [
        (f, v, s) for f in ("clutter-1", "turnover") for v in ("defaults", "round-1")
        for s in ("1", "2")]
    for column in (*ID_COLUMNS, "tracks_confirmed", "true_count", "ospa_tail_mean",
                   "components_peak", *battery.TIMING_COLUMNS):
        assert column in rows[0]
    assert {r["steps"] for r in rows} == {"40"}
    pytest.importorskip("matplotlib")
    for f in ("turnover", "clutter-1"):
        assert (out_dir / "plots" / f"{f}-ospa.png").stat().st_size > 0
        assert (out_dir / "plots" / f"{f}-count.png").stat().st_size > 0
