"""The SITL's rendered downward camera: a textured ground with tag36h11 tags, seen from a pose.

The geometry (camera model, poses, projection) is `companion.vision.camera`, the same the
service projects detections with. `Renderer` uses OpenCV and keeps only precomputed, read-only
state (textures, distortion maps), so one renderer may serve one thread at a time.
"""

from __future__ import annotations

import math
from collections.abc import Collection, Iterable
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from companion.errors import ConfigError, InputError
from companion.vision.camera import (
    BodyPose,
    CameraModel,
    camera_pose_ned,
    is_number,
    pixels_to_normalized,
    undistort_normalized,
)

__all__ = ["TAG36H11_COUNT", "Renderer", "Tag", "tag_bitmap"]

FloatArray = NDArray[np.float64]
ImageU8 = NDArray[np.uint8]

TAG36H11_COUNT = 587  # ids 0..586 in the tag36h11 family
TAG_BLACK_CELLS = 8  # the black square: 6 x 6 data cells inside a one-cell black border
TAG_TOTAL_CELLS = 10  # plus the one-cell white quiet zone on each side


# Photometry in gray levels: printed tags under daylight exposure are neither 0 nor 255, and a
# clear sky above the horizon is bright but not saturated.
BLACK_LEVEL = 30.0
WHITE_LEVEL = 220.0
SKY_LEVEL = 200.0
GROUND_MEAN_LEVEL = 118.0

# Supersampling of tags: samples per tag region, so big (close) tags stay cheap; 8 x 8 samples a
# pixel gives coverage in 1/64 steps, far below the detector's corner noise.
_SUPERSAMPLE_MAX = 8
_SUPERSAMPLE_BUDGET = 400_000

# Ground texture layers: (texel relative to ground_m_per_px, tile size in texels, gray std).
# Each layer holds wavelengths of 4..64 texels, so successive layers (x16) cover one continuous
# 1/f band from 4 texels of the finest to ~330 m; their different tiles, rotations and offsets
# keep the sum from looking periodic.
_LAYERS: tuple[tuple[float, int, float], ...] = ((1.0, 1024, 14.0), (16.0, 512, 20.0),
                                                 (256.0, 256, 14.0))
_BAND_TEXELS = (4.0, 64.0)
_MIP_MIN_SIZE = 16

# Rays whose down component (of K^-1 (x, y, 1)) is below this see the sky: about 0.06 degrees
# above the horizon for the optical axis, where the ground is ~1 km away at 1 m height.
_HORIZON_DOWN = 1e-3


# ---------------------------------------------------------------------------------------------
# Tags
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True, slots=True)
class Tag:
    """A tag36h11 tag lying on the ground: centre (m, NED), black-square edge size_m, yaw_rad.

    The tag is drawn with its own one-cell white quiet zone (its printed edge is 1.25 size_m).
    yaw_rad turns it about down (positive: north towards east); at yaw 0 the tag's top edge
    faces north, so a level camera heading north sees it upright and not mirrored.
    """

    tag_id: int
    north_m: float
    east_m: float
    size_m: float
    yaw_rad: float = 0.0

    def __post_init__(self) -> None:
        if (not isinstance(self.tag_id, int) or isinstance(self.tag_id, bool)
                or not 0 <= self.tag_id < TAG36H11_COUNT):
            raise InputError(f"tag.tag_id must be an int in [0, {TAG36H11_COUNT - 1}], "
                             f"got {self.tag_id!r}")
        for name in ("north_m", "east_m", "size_m", "yaw_rad"):
            value = getattr(self, name)
            if not isinstance(value, int | float) or not math.isfinite(value):
                raise InputError(f"tag.{name} must be a finite number, got {value!r}")
        if self.size_m <= 0.0:
            raise InputError(f"tag.size_m must be > 0, got {self.size_m!r}")

    def corners_ned(self, cells: float = TAG_BLACK_CELLS) -> FloatArray:
        """(4, 3) NED corners of the centred square `cells` cells wide, in tag image order.

        Order: top-left, top-right, bottom-right, bottom-left of the upright tag image; with
        cells = 8 (the default) the black square, with 10 the printed edge.
        """
        half = 0.5 * cells * self.size_m / TAG_BLACK_CELLS
        up = np.array([math.cos(self.yaw_rad), math.sin(self.yaw_rad)])  # NE of the tag's top
        right = np.array([-math.sin(self.yaw_rad), math.cos(self.yaw_rad)])
        centre = np.array([self.north_m, self.east_m])
        signs = np.array([[-1.0, 1.0], [1.0, 1.0], [1.0, -1.0], [-1.0, -1.0]])  # (right, up)
        ne = centre + half * (signs[:, :1] * right + signs[:, 1:] * up)
        return np.column_stack([ne, np.zeros(4)])


# ---------------------------------------------------------------------------------------------
# Tag images and ground texture
# ---------------------------------------------------------------------------------------------

def tag_bitmap(tag_id: int) -> NDArray[np.float32]:
    """(10,10) gray levels of tag36h11 `tag_id`: one cell a pixel, with its white quiet zone.

    Drawn from OpenCV's copy of the family's code table (cv2.aruco DICT_APRILTAG_36h11, whose
    ids and bit order are those of the AprilTag library).
    """
    if not isinstance(tag_id, int) or not 0 <= tag_id < TAG36H11_COUNT:
        raise InputError(f"tag_id must be an int in [0, {TAG36H11_COUNT - 1}], got {tag_id!r}")
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
    marker = cv2.aruco.generateImageMarker(dictionary, tag_id, TAG_BLACK_CELLS, borderBits=1)
    cells = np.ones((TAG_TOTAL_CELLS, TAG_TOTAL_CELLS), dtype=np.float32)
    cells[1:-1, 1:-1] = np.asarray(marker, dtype=np.float32) / 255.0
    out: NDArray[np.float32] = (BLACK_LEVEL + cells * (WHITE_LEVEL - BLACK_LEVEL)).astype(
        np.float32)
    return out


def _band_spectrum(rng: np.random.Generator, size: int) -> NDArray[np.complex128]:
    """Spectrum of a periodic size x size noise tile with a 1/f band of 4..64 texel waves."""
    spectrum = np.fft.fft2(rng.standard_normal((size, size)))
    freq = np.fft.fftfreq(size)
    f = np.hypot(freq[:, None], freq[None, :])  # cycles per texel
    f[0, 0] = 1.0
    log_f = np.log2(f)
    lo, hi = np.log2(1.0 / _BAND_TEXELS[1]), np.log2(1.0 / _BAND_TEXELS[0])
    outside = np.maximum(lo - log_f, 0.0) + np.maximum(log_f - hi, 0.0)  # octaves out of band
    amplitude = np.exp(-0.5 * (outside / 0.5) ** 2) / f  # 1/f in band, soft half-octave edges
    amplitude[0, 0] = 0.0
    out: NDArray[np.complex128] = spectrum * amplitude
    return out


def _mip_levels(spectrum: NDArray[np.complex128], std_gray: float) -> list[ImageU8]:
    """Periodic uint8 tiles (centred on 128) of the spectrum at sizes N, N/2, ... >= 16.

    Level m keeps the frequencies below its own Nyquist limit, so it is the tile low-passed and
    sampled every 2^m texels: a texture that does not alias when minified.
    """
    size = spectrum.shape[0]
    levels: list[ImageU8] = []
    scale = 0.0
    m_size = size
    while m_size >= _MIP_MIN_SIZE:
        half = m_size // 2
        idx = np.concatenate([np.arange(half), np.arange(size - half, size)])
        crop = spectrum[np.ix_(idx, idx)].copy()
        crop[half, :] = 0.0  # the Nyquist row and column: keep the tile real
        crop[:, half] = 0.0
        tile = np.real(np.fft.ifft2(crop)) * (m_size * m_size) / (size * size)
        if scale == 0.0:
            scale = std_gray / float(np.std(tile))
        levels.append(np.clip(np.rint(128.0 + scale * tile), 0, 255).astype(np.uint8))
        m_size //= 2
    return levels


@dataclass(frozen=True)
class _Layer:
    texel_m: float
    mips: list[ImageU8]
    ground_to_texel: FloatArray  # (3,3): (north, east, 1) -> level-0 texel (u, v, 1)


# ---------------------------------------------------------------------------------------------
# Renderer
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class _Canvas:
    """The ideal (undistorted) image the scene is drawn on before the lens distortion."""

    width_px: int
    height_px: int
    k: FloatArray  # intrinsics on the canvas (principal point shifted by the canvas origin)
    map1: Any = None  # cv2.remap maps output pixel -> canvas pixel (None: no distortion)
    map2: Any = None


def _canvas_for(camera: CameraModel) -> _Canvas:
    """The canvas covering every output pixel's ideal position, and its remap tables."""
    k = camera.matrix()
    if not camera.has_distortion:
        return _Canvas(camera.width_px, camera.height_px, k)
    gx, gy = np.meshgrid(np.arange(camera.width_px, dtype=np.float64),
                         np.arange(camera.height_px, dtype=np.float64))
    pixels = np.column_stack([gx.ravel(), gy.ravel()])
    ideal = undistort_normalized(camera.dist, pixels_to_normalized(camera, pixels))
    if not np.isfinite(ideal).all():
        raise ConfigError("camera.dist", "distortion does not invert over the whole image")
    ideal_px = np.column_stack([camera.fx_px * ideal[:, 0] + camera.cx_px,
                                camera.fy_px * ideal[:, 1] + camera.cy_px])
    x0 = math.floor(float(ideal_px[:, 0].min())) - 2
    y0 = math.floor(float(ideal_px[:, 1].min())) - 2
    width = math.ceil(float(ideal_px[:, 0].max())) - x0 + 3
    height = math.ceil(float(ideal_px[:, 1].max())) - y0 + 3
    if width > 4 * camera.width_px or height > 4 * camera.height_px:
        raise ConfigError("camera.dist", "distortion too strong to render (the undistorted "
                                         "image is over 4 times the output)")
    k_canvas = k.copy()
    k_canvas[0, 2] -= x0
    k_canvas[1, 2] -= y0
    map_x = (ideal_px[:, 0] - x0).reshape(camera.height_px, camera.width_px).astype(np.float32)
    map_y = (ideal_px[:, 1] - y0).reshape(camera.height_px, camera.width_px).astype(np.float32)
    map1, map2 = cv2.convertMaps(map_x, map_y, cv2.CV_16SC2)
    return _Canvas(width, height, k_canvas, map1, map2)


def _clip_half_plane(polygon: FloatArray, normal: FloatArray, offset: float) -> FloatArray:
    """The part of a convex polygon (k,2) where normal . p + offset <= 0 (Sutherland-Hodgman)."""
    out: list[FloatArray] = []
    values = polygon @ normal + offset
    for i in range(len(polygon)):
        j = (i + 1) % len(polygon)
        if values[i] <= 0.0:
            out.append(polygon[i])
        if (values[i] <= 0.0) != (values[j] <= 0.0):
            s = values[i] / (values[i] - values[j])
            out.append(polygon[i] + s * (polygon[j] - polygon[i]))
    return np.array(out).reshape(-1, 2)


class Renderer:
    """Renders what `camera` sees of a textured ground with tag36h11 tags lying on it.

    texture_seed fixes the ground texture; ground_m_per_px is its finest texel (the default
    2 cm resolves what the default camera sees at 8 m). Per frame randomness (exposure noise)
    comes from the generator passed to render(). Not thread-safe for concurrent renders.
    """

    def __init__(self, camera: CameraModel, texture_seed: int,
                 ground_m_per_px: float = 0.02) -> None:
        if not isinstance(camera, CameraModel):
            raise ConfigError("camera", f"must be a CameraModel, got {type(camera).__name__}")
        if not isinstance(texture_seed, int) or isinstance(texture_seed, bool):
            raise ConfigError("texture_seed", f"must be an integer, got {texture_seed!r}")
        if (not is_number(ground_m_per_px) or not math.isfinite(ground_m_per_px)
                or not 0.001 <= ground_m_per_px <= 1.0):
            raise ConfigError("ground_m_per_px", f"must be in [0.001, 1] m, got "
                                                 f"{ground_m_per_px!r}")
        self.camera = camera
        self.texture_seed = texture_seed
        self.ground_m_per_px = float(ground_m_per_px)
        self._canvas = _canvas_for(camera)
        self._layers = self._make_layers()
        self._tag_cache: dict[int, NDArray[np.float32]] = {}

    def _make_layers(self) -> list[_Layer]:
        rng = np.random.default_rng(self.texture_seed)
        layers = []
        for texel_rel, size, std_gray in _LAYERS:
            texel_m = texel_rel * self.ground_m_per_px
            mips = _mip_levels(_band_spectrum(rng, size), std_gray)
            angle = rng.uniform(0.0, 2.0 * math.pi)
            offset = rng.uniform(0.0, size, 2)
            c, s = math.cos(angle) / texel_m, math.sin(angle) / texel_m
            ground_to_texel = np.array([[-s, c, offset[0]], [-c, -s, offset[1]], [0, 0, 1.0]])
            layers.append(_Layer(texel_m, mips, ground_to_texel))
        return layers

    def _tag_cells(self, tag_id: int) -> NDArray[np.float32]:
        cells = self._tag_cache.get(tag_id)
        if cells is None:
            bitmap = tag_bitmap(tag_id)
            cells = np.ascontiguousarray(np.dstack([bitmap, np.ones_like(bitmap)]))
            self._tag_cache[tag_id] = cells
        return cells

    def render(self, pose: BodyPose, tags: Iterable[Tag], rng: np.random.Generator, *,
               distractors: Iterable[Tag] = (), hidden: Collection[int] = frozenset(),
               bgr: bool = False) -> ImageU8:
        """The (H, W) uint8 frame (H, W, 3 when bgr) the camera sees from `pose`.

        Tags whose id is in `hidden` are not drawn (a missed detection); distractors are drawn
        like tags (false detections placed by the SITL). Tags are drawn in the order given.
        """
        if not isinstance(pose, BodyPose):
            raise InputError(f"pose must be a BodyPose, got {type(pose).__name__}")
        if not isinstance(rng, np.random.Generator):
            raise InputError(f"rng must be a numpy Generator, got {type(rng).__name__}")
        r_ned_cam, centre = camera_pose_ned(self.camera, pose)
        r_cam_ned = r_ned_cam.T
        # Ground plane (north, east, 1) -> canvas pixel: K [r1 r2 -R C] (plane homography).
        h_ground = self._canvas.k @ np.column_stack(
            [r_cam_ned[:, 0], r_cam_ned[:, 1], -r_cam_ned @ centre])
        canvas = self._draw_ground(h_ground, r_ned_cam, centre)
        hidden_ids = frozenset(hidden)
        for tag in tags:
            if not isinstance(tag, Tag):
                raise InputError(f"tags must be Tag, got {type(tag).__name__}")
            if tag.tag_id not in hidden_ids:
                self._draw_tag(canvas, tag, h_ground, r_cam_ned, centre)
        for tag in distractors:
            if not isinstance(tag, Tag):
                raise InputError(f"distractors must be Tag, got {type(tag).__name__}")
            self._draw_tag(canvas, tag, h_ground, r_cam_ned, centre)
        if self._canvas.map1 is not None:
            canvas = np.asarray(cv2.remap(canvas, self._canvas.map1, self._canvas.map2,
                                          cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE),
                                dtype=np.float32)
        image = self._expose(canvas, rng)
        if bgr:
            return np.asarray(cv2.cvtColor(image, cv2.COLOR_GRAY2BGR), dtype=np.uint8)
        return image

    def _draw_ground(self, h_ground: FloatArray, r_ned_cam: FloatArray,
                     centre: FloatArray) -> NDArray[np.float32]:
        """Float32 canvas of the textured ground, mip-mapped by ground sample distance, with
        a uniform sky above the horizon."""
        cw, ch = self._canvas.width_px, self._canvas.height_px
        canvas_to_ground = np.asarray(np.linalg.inv(h_ground), dtype=np.float64)
        height_m = -centre[2]
        focal_px = min(self.camera.fx_px, self.camera.fy_px)
        # A canvas pixel's ray d = K^-1 (x, y, 1) has a down component linear in (x, y); its
        # ground sample distance (largest axis) is h / (f d_down^2), the texture's mip scale.
        down_coeffs = r_ned_cam[2, :] @ np.linalg.inv(self._canvas.k)
        rect = np.array([[-0.5, -0.5], [cw - 0.5, -0.5], [cw - 0.5, ch - 0.5], [-0.5, ch - 0.5]])
        corner_down = rect @ down_coeffs[:2] + down_coeffs[2]
        down_max = float(corner_down.max())
        down_min = max(float(corner_down.min()), _HORIZON_DOWN)
        log_gsd_lo = math.log2(height_m / (focal_px * down_max**2))
        log_gsd_hi = math.log2(height_m / (focal_px * down_min**2))
        log_gsd_map: NDArray[np.float32] | None = None
        if log_gsd_hi - log_gsd_lo > 0.05:
            xs = np.arange(cw, dtype=np.float32) * np.float32(down_coeffs[0])
            ys = np.arange(ch, dtype=np.float32) * np.float32(down_coeffs[1])
            down = np.maximum(ys[:, None] + xs[None, :] + np.float32(down_coeffs[2]),
                              np.float32(_HORIZON_DOWN))
            log_gsd_map = (np.float32(math.log2(height_m / focal_px))
                           - np.float32(2.0) * np.log2(down))
        centre_px: FloatArray = np.array([0.5 * (cw - 1), 0.5 * (ch - 1), 1.0])
        acc = np.full((ch, cw), GROUND_MEAN_LEVEL - 128.0 * len(self._layers), dtype=np.float32)
        for layer in self._layers:
            # Level lambda = log2(gsd / (2 texel)): the finest level whose band the pixel grid
            # resolves; blend the two nearest levels (trilinear mip-mapping).
            offset = math.log2(2.0 * layer.texel_m)
            top = len(layer.mips) - 1
            lo = min(max(math.floor(log_gsd_lo - offset), 0), top)
            hi = min(max(math.ceil(log_gsd_hi - offset), 0), top)
            if hi == lo:
                acc = np.asarray(cv2.add(acc, self._warp_level(layer, lo, canvas_to_ground,
                                                               centre_px), dtype=cv2.CV_32F))
                continue
            if log_gsd_map is None:  # uniform scale: constant weights
                frac = float(np.clip(log_gsd_lo - offset - lo, 0.0, 1.0))
                blend = cv2.addWeighted(
                    self._warp_level(layer, lo, canvas_to_ground, centre_px), 1.0 - frac,
                    self._warp_level(layer, lo + 1, canvas_to_ground, centre_px), frac, 0.0,
                    dtype=cv2.CV_32F)
                acc = np.asarray(cv2.add(acc, blend, dtype=cv2.CV_32F))
                continue
            lam = np.clip(log_gsd_map - np.float32(offset), lo, hi)
            for level in range(lo, hi + 1):
                weight = np.maximum(1.0 - np.abs(lam - np.float32(level)), 0.0)
                acc += weight * self._warp_level(layer, level, canvas_to_ground, centre_px)
        if corner_down.min() <= _HORIZON_DOWN:  # sky: rays at or above the horizon
            sky = _clip_half_plane(rect, down_coeffs[:2], down_coeffs[2] - _HORIZON_DOWN)
            if len(sky) >= 3:
                cv2.fillConvexPoly(acc, np.rint(sky * 16).astype(np.int32), SKY_LEVEL,
                                   lineType=cv2.LINE_AA, shift=4)
        return acc

    def _warp_level(self, layer: _Layer, level: int, canvas_to_ground: FloatArray,
                    centre_px: FloatArray) -> ImageU8:
        """One mip level of a texture layer seen through canvas -> ground (uint8, mean 128)."""
        tile = layer.mips[level]
        size = tile.shape[0]
        to_texel = np.diag([0.5**level, 0.5**level, 1.0]) @ layer.ground_to_texel
        m = to_texel @ canvas_to_ground  # canvas pixel -> texel of this level
        p = m @ centre_px
        if p[2] != 0.0:  # bring the view into the first tile (the texture is periodic)
            shift = np.floor(p[:2] / p[2] / size) * size
            m = np.array([[1.0, 0.0, -shift[0]], [0.0, 1.0, -shift[1]], [0.0, 0.0, 1.0]]) @ m
        warped = cv2.warpPerspective(tile, m, (self._canvas.width_px, self._canvas.height_px),
                                     flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                     borderMode=cv2.BORDER_WRAP)
        return np.asarray(warped, dtype=np.uint8)

    def _draw_tag(self, canvas: NDArray[np.float32], tag: Tag, h_ground: FloatArray,
                  r_cam_ned: FloatArray, centre: FloatArray) -> None:
        """Composite one tag (with its quiet zone) onto the canvas, antialiased."""
        corners = tag.corners_ned(TAG_TOTAL_CELLS)
        depth = (corners - centre) @ r_cam_ned[2, :]
        if np.any(depth <= 1e-3):
            return  # straddles or lies behind the camera plane: never in a real FOV
        projected = np.c_[corners[:, :2], np.ones(4)] @ h_ground.T
        projected = projected[:, :2] / projected[:, 2:3]
        ch, cw = canvas.shape
        x0 = max(math.floor(float(projected[:, 0].min())) - 1, 0)
        y0 = max(math.floor(float(projected[:, 1].min())) - 1, 0)
        x1 = min(math.ceil(float(projected[:, 0].max())) + 2, cw)
        y1 = min(math.ceil(float(projected[:, 1].max())) + 2, ch)
        if x1 <= x0 or y1 <= y0:
            return
        w, h = x1 - x0, y1 - y0
        ss = int(min(_SUPERSAMPLE_MAX, max(1, math.isqrt(_SUPERSAMPLE_BUDGET // (w * h)))))
        # Tag cell pixel (col, row) -> ground (north, east): cell centres at (i + 0.5 - 5) cells.
        cell_m = tag.size_m / TAG_BLACK_CELLS
        up = np.array([math.cos(tag.yaw_rad), math.sin(tag.yaw_rad)])
        right = np.array([-math.sin(tag.yaw_rad), math.cos(tag.yaw_rad)])
        origin = (np.array([tag.north_m, tag.east_m])
                  + (0.5 - 0.5 * TAG_TOTAL_CELLS) * cell_m * (right - up))
        cells_to_ground = np.array([[cell_m * right[0], -cell_m * up[0], origin[0]],
                                    [cell_m * right[1], -cell_m * up[1], origin[1]],
                                    [0.0, 0.0, 1.0]])
        # Canvas pixel x -> supersampled pixel X = ss (x - x0 + 0.5) - 0.5.
        to_super = np.array([[ss, 0.0, ss * (0.5 - x0) - 0.5],
                             [0.0, ss, ss * (0.5 - y0) - 0.5],
                             [0.0, 0.0, 1.0]])
        homography = to_super @ h_ground @ cells_to_ground
        warped = cv2.warpPerspective(self._tag_cells(tag.tag_id), homography, (w * ss, h * ss),
                                     flags=cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT,
                                     borderValue=(0.0, 0.0, 0.0, 0.0))
        if ss > 1:
            warped = cv2.resize(warped, (w, h), interpolation=cv2.INTER_AREA)  # box filter
        premultiplied, alpha = warped[:, :, 0], warped[:, :, 1]
        roi = canvas[y0:y1, x0:x1]
        roi *= 1.0 - alpha  # "over" compositing with the tag's coverage as alpha
        roi += premultiplied

    def _expose(self, canvas: NDArray[np.float32], rng: np.random.Generator) -> ImageU8:
        """Add exposure noise (std camera.noise_std gray levels) and quantise to uint8."""
        std = self.camera.noise_std
        if std > 0.0:
            # Sum of four uniform bytes: near-Gaussian (Irwin-Hall), ~10x faster than normal().
            u = rng.integers(0, 256, size=(4, *canvas.shape), dtype=np.uint8)
            total = np.add(np.add(u[0], u[1], dtype=np.int16), np.add(u[2], u[3], dtype=np.int16))
            gain = std / math.sqrt(4.0 * (256.0**2 - 1.0) / 12.0)
            out = cv2.addWeighted(canvas, 1.0, total.astype(np.float32), gain, -510.0 * gain,
                                  dtype=cv2.CV_8U)  # saturates and rounds
        else:
            out = cv2.add(canvas, np.zeros_like(canvas), dtype=cv2.CV_8U)
        return np.asarray(out, dtype=np.uint8)

