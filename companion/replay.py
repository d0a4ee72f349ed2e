"""Replay a flight offline through the pipeline: a run folder of ours, or another tool's log.

`replay_run(run_dir, out_dir, config)` reads the run's `steps.jsonl` (each step's input: the
autopilot boot time, the pose at the frame's capture time and the detected tag centres or the
kept frame, or the blind reason). It steps a fresh `Pipeline` over them with the run's
configuration (`config.json`) and camera (`camera.json`), or with another configuration to tune
parameters after the flight. Where the run kept its frames, detection runs again on them.

`replay_log(log, frames, out_dir, config, times)` pairs the poses of a flight log (.tlog, .bin,
.ulg; see `companion.flightlog`) with the frames of a video or an image folder, each frame at
its time on the autopilot's boot clock, and steps the pipeline at the configured estimator rate.
The log's poses reach the frames through a `VehicleView` and its position gate, as live telemetry
does: a GPS glitch in the log blinds the frames taken during it, as it did in flight.

Both write the live run's reports (steps.jsonl, tracks.geojson/csv, summary.json, plots), and
with true positions the error table and the Mahalanobis distance of each target to its closest
track over time. Deterministic: the same inputs give byte-identical outputs.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from companion.config import ServiceConfig
from companion.drive import Observation, drive, frame_observation
from companion.errors import InputError
from companion.flightlog import FlightLog, read_flight_log
from companion.metrics import mahalanobis_to_tracks
from companion.pipeline import Pipeline, StepRecord, camera_model
from companion.report import Score, TrackRecord, confirmed_tracks, score
from companion.run_folder import (
    STEP_STATUS_KEYS,
    RunFolder,
    read_camera,
    read_config,
    read_records,
)
from companion.vehicle.plausibility import PositionGate, offset_ne_m
from companion.vehicle.view import VehicleView
from companion.vision.camera import CameraModel
from companion.vision.projection import GeoPose, PoseUncertainty

__all__ = ["FrameTimes", "ReplayResult", "load_truth", "recorded_observations", "replay_log",
           "replay_run"]

FloatArray = NDArray[np.float64]
Progress = Callable[[int, int], None]
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp", ".pgm", ".tif", ".tiff")


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


@dataclass(frozen=True)
class FrameTimes:
    """When each frame was taken, on the log's boot clock: a file of times, or offset + k / rate.

    Neither given: an image folder's own index.csv (written by the service), else an error.
    rate_hz None with an offset: the video's own frame rate.
    """

    file: Path | None = None
    offset_s: float | None = None
    rate_hz: float | None = None


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


class _Replay:
    """A fresh pipeline and the replay's outputs: the steps log, then tracks, plots, summary."""

    def __init__(self, config: ServiceConfig, camera: CameraModel, out_dir: Path,
                 truth_latlon: FloatArray | None) -> None:
        self.config = config
        self.pipeline = Pipeline(config, camera)
        self.out_dir = out_dir
        self.warnings: list[str] = []
        self.started = time.perf_counter()
        frame = self.pipeline.frame
        self.truth_xy: FloatArray | None = None
        if truth_latlon is not None:
            e, n = frame.utm.geodetic_to_utm(truth_latlon[:, 0], truth_latlon[:, 1])
            self.truth_xy = frame.from_utm(np.column_stack([e, n]))
        self.t_s: list[float] = []
        self.mahalanobis: list[FloatArray] = []  # per step: each target to its closest track
        self.folder = RunFolder(out_dir)
        self.steps = 0

    def add(self, record: StepRecord) -> None:
        """Count one step; with truth, each target's Mahalanobis distance to its closest track."""
        self.steps += 1
        state = self.pipeline.state
        if self.truth_xy is not None and state is not None:
            confirmed = state.tracks.confirmed
            closest, _ = mahalanobis_to_tracks(self.truth_xy, state.tracks.means[confirmed, :2],
                                               state.tracks.covs[confirmed, :2, :2])
            self.t_s.append(record.t_s)
            self.mahalanobis.append(closest)

    def finish(self, steps: int, flight_s: float, **summary: Any) -> ReplayResult:
        """Write the tracks, plots and summary.json; the result."""
        self.folder.close()
        out, frame, state = self.out_dir, self.pipeline.frame, self.pipeline.state
        tracks = [] if state is None else confirmed_tracks(
            state.tracks, frame.origin_utm_m, frame.utm.epsg, frame.to_latlon, state.t_s,
            self.pipeline.params.tracks)
        tracks_en = np.array([[t.easting_m, t.northing_m] for t in tracks]).reshape(-1, 2)
        targets = 0 if self.truth_xy is None else len(self.truth_xy)
        mahal = np.array(self.mahalanobis, dtype=np.float64).reshape(len(self.t_s), targets)
        body: dict[str, Any] = {"steps": steps, **summary, "confirmed": len(tracks),
                                "warnings": self.warnings,
                                "tracks": [dataclasses.asdict(t) for t in tracks]}
        result_score = None
        if self.truth_xy is not None:
            result_score = score(tracks_en, frame.to_utm(self.truth_xy))
            final = mahal[-1] if len(mahal) else np.full(len(self.truth_xy), np.inf)
            body["truth"] = {"errors_m": _finite_or_none(result_score.errors_m, 4),
                             "mahalanobis_final": _finite_or_none(final, 3),
                             "missed": result_score.missed,
                             "false_tracks": result_score.false_tracks}
        self.folder.write_reports(
            tracks, body, plots=self.config.output.plots, area_en_m=frame.to_utm(frame.area_xy_m),
            mahalanobis=None if self.truth_xy is None else (np.array(self.t_s), mahal))
        return ReplayResult(out, steps, tracks, self.warnings,
                            time.perf_counter() - self.started, flight_s, result_score)


def _finite_or_none(values: FloatArray, digits: int) -> list[float | None]:
    return [round(float(x), digits) if math.isfinite(x) else None for x in values]


def _read_image(path: Path) -> NDArray[np.uint8]:
    image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise InputError(f"{path}: not an image OpenCV can read")
    return np.asarray(image, dtype=np.uint8)


def recorded_observations(run_dir: Path, inputs: list[tuple[dict[str, Any], str | None]],
                          redetect: bool, missing: list[int]) -> Iterator[Observation]:
    """The observations of a run folder's recorded step inputs (each with its blind reason):
    its kept frames where redetect is set and they exist, else its recorded detections; the
    index of each kept frame found missing is appended to missing."""
    for index, (step, blind) in enumerate(inputs):
        if "pose" not in step:
            yield Observation.nothing(step["boot_t_s"], blind or "blind")
            continue
        lat, lon, alt, height, *q = step["pose"]
        pose = GeoPose(step["boot_t_s"], lat, lon, alt, height, tuple(q))
        sigma = PoseUncertainty(*step["pose_sigma"]) if "pose_sigma" in step else None
        image_path = run_dir / step["frame"] if redetect and "frame" in step else None
        if image_path is not None and image_path.is_file():
            yield Observation(pose.t_s, pose, _read_image(image_path), sigma=sigma)
        else:
            if image_path is not None:
                missing.append(index)
            pixels = np.array(step["pixels"], dtype=np.float64).reshape(-1, 2)
            yield Observation(pose.t_s, pose, pixels=pixels, sigma=sigma)


def replay_run(run_dir: Path, out_dir: Path, config: ServiceConfig | None = None,
               progress: Progress | None = None, truth_latlon: FloatArray | None = None,
               redetect: bool = True) -> ReplayResult:
    """Re-run a run folder's steps (detection too where frames were kept and redetect is set);
    config replaces the run's own configuration."""
    if not (run_dir / "steps.jsonl").is_file():
        raise InputError(f"{run_dir}: not a run folder of the service (no steps.jsonl)")
    if config is None:
        config = read_config(run_dir)
    replay = _Replay(config, read_camera(run_dir), out_dir, truth_latlon)
    records = [r for r in read_records(run_dir / "steps.jsonl", replay.warnings) if "input" in r]
    inputs = [(r["input"], r.get("blind")) for r in records]
    statuses = [{k: r[k] for k in STEP_STATUS_KEYS if k in r} for r in records]
    missing: list[int] = []

    def on_step(record: StepRecord) -> None:
        record.extra.update(statuses[replay.steps])  # the live step's status, as recorded
        replay.add(record)
        if progress is not None:
            progress(replay.steps, len(inputs))

    drive(replay.pipeline, recorded_observations(run_dir, inputs, redetect, missing),
          replay.folder, on_step)
    if missing:
        replay.warnings.append(f"{len(missing)} kept frames are missing: their recorded "
                               "detections were used")
    span_s = inputs[-1][0]["boot_t_s"] - inputs[0][0]["boot_t_s"] if len(inputs) > 1 else 0.0
    return replay.finish(len(inputs), float(span_s))


# -- flight logs of other tools ---------------------------------------------------------------


def _frame_times_file(path: Path) -> FloatArray:
    """Frame times from a CSV with a t_s or capture_t_s column, or one number per line."""
    try:
        lines = [line.strip() for line in path.read_text().splitlines() if line.strip()]
        if lines and not _is_number(lines[0].split(",")[0]):
            rows = list(csv.DictReader(lines))
            column = next((c for c in ("t_s", "capture_t_s") if c in rows[0]), None) \
                if rows else None
            if column is None:
                raise InputError(f"{path}: frame times need a t_s or capture_t_s column")
            times = [float(row[column]) for row in rows]
        else:
            times = [float(line.split(",")[0]) for line in lines]
    except (OSError, ValueError) as exc:
        raise InputError(f"{path}: not a file of frame times: {exc}") from exc
    t = np.array(times, dtype=np.float64)
    if not np.all(np.isfinite(t)) or np.any(np.diff(t) < 0):
        raise InputError(f"{path}: frame times must be finite and in order")
    return t


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


class _Frames:
    """The frames of a video file or an image folder, read in order, with their times."""

    def __init__(self, path: Path, times: FrameTimes) -> None:
        self.path = path
        self._video: Any = None
        self._files: list[Path] = []
        own_times: FloatArray | None = None
        if path.is_dir():
            index = path / "index.csv"
            if index.is_file():
                with index.open(newline="") as fh:
                    rows = list(csv.DictReader(fh))
                self._files = [path.parent / r["file"] if (path.parent / r["file"]).is_file()
                               else path / Path(r["file"]).name for r in rows]
                own_times = _frame_times_file(index)
            else:
                self._files = sorted(f for f in path.iterdir()
                                     if f.suffix.lower() in IMAGE_SUFFIXES)
            if not self._files:
                raise InputError(f"{path}: no images in this folder")
            count, fps = len(self._files), None
        elif path.is_file():
            self._video = cv2.VideoCapture(str(path))
            if not self._video.isOpened():
                raise InputError(f"{path}: not a video OpenCV can read")
            count = int(self._video.get(cv2.CAP_PROP_FRAME_COUNT))
            fps = float(self._video.get(cv2.CAP_PROP_FPS)) or None
        else:
            raise InputError(f"{path}: no such video file or image folder")
        if times.file is not None:
            self.t_s = _frame_times_file(times.file)
        elif times.offset_s is not None:
            rate = times.rate_hz or fps
            if rate is None or not rate > 0:
                raise InputError(f"{path}: the video gives no frame rate: pass one")
            n = count if count > 0 else 0
            self.t_s = times.offset_s + np.arange(n, dtype=np.float64) / rate
        elif own_times is not None:
            self.t_s = own_times
        else:
            raise InputError(f"{path}: the frames' times are unknown: pass a file of frame "
                             "times, or the log time of the first frame (and the rate)")
        self.count = int(self.t_s.size)

    def __iter__(self) -> Iterator[tuple[int, float, NDArray[np.uint8] | None]]:
        """(index, t_s, image) for every frame; image None when it is not wanted (skipped)."""
        for k, t_s in enumerate(self.t_s):
            if self._video is not None:
                ok, image = self._video.read()
                if not ok:
                    return
                yield k, float(t_s), cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
            elif k < len(self._files):
                yield k, float(t_s), _read_image(self._files[k])
            else:
                return

    def close(self) -> None:
        """Release the video."""
        if self._video is not None:
            self._video.release()


class _LogTelemetry:
    """A flight log's poses fed to a `VehicleView` in time order, as live telemetry is: bad
    samples and implausible jumps (a GPS glitch) are refused as they would be in flight.

    A log has no velocities for the position gate: it gets the velocity between the last two
    positions the gate accepted (a glitch is never among them).
    """

    def __init__(self, log: FlightLog, config: ServiceConfig) -> None:
        self.config = config
        self._now_s = 0.0
        self.view = VehicleView(lambda: self._now_s, config.pose.max_gap_s, PositionGate(
            config.pose.glitch_gate_m, config.pose.glitch_accept_after_s))
        self._positions, self._attitudes = log.positions, log.attitudes
        self._next_position = self._next_attitude = 0
        self._accepted: list[tuple[float, float, float]] = []  # the last two: t_s, lat, lon

    def _velocity_ne(self) -> tuple[float, float]:
        if len(self._accepted) < 2:
            return 0.0, 0.0
        (t0, lat0, lon0), (t1, lat1, lon1) = self._accepted
        if t1 - t0 <= 0.0:
            return 0.0, 0.0
        north_m, east_m = offset_ne_m(lat1, lon1, lat0, lon0)
        return -north_m / (t1 - t0), -east_m / (t1 - t0)

    def _feed_until(self, until_s: float) -> None:
        """Every sample up to until_s, positions and attitudes interleaved by time."""
        view, pos, att = self.view, self._positions, self._attitudes
        while True:
            p_s = pos[self._next_position, 0] if self._next_position < len(pos) else math.inf
            a_s = att[self._next_attitude, 0] if self._next_attitude < len(att) else math.inf
            if min(p_s, a_s) > until_s:
                return
            if p_s <= a_s:
                t_s, lat, lon, amsl, rel = (float(v) for v in pos[self._next_position])
                self._next_position += 1
                self._now_s = t_s
                refused = sum(view.rejected.values())
                view.on_position(t_s, lat, lon, amsl, rel, self._velocity_ne())
                if sum(view.rejected.values()) == refused:
                    self._accepted = [*self._accepted[-1:], (t_s, lat, lon)]
            else:
                t_s, qw, qx, qy, qz = (float(v) for v in att[self._next_attitude])
                self._next_attitude += 1
                self._now_s = t_s
                view.on_attitude(t_s, (qw, qx, qy, qz))

    def observation(self, t_s: float, image: NDArray[np.uint8]) -> Observation:
        """The frame taken at t_s with the pose the live service would give it, or blind."""
        self._feed_until(t_s + self.config.pose.max_gap_s)  # the samples that bracket t_s
        obs = frame_observation(self.view, t_s, np.asarray(image, dtype=np.uint8),
                                self.config.pose)
        return dataclasses.replace(obs, extra={})  # a log replay's steps keep their keys


def replay_log(log_path: Path, frames_path: Path, out_dir: Path, config: ServiceConfig,
               times: FrameTimes, progress: Progress | None = None,
               truth_latlon: FloatArray | None = None) -> ReplayResult:
    """Detect, project and estimate over a video (or image folder) with the poses of a log."""
    log = read_flight_log(log_path)
    telemetry = _LogTelemetry(log, config)
    frames = _Frames(frames_path, times)
    replay = _Replay(config, camera_model(config.camera), out_dir, truth_latlon)
    replay.warnings.extend(log.warnings)
    period_s = 1.0 / config.estimator.rate_hz
    read = used = 0
    first_s = last_s = math.nan

    def observations() -> Iterator[Observation]:
        nonlocal read, first_s, last_s
        next_s = -math.inf
        for k, t_s, image in frames:
            read = k + 1
            if progress is not None:
                progress(read, frames.count)
            if t_s < next_s or image is None:
                continue  # one step per estimator period, as the live service does
            next_s = max(next_s + period_s, t_s)
            first_s = t_s if math.isnan(first_s) else first_s
            last_s = t_s
            yield telemetry.observation(t_s, image)

    def on_step(record: StepRecord) -> None:
        nonlocal used
        replay.add(record)
        used += record.blind is None

    try:
        steps = drive(replay.pipeline, observations(), replay.folder, on_step)
    finally:
        frames.close()
    if read < frames.count:
        replay.warnings.append(f"{frames_path.name}: {frames.count} frame times but only "
                               f"{read} frames (a truncated video?): replayed those")
    if used == 0:
        replay.warnings.append(f"no frame lies within the log's poses "
                               f"({log.positions[0, 0]:.1f}-{log.positions[-1, 0]:.1f} s): "
                               "check the frame times")
    rejected = telemetry.view.rejected
    if rejected["implausible"]:
        replay.warnings.append(f"{rejected['implausible']} positions of the log refused as "
                               "implausible jumps (a GPS glitch?), as in flight")
    flight_s = last_s - first_s if steps > 1 else 0.0
    return replay.finish(steps, float(flight_s), log=str(log_path), log_format=log.format,
                         frames=read, frames_used=used)
