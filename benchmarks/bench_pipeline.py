"""End-to-end speed of the service's pipeline on a 30 fps camera with five tags in view.

A thread publishes rendered frames over the SITL's MJPEG stream at 30 frames per second, each
stamped with its capture time. The service's newest-frame grabber reads them, and each newest
frame goes through the pipeline (detect, project, GM-PHD step) as fast as the machine allows.
It prints, at 640x480 and 1280x720: the frames per second processed, the frames skipped (the
grabber drops stale frames instead of queueing them), and the latency from capture to updated
tracks (median, p95, and its first and last fifths: a backlog would make the last grow), with
each estimator kind (filter.kind = "gmphd", then "lmb").

    python benchmarks/bench_pipeline.py [--seconds 10] [--fps 30]
"""

from __future__ import annotations

import time
from collections.abc import Iterator

import numpy as np

from companion.drive import Observation, drive
from companion.pipeline import Pipeline, StepRecord
from companion.vision.camera import BodyPose, CameraModel
from sitl.camera import Renderer, Tag
from sitl.rig import geo_pose, pipeline_config, published_frames, run_resolutions

ALTITUDE_M = 8.0
TAGS = [Tag(i, n, e, 0.5, 0.4 * i) for i, (n, e) in
        enumerate([(0.0, 0.0), (3.0, 4.0), (-3.0, 5.0), (2.5, -5.5), (-3.5, -4.0)])]


def bench(width_px: int, height_px: int, seconds: float, fps: float) -> None:
    """Each estimator kind in turn at one resolution."""
    for kind in ("gmphd", "lmb"):
        bench_kind(width_px, height_px, seconds, fps, kind)


def bench_kind(width_px: int, height_px: int, seconds: float, fps: float, kind: str) -> None:
    camera = CameraModel.from_hfov(90.0, width_px, height_px)
    renderer = Renderer(camera, texture_seed=1)
    rng = np.random.default_rng(0)
    pose = BodyPose(0.0, 0.0, 0.0, -ALTITUDE_M, (1.0, 0.0, 0.0, 0.0))
    frames = [renderer.render(pose, TAGS, rng) for _ in range(30)]
    pipeline = Pipeline(pipeline_config(camera, kind), camera)
    latencies_ms: list[float] = []
    detections = 0
    with published_frames(frames, fps) as (grabber, published):
        start = time.monotonic()

        def observations() -> Iterator[Observation]:
            while time.monotonic() - start < seconds:
                frame = grabber.get(1.0)
                if frame is None or frame.capture_time_s is None:
                    continue
                yield Observation(frame.capture_time_s,
                                  geo_pose(frame.capture_time_s, ALTITUDE_M), frame.image)

        def on_step(record: StepRecord) -> None:
            nonlocal detections
            detections += record.detections
            capture_s = record.extra["input"]["boot_t_s"]
            latencies_ms.append(1e3 * (time.monotonic() - capture_s))

        drive(pipeline, observations(), None, on_step)
        elapsed = time.monotonic() - start
    lat_ms = np.array(latencies_ms)
    fifth = max(len(lat_ms) // 5, 1)
    print(f"{width_px}x{height_px}, {kind}: {len(lat_ms) / elapsed:5.1f} frames/s processed of "
          f"{published[0] / elapsed:4.1f} published, {grabber.dropped} skipped by the grabber, "
          f"{detections / max(len(lat_ms), 1):.1f} tags per frame")
    print(f"  latency capture -> tracks: median {np.median(lat_ms):.1f} ms, "
          f"p95 {np.percentile(lat_ms, 95):.1f} ms; first fifth median "
          f"{np.median(lat_ms[:fifth]):.1f} ms, last fifth {np.median(lat_ms[-fifth:]):.1f} ms")


def main() -> None:
    """Print the figures."""
    run_resolutions(__doc__.splitlines()[0], bench)


if __name__ == "__main__":
    main()
