"""OpenCV calibration files (cv2.FileStorage YAML and XML) into CameraModel, and their errors."""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray

from companion.errors import ConfigError
from companion.vision.calibration import load_calibration
from companion.vision.camera import distort_normalized

FloatArray = NDArray[np.float64]

K = np.array([[612.5, 0.0, 318.2], [0.0, 610.1, 243.7], [0.0, 0.0, 1.0]])
DIST = np.array([[-0.11, 0.04, 0.0012, -0.0008, -0.01]])


Node = int | float | str | FloatArray | None  # None: leave the node out


def _k(**entries: float) -> FloatArray:
    """K with some entries replaced, e.g. k01=0.5."""
    k = K.copy()
    for name, value in entries.items():
        k[int(name[1]), int(name[2])] = value
    return k


def _write(path: Path, **nodes: Node) -> Path:
    """A calibration file written by cv2.FileStorage (format from the suffix)."""
    storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for name, value in nodes.items():
        if value is not None:
            storage.write(name, value)
    storage.release()
    return path


def _good(path: Path, **overrides: Node) -> Path:
    nodes: dict[str, Node] = {"calibration_time": "today", "image_width": 640,
                                "image_height": 480, "camera_matrix": K,
                                "distortion_coefficients": DIST, "avg_reprojection_error": 0.21}
    nodes.update(overrides)
    return _write(path, **nodes)


@pytest.mark.parametrize("name", ["calib.yaml", "calib.xml", "calib.json"])
def test_a_file_written_by_filestorage_gives_the_same_projection_as_opencv(
        tmp_path: Path, name: str) -> None:
    camera = load_calibration(_good(tmp_path / name, distortion_coefficients=DIST.T),
                              mount_rpy_deg=(0.0, 10.0, 0.0), mount_offset_m=(0.1, 0.0, 0.0),
                              rate_hz=15.0)
    assert (camera.width_px, camera.height_px) == (640, 480)
    np.testing.assert_array_equal(camera.matrix(), K)
    assert camera.dist == tuple(DIST.ravel())
    assert camera.mount_rpy_deg == (0.0, 10.0, 0.0) and camera.mount_offset_m == (0.1, 0.0, 0.0)
    assert camera.rate_hz == 15.0
    rng = np.random.default_rng(5)
    points_cam = np.column_stack([rng.uniform(-0.5, 0.5, (50, 2)), np.ones(50)])
    expected, _ = cv2.projectPoints(points_cam, np.zeros(3), np.zeros(3), K, DIST)
    xy = distort_normalized(camera.dist, points_cam[:, :2])
    ours = xy * [camera.fx_px, camera.fy_px] + [camera.cx_px, camera.cy_px]
    np.testing.assert_allclose(ours, expected.reshape(-1, 2), atol=1e-9)


def test_opencv_4_yaml_header_and_longer_distortion_vectors_with_zero_extras(
        tmp_path: Path) -> None:
    text = """%YAML:1.0
---
image_width: 800
image_height: 600
camera_matrix: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [ 700., 0., 399.5, 0., 701., 299.5, 0., 0., 1. ]
distortion_coefficients: !!opencv-matrix
   rows: 1
   cols: 4
   dt: d
   data: [ -0.05, 0.01, 0., 0. ]
"""
    path = tmp_path / "old.yml"
    path.write_text(text)
    camera = load_calibration(path)
    assert (camera.width_px, camera.fx_px, camera.fy_px, camera.cy_px) == (800, 700.0, 701.0,
                                                                          299.5)
    assert camera.dist == (-0.05, 0.01, 0.0, 0.0, 0.0)
    for size in (8, 12, 14):
        dist = np.zeros((size, 1))
        dist[:5, 0] = DIST.ravel()
        assert load_calibration(_good(tmp_path / f"d{size}.yaml",
                                      distortion_coefficients=dist)).dist == tuple(DIST.ravel())


def _refused(path: Path, *fragments: str) -> None:
    with pytest.raises(ConfigError) as info:
        load_calibration(path)
    assert info.value.key == "camera.calibration"
    for fragment in (str(path), *fragments):
        assert fragment in info.value.problem, (fragment, info.value.problem)


def test_missing_and_unparsable_files(tmp_path: Path) -> None:
    _refused(tmp_path / "absent.yaml", "no such file")
    broken = tmp_path / "broken.yaml"
    broken.write_text("%YAML:1.0\nimage_width: [1, 2\n  : :\n")
    _refused(broken, "cannot be parsed", "Missing , between the elements")
    xml = tmp_path / "broken.xml"
    xml.write_text('<?xml version="1.0"?><opencv_storage><image_width>6')
    _refused(xml, "cannot be parsed")
    sequence = tmp_path / "list.yaml"
    sequence.write_text("%YAML:1.0\n---\n- 1\n- 2\n")
    _refused(sequence, "not an OpenCV FileStorage map")


@pytest.mark.parametrize("node", ["image_width", "image_height", "camera_matrix",
                                  "distortion_coefficients"])
def test_each_missing_node_is_named(tmp_path: Path, node: str) -> None:
    _refused(_good(tmp_path / "c.yaml", **{node: None}), f"node {node} is missing")


@pytest.mark.parametrize(("overrides", "fragments"), [
    ({"image_width": "wide"}, ("node image_width must be an integer",)),
    ({"image_height": 480.5}, ("node image_height must be an integer",)),
    ({"camera_matrix": 612.5}, ("node camera_matrix must be an opencv-matrix",)),
    ({"camera_matrix": K[:, :2]}, ("node camera_matrix must be 3x3", "(3, 2)")),
    ({"camera_matrix": _k(k00=-612.5)}, ("fx = -612.5", "must be > 0")),
    ({"camera_matrix": _k(k11=0.0)}, ("fy = 0.0", "must be > 0")),
    ({"camera_matrix": _k(k01=0.5)}, ("no skew",)),
    ({"camera_matrix": _k(k22=2.0)}, ("no skew",)),
    ({"camera_matrix": _k(k02=900.0)}, ("camera.cx_px",)),
    ({"image_width": 8}, ("camera.width_px",)),
    ({"distortion_coefficients": np.zeros((2, 3))}, ("must be 1xN or Nx1", "(2, 3)")),
    ({"distortion_coefficients": np.zeros((1, 6))}, ("must be 1xN or Nx1", "(1, 6)")),
    ({"distortion_coefficients": np.array([[0.0, 0.0, 0.0, 0.0, 0.0, 0.3, 0.0, 0.0]])},
     ("non-zero k4 = 0.3", "only k1, k2, p1, p2, k3")),
    ({"distortion_coefficients": np.array([[0.0] * 12 + [0.0, 0.01]])}, ("tau_y = 0.01",)),
    ({"distortion_coefficients": np.array([[0.0, 0.0, 0.0, np.nan, 0.0]])}, ("NaN",)),
    ({"distortion_coefficients": np.array([[-1.0, 0.0, 0.0, 0.0, 0.0]])}, ("camera.dist", "folds")),
    ({"fisheye_model": 1}, ("node fisheye_model is set",)),
])
def test_bad_nodes_are_refused_with_the_node_and_file(
        tmp_path: Path, overrides: dict[str, Node], fragments: tuple[str, ...]) -> None:
    _refused(_good(tmp_path / "c.xml", **overrides), *fragments)


def test_mount_errors_keep_their_own_key(tmp_path: Path) -> None:
    path = _good(tmp_path / "c.yaml", fisheye_model=0)
    with pytest.raises(ConfigError, match=re.escape("camera.mount_offset_m")):
        load_calibration(path, mount_offset_m=(20.0, 0.0, 0.0))
