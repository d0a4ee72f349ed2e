"""Speed of the SITL camera renderer and of pupil-apriltags on its frames.

Run: python benchmarks/bench_render.py [--repeats N] [--threads T] [--no-sweep]

1. Frames per second rendering 640x480 and 1280x720 (90 degree hFOV, 8 m, six 0.5 m tags in
   view, a slightly tilted vehicle), without and with lens distortion: median over repeats.
2. pupil-apriltags detection time on those frames at decimate 1 and 2, with the tags found and
   the largest centre error against the projected tag centres (pupil's +0.5 px removed).
3. (unless --no-sweep) The tag size needed at 8 m: detection rate by tag size and decimation.
The machine is shared, so compare ratios rather than single figures.
"""

from __future__ import annotations

import argparse
import math
import time
from collections.abc import Callable

import numpy as np
import pupil_apriltags
from numpy.typing import NDArray

from companion.vision.camera import BodyPose, CameraModel, project_points
from companion.vision.tags import PUPIL_OFFSET_PX, TagDetector
from sitl.camera import Renderer, Tag

FloatArray = NDArray[np.float64]

ALTITUDE_M = 8.0
TARGET_FPS = 30.0
BARREL = (-0.2, 0.05, 0.001, -0.001, 0.0)
LAYOUT = [(0.0, 0.0, 0.0), (3.0, 2.0, 0.3), (-2.0, -4.0, 1.0), (4.0, -5.0, 2.0),
          (-4.0, 5.0, -1.0), (1.5, 6.0, 0.7)]


def _times_s(call: Callable[[int], object], repeats: int) -> FloatArray:
    """Wall time of call(i) for i in range(repeats), after one warm-up call, in seconds."""
    call(-1)
    out = np.empty(repeats)
    for i in range(repeats):
        start = time.perf_counter()
        call(i)
        out[i] = time.perf_counter() - start
    return out


def _poses(repeats: int) -> list[BodyPose]:
    """A vehicle drifting and wobbling a few degrees at 8 m, so frames differ."""
    return [BodyPose.from_euler(0.1 * i, 0.02 * i, -0.01 * i, -ALTITUDE_M,
                                math.radians(3.0 * math.sin(0.3 * i)),
                                math.radians(2.0 * math.cos(0.2 * i)), 0.01 * i)
            for i in range(repeats)]


def _centre_errors(camera: CameraModel, pose: BodyPose, tags: list[Tag],
                   detections: list[pupil_apriltags.Detection]) -> list[float]:
    by_id = {t.tag_id: t for t in tags}
    errors = []
    for det in detections:
        tag = by_id[det.tag_id]
        corners, _ = project_points(camera, pose, tag.corners_ned(10))
        if not (np.all(corners >= 0.0) and np.all(corners[:, 0] <= camera.width_px - 1)
                and np.all(corners[:, 1] <= camera.height_px - 1)):
            continue  # cut by the frame edge: such detections are dropped downstream
        centre, _ = project_points(camera, pose, np.array([[tag.north_m, tag.east_m, 0.0]]))
        errors.append(float(np.hypot(*(np.asarray(det.center) - PUPIL_OFFSET_PX - centre[0]))))
    return errors


def bench_resolution(width_px: int, height_px: int, dist: tuple[float, ...], repeats: int,
                     threads: int) -> None:
    camera = CameraModel.from_hfov(90.0, width_px, height_px, dist=dist)
    renderer = Renderer(camera, texture_seed=1)
    tags = [Tag(i, n, e, 0.5, yaw) for i, (n, e, yaw) in enumerate(LAYOUT)]
    poses = _poses(repeats + 1)
    rng = np.random.default_rng(0)
    frames: list[NDArray[np.uint8]] = []

    def render(i: int) -> None:
        frames.append(renderer.render(poses[i + 1], tags, rng))

    render_s = _times_s(render, repeats)
    frames.pop(0)  # the warm-up frame
    label = f"{width_px}x{height_px}{' distorted' if dist != (0.0,) * 5 else ''}"
    fps = 1.0 / float(np.median(render_s))
    print(f"render {label:22s} {fps:7.1f} frames/s (median {1e3 * np.median(render_s):.2f} ms, "
          f"p95 {1e3 * np.percentile(render_s, 95):.2f} ms) "
          f"{'ok' if fps > TARGET_FPS else 'BELOW'} target {TARGET_FPS:.0f}")
    for decimate in (1.0, 2.0):
        detector = TagDetector(families="tag36h11", quad_decimate=decimate,
                                            nthreads=threads)
        found: list[int] = []
        errors: list[float] = []

        def detect(i: int, detector: pupil_apriltags.Detector = detector,
                   found: list[int] = found, errors: list[float] = errors) -> None:
            k = max(i, 0)
            detections = detector.detect(frames[k])
            if i >= 0:
                found.append(len(detections))
                errors.extend(_centre_errors(camera, poses[k + 1], tags, detections))

        detect_s = _times_s(detect, len(frames))
        print(f"  detect decimate {decimate:.0f} ({threads} threads): "
              f"median {1e3 * np.median(detect_s):6.2f} ms, tags found per frame "
              f"{np.mean(found):.2f} of {len(tags)}, centre error max "
              f"{max(errors, default=math.nan):.2f} px, median "
              f"{np.median(errors) if errors else math.nan:.2f} px")


def sweep_tag_size(frames_per_size: int) -> None:
    """Detection rate of tags wholly in view at 8 m, by tag size, default camera."""
    camera = CameraModel()
    renderer = Renderer(camera, texture_seed=2)
    detectors = {d: TagDetector(families="tag36h11", quad_decimate=d)
                 for d in (1.0, 2.0)}
    print("tag size at 8 m (default camera: 40 px per metre), detection rate:")
    for size_m in (0.15, 0.2, 0.25, 0.3, 0.4, 0.5, 0.6, 0.7):
        tags = [Tag(i, n, e, size_m, yaw) for i, (n, e, yaw) in enumerate(LAYOUT)]
        rates = {}
        for decimate, detector in detectors.items():
            hits = 0
            for i, pose in enumerate(_poses(frames_per_size)):
                image = renderer.render(pose, tags, np.random.default_rng(i))
                hits += len(detector.detect(image))
            rates[decimate] = hits / (len(tags) * frames_per_size)
        print(f"  {size_m:4.2f} m ({size_m * 40.0:4.1f} px): decimate 1 {rates[1.0]:5.0%}, "
              f"decimate 2 {rates[2.0]:5.0%}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=60)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--no-sweep", action="store_true")
    args = parser.parse_args()
    for width_px, height_px in ((640, 480), (1280, 720)):
        for dist in ((0.0,) * 5, BARREL):
            bench_resolution(width_px, height_px, dist, args.repeats, args.threads)
    if not args.no_sweep:
        sweep_tag_size(10)


if __name__ == "__main__":
    main()
