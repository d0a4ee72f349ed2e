"""The pipeline on rendered frames (no network): tags found, blind steps keep tracks, reboots."""

from __future__ import annotations

import csv
import itertools
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from numpy.typing import NDArray

from companion.config import load_config
from companion.pipeline import Pipeline
from companion.report import confirmed_tracks, score, write_csv, write_geojson
from companion.sat.fov import prob_in_region
from companion.sim.scenario import Scenario, load_scenario
from companion.vision.camera import BodyPose
from companion.vision.projection import GeoPose
from sitl.camera import Renderer
from sitl.cli import sitl_scenarios
from sitl.world import TargetWorld

ROOT = Path(__file__).resolve().parent.parent
FloatArray = NDArray[np.float64]


def _lawnmower_xy(step_m: float = 1.0) -> list[FloatArray]:
    corners = [(4.0, 0.0), (4.0, 24.0), (12.0, 24.0), (12.0, 0.0), (20.0, 0.0), (20.0, 24.0),
               (28.0, 24.0), (28.0, 0.0)]
    path = [np.array(corners[0])]
    for a, b in itertools.pairwise(corners):
        a_xy, b_xy = np.array(a), np.array(b)
        n = int(np.ceil(np.linalg.norm(b_xy - a_xy) / step_m))
        path += [a_xy + (b_xy - a_xy) * k / n for k in range(1, n + 1)]
    return path


class Flight:
    """Frames of the field experiment rendered along a lawn mower, with their geodetic poses."""

    def __init__(self) -> None:
        self.scenario: Scenario = load_scenario(sitl_scenarios()["field-5-tags"])
        self.world = TargetWorld(self.scenario, np.random.default_rng(0))
        self.renderer = Renderer(self.scenario.camera, texture_seed=1)
        self.rng = np.random.default_rng(1)
        self.geo = self.scenario.geo.local_ned()

    def frame(self, t_s: float, xy: FloatArray) -> tuple[NDArray[np.uint8], GeoPose]:
        pose = BodyPose(t_s, float(xy[1]), float(xy[0]), -8.0, (1.0, 0.0, 0.0, 0.0))
        image = self.renderer.render(pose, self.world.tags(t_s), self.rng)
        lat, lon, alt = (float(v) for v in self.geo.ned_to_geodetic(xy[1], xy[0], -8.0))
        return image, GeoPose(t_s, lat, lon, alt, 8.0, (1.0, 0.0, 0.0, 0.0))

    def truth_xy(self, pipeline: Pipeline) -> FloatArray:
        out = []
        for tag in self.world.tags(0.0):
            lat, lon, _ = self.geo.ned_to_geodetic(tag.north_m, tag.east_m, 0.0)
            e, n = pipeline.frame.utm.geodetic_to_utm(lat, lon)
            out.append(pipeline.frame.from_utm(np.array([float(e), float(n)])))
        return np.array(out)


@pytest.fixture(scope="module")
def flown() -> tuple[Flight, Pipeline, list[float]]:
    flight = Flight()
    pipeline = Pipeline(load_config(ROOT / "sitl" / "service.toml"), flight.scenario.camera)
    times = []
    for k, xy in enumerate(_lawnmower_xy()):
        t_s = 10.0 + 0.5 * k
        pipeline.step(*flight.frame(t_s, xy))
        times.append(t_s)
    return flight, pipeline, times


def test_every_tag_is_confirmed_where_it_is(flown: tuple[Flight, Pipeline, list[float]]) -> None:
    flight, pipeline, _ = flown
    assert pipeline.state is not None
    tracks = pipeline.state.tracks
    result = score(tracks.means[tracks.confirmed, :2], flight.truth_xy(pipeline), gate_m=3.0)
    assert result.missed == 0 and result.false_tracks == 0
    assert np.all(result.errors_m < 0.1), result.errors_m


def test_blind_steps_and_a_reboot_keep_the_tracks(flown: tuple[Flight, Pipeline, list[float]]
                                                   ) -> None:
    _, pipeline, times = flown
    assert pipeline.state is not None
    before = set(pipeline.state.tracks.ids[pipeline.state.tracks.confirmed].tolist())
    t_s = times[-1]
    for k in range(40):  # 20 s without a usable frame
        record = pipeline.blind(t_s + 0.5 * (k + 1), "no frame")
        assert record.blind == "no frame" and record.region_xy_m is None
    assert set(record.extra["confirmed_ids"]) == before
    reboot = pipeline.blind(3.0, "no pose at the capture time")  # the autopilot rebooted
    assert reboot.t_s == record.t_s  # its new boot time carries on from where we were
    assert pipeline.blind(3.5, "no frame").t_s == pytest.approx(record.t_s + 0.5)
    assert set(reboot.extra["confirmed_ids"]) == before


def test_reports_of_the_tracks(flown: tuple[Flight, Pipeline, list[float]],
                               tmp_path: Path) -> None:
    _, pipeline, _ = flown
    assert pipeline.state is not None
    frame = pipeline.frame
    records = confirmed_tracks(pipeline.state.tracks, frame.origin_utm_m, frame.utm.epsg,
                               frame.to_latlon, pipeline.state.t_s, pipeline.params.tracks)
    assert len(records) == 5
    write_geojson(tmp_path / "t.geojson", records)
    write_csv(tmp_path / "t.csv", records)
    features = json.loads((tmp_path / "t.geojson").read_text())["features"]
    rows = list(csv.DictReader((tmp_path / "t.csv").open()))
    for record, feature, row in zip(records, features, rows, strict=True):
        assert feature["geometry"]["coordinates"] == [record.lon_deg, record.lat_deg]
        lat, lon = frame.utm.utm_to_geodetic(record.easting_m, record.northing_m)
        assert (float(lat), float(lon)) == pytest.approx((record.lat_deg, record.lon_deg))
        assert int(row["id"]) == record.id and row["utm_epsg"] == "32632"
        assert record.cov_ee_m2 > 0 and record.first_seen_s <= record.last_seen_s


def test_coasting_tracks_are_confined_to_the_search_area_as_in_the_simulator(
        flown: tuple[Flight, Pipeline, list[float]]) -> None:
    # The service's estimator had no area: a track coasting out of the field lived on.
    _, pipeline, _ = flown
    area_xy = pipeline.frame.area_xy_m
    centre_xy = area_xy.mean(axis=0)
    outside_xy = area_xy.max(axis=0) + 50.0
    region = pipeline.params.tracks.area
    assert region is not None
    mass = prob_in_region(np.array([centre_xy, outside_xy]), np.array([np.eye(2)] * 2), region)
    assert mass == pytest.approx([1.0, 0.0], abs=1e-6)


def test_score_matches_one_to_one_within_the_gate() -> None:
    result = score(np.array([[0.0, 0.0], [10.0, 10.0], [0.5, 0.0]]),
                   np.array([[0.0, 0.2], [20.0, 20.0]]))
    np.testing.assert_allclose(result.errors_m, [0.2, np.inf])
    assert result.missed == 1 and result.false_tracks == 2
    assert score(np.zeros((0, 2)), np.array([[0.0, 0.0]])).missed == 1
    assert score(np.array([[1.0, 1.0]]), np.zeros((0, 2))).false_tracks == 1




WARM_UP_CHECK = """
import json, sys
from numba.core.registry import CPUDispatcher
from companion.config import load_config
from companion.pipeline import Pipeline
from companion.sat import filter, fov, gp, predict, reduce, track_kernels, update
from tests.test_pipeline import Flight, _lawnmower_xy

def loaded():
    return {f"{m.__name__}.{name}": len(kernel.overloads)
            for m in (filter, fov, gp, predict, reduce, track_kernels, update)
            for name, kernel in vars(m).items() if isinstance(kernel, CPUDispatcher)}

flight = Flight()
pipeline = Pipeline(load_config(sys.argv[1]), flight.scenario.camera)
before = loaded()
pipeline.warm_up()
warm, state = loaded(), repr(pipeline.state)
for k, xy in enumerate(_lawnmower_xy()):
    pipeline.step(*flight.frame(10.0 + 0.5 * k, xy))
flown = loaded()
print(json.dumps({"state after warm-up": state,
                  "warm-up": sorted(n for n in warm if warm[n] > before[n]),
                  "flight": sorted(n for n in warm if flown[n] > warm[n]),
                  "confirmed": int(pipeline.state.tracks.confirmed.sum())}))
"""


@pytest.mark.parametrize("fov", ["camera", "disk"])
def test_after_warm_up_a_flight_compiles_or_loads_no_more_kernels(tmp_path: Path,
                                                                 fov: str) -> None:
    """In a fresh interpreter, warm_up compiles or loads (numba's cache) every estimator
    kernel that the field flight then steps through, GP prediction included, and leaves the
    pipeline's state alone."""
    text = (ROOT / "sitl" / "service.toml").read_text()
    config = tmp_path / "service.toml"
    config.write_text(text.replace("[estimator]\n", f'[estimator]\nfov = "{fov}"\n'))
    done = subprocess.run([sys.executable, "-c", WARM_UP_CHECK, str(config)], cwd=ROOT,
                          capture_output=True, text=True, timeout=600, check=True)
    seen = json.loads(done.stdout)
    assert seen["state after warm-up"] == "None" and seen["confirmed"] >= 3, seen
    assert len(seen["warm-up"]) >= 5 and seen["flight"] == [], seen
