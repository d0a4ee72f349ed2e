"""The pipeline benchmarks' rig: rendered frames published over MJPEG and read back newest-first.

It holds what the frame-rate benchmarks share: the origin and the service configuration they run,
a level pose over the origin, the camera publishing at a fixed rate to the service's newest-frame
grabber, and the command line that runs a benchmark at 640x480 and 1280x720.
"""

from __future__ import annotations

import argparse
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np
from numpy.typing import NDArray

from companion.camera.source import LatestFrameGrabber, MjpegSource
from companion.config import parse_config
from companion.geo import LocalNed
from companion.vision.camera import CameraModel
from companion.vision.projection import GeoPose
from sitl.stream import MjpegServer, publish_at_rate

__all__ = ["ORIGIN", "RESOLUTIONS_PX", "geo_pose", "pipeline_config", "published_frames",
           "run_resolutions"]

ORIGIN = LocalNed(47.397742, 8.545594, 488.0)
RESOLUTIONS_PX = ((640, 480), (1280, 720))
_AREA_HALF_M = 30
_CONNECT_S = 5.0


def pipeline_config(camera: CameraModel, kind: str = "gmphd") -> Any:
    """A service configuration for this camera over a 60 m square around the origin, with the
    estimator `kind` (filter.kind)."""
    h = _AREA_HALF_M
    corners = [ORIGIN.ned_to_geodetic(n, e, 0.0)[:2] for n, e in
               ((-h, -h), (-h, h), (h, h), (h, -h))]
    return parse_config({
        "camera": {"source": "bench", "width_px": camera.width_px,
                   "height_px": camera.height_px},
        "search": {"area": [[float(a), float(b)] for a, b in corners]},
        "detector": {"threads": 2},
        "filter": {"kind": kind},
    })


def geo_pose(t_s: float, altitude_m: float) -> GeoPose:
    """The level, north-facing pose over the origin at altitude_m, at time t_s."""
    lat, lon, alt = (float(v) for v in ORIGIN.ned_to_geodetic(0.0, 0.0, -altitude_m))
    return GeoPose(t_s, lat, lon, alt, altitude_m, (1.0, 0.0, 0.0, 0.0))


@contextmanager
def published_frames(frames: list[NDArray[np.uint8]],
                     fps: float) -> Iterator[tuple[LatestFrameGrabber, list[int]]]:
    """(grabber, published): frames published round-robin at fps, the grabber connected to them;
    published[0] counts the frames sent. Publisher and grabber stop on leaving."""
    stop, published = threading.Event(), [0]
    with MjpegServer() as server:
        publisher = threading.Thread(target=publish_at_rate,
                                     args=(server, frames, fps, stop, published))
        publisher.start()
        grabber = LatestFrameGrabber(MjpegSource(server.url)).start()
        try:
            grabber.get(_CONNECT_S)  # connected and flowing
            yield grabber, published
        finally:
            stop.set()
            publisher.join()
            grabber.stop()


def run_resolutions(description: str, bench: Callable[[int, int, float, float], None]) -> None:
    """Parse --seconds (per resolution) and --fps, then bench(width, height, seconds, fps)."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--seconds", type=float, default=10.0, help="per resolution")
    parser.add_argument("--fps", type=float, default=30.0, help="camera frame rate")
    args = parser.parse_args()
    for width_px, height_px in RESOLUTIONS_PX:
        bench(width_px, height_px, args.seconds, args.fps)
