"""The drive loop: each kind of observation steps the pipeline its way, records reach the sink
in order with the observation's extra fields; a flight log's poses pass the same checks as live
telemetry, so a GPS glitch in a log blinds its frames as it did in flight."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from companion.config import ServiceConfig, load_config
from companion.drive import Observation, drive, frame_observation, observe
from companion.errors import InputError
from companion.flightlog import FlightLog
from companion.pipeline import Pipeline, StepRecord, camera_model
from companion.replay import _LogTelemetry
from companion.vision.projection import GeoPose

ROOT = Path(__file__).resolve().parent.parent
LEVEL = (1.0, 0.0, 0.0, 0.0)


@pytest.fixture(scope="module")
def config() -> ServiceConfig:
    return load_config(ROOT / "sitl" / "service.toml")


def _pose(config: ServiceConfig, t_s: float) -> GeoPose:
    lat, lon = (float(v) for v in np.asarray(config.search.area_latlon).mean(axis=0))
    return GeoPose(t_s, lat, lon, 500.0, 10.0, LEVEL)


class _Sink:
    def __init__(self) -> None:
        self.records: list[dict[str, Any]] = []

    def write_step(self, record: dict[str, Any]) -> None:
        self.records.append(record)


def test_each_observation_steps_the_pipeline_its_way(config: ServiceConfig) -> None:
    pipeline = Pipeline(config, camera_model(config.camera))
    centre = np.array([[config.camera.width_px / 2.0, config.camera.height_px / 2.0]])
    sink, seen = _Sink(), list[StepRecord]()
    steps = drive(pipeline, [
        Observation.nothing(1.0, "no frame"),
        Observation(1.5, _pose(config, 1.5), pixels=centre, extra={"height_source": "altitude"}),
        Observation(2.0, _pose(config, 2.0), image=np.zeros((48, 64), dtype=np.uint8)),
    ], sink, seen.append)
    assert steps == 3 and len(seen) == 3
    assert [r["blind"] for r in sink.records] == ["no frame", None, "blank frame"]
    assert sink.records[1]["detections"] == 1 and sink.records[1]["height_source"] == "altitude"
    assert sink.records[1]["input"]["pixels"] == centre.tolist()
    with pytest.raises(InputError, match="neither image nor pixels"):
        observe(pipeline, Observation(3.0, _pose(config, 3.0)))


def _log(config: ServiceConfig, glitch_s: tuple[float, float]) -> FlightLog:
    """10 s at 10 Hz flying north at 2 m/s, the positions 60 m east during glitch_s."""
    lat0, lon0 = (float(v) for v in np.asarray(config.search.area_latlon).mean(axis=0))
    t = np.arange(0.0, 10.0, 0.1)
    lat = lat0 + 2.0 * t / 111_320.0
    lon = np.where((t >= glitch_s[0]) & (t < glitch_s[1]),
                   lon0 + 60.0 / (111_320.0 * np.cos(np.radians(lat0))), lon0)
    positions = np.column_stack([t, lat, lon, np.full_like(t, 510.0), np.full_like(t, 10.0)])
    attitudes = np.column_stack([t, np.ones_like(t), np.zeros((t.size, 3))])
    return FlightLog(Path("made-up.tlog"), "tlog", positions, attitudes, [])


def test_a_gps_glitch_in_a_log_is_refused_as_live(config: ServiceConfig) -> None:
    telemetry = _LogTelemetry(_log(config, (4.0, 6.0)), config)
    image = np.zeros((8, 8), dtype=np.uint8)
    before = telemetry.observation(3.0, image)
    assert before.blind is None and before.pose is not None
    during = telemetry.observation(5.0, image)
    assert during.blind == "implausible position (GPS glitch?)" and during.pose is None
    after = telemetry.observation(8.0, image)
    assert after.blind is None and after.pose is not None
    assert after.pose.lon_deg == pytest.approx(before.pose.lon_deg, abs=1e-9)
    assert after.pose.lat_deg - before.pose.lat_deg == pytest.approx(10.0 / 111_320.0, rel=1e-3)
    assert telemetry.view.rejected["implausible"] == 20
    # a frame captured in the glitch but processed after it (a loaded computer) is blind for it
    late = frame_observation(telemetry.view, 5.0, image, config.pose)
    assert late.blind == "implausible position (GPS glitch?)"


def test_a_clean_log_gives_every_frame_its_interpolated_pose(config: ServiceConfig) -> None:
    telemetry = _LogTelemetry(_log(config, (0.0, 0.0)), config)
    image = np.zeros((8, 8), dtype=np.uint8)
    first = telemetry.observation(1.05, image)
    second = telemetry.observation(1.1, image)
    assert first.pose is not None and second.pose is not None
    assert second.pose.lat_deg - first.pose.lat_deg == pytest.approx(0.1 / 111_320.0, rel=1e-6)
    assert telemetry.view.rejected["implausible"] == 0
    assert telemetry.observation(20.0, image).blind == "no pose at the capture time"
