"""The `companion` command: output contract, exit status and messages."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from companion.cli import KINDS, main
from companion.sat.filter import FilterKind
from companion.scenario_lookup import shipped_scenarios
from companion.sim.scenario import load_scenario

CONTRACT_KEYS = {
    "scenario", "seed", "steps", "wall_s", "step_ms_median", "step_ms_p95", "true_count",
    "tracks_confirmed", "weight_sum", "components", "mahal_closest_mean", "mahal_closest_std",
    "mahal_second_mean", "ospa_mean", "ospa_tail_mean", "ospa_final",
    "gospa_final", "gospa_tail_mean", "gospa_localisation_final", "gospa_missed_final",
    "gospa_false_final", "nees_mean", "t_all_confirmed_s", "tracks_coasting",
}

SHORT = """
name = "cli-short"
seed = 3
steps = 150
[world]
size = [40.0, 40.0]
[targets]
positions = [[10.0, 10.0], [30.0, 25.0]]
[sensor]
fov_radius = 12.0
[robot]
speed = 1.0
lane_spacing = 12.0
sweeps = 1
[belief]
kind = "empty"
"""


@pytest.fixture
def short_scenario(tmp_path: Path) -> Path:
    path = tmp_path / "short.toml"
    path.write_text(SHORT)
    return path


def test_simulate_json_prints_exactly_the_contract_object(
    short_scenario: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["simulate", str(short_scenario), "--json", "--seed", "7"]) == 0
    out = capsys.readouterr().out
    summary = json.loads(out)  # nothing but one JSON object on standard output
    assert summary.keys() >= CONTRACT_KEYS
    assert summary["seed"] == 7
    assert summary["steps"] == 150
    assert summary["scenario"] == "cli-short"
    assert summary["true_count"] == 2
    for key in ("gospa_final", "gospa_tail_mean", "gospa_localisation_final"):
        assert isinstance(summary[key], float) and summary[key] >= 0.0
    for key in ("gospa_missed_final", "gospa_false_final"):
        assert type(summary[key]) is int and summary[key] >= 0
    assert 0 <= summary["tracks_coasting"] <= summary["tracks_confirmed"]
    for key in ("nees_mean", "t_all_confirmed_s"):  # null when never defined
        assert summary[key] is None or (isinstance(summary[key], float) and summary[key] >= 0.0)


def test_simulate_writes_plots(
    short_scenario: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out_dir = tmp_path / "plots"
    assert main(["simulate", str(short_scenario), "--out", str(out_dir)]) == 0
    names = sorted(p.name for p in out_dir.glob("*.png"))
    assert names == [f"cli-short-s3-{kind}.png"
                     for kind in ("count", "mahalanobis", "ospa", "trajectory")]
    assert "wrote" in capsys.readouterr().err


def test_bad_scenario_exits_2_with_one_line_naming_the_key(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "bad.toml"
    path.write_text("[targets]\ncount = -1\n")
    assert main(["simulate", str(path), "--json"]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1
    assert "targets.count" in lines[0]


def test_missing_scenario_names_the_shipped_ones(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["simulate", "no-such-scenario"]) == 2
    err = capsys.readouterr().err
    assert "no-such-scenario" in err
    assert "paper-lawnmower-exact-c10" in err


def test_bad_arguments_exit_2() -> None:
    with pytest.raises(SystemExit) as exc:
        main(["study", "--seeds", "0"])
    assert exc.value.code == 2


def test_every_shipped_scenario_loads() -> None:
    shipped = shipped_scenarios()
    assert len(shipped) >= 10
    for name, path in shipped.items():
        assert load_scenario(path).name == name


def test_learn_gp_prints_scenario_lines(capsys: pytest.CaptureFixture[str]) -> None:
    args = ["learn-gp", "paper-lawnmower-dynamic-c10", "--targets", "4", "--steps", "200"]
    assert main(args) == 0
    lines = capsys.readouterr().out.splitlines()
    values = dict(line.split(" = ") for line in lines if " = " in line)
    assert set(values) == {"gp_sigma_f", "gp_lengthscale", "gp_sigma_n", "target_speed",
                           "manoeuvre_time"}
    assert 0.02 < float(values["target_speed"]) < 0.15  # the targets walk at 0.05 m/s
    # Targets at 0.05 m/s on 200 s legs: a smooth trend well above the 1 m noise floor.
    assert float(values["gp_lengthscale"]) > 10.0
    assert 0.5 < float(values["gp_sigma_n"]) < 1.5


def test_console_script_runs_as_a_program(short_scenario: Path) -> None:
    done = subprocess.run(
        [sys.executable, "-m", "companion.cli", "simulate", str(short_scenario), "--json"],
        capture_output=True, text=True, check=False, timeout=120,
    )
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["tracks_confirmed"] >= 0


def test_quick_study_writes_every_table_and_plot(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out_dir = tmp_path / "study"
    args = ["study", "--seeds", "1", "--steps", "60", "--jobs", "2", "--out", str(out_dir),
            "--kinds", "gmphd"]
    assert main(args) == 0
    markdown = (out_dir / "tables.md").read_text()
    assert capsys.readouterr().out.strip() == markdown.strip()
    for title in ("vs clutter", "vs initial estimate", "Dynamic targets", "Estimated number",
                  "limited-FOV update rule", "Goals", "Qualitative findings", "Filter time"):
        assert title in markdown
    assert "3.03" in markdown  # the paper's numbers sit beside ours
    for row in ("GOSPA at the end", "GOSPA missed targets", "GOSPA false tracks", "NEES"):
        assert row in markdown
    assert len(list(out_dir.glob("table*.csv"))) == 8
    assert (out_dir / "runs.csv").read_text().count("\n") == 15  # header + 14 runs
    header = (out_dir / "runs.csv").read_text().splitlines()[0].split(",")
    assert set(header) >= CONTRACT_KEYS
    assert len(list((out_dir / "plots").glob("*.png"))) == 10
    assert len(list((out_dir / "runs").glob("*.png"))) == 14 * 4


def test_study_runs_both_estimators_side_by_side(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out_dir = tmp_path / "study"
    args = ["study", "--seeds", "2", "--steps", "200", "--jobs", "2", "--out", str(out_dir),
            "--only", "exact-c10-nopush"]
    assert main(args) == 0
    printed = capsys.readouterr().out
    table = (out_dir / "kinds.md").read_text()
    assert table.strip() in printed
    header = table.splitlines()[2]
    assert header == "| scenario | measure | gmphd | lmb |"
    rows = [line for line in table.splitlines() if "paper-lawnmower-exact-c10-nopush" in line]
    assert len(rows) == 10  # every measure, one cell per kind
    count = next(line for line in rows if "count = truth" in line)
    assert count.count("/2") == 2
    assert "## filter.kind = lmb" in printed


def test_bad_kinds_are_refused(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["study", "--kinds", "gmphd,glmb"]) == 2
    assert "--kinds" in capsys.readouterr().err


def test_the_cli_knows_every_estimator_kind() -> None:
    assert tuple(k.value for k in FilterKind) == KINDS
