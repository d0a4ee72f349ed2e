"""A run folder: what a flight (live or replayed) leaves behind, written and read in one place.

A live run gets a new folder `run-YYYYmmddTHHMMSSZ` (`-2`, `-3`, ... when that exists) under the
output directory; a replay writes into the folder it is given. Every estimator step is a JSON
line in `steps.jsonl`, every event of a live run one in `events.jsonl`, each flushed as it is
written (a crash loses at most the last line). At the end: the confirmed tracks as
`tracks.geojson` and `tracks.csv`, the flight plots, and `summary.json`.

A live run also keeps what a replay needs besides its steps: `config.json`, `camera.json`
(and `version.txt`); `read_config` and `read_camera` read them back.

`read_records` reads the JSON lines back; a torn last line (a crash mid-write) ends them with a
warning, any other bad line is an error. The format is that of every earlier version.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable, Iterator
from datetime import datetime
from importlib.metadata import version
from pathlib import Path
from typing import Any, Literal, TextIO

import numpy as np
from numpy.typing import NDArray

from companion.config import ServiceConfig, parse_config
from companion.errors import CompanionError, InputError
from companion.report import TrackRecord, write_csv, write_geojson
from companion.run_plots import plot_flight, plot_mahalanobis
from companion.vision.camera import CameraModel

__all__ = ["EVENTS", "STEPS", "STEP_STATUS_KEYS", "JsonLines", "RunFolder", "new_run_dir",
           "read_camera", "read_config", "read_records", "read_steps"]

FloatArray = NDArray[np.float64]
STEPS = "steps.jsonl"
# the service's status a live step records beside the estimator's (none in older folders)
STEP_STATUS_KEYS = ("mission", "link_ok", "camera_ok", "home_utm")
EVENTS = "events.jsonl"


class JsonLines:
    """Appends one JSON object per line and flushes it (a crash loses at most the last line)."""

    def __init__(self, path: Path, mode: Literal["a", "w"] = "a") -> None:
        self.path = path
        self._fh: TextIO = path.open(mode, encoding="utf-8")

    def write(self, record: dict[str, Any]) -> None:
        """One line, written through to the file."""
        self._fh.write(json.dumps(record, separators=(",", ":")) + "\n")
        self._fh.flush()

    def close(self) -> None:
        """Close the file (idempotent)."""
        self._fh.close()


def new_run_dir(root: Path, now: datetime) -> Path:
    """A new, empty folder under root named after the UTC time now (suffixed when taken)."""
    base = root / now.strftime("run-%Y%m%dT%H%M%SZ")
    path, n = base, 1
    while path.exists():
        n += 1
        path = base.with_name(f"{base.name}-{n}")
    path.mkdir(parents=True)
    return path


def read_records(path: Path, warnings: list[str]) -> Iterator[dict[str, Any]]:
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


def read_steps(run_dir: Path, warnings: list[str] | None = None) -> list[dict[str, Any]]:
    """Every step record of a run folder (a torn last line is left out, with a warning)."""
    return list(read_records(run_dir / STEPS, [] if warnings is None else warnings))


def read_events(run_dir: Path, warnings: list[str] | None = None) -> list[dict[str, Any]]:
    """Every event record of a run folder (a torn last line is left out, with a warning)."""
    return list(read_records(run_dir / EVENTS, [] if warnings is None else warnings))


def read_config(run_dir: Path) -> ServiceConfig:
    """The configuration a run flew with."""
    return parse_config(json.loads((run_dir / "config.json").read_text()))


def read_camera(run_dir: Path) -> CameraModel:
    """The camera model a run flew with."""
    path = run_dir / "camera.json"
    try:
        fields: dict[str, Any] = {k: tuple(v) if isinstance(v, list) else v
                                  for k, v in json.loads(path.read_text()).items()}
        return CameraModel(**fields)
    except (OSError, ValueError, TypeError) as exc:
        raise InputError(f"{path}: not a camera model written by the service: {exc}") from exc


class RunFolder:
    """One run's folder: its steps (and events) as they happen, its reports at the end."""

    def __init__(self, path: Path, *, events: bool = False) -> None:
        path.mkdir(parents=True, exist_ok=True)
        self.path = path
        self.events: JsonLines | None = JsonLines(path / EVENTS) if events else None
        self.steps = JsonLines(path / STEPS, "w")

    @staticmethod
    def create(root: Path, now: datetime) -> RunFolder:
        """A live run's new timestamped folder under root, with its events log."""
        return RunFolder(new_run_dir(root, now), events=True)

    def write_snapshot(self, config: ServiceConfig, camera: CameraModel) -> None:
        """What a replay needs besides the steps: the configuration (its orthophoto named by
        absolute path, so that a replay finds it) and the camera model."""
        data = dict(config.data)
        if config.view.orthophoto is not None:
            view = data.get("view")
            data["view"] = {**(view if isinstance(view, dict) else {}),
                            "orthophoto": str(Path(config.view.orthophoto).resolve())}
        (self.path / "config.json").write_text(json.dumps(data, indent=1))
        fields = {f.name: getattr(camera, f.name) for f in dataclasses.fields(camera)}
        (self.path / "camera.json").write_text(json.dumps(fields, indent=1))
        (self.path / "version.txt").write_text(f"companion {version('companion')}\n")

    def write_step(self, record: dict[str, Any]) -> None:
        """One step's JSON record."""
        self.steps.write(record)

    def write_event(self, record: dict[str, Any]) -> None:
        """One event's JSON record (a folder without an events log drops it)."""
        if self.events is not None:
            self.events.write(record)

    def close(self) -> None:
        """Close the logs."""
        self.steps.close()
        if self.events is not None:
            self.events.close()

    def write_reports(self, tracks: list[TrackRecord], summary: dict[str, Any], *,
                      plots: bool, area_en_m: FloatArray | None = None,
                      mahalanobis: tuple[FloatArray, FloatArray] | None = None,
                      on_plots_skipped: Callable[[str], None] | None = None) -> None:
        """tracks.geojson, tracks.csv, the plots (with (t_s, closest) the Mahalanobis plot too)
        and summary.json. Without matplotlib the plots raise, unless on_plots_skipped takes
        the reason."""
        write_geojson(self.path / "tracks.geojson", tracks)
        write_csv(self.path / "tracks.csv", tracks)
        if plots:
            try:
                self._plot(tracks, area_en_m, mahalanobis)
            except CompanionError as exc:
                if on_plots_skipped is None:
                    raise
                on_plots_skipped(str(exc))
        (self.path / "summary.json").write_text(json.dumps(summary, indent=1))

    def _plot(self, tracks: list[TrackRecord], area_en_m: FloatArray | None,
              mahalanobis: tuple[FloatArray, FloatArray] | None) -> None:
        tracks_en = np.array([[t.easting_m, t.northing_m] for t in tracks]).reshape(-1, 2)
        plot_flight(read_steps(self.path), tracks_en, self.path, area_en_m)
        if mahalanobis is not None:
            plot_mahalanobis(mahalanobis[0], mahalanobis[1], self.path)
