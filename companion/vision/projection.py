"""One frame's tag detections -> ground measurements (UTM metres, propagated covariance).

The vehicle's pose is geodetic (the autopilot's latitude, longitude, altitude and its height
above the ground); the ground is the horizontal plane height_agl_m below the vehicle. Each pixel
is undistorted into a ray, turned into NED by the camera mount and the attitude, met with the
ground in the local NED frame whose origin is the ground point below the vehicle, and the
north/east offset is carried to UTM through pyproj (LocalNed -> geodetic -> Utm), so the grid's
meridian convergence and scale factor are applied exactly, to the points and the covariances.

Covariance, first order: central differences of the ground point over the pixel (u, v), the
height and three small attitude rotations about the NED axes (tilt about north and east with
sigma attitude_deg each, heading about down with sigma heading_deg), plus the vehicle's
horizontal position error horizontal_m^2 I.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import ConvexHull

from companion.errors import ConfigError, InputError
from companion.geo import LocalNed, Utm
from companion.rotation import rotation_from_quaternion
from companion.sat.fov import ConvexPolygon
from companion.vision.camera import (
    MIN_CAMERA_HEIGHT_M,
    BodyPose,
    CameraModel,
    ground_footprint,
    is_number,
    pixel_rays_camera,
)

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

__all__ = [
    "DEFAULT_POSE_UNCERTAINTY",
    "GeoPose",
    "GroundMeasurements",
    "PoseUncertainty",
    "footprint_utm",
    "project_detections",
    "vehicle_utm",
]

_PIXEL_STEP_PX = 1e-3  # central-difference steps of the Jacobian
_HEIGHT_STEP_M = 1e-3
_ANGLE_STEP_RAD = 1e-6
_UTM_STEP_M = 1.0  # NE -> UTM is linear to ~1e-7 over a metre


def _finite(name: str, value: object) -> float:
    """`value` as a finite float, or InputError naming `name`."""
    if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating):
        raise InputError(f"{name} must be a finite number, got {value!r}")
    if not math.isfinite(float(value)):
        raise InputError(f"{name} must be a finite number, got {value!r}")
    return float(value)


@dataclass(frozen=True, slots=True)
class GeoPose:
    """The vehicle at a frame's capture time t_s: WGS84 position, height above ground, attitude.

    alt_amsl_m only places the local tangent plane (used as ellipsoidal: a geoid offset of 50 m
    scales ground offsets by 8e-6, under 1 mm at 100 m); height_agl_m (>= 0) sets the ground.
    q_wxyz is the body(FRD)->NED Hamilton quaternion (unit within 1e-3, normalised here).
    """

    t_s: float
    lat_deg: float
    lon_deg: float
    alt_amsl_m: float
    height_agl_m: float
    q_wxyz: tuple[float, float, float, float]

    def __post_init__(self) -> None:
        for name in ("t_s", "lat_deg", "lon_deg", "alt_amsl_m", "height_agl_m"):
            object.__setattr__(self, name, _finite(f"pose.{name}", getattr(self, name)))
        if not -90.0 <= self.lat_deg <= 90.0 or not -180.0 <= self.lon_deg <= 180.0:
            raise InputError(f"pose.lat_deg, lon_deg must be in [-90, 90], [-180, 180], got "
                             f"{self.lat_deg}, {self.lon_deg}")
        if self.height_agl_m < 0.0:
            raise InputError(f"pose.height_agl_m must be >= 0, got {self.height_agl_m}")
        q = tuple(self.q_wxyz) if isinstance(self.q_wxyz, tuple | list | np.ndarray) else ()
        if len(q) != 4:  # a scalar or a string is refused too
            raise InputError(f"pose.q_wxyz must be 4 finite numbers, got {self.q_wxyz!r}")
        q = tuple(_finite("pose.q_wxyz", c) for c in q)
        norm = math.sqrt(sum(c * c for c in q))
        if abs(norm - 1.0) > 1e-3:
            raise InputError(f"pose.q_wxyz must be a unit quaternion, norm is {norm:.6f}")
        if abs(norm - 1.0) > 1e-15:  # a unit quaternion stays bit for bit (replay is exact)
            q = tuple(c / norm for c in q)
        object.__setattr__(self, "q_wxyz", q)

    def local_ned(self) -> LocalNed:
        """The local NED frame whose origin is the ground point below the vehicle."""
        return LocalNed(self.lat_deg, self.lon_deg, self.alt_amsl_m - self.height_agl_m)

    def body_pose(self) -> BodyPose:
        """The same pose in local_ned(): (0, 0, -height_agl_m), same attitude."""
        return BodyPose(self.t_s, 0.0, 0.0, -self.height_agl_m, self.q_wxyz)


@dataclass(frozen=True, slots=True)
class PoseUncertainty:
    """1-sigma pose errors: horizontal position (m, each axis), height (m), tilt, heading (deg)."""

    horizontal_m: float = 0.5
    vertical_m: float = 0.5
    attitude_deg: float = 1.0  # roll and pitch: tilt about the north and east axes
    heading_deg: float = 2.0

    def __post_init__(self) -> None:
        for name in ("horizontal_m", "vertical_m", "attitude_deg", "heading_deg"):
            value = getattr(self, name)
            if not is_number(value) or not math.isfinite(value) or value < 0.0:
                raise ConfigError(f"projection.pose_sigma.{name}",
                                  f"must be a finite number >= 0, got {value!r}")
            object.__setattr__(self, name, float(value))


DEFAULT_POSE_UNCERTAINTY = PoseUncertainty()


@dataclass(frozen=True, slots=True, eq=False)
class GroundMeasurements:
    """Per detection: UTM position (n,2) [easting, northing] m, covariance (n,2,2) m^2, valid (n,).

    Rows that are not valid (ray above the horizon, beyond max_range_m, or not undistortable)
    hold NaN.
    """

    xy_utm_m: FloatArray
    cov_utm_m2: FloatArray
    valid: BoolArray


def _pixels(pixels: object) -> FloatArray:
    """pixels as a finite (n, 2) float array, or InputError."""
    try:
        arr = np.asarray(pixels, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"pixels must be numbers: {exc}") from exc
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise InputError(f"pixels must have shape (n, 2), got {arr.shape}")
    if not np.isfinite(arr).all():
        raise InputError("pixels contains NaN or infinite values")
    return arr


def _axis_rotation(axis: int, angle_rad: float) -> FloatArray:
    """The rotation by angle_rad about NED axis `axis` (0 north, 1 east, 2 down)."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    i, j = (axis + 1) % 3, (axis + 2) % 3
    r = np.eye(3)
    r[i, i], r[i, j], r[j, i], r[j, j] = c, -s, s, c
    return r


def _hit_ne(camera: CameraModel, rays_cam: FloatArray, r_ned_body: FloatArray,
            height_m: float) -> tuple[FloatArray, FloatArray]:
    """((n,2) NE where rays meet the ground, about the point below the body origin; (n,)
    horizontal range from the camera); NaN where a ray does not point down."""
    centre = np.array([0.0, 0.0, -height_m]) + r_ned_body @ np.asarray(camera.mount_offset_m)
    centre[2] = min(centre[2], -MIN_CAMERA_HEIGHT_M)  # as camera_pose_ned
    rays = rays_cam @ (r_ned_body @ camera.rotation_body_camera()).T  # d_ned = R_ned_cam d_cam
    down = rays[:, 2] > 1e-9  # NaN compares False
    t = np.full(rays.shape[0], np.nan)
    t[down] = -centre[2] / rays[down, 2]  # C_d + t d_d = 0
    offset = t[:, None] * rays[:, :2]
    return centre[None, :2] + offset, np.hypot(offset[:, 0], offset[:, 1])


def _ne_to_utm(local: LocalNed, utm: Utm, ne_m: FloatArray) -> FloatArray:
    """(n,2) ground points north, east in `local` (down = 0) -> (n,2) easting, northing."""
    lat, lon, _ = local.ned_to_geodetic(ne_m[:, 0], ne_m[:, 1], np.zeros(len(ne_m)))
    easting, northing = utm.geodetic_to_utm(lat, lon)
    return np.column_stack([easting, northing])


def _check_range(max_range_m: float) -> float:
    """max_range_m as a finite float > 0, or InputError."""
    value = _finite("max_range_m", max_range_m)
    if value <= 0.0:
        raise InputError(f"max_range_m must be > 0, got {value}")
    return value


def _covariance_ne(camera: CameraModel, px: FloatArray, rays: FloatArray, r_body: FloatArray,
                   h: float, std_px: float, sigma: PoseUncertainty) -> FloatArray:
    """(n,2,2) NE covariance of the ground points: central-difference Jacobians times sigmas."""
    columns: list[tuple[FloatArray, float]] = []  # d(ground NE)/d(parameter) (n,2), its sigma
    for k in range(2):
        step = np.zeros(2)
        step[k] = _PIXEL_STEP_PX
        plus, _ = _hit_ne(camera, pixel_rays_camera(camera, px + step), r_body, h)
        minus, _ = _hit_ne(camera, pixel_rays_camera(camera, px - step), r_body, h)
        columns.append(((plus - minus) / (2.0 * _PIXEL_STEP_PX), std_px))
    low_m = max(h - _HEIGHT_STEP_M, 0.0)
    plus, _ = _hit_ne(camera, rays, r_body, h + _HEIGHT_STEP_M)
    minus, _ = _hit_ne(camera, rays, r_body, low_m)
    columns.append(((plus - minus) / (h + _HEIGHT_STEP_M - low_m), sigma.vertical_m))
    for axis, sigma_deg in enumerate((sigma.attitude_deg, sigma.attitude_deg, sigma.heading_deg)):
        plus, _ = _hit_ne(camera, rays, _axis_rotation(axis, _ANGLE_STEP_RAD) @ r_body, h)
        minus, _ = _hit_ne(camera, rays, _axis_rotation(axis, -_ANGLE_STEP_RAD) @ r_body, h)
        columns.append(((plus - minus) / (2.0 * _ANGLE_STEP_RAD), math.radians(sigma_deg)))
    cov = np.broadcast_to(sigma.horizontal_m ** 2 * np.eye(2), (px.shape[0], 2, 2)).copy()
    for jac, std in columns:
        cov += std ** 2 * jac[:, :, None] * jac[:, None, :]
    return cov


def _to_utm(local: LocalNed, utm: Utm, ne_m: FloatArray,
            cov_ne_m2: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Ground points (m,2) NE and their covariances -> UTM, through pyproj's local Jacobian."""
    m = ne_m.shape[0]
    north_step, east_step = np.array([_UTM_STEP_M, 0.0]), np.array([0.0, _UTM_STEP_M])
    mapped = _ne_to_utm(local, utm, np.vstack([ne_m, ne_m + north_step, ne_m + east_step]))
    xy = mapped[:m]
    j_utm_ne = np.stack([mapped[m:2 * m] - xy, mapped[2 * m:] - xy], axis=2) / _UTM_STEP_M
    cov = j_utm_ne @ cov_ne_m2 @ j_utm_ne.transpose(0, 2, 1)  # turns by the grid convergence
    return xy, 0.5 * (cov + cov.transpose(0, 2, 1))


def project_detections(camera: CameraModel, pose: GeoPose, pixels: FloatArray, utm: Utm,
                       pixel_std_px: float = 1.0,
                       pose_sigma: PoseUncertainty = DEFAULT_POSE_UNCERTAINTY,
                       max_range_m: float = 100.0) -> GroundMeasurements:
    """Detection centres (n,2) OpenCV pixels -> their ground points and covariances in UTM."""
    px = _pixels(pixels)
    std_px = _finite("pixel_std_px", pixel_std_px)
    if std_px < 0.0:
        raise InputError(f"pixel_std_px must be >= 0, got {std_px}")
    max_range = _check_range(max_range_m)
    r_body = rotation_from_quaternion(pose.q_wxyz)
    rays = pixel_rays_camera(camera, px)  # NaN where the distortion does not invert
    nominal, range_m = _hit_ne(camera, rays, r_body, pose.height_agl_m)
    cov_ne = _covariance_ne(camera, px, rays, r_body, pose.height_agl_m, std_px, pose_sigma)
    valid = (np.isfinite(nominal).all(axis=1) & (range_m <= max_range)
             & np.isfinite(cov_ne).all(axis=(1, 2)))
    xy = np.full((px.shape[0], 2), np.nan)
    cov = np.full((px.shape[0], 2, 2), np.nan)
    if valid.any():
        xy[valid], cov[valid] = _to_utm(pose.local_ned(), utm, nominal[valid], cov_ne[valid])
    return GroundMeasurements(xy, cov, valid)


def vehicle_utm(pose: GeoPose, utm: Utm) -> FloatArray:
    """(2,) easting, northing (m) of the vehicle."""
    easting, northing = utm.geodetic_to_utm(pose.lat_deg, pose.lon_deg)
    return np.array([float(easting), float(northing)])


def footprint_utm(camera: CameraModel, pose: GeoPose, utm: Utm,
                  max_range_m: float = 100.0) -> ConvexPolygon:
    """The convex hull, in UTM, of the ground the frame covers (clipped at max_range_m)."""
    samples = 8 if camera.has_distortion else 1
    ne = ground_footprint(camera, pose.body_pose(), _check_range(max_range_m), samples)
    xy = _ne_to_utm(pose.local_ned(), utm, ne)
    return ConvexPolygon(xy[ConvexHull(xy).vertices])
