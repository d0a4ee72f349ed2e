"""Fifty tags in view: the service's pipeline on a 30 fps camera whose every frame holds 50 tags.

Fifty 0.5 m tag36h11 tags (ids 0..49) lie on a 10 x 5 grid filling 85 % of a level camera's
footprint, at an altitude where each tag's black square is about 24 px wide (decodable without
decimation). A thread publishes rendered frames of them over the SITL's MJPEG stream at --fps,
each stamped with its capture time; the service's newest-frame grabber reads them and each newest
frame goes through `Pipeline.step` (detect, project, GM-PHD step) as fast as the machine allows.
It prints, at 640x480 and 1280x720: detections and measurements per frame (should be 50), the
processing time of a step (median, p95; and of the detection alone), the frames processed per
second of those published, the frames the grabber dropped (counted explicitly: it keeps only
the newest), and whether the pipeline keeps up with the camera.

    python benchmarks/bench_many_tags.py [--seconds 10] [--fps 30]

The machine is shared, so the timing figures are noisy; the counts are not. The figures also go
to out/reliability/many-tags-WxH.json for docs/reliability.md. The components and
confirmed tracks at the end are the filter's: with the default pose uncertainty (0.5 m) it
merges tags closer than about 1.2 m into one component, so on the 640x480 grid (tags 1.1 m
apart) it confirms fewer tracks than there are tags.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterator

import numpy as np

from companion.drive import Observation, drive
from companion.pipeline import Pipeline, StepRecord
from companion.vision.camera import BodyPose, CameraModel
from companion.vision.tags import detect_centres
from sitl.camera import Renderer, Tag
from sitl.figures import record_figure
from sitl.rig import geo_pose, pipeline_config, published_frames, run_resolutions

TAG_SIZE_M = 0.5
GRID_COLS, GRID_ROWS = 10, 5  # across (east) x along (north) the image
GRID_FILL = 0.85  # share of the footprint the grid spans
TAG_PX = 24.0  # black-square width aimed at: 3 px per cell
KEEP_UP_SHARE = 0.95  # keeps up: processes at least this share of the frames published


def grid_altitude_m(camera: CameraModel, tag_px: float = TAG_PX) -> float:
    """The altitude at which a level camera sees a TAG_SIZE_M tag tag_px pixels wide."""
    return min(camera.fx_px, camera.fy_px) * TAG_SIZE_M / tag_px


def grid_tags(camera: CameraModel, altitude_m: float, rng: np.random.Generator) -> list[Tag]:
    """GRID_COLS x GRID_ROWS tags (ids 0, 1, ...) filling GRID_FILL of the footprint of a level
    camera at altitude_m heading north over (0, 0), each turned by a seeded yaw within +-15 deg
    (turned further, neighbours' quiet zones could touch on the smaller images)."""
    half_east_m = altitude_m * 0.5 * camera.width_px / camera.fx_px
    half_north_m = altitude_m * 0.5 * camera.height_px / camera.fy_px
    east = GRID_FILL * half_east_m * np.linspace(-1.0, 1.0, 2 * GRID_COLS + 1)[1::2]
    north = GRID_FILL * half_north_m * np.linspace(-1.0, 1.0, 2 * GRID_ROWS + 1)[1::2]
    yaws = rng.uniform(-math.radians(15.0), math.radians(15.0), GRID_COLS * GRID_ROWS)
    return [Tag(i, float(n), float(e), TAG_SIZE_M, float(yaws[i]))
            for i, (n, e) in enumerate((n, e) for n in north for e in east)]


def bench(width_px: int, height_px: int, seconds: float, fps: float) -> None:
    """Print the figures for one resolution."""
    camera = CameraModel.from_hfov(90.0, width_px, height_px)
    altitude_m = grid_altitude_m(camera)
    renderer = Renderer(camera, texture_seed=1)
    rng = np.random.default_rng(0)
    tags = grid_tags(camera, altitude_m, rng)
    pose = BodyPose(0.0, 0.0, 0.0, -altitude_m, (1.0, 0.0, 0.0, 0.0))
    frames = [renderer.render(pose, tags, rng) for _ in range(30)]  # differ by exposure noise
    pipeline = Pipeline(pipeline_config(camera), camera)
    detections: list[int] = []
    measurements: list[int] = []
    step_ms: list[float] = []
    latencies_ms: list[float] = []
    with published_frames(frames, fps) as (grabber, published):
        published_before, dropped_before = published[0], grabber.dropped
        start = time.monotonic()
        step_started = [0.0]  # when the step under way began

        def observations() -> Iterator[Observation]:
            while time.monotonic() - start < seconds:
                frame = grabber.get(1.0)
                if frame is None or frame.capture_time_s is None:
                    continue
                step_started[0] = time.perf_counter()
                yield Observation(frame.capture_time_s,
                                  geo_pose(frame.capture_time_s, altitude_m), frame.image)

        def on_step(record: StepRecord) -> None:
            step_ms.append(1e3 * (time.perf_counter() - step_started[0]))
            detections.append(record.detections)
            measurements.append(len(record.measurements_xy_m))
            latencies_ms.append(1e3 * (time.monotonic() - record.extra["input"]["boot_t_s"]))

        drive(pipeline, observations(), None, on_step)
        elapsed_s = time.monotonic() - start
        n_published = published[0] - published_before
        n_dropped = grabber.dropped - dropped_before
    detect_ms = []
    det = pipeline.config.detector
    for image in frames[:10]:
        started = time.perf_counter()
        detect_centres(pipeline.detector, image, det.min_decision_margin, det.allowed_ids)
        detect_ms.append(1e3 * (time.perf_counter() - started))
    step = np.array(step_ms)
    processed_fps = len(step) / elapsed_s
    keeps_up = len(step) >= KEEP_UP_SHARE * n_published
    state = pipeline.state
    east_m = sorted({round(t.east_m, 3) for t in tags})
    north_m = sorted({round(t.north_m, 3) for t in tags})
    print(f"{width_px}x{height_px} at {altitude_m:.1f} m ({len(tags)} tags, black square "
          f"{TAG_PX:g} px, {east_m[1] - east_m[0]:.2f} m x {north_m[1] - north_m[0]:.2f} m "
          f"apart): detections per frame min {min(detections)}, median "
          f"{np.median(detections):.0f}; measurements per frame min {min(measurements)}; "
          f"components at the end {0 if state is None else state.mixture.size}, confirmed "
          f"{0 if state is None else int(state.tracks.confirmed.sum())}")
    print(f"  Pipeline.step: median {np.median(step):.1f} ms, p95 {np.percentile(step, 95):.1f} "
          f"ms (detection alone: median {np.median(detect_ms):.1f} ms); latency capture -> "
          f"tracks median {np.median(latencies_ms):.1f} ms")
    print(f"  {processed_fps:.1f} frames/s processed ({len(step)}) of {n_published / elapsed_s:.1f}"
          f" published ({n_published}); dropped by the grabber: {n_dropped}; keeps up with "
          f"{fps:g} fps: {'yes' if keeps_up else 'no'}")
    record_figure(f"many-tags-{width_px}x{height_px}", detections_min=min(detections),
                  step_median_ms=round(float(np.median(step)), 1),
                  step_p95_ms=round(float(np.percentile(step, 95)), 1),
                  processed_fps=round(processed_fps, 1),
                  published_fps=round(n_published / elapsed_s, 1), dropped=n_dropped,
                  keeps_up=keeps_up)


def main() -> None:
    """Print the figures."""
    run_resolutions(__doc__.splitlines()[0], bench)


if __name__ == "__main__":
    main()
