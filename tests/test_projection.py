"""Detections to UTM ground measurements: geometry against camera.py and pyproj, covariances."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.typing import NDArray
from pyproj import Geod, Transformer
from scipy.spatial.transform import Rotation

from companion.errors import ConfigError, InputError
from companion.geo import Utm
from companion.rotation import quaternion_from_euler
from companion.vision.camera import (
    BodyPose,
    CameraModel,
    pixels_to_ground,
    project_points,
)
from companion.vision.projection import (
    GeoPose,
    PoseUncertainty,
    footprint_utm,
    project_detections,
    vehicle_utm,
)

FloatArray = NDArray[np.float64]

LAT, LON, ALT = 47.40, 8.55, 520.0
UTM = Utm.at(LAT, LON)
LEVEL = (1.0, 0.0, 0.0, 0.0)
DISTORTED = CameraModel(dist=(-0.12, 0.03, 0.001, -0.0015, 0.0), mount_offset_m=(0.1, 0.0, 0.05))


def _pose(height_m: float, roll_deg: float = 0.0, pitch_deg: float = 0.0, yaw_deg: float = 0.0,
          lat: float = LAT, lon: float = LON) -> GeoPose:
    q = quaternion_from_euler(*(math.radians(a) for a in (roll_deg, pitch_deg, yaw_deg)))
    return GeoPose(12.5, lat, lon, ALT + height_m, height_m, q)


def _ground_utm(pose: GeoPose, ne_m: FloatArray, utm: Utm = UTM) -> FloatArray:
    """Reference: local NE ground points -> UTM through LocalNed and pyproj."""
    lat, lon, _ = pose.local_ned().ned_to_geodetic(ne_m[:, 0], ne_m[:, 1], np.zeros(len(ne_m)))
    easting, northing = utm.geodetic_to_utm(lat, lon)
    return np.column_stack([easting, northing])


def test_principal_point_from_a_level_hover_lands_below_the_vehicle() -> None:
    camera = CameraModel()
    pose = _pose(8.0)
    out = project_detections(camera, pose, np.array([[camera.cx_px, camera.cy_px]]), UTM)
    to_utm = Transformer.from_crs("EPSG:4326", f"EPSG:{UTM.epsg}", always_xy=True)
    expected = np.array(to_utm.transform(LON, LAT))
    assert out.valid.tolist() == [True]
    assert np.linalg.norm(out.xy_utm_m[0] - expected) < 1e-3
    assert np.linalg.norm(vehicle_utm(pose, UTM) - expected) < 1e-6


@pytest.mark.parametrize("camera", [CameraModel(), DISTORTED])
@pytest.mark.parametrize("attitude", [(0.0, 0.0, 0.0), (6.0, -9.0, 35.0), (-12.0, 15.0, -150.0)])
def test_round_trip_through_project_points(camera: CameraModel,
                                           attitude: tuple[float, float, float]) -> None:
    pose = _pose(11.0, *attitude)
    rng = np.random.default_rng(4)
    ne = rng.uniform(-15.0, 15.0, (400, 2))
    ned = np.column_stack([ne, np.zeros(400)])
    pixels, in_front = project_points(camera, pose.body_pose(), ned)
    size = np.array([camera.width_px - 1, camera.height_px - 1])
    inside = in_front & np.all((pixels > 0.0) & (pixels < size), axis=1)
    assert inside.sum() >= 20
    out = project_detections(camera, pose, pixels[inside], UTM)
    assert out.valid.all()
    err = np.linalg.norm(out.xy_utm_m - _ground_utm(pose, ne[inside]), axis=1)
    assert err.max() < 1e-3


def test_north_offset_far_from_the_central_meridian_follows_grid_convergence() -> None:
    lat, lon = 60.0, 17.9  # zone 33 (central meridian 15 E): convergence about 2.5 degrees
    utm = Utm.at(lat, lon)
    pose = _pose(80.0, lat=lat, lon=lon)
    camera = CameraModel()
    pixel, _ = project_points(camera, pose.body_pose(), np.array([[50.0, 0.0, 0.0]]))
    out = project_detections(camera, pose, pixel, utm)
    lon2, lat2, _ = Geod(ellps="WGS84").fwd(lon, lat, 0.0, 50.0)  # 50 m along the meridian
    expected = np.array(utm.geodetic_to_utm(lat2, lon2))
    assert np.linalg.norm(out.xy_utm_m[0] - expected) < 0.01
    naive = vehicle_utm(pose, utm) + np.array([0.0, 50.0])
    assert np.linalg.norm(naive - expected) > 1.0  # the test can tell the two apart
    # A heading error moves the point along true east: the covariance's axis turns with the grid.
    heading_only = PoseUncertainty(horizontal_m=0.0, vertical_m=0.0, attitude_deg=0.0,
                                   heading_deg=2.0)
    cov = project_detections(camera, pose, pixel, utm, pixel_std_px=0.0,
                             pose_sigma=heading_only).cov_utm_m2[0]
    lon3, lat3, _ = Geod(ellps="WGS84").fwd(lon2, lat2, 90.0, 1.0)
    true_east = np.array(utm.geodetic_to_utm(lat3, lon3)) - expected
    true_east /= np.linalg.norm(true_east)
    eigval, eigvec = np.linalg.eigh(cov)
    sin_angle = abs(eigvec[0, 1] * true_east[1] - eigvec[1, 1] * true_east[0])
    assert sin_angle < math.radians(0.05) and abs(true_east[1]) > math.sin(math.radians(2.0))
    assert math.sqrt(eigval[1]) == pytest.approx(50.0 * math.radians(2.0), rel=2e-3)


def test_nadir_covariance_has_its_closed_form() -> None:
    camera = CameraModel()
    sigma = PoseUncertainty(horizontal_m=0.3, vertical_m=0.7, attitude_deg=1.5, heading_deg=3.0)
    h = 9.0
    out = project_detections(camera, _pose(h), np.array([[camera.cx_px, camera.cy_px]]), UTM,
                             pixel_std_px=2.0, pose_sigma=sigma)
    # Height and heading do not move the nadir point; pixel and tilt move it by h tan(angle).
    var = 0.3**2 + (h * 2.0 / camera.fx_px) ** 2 + (h * math.radians(1.5)) ** 2
    np.testing.assert_allclose(out.cov_utm_m2[0], var * np.eye(2), rtol=2e-3, atol=1e-6 * var)


def test_covariance_grows_with_height_and_attitude_sigma_and_is_positive_definite() -> None:
    pixels = np.array([[319.5, 239.5], [40.0, 420.0], [600.0, 30.0], [200.0, 100.0]])
    low = project_detections(DISTORTED, _pose(8.0, 4.0, -3.0, 20.0), pixels, UTM)
    high = project_detections(DISTORTED, _pose(20.0, 4.0, -3.0, 20.0), pixels, UTM)
    shaky = project_detections(DISTORTED, _pose(8.0, 4.0, -3.0, 20.0), pixels, UTM,
                               pose_sigma=PoseUncertainty(attitude_deg=3.0))
    for out in (low, high, shaky):
        assert out.valid.all()
        np.testing.assert_array_equal(out.cov_utm_m2, out.cov_utm_m2.transpose(0, 2, 1))
        assert np.all(np.linalg.eigvalsh(out.cov_utm_m2) > 0.0)
    trace = {name: np.trace(out.cov_utm_m2, axis1=1, axis2=2)
             for name, out in (("low", low), ("high", high), ("shaky", shaky))}
    position = 2.0 * 0.5**2  # the horizontal position error does not grow
    assert np.all(trace["high"] - position > 2.0 * (trace["low"] - position))
    assert np.all(trace["shaky"] > 1.5 * trace["low"])
    assert trace["low"][1] > 1.5 * trace["low"][0]  # a corner pixel is less certain than nadir


def test_covariance_matches_monte_carlo() -> None:
    camera, pose = DISTORTED, _pose(15.0, 5.0, -8.0, 40.0)
    pixels = np.array([[319.5, 239.5], [100.0, 400.0], [600.0, 50.0]])
    std_px = 1.5
    sigma = PoseUncertainty(horizontal_m=0.5, vertical_m=0.5, attitude_deg=1.0, heading_deg=2.0)
    predicted = project_detections(camera, pose, pixels, UTM, pixel_std_px=std_px,
                                   pose_sigma=sigma)
    rng = np.random.default_rng(11)
    samples = 4000
    r_nominal = Rotation.from_quat(np.roll(pose.q_wxyz, -1))  # scipy wants x, y, z, w
    tilt = np.radians([sigma.attitude_deg, sigma.attitude_deg, sigma.heading_deg])
    hits = np.empty((samples, len(pixels), 2))
    for i in range(samples):
        q_xyzw = (Rotation.from_rotvec(rng.normal(0.0, tilt)) * r_nominal).as_quat()
        north, east = rng.normal(0.0, sigma.horizontal_m, 2)
        down = -(pose.height_agl_m + rng.normal(0.0, sigma.vertical_m))
        body = BodyPose(0.0, north, east, down, tuple(np.roll(q_xyzw, 1)))
        hits[i] = pixels_to_ground(camera, body, pixels + rng.normal(0.0, std_px, pixels.shape))
    assert np.isfinite(hits).all()
    for k in range(len(pixels)):
        xy = _ground_utm(pose, hits[:, k])
        mc = np.cov(xy.T)
        cov = predicted.cov_utm_m2[k]
        assert np.linalg.norm(mc - cov) < 0.1 * np.linalg.norm(cov)
        assert np.linalg.norm(xy.mean(axis=0) - predicted.xy_utm_m[k]) < 0.1 * math.sqrt(
            np.trace(cov))


def test_rays_above_the_horizon_or_too_far_are_invalid() -> None:
    camera = CameraModel(mount_rpy_deg=(0.0, 60.0, 0.0))  # optical axis 60 deg from nadir
    pose = _pose(8.0)
    far_v = camera.cy_px - camera.fy_px * math.tan(math.radians(25.0))  # 85 deg from nadir
    pixels = np.array([[319.5, -0.5], [319.5, 239.5], [319.5, far_v]])
    out = project_detections(camera, pose, pixels, UTM)
    assert out.valid.tolist() == [False, True, True]
    assert np.isnan(out.xy_utm_m[0]).all() and np.isnan(out.cov_utm_m2[0]).all()
    assert np.isfinite(out.cov_utm_m2[1:]).all()
    near = project_detections(camera, pose, pixels, UTM, max_range_m=50.0)
    assert near.valid.tolist() == [False, True, False]
    empty = project_detections(camera, pose, np.zeros((0, 2)), UTM)
    assert empty.xy_utm_m.shape == (0, 2) and empty.cov_utm_m2.shape == (0, 2, 2)
    assert empty.valid.shape == (0,)


def test_footprint_is_the_image_on_the_ground_in_utm() -> None:
    camera = CameraModel()  # 90 deg across 640 px: at 8 m, 16 m east-west by 12 m north-south
    pose = _pose(8.0)
    poly = footprint_utm(camera, pose, UTM)
    corners = _ground_utm(pose, np.array([[6.0, -8.0], [6.0, 8.0], [-6.0, 8.0], [-6.0, -8.0]]))
    assert poly.vertices_xy.shape == (4, 2)
    for corner in corners:
        assert np.min(np.linalg.norm(poly.vertices_xy - corner, axis=1)) < 1e-6
    assert poly.area_m2 == pytest.approx(192.0, rel=2e-3)  # times the UTM scale factor squared
    tilted = _pose(12.0, 8.0, -5.0, 70.0)
    rng = np.random.default_rng(3)
    pixels = rng.uniform([0.0, 0.0], [639.0, 479.0], (200, 2))
    for cam in (camera, DISTORTED):  # barrel distortion: the hull of the sampled border
        poly = footprint_utm(cam, tilted, UTM)
        assert poly.contains(project_detections(cam, tilted, pixels, UTM).xy_utm_m).all()
        assert poly.contains(vehicle_utm(tilted, UTM)[None, :]).tolist() == [True]


def test_bad_input_is_refused_with_its_name() -> None:
    camera, pose = CameraModel(), _pose(8.0)
    with pytest.raises(InputError, match="pixels contains NaN"):
        project_detections(camera, pose, np.array([[1.0, np.nan]]), UTM)
    for shape in ((3,), (2, 3), (1, 2, 2)):
        with pytest.raises(InputError, match=r"pixels must have shape \(n, 2\)"):
            project_detections(camera, pose, np.zeros(shape), UTM)
    with pytest.raises(InputError, match="q_wxyz must be a unit quaternion"):
        GeoPose(0.0, LAT, LON, ALT, 8.0, (1.0, 0.1, 0.0, 0.0))
    with pytest.raises(InputError, match="q_wxyz must be 4"):
        GeoPose(0.0, LAT, LON, ALT, 8.0, (1.0, 0.0, 0.0))  # type: ignore[arg-type]
    with pytest.raises(InputError, match="height_agl_m must be >= 0"):
        GeoPose(0.0, LAT, LON, ALT, -0.5, LEVEL)
    with pytest.raises(InputError, match="lat_deg must be a finite number"):
        GeoPose(0.0, math.nan, LON, ALT, 8.0, LEVEL)
    with pytest.raises(InputError, match="lat_deg, lon_deg must be in"):
        GeoPose(0.0, LAT, 190.0, ALT, 8.0, LEVEL)
    with pytest.raises(InputError, match="pixel_std_px must be >= 0"):
        project_detections(camera, pose, np.zeros((1, 2)), UTM, pixel_std_px=-1.0)
    with pytest.raises(InputError, match="max_range_m must be > 0"):
        footprint_utm(camera, pose, UTM, max_range_m=0.0)
    with pytest.raises(ConfigError, match=r"pose_sigma\.heading_deg"):
        PoseUncertainty(heading_deg=-1.0)
