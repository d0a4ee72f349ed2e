"""Fifty tags in one frame: the pipeline detects and measures every one (bench_many_tags' scene).

That the newest-frame grabber counts the frames it drops when the consumer is slower than the
camera is tested in tests/test_camera_source.py
(test_grabber_hands_over_the_newest_and_counts_what_it_dropped): not repeated here.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.config import parse_config
from companion.geo import LocalNed
from companion.pipeline import Pipeline
from companion.vision.camera import BodyPose, CameraModel
from companion.vision.projection import GeoPose
from sitl.camera import Renderer, Tag

ORIGIN = LocalNed(47.397742, 8.545594, 488.0)
TAG_SIZE_M = 0.5
COLS, ROWS = 10, 5


def _grid(camera: CameraModel, altitude_m: float) -> list[Tag]:
    """COLS x ROWS tags over 85 % of a level north-facing camera's footprint, seeded yaws."""
    half_east_m = altitude_m * 0.5 * camera.width_px / camera.fx_px
    half_north_m = altitude_m * 0.5 * camera.height_px / camera.fy_px
    east = 0.85 * half_east_m * np.linspace(-1.0, 1.0, 2 * COLS + 1)[1::2]
    north = 0.85 * half_north_m * np.linspace(-1.0, 1.0, 2 * ROWS + 1)[1::2]
    yaws = np.random.default_rng(5).uniform(-math.radians(15), math.radians(15), COLS * ROWS)
    return [Tag(i, float(n), float(e), TAG_SIZE_M, float(yaws[i]))
            for i, (n, e) in enumerate((n, e) for n in north for e in east)]


@pytest.mark.parametrize(("width_px", "height_px"), [(640, 480), (1280, 720)])
def test_fifty_tags_in_one_frame_give_fifty_measurements(width_px: int, height_px: int) -> None:
    camera = CameraModel.from_hfov(90.0, width_px, height_px)
    altitude_m = camera.fx_px * TAG_SIZE_M / 24.0  # each black square 24 px wide
    tags = _grid(camera, altitude_m)
    assert len(tags) == 50
    image = Renderer(camera, texture_seed=1).render(
        BodyPose(0.0, 0.0, 0.0, -altitude_m, (1.0, 0.0, 0.0, 0.0)), tags,
        np.random.default_rng(0))
    corners = [ORIGIN.ned_to_geodetic(n, e, 0.0)[:2] for n, e in
               ((-30, -30), (-30, 30), (30, 30), (30, -30))]
    config = parse_config({
        "camera": {"source": "test", "width_px": width_px, "height_px": height_px},
        "search": {"area": [[float(a), float(b)] for a, b in corners]},
    })
    pipeline = Pipeline(config, camera)
    lat, lon, alt = (float(v) for v in ORIGIN.ned_to_geodetic(0.0, 0.0, -altitude_m))
    record = pipeline.step(image, GeoPose(10.0, lat, lon, alt, altitude_m, (1.0, 0.0, 0.0, 0.0)))

    assert record.blind is None
    assert record.detections == 50
    assert record.measurements_xy_m.shape == (50, 2)
    # Each measurement lies where its tag is: match them one to one within 0.3 m.
    truth_en = []
    for tag in tags:
        t_lat, t_lon, _ = ORIGIN.ned_to_geodetic(tag.north_m, tag.east_m, 0.0)
        e, n = pipeline.frame.utm.geodetic_to_utm(t_lat, t_lon)
        truth_en.append([float(e), float(n)])
    truth_xy = pipeline.frame.from_utm(np.array(truth_en))
    d = np.linalg.norm(record.measurements_xy_m[:, None] - truth_xy[None], axis=2)
    assert np.all(d.min(axis=1) < 0.3) and np.all(d.min(axis=0) < 0.3)
