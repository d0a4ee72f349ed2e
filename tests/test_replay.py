"""Replay of a run folder: the live run's tracks exactly, byte-identical outputs, torn logs."""

from __future__ import annotations

import asyncio
import copy
import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from companion.config import parse_config
from companion.errors import InputError
from companion.replay import load_truth, replay_run
from companion.sim.scenario import load_scenario
from sitl.cli import sitl_scenarios
from sitl.demo import fly


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A live SITL run of the field experiment, stopped after 70 simulated seconds."""
    scenario = load_scenario(sitl_scenarios()["field-5-tags"])
    out = tmp_path_factory.mktemp("live")
    result = asyncio.run(fly(scenario, speedup=4.0, out_dir=out, stop_after_s=70.0))
    assert len(result.run.tracks) >= 2
    return result.run.out_dir


def _files(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


def test_replay_gives_the_live_tracks_and_the_same_bytes_twice(run_dir: Path,
                                                                tmp_path: Path) -> None:
    first = replay_run(run_dir, tmp_path / "a")
    second = replay_run(run_dir, tmp_path / "b")
    assert (run_dir / "tracks.csv").read_bytes() == (tmp_path / "a" / "tracks.csv").read_bytes()
    assert (run_dir / "tracks.geojson").read_bytes() == \
        (tmp_path / "a" / "tracks.geojson").read_bytes()
    assert _files(tmp_path / "a") == _files(tmp_path / "b")
    assert {"steps.jsonl", "tracks.csv", "tracks.geojson", "summary.json", "flight-map.png",
            "flight-count.png"} <= set(_files(tmp_path / "a"))
    assert first.steps == second.steps > 100 and not first.warnings
    assert first.flight_s / first.wall_s > 5.0  # faster than real time


def test_a_torn_log_replays_up_to_its_end_with_a_warning(run_dir: Path, tmp_path: Path) -> None:
    torn = tmp_path / "torn"
    shutil.copytree(run_dir, torn)
    steps = torn / "steps.jsonl"
    data = steps.read_bytes()
    steps.write_bytes(data[: len(data) - 40])  # a power cut in the middle of the last line
    result = replay_run(torn, tmp_path / "out")
    whole = len(data.splitlines())
    assert result.steps == whole - 1
    assert result.warnings == [f"steps.jsonl: line {whole} is cut short (a crash?): "
                               f"replayed up to line {whole - 1}"]


def test_another_configuration_tunes_the_replay(run_dir: Path, tmp_path: Path) -> None:
    data = copy.deepcopy(json.loads((run_dir / "config.json").read_text()))
    data.setdefault("filter", {})["confirm_length"] = 10_000  # nothing can be confirmed
    result = replay_run(run_dir, tmp_path / "strict", parse_config(data))
    assert result.tracks == []
    assert json.loads((tmp_path / "strict" / "summary.json").read_text())["confirmed"] == 0


def test_not_a_run_folder(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="not a run folder of the service"):
        replay_run(tmp_path, tmp_path / "out")
    done = subprocess.run([sys.executable, "-m", "companion", "replay", str(tmp_path)],
                          capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 1
    assert done.stderr.strip().endswith("not a run folder of the service (no steps.jsonl)")
    assert "Traceback" not in done.stderr


def _truth_latlon() -> list[tuple[float, float]]:
    scenario = load_scenario(sitl_scenarios()["field-5-tags"])
    geo = scenario.geo.local_ned()
    out = []
    for x, y in scenario.targets.positions_xy:
        lat, lon, _ = geo.ned_to_geodetic(y, x, 0.0)
        out.append((float(lat), float(lon)))
    return out


def test_a_truth_file_scores_the_tracks(run_dir: Path, tmp_path: Path) -> None:
    truth = _truth_latlon()
    as_csv = tmp_path / "truth.csv"
    as_csv.write_text("lat,lon\n" + "".join(f"{a!r},{b!r}\n" for a, b in truth))
    as_geojson = tmp_path / "truth.geojson"
    as_geojson.write_text(json.dumps({"type": "FeatureCollection", "features": [
        {"type": "Feature", "geometry": {"type": "Point", "coordinates": [b, a]},
         "properties": {}} for a, b in truth]}))
    for path in (as_csv, as_geojson):
        result = replay_run(run_dir, tmp_path / path.stem, truth_latlon=load_truth(path))
        assert result.score is not None
        found = result.score.errors_m[result.score.errors_m < float("inf")]
        assert len(found) == len(result.tracks) and (found < 0.5).all()
        assert result.score.missed == 5 - len(result.tracks)
        assert result.score.false_tracks == 0
    done = subprocess.run([sys.executable, "-m", "companion", "replay", str(run_dir), "--out",
                           str(tmp_path / "cli"), "--truth", str(as_csv)],
                          capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 0, done.stderr
    assert "target         lat         lon  error m" in done.stdout
    assert f"{5 - len(result.tracks)} missed, 0 false tracks" in done.stdout
    bad = tmp_path / "bad.csv"
    bad.write_text("x,y\n1,2\n")
    with pytest.raises(InputError, match="not a truth file"):
        load_truth(bad)
