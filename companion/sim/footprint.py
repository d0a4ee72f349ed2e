"""Sensing polygons: a convexity check, and the ground a level camera sees (its footprint)."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import ConvexHull

from companion.errors import ConfigError
from companion.keys import frozen_rows
from companion.vision.camera import BodyPose, CameraModel, ground_footprint

FloatArray = NDArray[np.float64]


def convex_ccw(key: str, points: FloatArray) -> FloatArray:
    """The polygon, counter-clockwise, after checking >= 3 vertices, positive area, convexity."""
    n = points.shape[0]
    if n < 3:
        raise ConfigError(key, f"must have at least 3 points, got {n}")
    scale = float(np.max(np.abs(points)))
    if scale == 0.0:
        raise ConfigError(key, "must enclose a positive area")
    q = points / scale  # in [-1, 1]: no overflow below
    area2 = float(np.sum(q[:, 0] * np.roll(q[:, 1], -1) - np.roll(q[:, 0], -1) * q[:, 1]))
    if area2 == 0.0:  # shoelace formula, twice the signed area
        raise ConfigError(key, "must enclose a positive area")
    if area2 < 0.0:
        points, q = points[::-1], q[::-1]
    edge = np.roll(q, -1, axis=0) - q
    nxt = np.roll(edge, -1, axis=0)
    cross = edge[:, 0] * nxt[:, 1] - edge[:, 1] * nxt[:, 0]
    dot = np.sum(edge * nxt, axis=1)
    # Strictly left turns everywhere, and one full turn in total (a star polygon makes two).
    turning = float(np.sum(np.arctan2(cross, dot)))
    if np.any(cross <= 0.0) or not math.isclose(turning, 2.0 * math.pi, rel_tol=1e-6):
        raise ConfigError(
            key, "must be convex, with its vertices in order and none repeated or collinear"
        )
    return frozen_rows(points.tolist(), 2)


_FOOTPRINT_MAX_RANGE_M = 10_000.0


def camera_footprint_xy(camera: CameraModel, altitude_m: float, heading_deg: float) -> FloatArray:
    """(k, 2) counter-clockwise (x east, y north) offsets of the ground a level camera sees."""
    pose = BodyPose.from_euler(0.0, 0.0, 0.0, -altitude_m, yaw_rad=math.radians(heading_deg))
    samples = 8 if camera.has_distortion else 1
    ne = ground_footprint(camera, pose, _FOOTPRINT_MAX_RANGE_M, samples)
    if np.max(np.hypot(ne[:, 0], ne[:, 1])) >= 0.999 * _FOOTPRINT_MAX_RANGE_M:
        raise ConfigError("sensor.fov", '"camera": the level camera sees the horizon (check '
                                        "camera.mount_rpy_deg); its footprint is unbounded")
    xy = ne[:, ::-1]
    hull = ConvexHull(xy)  # 2-D hull vertices come counter-clockwise
    return convex_ccw("sensor.fov", xy[hull.vertices])

