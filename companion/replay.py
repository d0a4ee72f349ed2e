"""Replay a run folder of the service: its recorded detections and poses through the pipeline.

`replay_run(run_dir, out_dir, config)` reads the run's `steps.jsonl` (each step's input: the
autopilot boot time, the pose at the frame's capture time and the detected tag centres, or the
blind reason). It steps a fresh `Pipeline` over them with the run's configuration
(`config.json`) and camera (`camera.json`), or with another configuration to tune parameters
after the flight. It writes the same reports as the live run. It is deterministic: the same
inputs give byte-identical outputs, and with the run's own configuration the confirmed tracks
are the live run's.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from companion.config import ServiceConfig, parse_config
from companion.errors import InputError
from companion.pipeline import Pipeline
from companion.report import (
    Score,
    TrackRecord,
    confirmed_tracks,
    score,
    write_csv,
    write_geojson,
)
from companion.sim.plots import plot_flight
from companion.vision.camera import CameraModel
from companion.vision.projection import GeoPose

__all__ = ["ReplayResult", "load_truth", "replay_run"]

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class ReplayResult:
    """What a replay produced."""

    out_dir: Path
    steps: int
    tracks: list[TrackRecord]
    warnings: list[str]
    wall_s: float
    flight_s: float  # the autopilot time the steps span
    score: Score | None = None  # against the truth file, when one was given


def load_truth(path: Path) -> FloatArray:
    """True target positions (n, 2) [lat, lon] from a CSV (columns lat, lon) or GeoJSON points."""
    try:
        if path.suffix.lower() in (".geojson", ".json"):
            features = json.loads(path.read_text())["features"]
            points = [f["geometry"]["coordinates"][:2][::-1] for f in features
                      if f["geometry"]["type"] == "Point"]
        else:
            with path.open(newline="") as fh:
                points = [[float(row["lat"]), float(row["lon"])] for row in csv.DictReader(fh)]
    except (OSError, KeyError, TypeError, ValueError) as exc:
        raise InputError(f"{path}: not a truth file (CSV with lat, lon columns, or GeoJSON "
                         f"points): {exc}") from exc
    truth = np.array(points, dtype=np.float64).reshape(-1, 2)
    if not np.all(np.isfinite(truth)) or np.any(np.abs(truth[:, 0]) > 90.0):
        raise InputError(f"{path}: positions must be finite [lat, lon] in degrees")
    return truth


def _records(path: Path, warnings: list[str]) -> Iterator[dict[str, Any]]:
    """The JSON lines of a file; a torn last line (a crash mid-write) ends it with a warning."""
    lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    for number, line in enumerate(lines, start=1):
        try:
            yield json.loads(line)
        except json.JSONDecodeError as exc:
            if number == len(lines):
                warnings.append(f"{path.name}: line {number} is cut short (a crash?): "
                                f"replayed up to line {number - 1}")
                return
            raise InputError(f"{path}: line {number} is not JSON: {exc}") from exc


def _camera(path: Path) -> CameraModel:
    try:
        fields: dict[str, Any] = {k: tuple(v) if isinstance(v, list) else v
                                  for k, v in json.loads(path.read_text()).items()}
        return CameraModel(**fields)
    except (OSError, ValueError, TypeError) as exc:
        raise InputError(f"{path}: not a camera model written by the service: {exc}") from exc


def replay_run(run_dir: Path, out_dir: Path, config: ServiceConfig | None = None,
               progress: Callable[[int, int], None] | None = None,
               truth_latlon: FloatArray | None = None) -> ReplayResult:
    """Re-run a run folder's steps; config replaces the run's own configuration."""
    started = time.perf_counter()
    if not (run_dir / "steps.jsonl").is_file():
        raise InputError(f"{run_dir}: not a run folder of the service (no steps.jsonl)")
    if config is None:
        config = parse_config(json.loads((run_dir / "config.json").read_text()))
    camera = _camera(run_dir / "camera.json")
    pipeline = Pipeline(config, camera)
    warnings: list[str] = []
    inputs = [(r["input"], r.get("blind")) for r in _records(run_dir / "steps.jsonl", warnings)
              if "input" in r]
    out_dir.mkdir(parents=True, exist_ok=True)
    with (out_dir / "steps.jsonl").open("w", encoding="utf-8") as steps:
        for k, (step, blind) in enumerate(inputs):
            if "pixels" in step:
                lat, lon, alt, height, *q = step["pose"]
                pose = GeoPose(step["boot_t_s"], lat, lon, alt, height, tuple(q))
                pixels = np.array(step["pixels"], dtype=np.float64).reshape(-1, 2)
                record = pipeline.step_detections(pixels, pose)
            else:
                record = pipeline.blind(step["boot_t_s"], blind or "blind")
            steps.write(json.dumps(record.to_json(pipeline.frame), separators=(",", ":")) + "\n")
            if progress is not None:
                progress(k + 1, len(inputs))
    frame = pipeline.frame
    tracks = [] if pipeline.state is None else confirmed_tracks(
        pipeline.state.tracks, frame.origin_utm_m, frame.utm.epsg, frame.to_latlon)
    write_geojson(out_dir / "tracks.geojson", tracks)
    write_csv(out_dir / "tracks.csv", tracks)
    if config.output.plots:
        records = [json.loads(line) for line in (out_dir / "steps.jsonl").read_text().splitlines()]
        plot_flight(records, np.array([[t.easting_m, t.northing_m] for t in tracks]), out_dir)
    span_s = inputs[-1][0]["boot_t_s"] - inputs[0][0]["boot_t_s"] if len(inputs) > 1 else 0.0
    summary: dict[str, Any] = {"steps": len(inputs), "confirmed": len(tracks),
                               "warnings": warnings,
                               "tracks": [dataclasses.asdict(t) for t in tracks]}
    result_score = None
    if truth_latlon is not None:
        e, n = frame.utm.geodetic_to_utm(truth_latlon[:, 0], truth_latlon[:, 1])
        truth_en = np.column_stack([e, n])
        tracks_en = np.array([[t.easting_m, t.northing_m] for t in tracks]).reshape(-1, 2)
        result_score = score(tracks_en, truth_en)
        summary["truth"] = {"errors_m": [None if not np.isfinite(x) else round(float(x), 4)
                                         for x in result_score.errors_m],
                            "missed": result_score.missed,
                            "false_tracks": result_score.false_tracks}
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=1))
    return ReplayResult(out_dir, len(inputs), tracks, warnings,
                        time.perf_counter() - started, float(span_s), result_score)
