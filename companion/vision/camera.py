"""The camera's geometry: pinhole + OpenCV distortion, mounted on the body, over a flat ground.

Frames:
- World: local NED in metres, origin on the ground; the ground is the plane down = 0.
- Body: FRD (forward, right, down); `BodyPose.q_wxyz` rotates body vectors into NED.
- Camera: OpenCV's (x right in the image, y down in the image, z along the optical axis).
  The mount rotation `mount_rpy_deg = (0, 0, 0)` (the default) is the downward camera:
  camera x = body right, camera y = body backward, camera z = body down, so the top of the image
  looks towards the vehicle's forward direction and, for a level vehicle heading north, the image
  is a map view with north up and east to the right. A non-zero mount (roll, pitch, yaw) turns
  the camera as if the body had that extra attitude: R_body_cam = Rz(yaw) Ry(pitch) Rx(roll) R_down,
  so a positive mount pitch tilts the view forward of nadir.
- Pixels: OpenCV's convention, pixel centres at integer coordinates; the image spans
  [-0.5, width - 0.5] x [-0.5, height - 0.5].

Pure numpy: the SITL renders with it and the service projects detections with it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from companion.errors import ConfigError, InputError
from companion.rotation import quaternion_from_euler, rotation_from_quaternion, rotation_zyx

__all__ = [
    "MIN_CAMERA_HEIGHT_M",
    "BodyPose",
    "CameraModel",
    "camera_pose_ned",
    "distort_normalized",
    "ground_footprint",
    "image_border_pixels",
    "is_number",
    "pixel_rays_camera",
    "pixels_to_ground",
    "pixels_to_normalized",
    "project_points",
    "undistort_normalized",
]

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

# A landed vehicle's camera is a few centimetres above the grass; never let it reach the plane.
MIN_CAMERA_HEIGHT_M = 0.05
_NEWTON_ITERATIONS = 30
# R_body_cam of the default (downward) mount: camera x = right, y = backward, z = down.
_R_DOWN: FloatArray = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


# ---------------------------------------------------------------------------------------------
# The vehicle's pose
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True, slots=True)
class BodyPose:
    """The vehicle's true pose at time t_s: NED position (m) and body(FRD)->NED quaternion."""

    t_s: float
    north_m: float
    east_m: float
    down_m: float  # negative above the ground
    q_wxyz: tuple[float, float, float, float]  # Hamilton, scalar first, rotates body into NED

    def __post_init__(self) -> None:
        for name in ("t_s", "north_m", "east_m", "down_m"):
            value = getattr(self, name)
            if not isinstance(value, int | float) or not math.isfinite(value):
                raise InputError(f"pose.{name} must be a finite number, got {value!r}")
        q = tuple(self.q_wxyz)
        if len(q) != 4 or not all(isinstance(c, int | float) and math.isfinite(c) for c in q):
            raise InputError(f"pose.q_wxyz must be 4 finite numbers, got {self.q_wxyz!r}")
        norm = math.sqrt(sum(c * c for c in q))
        if abs(norm - 1.0) > 1e-3:
            raise InputError(f"pose.q_wxyz must be a unit quaternion, norm is {norm:.6f}")
        object.__setattr__(self, "q_wxyz", tuple(float(c) / norm for c in q))

    @property
    def position_ned(self) -> FloatArray:
        """(3,) NED position in metres."""
        return np.array([self.north_m, self.east_m, self.down_m], dtype=np.float64)

    @staticmethod
    def from_euler(t_s: float, north_m: float, east_m: float, down_m: float,
                   roll_rad: float = 0.0, pitch_rad: float = 0.0,
                   yaw_rad: float = 0.0) -> BodyPose:
        """A pose from position and aerospace (yaw-pitch-roll, ZYX) Euler angles in radians."""
        return BodyPose(t_s, north_m, east_m, down_m,
                        quaternion_from_euler(roll_rad, pitch_rad, yaw_rad))


# ---------------------------------------------------------------------------------------------
# Camera model
# ---------------------------------------------------------------------------------------------

def is_number(value: object) -> bool:
    """True for an int or float that is not a bool."""
    return isinstance(value, int | float) and not isinstance(value, bool)


def _float_tuple(key: str, value: object, length: int) -> tuple[float, ...]:
    """`value` as a tuple of `length` finite floats, or ConfigError naming `key`."""
    if isinstance(value, str | bytes) or not isinstance(value, Sequence | np.ndarray):
        raise ConfigError(key, f"must be a list of {length} numbers, got {value!r}")
    items = list(value)
    if len(items) != length or not all(is_number(v) or isinstance(v, np.floating)
                                       for v in items):
        raise ConfigError(key, f"must be a list of {length} numbers, got {value!r}")
    out = tuple(float(v) for v in items)
    if not all(math.isfinite(v) for v in out):
        raise ConfigError(key, f"must be finite, got {value!r}")
    return out


@dataclass(frozen=True, slots=True)
class CameraModel:
    """A pinhole camera with OpenCV's distortion (k1, k2, p1, p2, k3) mounted on the body.

    Camera frame: OpenCV's (x right, y down in the image, z along the optical axis). The
    default mount_rpy_deg (0, 0, 0) looks straight down: camera x = body right, camera y = body
    backward, camera z = body down (image top towards the vehicle's forward direction); a
    non-zero mount turns it by R_body_cam = Rz(yaw) Ry(pitch) Rx(roll) R_down (positive pitch:
    looks forward of nadir). mount_offset_m is the camera centre in body FRD.
    Intrinsics left at NaN (the default) are derived: fx = fy for a 90 degree horizontal FOV
    over width_px, principal point at the image centre ((w - 1) / 2, (h - 1) / 2). Every bad
    value raises ConfigError naming `camera.<field>`.
    """

    width_px: int = 640
    height_px: int = 480
    fx_px: float = math.nan
    fy_px: float = math.nan
    cx_px: float = math.nan
    cy_px: float = math.nan
    dist: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    mount_rpy_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)
    mount_offset_m: tuple[float, float, float] = (0.0, 0.0, 0.0)  # camera centre, body FRD
    rate_hz: float = 10.0
    noise_std: float = 2.0  # exposure noise, gray levels

    def __post_init__(self) -> None:
        for name in ("width_px", "height_px"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool):
                raise ConfigError(f"camera.{name}", f"must be an integer, got {value!r}")
            if not 16 <= value <= 8192:
                raise ConfigError(f"camera.{name}", f"must be in [16, 8192], got {value}")
        for name in ("fx_px", "fy_px", "cx_px", "cy_px", "rate_hz", "noise_std"):
            value = getattr(self, name)
            if not is_number(value):
                raise ConfigError(f"camera.{name}", f"must be a number, got {value!r}")
        default_f = 0.5 * self.width_px  # 90 degree horizontal FOV: (w / 2) / tan(45 deg)
        derived = {"fx_px": default_f, "fy_px": default_f, "cx_px": 0.5 * (self.width_px - 1),
                   "cy_px": 0.5 * (self.height_px - 1)}
        for name, default in derived.items():
            value = float(getattr(self, name))
            object.__setattr__(self, name, default if math.isnan(value) else value)
        for name in ("fx_px", "fy_px"):
            value = getattr(self, name)
            if not math.isfinite(value) or value <= 0.0:
                raise ConfigError(f"camera.{name}", f"must be a finite number > 0, got {value}")
        for name, size in (("cx_px", self.width_px), ("cy_px", self.height_px)):
            value = getattr(self, name)
            if not math.isfinite(value) or not -0.5 <= value <= size - 0.5:
                raise ConfigError(f"camera.{name}",
                                  f"must lie inside the image [-0.5, {size - 0.5}], got {value}")
        object.__setattr__(self, "dist", _float_tuple("camera.dist", self.dist, 5))
        object.__setattr__(self, "mount_rpy_deg",
                           _float_tuple("camera.mount_rpy_deg", self.mount_rpy_deg, 3))
        object.__setattr__(self, "mount_offset_m",
                           _float_tuple("camera.mount_offset_m", self.mount_offset_m, 3))
        if max(abs(v) for v in self.mount_offset_m) > 10.0:
            raise ConfigError("camera.mount_offset_m",
                              f"must be within 10 m of the body origin, got {self.mount_offset_m}")
        if not math.isfinite(self.rate_hz) or not 0.0 < self.rate_hz <= 1000.0:
            raise ConfigError("camera.rate_hz", f"must be in (0, 1000], got {self.rate_hz}")
        if not math.isfinite(self.noise_std) or not 0.0 <= self.noise_std <= 64.0:
            raise ConfigError("camera.noise_std", f"must be in [0, 64], got {self.noise_std}")
        object.__setattr__(self, "rate_hz", float(self.rate_hz))
        object.__setattr__(self, "noise_std", float(self.noise_std))
        if self.has_distortion:
            _check_distortion_invertible(self)

    @classmethod
    def from_hfov(cls, hfov_deg: float = 90.0, width_px: int = 640, height_px: int = 480,
                  **kwargs: Any) -> CameraModel:
        """Square pixels giving `hfov_deg` across width_px, principal point at the centre."""
        if not is_number(hfov_deg) or not 1.0 <= hfov_deg <= 170.0:
            raise ConfigError("camera.hfov_deg", f"must be in [1, 170] degrees, got {hfov_deg!r}")
        if not isinstance(width_px, int) or isinstance(width_px, bool) or width_px < 16:
            raise ConfigError("camera.width_px", f"must be an integer >= 16, got {width_px!r}")
        f_px = 0.5 * width_px / math.tan(math.radians(0.5 * hfov_deg))
        return cls(width_px=width_px, height_px=height_px, fx_px=f_px, fy_px=f_px, **kwargs)

    @property
    def has_distortion(self) -> bool:
        """True when any distortion coefficient is non-zero."""
        return any(c != 0.0 for c in self.dist)

    def matrix(self) -> FloatArray:
        """The 3x3 intrinsic matrix K."""
        return np.array([[self.fx_px, 0.0, self.cx_px],
                         [0.0, self.fy_px, self.cy_px],
                         [0.0, 0.0, 1.0]])

    def rotation_body_camera(self) -> FloatArray:
        """R_body_cam: camera (OpenCV) vectors into body FRD, from the mount angles."""
        roll, pitch, yaw = (math.radians(a) for a in self.mount_rpy_deg)
        return rotation_zyx(roll, pitch, yaw) @ _R_DOWN


def _check_distortion_invertible(camera: CameraModel) -> None:
    """ConfigError('camera.dist') unless every image pixel undistorts to a unique ray."""
    xs = np.linspace(-0.5, camera.width_px - 0.5, 33)
    ys = np.linspace(-0.5, camera.height_px - 0.5, 25)
    gx, gy = np.meshgrid(xs, ys)
    pixels = np.column_stack([gx.ravel(), gy.ravel()])
    distorted = pixels_to_normalized(camera, pixels)
    ideal = undistort_normalized(camera.dist, distorted)
    ok = np.all(np.isfinite(ideal), axis=1)
    if ok.all():
        residual = np.max(np.abs(distort_normalized(camera.dist, ideal) - distorted))
        det = _distortion_jacobian_det(camera.dist, ideal)
        ok_all = residual < 1e-9 and bool(np.all(det > 0.0))
        spread = float(np.max(np.abs(ideal)))
        if ok_all and spread < 20.0:
            return
    raise ConfigError("camera.dist", f"distortion {camera.dist} folds over or does not invert "
                                     "inside the image: each pixel must see exactly one ray")


# ---------------------------------------------------------------------------------------------
# Distortion, projection
# ---------------------------------------------------------------------------------------------

def camera_pose_ned(camera: CameraModel, pose: BodyPose) -> tuple[FloatArray, FloatArray]:
    """(R_ned_cam (3,3), camera centre (3,) NED) of the camera on a vehicle at `pose`.

    The centre is kept at least MIN_CAMERA_HEIGHT_M above the ground (a landed vehicle).
    """
    r_ned_body = rotation_from_quaternion(pose.q_wxyz)
    centre = pose.position_ned + r_ned_body @ np.asarray(camera.mount_offset_m)
    centre[2] = min(centre[2], -MIN_CAMERA_HEIGHT_M)
    return r_ned_body @ camera.rotation_body_camera(), centre


def distort_normalized(dist: Sequence[float], xy: FloatArray) -> FloatArray:
    """(n,2) ideal normalised coordinates (x/z, y/z) -> distorted ones, OpenCV's model."""
    k1, k2, p1, p2, k3 = dist
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))  # 1 + k1 r^2 + k2 r^4 + k3 r^6
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)  # OpenCV calib3d model
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return np.column_stack([xd, yd])


def _distortion_jacobian(dist: Sequence[float],
                         xy: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Entries (a, b, c, d) of d(distorted)/d(ideal) = [[a, b], [c, d]] at each point."""
    k1, k2, p1, p2, k3 = dist
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    g = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d radial / d r^2
    a = radial + 2.0 * x * x * g + 2.0 * p1 * y + 6.0 * p2 * x
    b = 2.0 * x * y * g + 2.0 * p1 * x + 2.0 * p2 * y
    d = radial + 2.0 * y * y * g + 6.0 * p1 * y + 2.0 * p2 * x
    return a, b, b, d


def _distortion_jacobian_det(dist: Sequence[float], xy: FloatArray) -> FloatArray:
    a, b, c, d = _distortion_jacobian(dist, xy)
    return a * d - b * c


def undistort_normalized(dist: Sequence[float], xy_distorted: FloatArray) -> FloatArray:
    """(n,2) distorted normalised coordinates -> ideal ones, by Newton's method.

    Points where the iteration does not converge (outside the region where the model is
    invertible) come back as NaN.
    """
    target = np.asarray(xy_distorted, dtype=np.float64)
    xy = target.copy()
    with np.errstate(all="ignore"):
        for _ in range(_NEWTON_ITERATIONS):
            residual = distort_normalized(dist, xy) - target
            if not np.any(np.abs(residual) > 1e-14):  # converged (quadratically, ~5 steps)
                break
            a, b, c, d = _distortion_jacobian(dist, xy)
            det = a * d - b * c
            step_x = (d * residual[:, 0] - b * residual[:, 1]) / det
            step_y = (a * residual[:, 1] - c * residual[:, 0]) / det
            xy = xy - np.column_stack([step_x, step_y])
        final = np.max(np.abs(distort_normalized(dist, xy) - target), axis=1)
    bad = ~(final < 1e-10) | ~np.all(np.isfinite(xy), axis=1)
    xy[bad] = np.nan
    return xy


def pixels_to_normalized(camera: CameraModel, pixels: FloatArray) -> FloatArray:
    """(n,2) pixels -> distorted normalised coordinates ((u - cx) / fx, (v - cy) / fy)."""
    return np.column_stack([(pixels[:, 0] - camera.cx_px) / camera.fx_px,
                            (pixels[:, 1] - camera.cy_px) / camera.fy_px])


def _as_points(points: object, columns: int, name: str) -> FloatArray:
    try:
        arr = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name} must be numbers: {exc}") from exc
    if arr.ndim == 1 and arr.shape[0] == columns:
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[1] != columns:
        raise InputError(f"{name} must have shape (n, {columns}), got {arr.shape}")
    if not np.isfinite(arr).all():
        raise InputError(f"{name} contains NaN or infinite values")
    return arr


def project_points(camera: CameraModel, pose: BodyPose,
                   points_ned: FloatArray) -> tuple[FloatArray, BoolArray]:
    """NED points (n,3) -> (pixels (n,2), in_front (n,)): pinhole + distortion, OpenCV pixels.

    Pixels of points not in front of the camera (z <= 0) are NaN. With distortion the result is
    meaningful inside the image and a little beyond it (the polynomial folds far outside).
    """
    pts = _as_points(points_ned, 3, "points_ned")
    r_ned_cam, centre = camera_pose_ned(camera, pose)
    cam = (pts - centre) @ r_ned_cam  # rows: R_cam_ned (X - C)
    in_front = cam[:, 2] > 1e-9
    pixels = np.full((pts.shape[0], 2), np.nan)
    if in_front.any():
        front = cam[in_front]
        xy = front[:, :2] / front[:, 2:3]  # pinhole: x/z, y/z
        if camera.has_distortion:
            xy = distort_normalized(camera.dist, xy)
        pixels[in_front, 0] = camera.fx_px * xy[:, 0] + camera.cx_px  # u = fx x + cx
        pixels[in_front, 1] = camera.fy_px * xy[:, 1] + camera.cy_px
    return pixels, in_front


def pixel_rays_camera(camera: CameraModel, pixels: FloatArray) -> FloatArray:
    """(n,2) pixels -> (n,3) ray directions (x/z, y/z, 1) in the camera frame, undistorted."""
    px = _as_points(pixels, 2, "pixels")
    xy = pixels_to_normalized(camera, px)
    if camera.has_distortion:
        xy = undistort_normalized(camera.dist, xy)
    return np.column_stack([xy, np.ones(len(xy))])


def pixels_to_ground(camera: CameraModel, pose: BodyPose, pixels: FloatArray) -> FloatArray:
    """(n,2) pixels -> (n,2) north, east (m) where their rays meet the ground plane; NaN if never.

    The ground is the plane down = 0 of the pose's frame (flat ground at the home altitude).
    """
    rays = pixel_rays_camera(camera, pixels)
    r_ned_cam, centre = camera_pose_ned(camera, pose)
    rays = rays @ r_ned_cam.T  # d_ned = R_ned_cam d_cam
    out = np.full((rays.shape[0], 2), np.nan)
    down = rays[:, 2] > 1e-9
    t = -centre[2] / rays[down, 2]  # C_d + t d_d = 0
    out[down] = centre[None, :2] + t[:, None] * rays[down, :2]
    return out


def image_border_pixels(camera: CameraModel, samples_per_edge: int) -> FloatArray:
    """(4 * samples_per_edge, 2) points on the image's outer edge, clockwise from top-left."""
    left, top = -0.5, -0.5
    right, bottom = camera.width_px - 0.5, camera.height_px - 0.5
    s = np.arange(samples_per_edge) / samples_per_edge
    edges = [np.column_stack([left + s * (right - left), np.full_like(s, top)]),
             np.column_stack([np.full_like(s, right), top + s * (bottom - top)]),
             np.column_stack([right - s * (right - left), np.full_like(s, bottom)]),
             np.column_stack([np.full_like(s, left), bottom - s * (bottom - top)])]
    return np.vstack(edges)


def ground_footprint(camera: CameraModel, pose: BodyPose, max_range_m: float = 100.0,
                     samples_per_edge: int = 1) -> FloatArray:
    """(4 * samples_per_edge, 2) NE polygon where the image border's rays meet the ground.

    Vertices run clockwise around the image from its top-left corner (the first vertices are
    the corners when samples_per_edge = 1). A ray that misses the ground, or meets it farther
    than max_range_m horizontally from the camera, is clipped at max_range_m along its
    horizontal direction. Without distortion and with every ray on the ground the polygon is a
    convex quadrilateral (more samples add collinear points); a distorted border is curved, so
    sample it (e.g. 8 per edge) and take the convex hull if a convex region is needed.
    """
    if not is_number(max_range_m) or not math.isfinite(max_range_m) or max_range_m <= 0.0:
        raise InputError(f"max_range_m must be a finite number > 0, got {max_range_m!r}")
    if not isinstance(samples_per_edge, int) or samples_per_edge < 1:
        raise InputError(f"samples_per_edge must be an int >= 1, got {samples_per_edge!r}")
    rays_cam = pixel_rays_camera(camera, image_border_pixels(camera, samples_per_edge))
    r_ned_cam, centre = camera_pose_ned(camera, pose)
    rays = rays_cam @ r_ned_cam.T  # d_ned = R_ned_cam d_cam
    height_m = -centre[2]
    horizontal = np.hypot(rays[:, 0], rays[:, 1])
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(rays[:, 2] > 0.0, height_m / rays[:, 2], np.inf)  # C_d + t d_d = 0
        range_m = t * horizontal
        unit = np.where(horizontal[:, None] > 1e-12, rays[:, :2] / horizontal[:, None], 0.0)
    hit = np.isfinite(range_m) & (range_m <= max_range_m)
    out = centre[None, :2] + max_range_m * unit
    out[hit] = centre[None, :2] + t[hit, None] * rays[hit, :2]
    return out
