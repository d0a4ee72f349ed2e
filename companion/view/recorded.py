"""The view of a recorded run folder: one step message per recorded step, for a time slider.

`recorded_view(run_dir)` re-runs the estimator over the run's recorded detections (fast: no
image is decoded) with the run's configuration and camera, so that every step shows the
estimate as it was then. A run folder of an earlier version without its configuration or
camera, or without step inputs, still opens: its steps show the path, footprints and
detections, and its last step the confirmed tracks of tracks.csv. Each step shows the mission
state, link and camera health the service recorded with it (`mission`, `link_ok`, `camera_ok`,
`home_utm` in steps.jsonl); a folder of an earlier version has none, and the page says so.
The orthophoto is the one given (a bad file is an error) or the run's configuration's (a bad
or missing one is a warning: the run opens without it).
"""

from __future__ import annotations

import csv
import json
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from companion.config import ServiceConfig
from companion.drive import observe
from companion.errors import CompanionError, ConfigError, InputError
from companion.geo import Utm
from companion.pipeline import Pipeline, SearchFrame
from companion.plan.world import World
from companion.replay import recorded_observations
from companion.run_folder import STEPS, read_camera, read_config, read_records
from companion.sat.tracks import TrackParams
from companion.view.model import (
    Status,
    Trails,
    Vehicle,
    encode,
    scene_message,
    step_message,
    yaw_deg,
)
from companion.view.orthophoto import Orthophoto, load_orthophoto
from companion.vision.camera import CameraModel

__all__ = ["RecordedView", "recorded_view"]

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class RecordedView:
    """A run's scene and its step messages (each zlib-compressed JSON), with any warnings,
    and the orthophoto the scene names."""

    scene: dict[str, Any]
    steps: list[bytes]
    warnings: list[str]
    orthophoto: Orthophoto | None = None


def _pack(message: dict[str, Any]) -> bytes:
    return zlib.compress(encode(message).encode("utf-8"), 6)


def _vehicle(frame: SearchFrame, step_input: dict[str, Any]) -> Vehicle | None:
    """The vehicle at a recorded step: its pose's position and heading, when it has one."""
    pose = step_input.get("pose")
    if not pose or len(pose) < 8:
        return None
    e, n = frame.utm.geodetic_to_utm(float(pose[0]), float(pose[1]))
    xy = frame.from_utm(np.array([float(e), float(n)]))
    return Vehicle((float(xy[0]), float(xy[1])), yaw_deg(pose[4:8]), float(pose[3]))


def _status(frame: SearchFrame, record: dict[str, Any], counters: dict[str, int],
            home_xy: tuple[float, float] | None) -> Status:
    """The service's status a step recorded (None where the run folder's version kept none);
    home as recorded, else home_xy."""
    home_en = record.get("home_utm")
    if home_en:
        xy = frame.from_utm(np.asarray(home_en, dtype=np.float64))
        home_xy = (float(xy[0]), float(xy[1]))
    mission, link_ok, camera_ok = (record.get(k) for k in ("mission", "link_ok", "camera_ok"))
    return Status(mission if isinstance(mission, str) else None,
                  link_ok if isinstance(link_ok, bool) else None,
                  camera_ok if isinstance(camera_ok, bool) else None, counters, home_xy)


def _orthophoto(frame: SearchFrame, fence: FloatArray | None, given: Path | None,
                config: ServiceConfig | None, warnings: list[str]) -> Orthophoto | None:
    """The orthophoto given (ConfigError naming --orthophoto if it is bad), else the one of
    the configuration (a warning if it is bad or missing), else None."""
    if given is not None:
        return load_orthophoto(given, frame, fence, key="--orthophoto")
    path = None if config is None else config.view.orthophoto
    if path is None:
        return None
    try:
        return load_orthophoto(Path(path), frame, fence)
    except ConfigError as exc:
        warnings.append(f"The run's orthophoto is not shown: {exc}")
        return None


def recorded_view(run_dir: Path, config: ServiceConfig | None = None,
                  camera: CameraModel | None = None,
                  orthophoto: Path | None = None) -> RecordedView:
    """The view of run_dir (config, camera: instead of the run's own; orthophoto: instead of
    the configuration's); InputError names what is wrong with a folder that is not a run
    folder, ConfigError a bad orthophoto given."""
    if not run_dir.is_dir():
        raise InputError(f"{run_dir}: no such run folder")
    if not (run_dir / STEPS).is_file():
        raise InputError(f"{run_dir}: not a run folder of the service (no {STEPS})")
    warnings: list[str] = []
    records = list(read_records(run_dir / STEPS, warnings))
    if not records:
        raise InputError(f"{run_dir}: {STEPS} holds no step")
    try:
        config = config or read_config(run_dir)
        camera = camera or read_camera(run_dir)
    except (CompanionError, OSError, ValueError) as exc:
        warnings.append(f"the run's configuration or camera cannot be read ({exc}): its steps "
                        "are shown as recorded, the tracks of tracks.csv at the last step")
        return _as_recorded(run_dir, records, warnings, orthophoto=orthophoto)
    if not all("input" in r for r in records):
        warnings.append(f"{STEPS} was written by a version that kept no step inputs: its "
                        "steps are shown as recorded, the tracks of tracks.csv at the last step")
        return _as_recorded(run_dir, records, warnings, config, orthophoto)
    pipeline = Pipeline(config, camera)
    frame, params = pipeline.frame, pipeline.params.tracks
    fence = config.safety.geofence_latlon
    ortho = _orthophoto(frame, fence, orthophoto, config, warnings)
    scene = scene_message(frame, fence, mode="replay", rate_hz=config.estimator.rate_hz,
                          expected_targets=config.search.expected_targets, name=run_dir.name,
                          notes=warnings, orthophoto=None if ortho is None else ortho.scene())
    scene["notes"] = warnings
    inputs = [(r["input"], r.get("blind")) for r in records]
    trails, counters = Trails(), {"steps": 0, "blind_steps": 0, "frames_used": 0}
    steps: list[bytes] = []
    times: list[float] = []
    last_vehicle: Vehicle | None = None
    for recorded, (step_input, _), obs in zip(
            records, inputs, recorded_observations(run_dir, inputs, False, []), strict=True):
        record = observe(pipeline, obs).to_json(frame)
        vehicle = _vehicle(frame, step_input) or last_vehicle  # a blind step: where it was
        last_vehicle = vehicle
        meas = record.get("measurements_utm") or []
        detections = frame.from_utm(np.asarray(meas, dtype=np.float64)) if meas else np.zeros(
            (0, 2))
        trails = trails.after(record["t_s"], None if vehicle is None else vehicle.xy_m,
                              detections, record["blind"], pipeline.state)
        counters = {"steps": counters["steps"] + 1,
                    "blind_steps": counters["blind_steps"] + (record["blind"] is not None),
                    "frames_used": counters["frames_used"] + (record["blind"] is None)}
        status = _status(frame, recorded, counters, trails.path[0] if trails.path else None)
        steps.append(_pack(step_message(len(steps) + 1, frame, pipeline.state, record, trails,
                                        params, vehicle, status)))
        times.append(record["t_s"])
    scene["steps"] = len(steps)
    scene["times_s"] = [round(t, 3) for t in times]
    return RecordedView(scene, steps, warnings, ortho)


def _epsg(run_dir: Path, config: ServiceConfig | None) -> int:
    """The UTM zone of a run: its configuration's, its summary's or its tracks'."""
    if config is not None:
        return config.search.utm_epsg
    try:
        return int(json.loads((run_dir / "summary.json").read_text())["utm_epsg"])
    except (OSError, ValueError, KeyError, TypeError):
        pass
    try:
        with (run_dir / "tracks.csv").open(newline="") as fh:
            for row in csv.DictReader(fh):
                return int(row["utm_epsg"])
    except (OSError, ValueError, KeyError):
        pass
    raise InputError(f"{run_dir}: neither config.json, summary.json nor tracks.csv says in "
                     "which UTM zone its steps are: the run cannot be drawn")


def _final_tracks(run_dir: Path, frame: SearchFrame) -> list[dict[str, Any]]:
    """The confirmed tracks of tracks.csv as the page's tracks (none if there is no file)."""
    try:
        with (run_dir / "tracks.csv").open(newline="") as fh:
            rows = list(csv.DictReader(fh))
    except OSError:
        return []
    out = []
    for row in rows:
        try:
            x, y = frame.from_utm(np.array([float(row["easting_m"]), float(row["northing_m"])]))
            out.append({"id": int(row["id"]), "x": round(float(x), 2), "y": round(float(y), 2),
                        "cov": [float(row["cov_ee_m2"]), float(row["cov_en_m2"]),
                                float(row["cov_nn_m2"])],
                        "lat": float(row["lat_deg"]), "lon": float(row["lon_deg"]),
                        "confirmed": True, "coasting": row.get("coasting") == "True",
                        "seen_s": float(row["last_detected_s"]),
                        "born_s": float(row["first_seen_s"]), "history": []})
        except (KeyError, ValueError):
            continue
    return out


def _as_recorded(run_dir: Path, records: list[dict[str, Any]], warnings: list[str],
                 config: ServiceConfig | None = None,
                 orthophoto: Path | None = None) -> RecordedView:
    """The view of the steps as recorded: no estimate but the final tracks."""
    utm = Utm(_epsg(run_dir, config))
    if config is not None:
        frame = SearchFrame.from_config(config.search)
    else:
        points = [p for r in records for key in ("vehicle_utm", "region_utm")
                  for p in (r.get(key) or [])]
        if not points:
            raise InputError(f"{run_dir}: its steps hold no position to draw")
        en = np.asarray(points, dtype=np.float64)
        origin, size = en.min(axis=0) - 5.0, np.ptp(en, axis=0) + 10.0
        box = np.array([[0.0, 0.0], [size[0], 0.0], [size[0], size[1]], [0.0, size[1]]])
        frame = SearchFrame(utm, origin, World(float(size[0]), float(size[1])), box)
    geofence = None if config is None else config.safety.geofence_latlon
    ortho = _orthophoto(frame, geofence, orthophoto, config, warnings)
    scene = scene_message(frame, geofence, mode="replay",
                          rate_hz=2.0 if config is None else config.estimator.rate_hz,
                          expected_targets=None, name=run_dir.name, notes=warnings,
                          orthophoto=None if ortho is None else ortho.scene())
    scene["notes"] = warnings
    trails, steps, times = Trails(), list[bytes](), list[float]()
    final = _final_tracks(run_dir, frame)
    params = TrackParams()
    for k, record in enumerate(records):
        vehicle_en = record.get("vehicle_utm")
        xy = None
        if vehicle_en:
            v = frame.from_utm(np.asarray(vehicle_en[0], dtype=np.float64))
            xy = (float(v[0]), float(v[1]))
        meas = record.get("measurements_utm") or []
        detections = frame.from_utm(np.asarray(meas, dtype=np.float64)) if meas else np.zeros(
            (0, 2))
        t_s = float(record.get("t_s", k))
        trails = trails.after(t_s, xy, detections, record.get("blind"), None)
        message = step_message(k + 1, frame, None, record, trails, params,
                               None if xy is None else Vehicle(xy),
                               _status(frame, record, {}, None))
        if k == len(records) - 1:
            message["tracks"] = final
        steps.append(_pack(message))
        times.append(round(t_s, 3))
    scene["steps"] = len(steps)
    scene["times_s"] = times
    return RecordedView(scene, steps, warnings, ortho)
