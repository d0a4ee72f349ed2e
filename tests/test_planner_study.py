"""The study's planners side by side: the table's rows and numbers from given runs, the flown
paths and GOSPA figures, a quick real study with two planners, and the --planners option."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")

import matplotlib.image as mpimg
import numpy as np
import pytest

from companion.cli import main
from companion.errors import ConfigError
from companion.sim.path_plots import PANEL_SIZE_IN, FlownPath, plot_paths
from companion.sim.planner_study import (
    HEADER,
    PLANNERS,
    parse_planners,
    planner_rows,
    planners_table,
    time_ratio,
    write_planner_outputs,
)
from companion.sim.study import run_one

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
LAWN, SEARCH = "lawnmower", "search-track"
A, B = "paper-lawnmower-a", "paper-lawnmower-b"


def _result(t_all: float | None, tracks: int, gospa_tail: float, seed: int = 1,
            steps: int = 5, path: FlownPath | None = None) -> dict[str, Any]:
    """A run's result as `run_one` returns it, with the values the planners table reads."""
    summary = {"seed": seed, "t_all_confirmed_s": t_all, "tracks_confirmed": tracks,
               "true_count": 10, "gospa_tail_mean": gospa_tail,
               "mahal_closest_mean": 0.5 + seed, "ospa_tail_mean": 2.0 * seed}
    out: dict[str, Any] = {
        "summary": summary, "t_s": np.arange(1, steps + 1, dtype=np.float32),
        "series": {"gospa": np.linspace(20.0, gospa_tail, steps, dtype=np.float32)},
    }
    if path is not None:
        out["path"] = path
    return out


def _results() -> dict[tuple[str, str], list[dict[str, Any]]]:
    return {
        (A, LAWN): [_result(100.0, 10, 1.0, 1), _result(300.0, 10, 1.0, 2),
                    _result(None, 8, 4.0, 3)],
        (A, SEARCH): [_result(50.0, 10, 1.0, 1), _result(150.0, 9, 2.0, 2),
                      _result(90.0, 12, 3.0, 3)],
        (B, LAWN): [_result(None, 7, 5.0, 1), _result(None, 7, 5.0, 2),
                    _result(None, 7, 5.0, 3)],
        (B, SEARCH): [_result(400.0, 10, 0.5, 1), _result(None, 11, 0.5, 2),
                      _result(200.0, 10, 0.5, 3)],
    }


def test_a_row_per_experiment_and_planner_with_the_runs_numbers() -> None:
    rows = planner_rows(_results(), [A, B], [LAWN, SEARCH])
    assert [row[:2] for row in rows] == [[A, LAWN], [A, SEARCH], [B, LAWN], [B, SEARCH]]
    assert all(len(row) == len(HEADER) for row in rows)
    cells = [dict(zip(HEADER, row, strict=True)) for row in rows]
    lawn_a, search_a, lawn_b, search_b = cells
    assert lawn_a["every target confirmed at (s)"] == "200 ± 100"
    assert lawn_a["never all confirmed"] == "1/3"
    assert lawn_a["time / lawn mower"] == "1.00 (2 paired seeds)"
    assert lawn_a["count = truth at the end"] == "2/3"
    assert lawn_a["count within ±1"] == "2/3"
    # 50, 150, 90 s: mean 96.7, population sd 41.1; paired with the lawn mower on seeds 1, 2.
    assert search_a["every target confirmed at (s)"] == "97 ± 41"
    assert search_a["never all confirmed"] == "0/3"
    assert search_a["time / lawn mower"] == "0.50 (2 paired seeds)"
    assert search_a["GOSPA last 20 % (m)"] == "2.00 ± 0.82"
    assert search_a["count = truth at the end"] == "1/3"  # 10, 9, 12 of 10
    assert search_a["count within ±1"] == "2/3"
    assert search_a["Mahalanobis to closest"] == "2.50 ± 0.82"
    assert search_a["OSPA last 20 % (m)"] == "4.00 ± 1.63"
    assert lawn_b["every target confirmed at (s)"] == "n/a"
    assert lawn_b["never all confirmed"] == "3/3"
    assert lawn_b["time / lawn mower"] == "n/a"  # nothing to pair with
    assert search_b["every target confirmed at (s)"] == "300 ± 100"
    assert search_b["never all confirmed"] == "1/3"
    assert search_b["time / lawn mower"] == "n/a"


def test_the_ratio_is_to_the_lawn_mower_even_when_it_is_not_a_row() -> None:
    rows = planner_rows(_results(), [A], [SEARCH])
    assert len(rows) == 1
    assert rows[0][1] == SEARCH
    assert rows[0][HEADER.index("time / lawn mower")] == "0.50 (2 paired seeds)"


def test_time_ratio_over_paired_seeds() -> None:
    both = np.array([10.0, 20.0])
    assert time_ratio(both, np.array([20.0, 40.0])) == "0.50"
    assert time_ratio(np.array([np.nan, 20.0]), np.array([20.0, np.nan])) == "n/a"


def test_the_table_is_markdown_with_a_line_per_row() -> None:
    table = planners_table(_results(), [A, B], [LAWN, SEARCH], seeds=3, steps=40)
    lines = table.splitlines()
    assert lines[0].startswith("### Planners side by side") and "cut to 40 steps" in lines[0]
    assert "| " + " | ".join(HEADER) + " |" in lines
    assert len([line for line in lines if line.startswith(f"| {A} |")]) == 2
    assert len([line for line in lines if line.startswith(f"| {B} |")]) == 2


def test_planner_names_are_checked() -> None:
    assert parse_planners(f"{LAWN}, {SEARCH},{LAWN}") == [LAWN, SEARCH]
    assert set(PLANNERS) == {"lawnmower", "nearest-gaussian", "largest-gaussian", SEARCH}
    for bad in ("lawnmower,spiral", "lawnmower,,search-track", ""):
        with pytest.raises(ConfigError, match="--planners"):
            parse_planners(bad)


def _path(label: str, offset: float) -> FlownPath:
    t = np.linspace(0.0, 1.0, 200)
    return FlownPath(
        label=label, world_m=(50.0, 40.0),
        robot_xy=np.column_stack([50.0 * t, 20.0 + offset * np.sin(12.0 * t)]),
        truth_xy=np.array([[10.0, 10.0], [30.0, 25.0], [45.0, 5.0]]),
        tracks_xy=np.array([[10.5, 9.5], [29.0, 25.5]]),
    )


def _assert_png(path: Path, size_in: tuple[float, float]) -> None:
    assert path.is_file()
    assert path.read_bytes()[:8] == PNG_MAGIC
    image = mpimg.imread(path)
    assert image.shape[:2] == (round(size_in[1] * 100), round(size_in[0] * 100))
    assert float(image[..., :3].std()) > 0.01  # something was drawn, not a blank canvas


def test_paths_figure_has_a_panel_per_path(tmp_path: Path) -> None:
    out = plot_paths([_path(LAWN, 5.0), _path(SEARCH, 15.0)], "two planners",
                     tmp_path / "paths.png")
    assert out == tmp_path / "paths.png"
    _assert_png(out, (2 * PANEL_SIZE_IN[0], PANEL_SIZE_IN[1]))
    with pytest.raises(Exception, match="robot_xy"):
        FlownPath("bad", (1.0, 1.0), np.zeros(3), np.zeros((0, 2)), np.zeros((0, 2)))


def test_outputs_from_given_runs(tmp_path: Path) -> None:
    results = _results()
    results[(A, LAWN)][0]["path"] = _path(LAWN, 5.0)
    results[(A, SEARCH)][0]["path"] = _path(SEARCH, 15.0)
    markdown, figures = write_planner_outputs(results, [A, B], [LAWN, SEARCH], 3, tmp_path)
    assert (tmp_path / "planners.md").read_text() == markdown
    # B's runs carry no path: its GOSPA figure only.
    assert sorted(p.name for p in figures) == [f"gospa-{A}.png", f"gospa-{B}.png",
                                               f"paths-{A}.png"]
    for figure in figures:
        assert figure.read_bytes()[:8] == PNG_MAGIC


def test_a_quick_study_with_two_planners(tmp_path: Path, capsys: pytest.CaptureFixture[str]
                                         ) -> None:
    out_dir = tmp_path / "study"
    scenario = "paper-lawnmower-exact-c10-nopush"
    args = ["study", "--seeds", "1", "--steps", "40", "--jobs", "1", "--kinds", "gmphd",
            "--only", "exact-c10-nopush", "--planners", f"{LAWN},{SEARCH}",
            "--out", str(out_dir)]
    assert main(args) == 0
    table = (out_dir / "planners.md").read_text()
    assert table.strip() in capsys.readouterr().out
    rows = [line.split(" | ") for line in table.splitlines() if line.startswith(f"| {scenario}")]
    assert [row[1] for row in rows] == [LAWN, SEARCH]
    gospa = HEADER.index("GOSPA last 20 % (m)")
    for row, planner in zip(rows, (None, SEARCH), strict=True):
        again = run_one(scenario, 1, None, 40, "gmphd", planner)["summary"]
        assert row[gospa] == f"{again['gospa_tail_mean']:.2f} ± 0.00"
    for name in (f"paths-{scenario}.png", f"gospa-{scenario}.png"):
        path = out_dir / name
        assert path.read_bytes()[:8] == PNG_MAGIC
        assert float(mpimg.imread(path)[..., :3].std()) > 0.01
    assert (out_dir / "runs" / f"{scenario}-{SEARCH}-s1-trajectory.png").is_file()


def test_no_planners_no_planner_outputs(tmp_path: Path) -> None:
    out_dir = tmp_path / "study"
    assert main(["study", "--seeds", "1", "--steps", "20", "--jobs", "1", "--kinds", "gmphd",
                 "--only", "exact-c10-nopush", "--out", str(out_dir)]) == 0
    assert not (out_dir / "planners.md").exists()
    assert not list(out_dir.glob("paths-*.png"))


@pytest.mark.parametrize("value", ["lawnmower,spiral", "lawnmower,,search-track"])
def test_a_bad_planner_exits_2_with_one_line(value: str, capsys: pytest.CaptureFixture[str]
                                             ) -> None:
    assert main(["study", "--planners", value]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1
    assert "--planners" in err
    assert "Traceback" not in err
    if "spiral" in value:
        assert "'spiral'" in err and "search-track" in err  # the known names are listed


def test_planners_need_a_lawn_mower_experiment(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["study", "--only", "paper-largest", "--planners", SEARCH]) == 2
    err = capsys.readouterr().err
    assert "--planners" in err and "Traceback" not in err


def test_the_study_help_names_every_planner(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(["study", "--help"])
    text = " ".join(capsys.readouterr().out.split()).replace("- ", "-")  # wrapped at hyphens
    for planner in PLANNERS:
        assert planner in text
