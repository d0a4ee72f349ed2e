"""Camera intrinsics from an OpenCV calibration file, as cv2.FileStorage writes it (YAML or XML).

Nodes read: image_width, image_height, camera_matrix (3x3 opencv-matrix, no skew) and
distortion_coefficients (1xN or Nx1, N in 4, 5, 8, 12, 14: OpenCV's k1 k2 p1 p2 [k3 [k4 k5 k6
[s1 s2 s3 s4 [tau_x tau_y]]]]). CameraModel has k1, k2, p1, p2, k3 only, so any non-zero term
after k3 is refused, and so is a file from the fisheye model (a non-zero `fisheye_model` node,
as OpenCV's calibration tutorial writes). Every problem is a ConfigError('camera.calibration')
naming the file and the node.
"""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from companion.errors import ConfigError
from companion.vision.camera import CameraModel

__all__ = ["load_calibration"]

FloatArray = NDArray[np.float64]

_KEY = "camera.calibration"
_DIST_SIZES = (4, 5, 8, 12, 14)
_DIST_EXTRA = ("k4", "k5", "k6", "s1", "s2", "s3", "s4", "tau_x", "tau_y")
# CameraModel fields whose values come from the file: their errors are the file's.
_FROM_FILE = {f"camera.{name}" for name in ("width_px", "height_px", "fx_px", "fy_px", "cx_px",
                                             "cy_px", "dist")}


def _node(storage: cv2.FileStorage, file: Path, name: str) -> cv2.FileNode:
    """The node `name` of the file's top-level map, or ConfigError if it is absent."""
    node = storage.getNode(name)
    if node.empty():
        raise ConfigError(_KEY, f"{file}: node {name} is missing")
    return node


def _int(storage: cv2.FileStorage, file: Path, name: str) -> int:
    """An integer node."""
    node = _node(storage, file, name)
    value = node.real() if node.isInt() or node.isReal() else None
    if value is None or not value.is_integer():  # NaN and infinities too
        raise ConfigError(_KEY, f"{file}: node {name} must be an integer")
    return int(value)


def _matrix(storage: cv2.FileStorage, file: Path, name: str) -> FloatArray:
    """A matrix node (!!opencv-matrix / type_id="opencv-matrix") as a finite float array."""
    node = _node(storage, file, name)
    try:
        mat = node.mat() if node.isMap() else None
    except (cv2.error, SystemError):  # a map that is not a complete opencv-matrix
        mat = None
    if mat is None:
        raise ConfigError(_KEY, f"{file}: node {name} must be an opencv-matrix")
    out = np.asarray(mat, dtype=np.float64)
    if not np.isfinite(out).all():
        raise ConfigError(_KEY, f"{file}: node {name} contains NaN or infinite values")
    return out


def _intrinsics(k: FloatArray, file: Path) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) of a 3x3 camera matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]."""
    if k.shape != (3, 3):
        raise ConfigError(_KEY, f"{file}: node camera_matrix must be 3x3, got shape {k.shape}")
    fx, fy, cx, cy = float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2])
    if fx <= 0.0 or fy <= 0.0:
        raise ConfigError(_KEY, f"{file}: node camera_matrix has focal lengths fx = {fx}, "
                                f"fy = {fy}; both must be > 0")
    if k[0, 1] != 0.0 or k[1, 0] != 0.0 or not np.array_equal(k[2], [0.0, 0.0, 1.0]):
        raise ConfigError(_KEY, f"{file}: node camera_matrix must be [[fx, 0, cx], [0, fy, cy], "
                                f"[0, 0, 1]] (no skew), got {k.tolist()}")
    return fx, fy, cx, cy


def _distortion(d: FloatArray, file: Path) -> tuple[float, float, float, float, float]:
    """(k1, k2, p1, p2, k3) of an OpenCV distortion vector whose further terms are zero."""
    if d.ndim != 2 or min(d.shape) != 1 or d.size not in _DIST_SIZES:
        raise ConfigError(_KEY, f"{file}: node distortion_coefficients must be 1xN or Nx1 with "
                                f"N in {_DIST_SIZES}, got shape {d.shape}")
    coeffs = [float(c) for c in d.ravel()] + [0.0] * (5 - min(d.size, 5))
    extra = [f"{name} = {c}" for name, c in zip(_DIST_EXTRA, coeffs[5:], strict=False) if c]
    if extra:
        raise ConfigError(_KEY, f"{file}: node distortion_coefficients has non-zero "
                                f"{', '.join(extra)}; only k1, k2, p1, p2, k3 are supported")
    k1, k2, p1, p2, k3 = coeffs[:5]
    return k1, k2, p1, p2, k3


def load_calibration(path: str | os.PathLike[str],
                     mount_rpy_deg: tuple[float, float, float] = (0.0, 0.0, 0.0),
                     mount_offset_m: tuple[float, float, float] = (0.0, 0.0, 0.0),
                     rate_hz: float = 10.0, noise_std: float = 2.0) -> CameraModel:
    """The CameraModel of an OpenCV calibration file, with the given mount and frame rate."""
    file = Path(path)
    if not file.is_file():
        raise ConfigError(_KEY, f"{file}: no such file")
    try:
        storage = cv2.FileStorage(str(file), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as exc:  # the binding wraps cv2.error in SystemError
        reason = str(exc.__cause__ or exc).strip().splitlines()[-1]
        raise ConfigError(_KEY, f"{file}: cannot be parsed: {reason}") from exc
    try:
        if not storage.isOpened() or not storage.root().isMap():
            raise ConfigError(_KEY, f"{file}: is not an OpenCV FileStorage map of named nodes")
        fisheye = storage.getNode("fisheye_model")
        if not fisheye.empty() and fisheye.real() != 0.0:
            raise ConfigError(_KEY, f"{file}: node fisheye_model is set; only the pinhole "
                                    "model (k1, k2, p1, p2, k3) is supported")
        width, height = _int(storage, file, "image_width"), _int(storage, file, "image_height")
        fx, fy, cx, cy = _intrinsics(_matrix(storage, file, "camera_matrix"), file)
        dist = _distortion(_matrix(storage, file, "distortion_coefficients"), file)
    finally:
        storage.release()
    try:
        return CameraModel(width_px=width, height_px=height, fx_px=fx, fy_px=fy, cx_px=cx,
                           cy_px=cy, dist=dist, mount_rpy_deg=mount_rpy_deg,
                           mount_offset_m=mount_offset_m, rate_hz=rate_hz, noise_std=noise_std)
    except ConfigError as exc:
        if exc.key in _FROM_FILE:
            raise ConfigError(_KEY, f"{file}: {exc}") from exc
        raise
