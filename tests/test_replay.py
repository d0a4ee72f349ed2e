"""Replay: a run folder gives the live run's tracks exactly (re-detected on its kept frames, or
from its recorded detections), byte-identical outputs, torn logs; the run's own .tlog with its
frames, as a foreign flight log with a video, gives the same tracks."""

from __future__ import annotations

import asyncio
import copy
import dataclasses
import json
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from companion.config import ServiceConfig, parse_config
from companion.errors import InputError
from companion.flightlog import read_flight_log
from companion.replay import FrameTimes, load_truth, replay_log, replay_run
from companion.sim.scenario import load_scenario
from sitl.cli import sitl_scenarios
from sitl.demo import fly
from tests.logwriters import write_bin, write_ulg

pytestmark = pytest.mark.sitl


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A live SITL run of the field experiment keeping its frames (PNG), stopped at 70 s."""
    s = load_scenario(sitl_scenarios()["field-5-tags"])
    # No rangefinder: a log's replay takes the height from its positions (the relative
    # altitude), as the live service then does. The true pose, so that the truth-file scores
    # are about replay, not about the autopilot's estimate.
    scenario = dataclasses.replace(s, vehicle=dataclasses.replace(
        s.vehicle, rangefinder=False, heading_error_deg=0.0, attitude_error_deg=0.0,
        position_error_m=0.0, height_error_m=0.0))
    out = tmp_path_factory.mktemp("live")
    result = asyncio.run(fly(scenario, speedup=4.0, out_dir=out, stop_after_s=70.0,
                             output={"frames": "png"}))
    assert len(result.run.tracks) >= 2
    steps = [json.loads(line)["input"] for line in
             (result.run.out_dir / "steps.jsonl").read_text().splitlines()]
    with_frame = [s for s in steps if "frame" in s]
    assert len(with_frame) == len([s for s in steps if "pose" in s]) > 50
    assert all((result.run.out_dir / s["frame"]).is_file() for s in with_frame)
    return result.run.out_dir


def _files(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


def _config(run_dir: Path) -> ServiceConfig:
    return parse_config(json.loads((run_dir / "config.json").read_text()))


def _tracks_xy(result_dir: Path) -> np.ndarray:
    rows = (result_dir / "tracks.csv").read_text().splitlines()
    header = rows[0].split(",")
    e, n = header.index("easting_m"), header.index("northing_m")
    return np.array([[float(r.split(",")[e]), float(r.split(",")[n])] for r in rows[1:]])


def test_replay_gives_the_live_tracks_and_the_same_bytes_twice(run_dir: Path,
                                                                tmp_path: Path) -> None:
    first = replay_run(run_dir, tmp_path / "a")  # detection runs again on the kept frames
    second = replay_run(run_dir, tmp_path / "b")
    recorded = replay_run(run_dir, tmp_path / "c", redetect=False)
    for out in ("a", "c"):
        assert (run_dir / "tracks.csv").read_bytes() == (tmp_path / out / "tracks.csv").read_bytes()
        assert (run_dir / "tracks.geojson").read_bytes() == \
            (tmp_path / out / "tracks.geojson").read_bytes()
    assert _files(tmp_path / "a") == _files(tmp_path / "b")
    assert {"steps.jsonl", "tracks.csv", "tracks.geojson", "summary.json", "flight-map.png",
            "flight-count.png"} <= set(_files(tmp_path / "a"))
    assert first.steps == second.steps == recorded.steps > 100 and not first.warnings
    assert first.flight_s / first.wall_s > 5.0  # faster than real time


def test_missing_frames_fall_back_to_the_recorded_detections(run_dir: Path,
                                                             tmp_path: Path) -> None:
    copy_dir = tmp_path / "run"
    shutil.copytree(run_dir, copy_dir)
    dropped = sorted((copy_dir / "frames").glob("*.png"))[::2]
    for path in dropped:
        path.unlink()
    result = replay_run(copy_dir, tmp_path / "out")
    assert result.warnings == [f"{len(dropped)} kept frames are missing: their recorded "
                               "detections were used"]
    assert (tmp_path / "out" / "tracks.csv").read_bytes() == (run_dir / "tracks.csv").read_bytes()


def test_the_runs_tlog_and_frames_replay_as_a_flight_log(run_dir: Path, tmp_path: Path) -> None:
    """The .tlog and the frame folder (with its index of capture times) as another tool's log."""
    result = replay_log(run_dir / "flight.tlog", run_dir / "frames", tmp_path / "log",
                        _config(run_dir), FrameTimes())
    assert not result.warnings
    live, replayed = _tracks_xy(run_dir), _tracks_xy(tmp_path / "log")
    assert len(replayed) == len(live)
    gaps = np.linalg.norm(live[:, None] - replayed[None], axis=2).min(axis=1)
    assert (gaps < 0.3).all(), gaps
    summary = json.loads((tmp_path / "log" / "summary.json").read_text())
    assert summary["log_format"] == "tlog" and summary["frames_used"] > 50


@pytest.mark.parametrize("write", [write_bin, write_ulg], ids=["ardupilot-bin", "px4-ulg"])
def test_the_flight_as_an_ardupilot_or_px4_log_replays(run_dir: Path, tmp_path: Path,
                                                       write: Any) -> None:
    """The run's poses written as a DataFlash .bin or a ULog .ulg, replayed with its frames."""
    poses = read_flight_log(run_dir / "flight.tlog")
    log = write(tmp_path / ("flight.bin" if write is write_bin else "flight.ulg"),
                poses.positions, poses.attitudes)
    result = replay_log(log, run_dir / "frames", tmp_path / "out", _config(run_dir),
                        FrameTimes())
    assert not result.warnings
    live, replayed = _tracks_xy(run_dir), _tracks_xy(tmp_path / "out")
    assert len(replayed) == len(live)
    gaps = np.linalg.norm(live[:, None] - replayed[None], axis=2).min(axis=1)
    assert (gaps < 0.3).all(), gaps


def _video(run_dir: Path, path: Path) -> Path:
    """The kept frames as an MJPEG AVI, and their capture times as a CSV beside it."""
    index = (run_dir / "frames" / "index.csv").read_text().splitlines()
    files = [run_dir / "frames" / line.split(",")[2] for line in index[1:]]
    images = [cv2.imread(str(file)) for file in files]
    height, width = images[0].shape[:2] if images[0] is not None else (0, 0)
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), 2.0, (width, height))
    for image in images:
        assert image is not None
        writer.write(image)
    writer.release()
    path.with_suffix(".csv").write_text(
        "t_s\n" + "".join(line.split(",")[1] + "\n" for line in index[1:]))
    return path


def test_a_video_with_frame_times_replays_and_a_cut_video_warns(run_dir: Path,
                                                                tmp_path: Path) -> None:
    video = _video(run_dir, tmp_path / "flight.avi")
    times = FrameTimes(file=video.with_suffix(".csv"))
    whole = replay_log(run_dir / "flight.tlog", video, tmp_path / "whole", _config(run_dir),
                       times)
    assert not whole.warnings
    gaps = np.linalg.norm(_tracks_xy(run_dir)[:, None] - _tracks_xy(tmp_path / "whole")[None],
                          axis=2).min(axis=1)
    assert (gaps < 0.5).all(), gaps  # JPEG-compressed frames: the same tags, a little noise
    cut = tmp_path / "cut.avi"
    data = video.read_bytes()
    cut.write_bytes(data[: len(data) // 2])
    half = replay_log(run_dir / "flight.tlog", cut, tmp_path / "cut", _config(run_dir), times)
    assert 0 < half.steps < whole.steps
    assert any("a truncated video?" in w for w in half.warnings), half.warnings


def test_log_replay_needs_frames_and_a_configuration(run_dir: Path, tmp_path: Path) -> None:
    for extra, named in (([], "--frames"), (["--frames", str(run_dir / "frames")], "--config")):
        done = subprocess.run([sys.executable, "-m", "companion", "replay",
                               str(run_dir / "flight.tlog"), *extra],
                              capture_output=True, text=True, timeout=60, check=False)
        assert done.returncode == 2 and done.stderr.startswith(f"companion: {named}: ")
        assert "Traceback" not in done.stderr
    junk = tmp_path / "junk.avi"
    junk.write_bytes(np.random.default_rng(3).bytes(5000))
    done = subprocess.run([sys.executable, "-m", "companion", "replay",
                           str(run_dir / "flight.tlog"), "--frames", str(junk),
                           "--frame-offset-s", "0", "--config",
                           str(Path(__file__).resolve().parent.parent / "sitl" / "service.toml")],
                          capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 1 and "not a video OpenCV can read" in done.stderr, done.stderr
    assert "Traceback" not in done.stderr


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
        assert (tmp_path / path.stem / "flight-mahalanobis.png").is_file()
        final = json.loads((tmp_path / path.stem / "summary.json").read_text())["truth"][
            "mahalanobis_final"]
        assert sum(d is not None and d < 3.0 for d in final) == len(result.tracks)
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
