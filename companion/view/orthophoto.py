"""The operator's orthophoto: a GeoTIFF or MBTiles file made one north-up image on the run's grid.

`load_orthophoto(path, frame, fence)` reads the file once, crops it to the search area and the
geofence plus MARGIN_M, reprojects it into the run's UTM zone (inverse mapping of the output
pixels' centres, bilinear) and gives an `Orthophoto`: a PNG of at most MAX_SIDE_PX on a side
with its bounds in the grid's metres (x east, y north of the search area's south-west corner).
Nothing is fetched: the file is the operator's. Every problem (missing file, not a GeoTIFF or
MBTiles, no georeference, a CRS without an EPSG code, a rotated raster, no tile over the area,
no overlap with the area) is a ConfigError naming the key (or flag), the file and what is wrong.

GeoTIFF: tifffile reads ModelPixelScale with one ModelTiepoint, or a ModelTransformation without
rotation or shear, and the EPSG code of the GeoKeyDirectory (projected, or geographic degrees);
GDAL_NODATA pixels are transparent. A file tifffile can memory-map is read in the window needed
only; a compressed one that decodes to more than MAX_DECODED_BYTES is refused. MBTiles: the
coarsest zoom at least as fine as the served image shows (else the finest; others when it has
no tile over the area), its PNG or JPEG tiles (TMS rows) decoded with OpenCV into a
web-mercator mosaic.
"""

from __future__ import annotations

import math
import sqlite3
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import tifffile
from numpy.typing import NDArray
from pyproj import CRS, Transformer
from pyproj.exceptions import CRSError, ProjError

from companion.errors import ConfigError
from companion.pipeline import SearchFrame

__all__ = ["MARGIN_M", "MAX_SIDE_PX", "Orthophoto", "load_orthophoto"]

FloatArray = NDArray[np.float64]
MARGIN_M = 30.0  # around the search area and the fence: the map's edge shows ground, not grey
MAX_SIDE_PX = 4096  # the served image: at most 4096 x 4096 RGBA (64 MB while it is made)
MAX_DECODED_BYTES = 480_000_000  # a compressed GeoTIFF is decoded whole: at most this much
MAX_MOSAIC_SIDE_PX = 2 * MAX_SIDE_PX  # the MBTiles mosaic of one zoom, before its warp
LATTICE_PX = 32  # the projection is evaluated every 32 output pixels, interpolated between
CHUNK_ROWS = 256  # output rows sampled at once (bounds the temporary arrays)
EARTH_R_M = 6378137.0  # the web-mercator sphere
MERCATOR_HALF_M = math.pi * EARTH_R_M
GEOTIFF_EXT = (".tif", ".tiff")
MBTILES_EXT = (".mbtiles",)

# TIFF tags and GeoKeys (GeoTIFF 1.0 / OGC 19-008)
TAG_PIXEL_SCALE, TAG_TIEPOINT, TAG_TRANSFORMATION, TAG_GEOKEYS = 33550, 33922, 34264, 34735
TAG_GDAL_NODATA = 42113
KEY_MODEL_TYPE, KEY_RASTER_TYPE, KEY_GEOGRAPHIC, KEY_PROJECTED = 1024, 1025, 2048, 3072
MODEL_PROJECTED, MODEL_GEOGRAPHIC, PIXEL_IS_POINT, USER_DEFINED = 1, 2, 2, 32767


@dataclass(frozen=True)
class Orthophoto:
    """A north-up PNG on the run's grid and where it lies: [west, south, east, north] metres."""

    png: bytes
    bounds_m: tuple[float, float, float, float]
    size_px: tuple[int, int]  # width, height
    resolution_m: float  # ground size of one pixel
    name: str  # the file's name, for the page

    def scene(self, url: str = "api/orthophoto.png") -> dict[str, Any]:
        """What the page's scene says of it: where to fetch it and where to lay it."""
        w, s, e, n = self.bounds_m
        return {"url": url, "bounds": [[round(w, 3), round(s, 3)], [round(e, 3), round(n, 3)]],
                "size_px": list(self.size_px), "resolution_m": round(self.resolution_m, 4),
                "name": self.name}


@dataclass(frozen=True)
class _Grid:
    """Pixel centres (col, row) of a north-up raster in its CRS: X = x0 + dx col, Y = y0 + dy
    row."""

    x0: float
    dx: float
    y0: float
    dy: float

    def pixel(self, x: FloatArray, y: FloatArray) -> tuple[FloatArray, FloatArray]:
        """(col, row) of CRS coordinates."""
        return (x - self.x0) / self.dx, (y - self.y0) / self.dy

    def model(self, col: FloatArray, row: FloatArray) -> tuple[FloatArray, FloatArray]:
        """CRS coordinates of (col, row)."""
        return self.x0 + self.dx * col, self.y0 + self.dy * row


@dataclass(frozen=True)
class _Target:
    """The output box on the run's grid: [x0, x1] x [y0, y1] metres, and its UTM zone."""

    frame: SearchFrame
    x0: float
    y0: float
    x1: float
    y1: float

    @property
    def longest_m(self) -> float:
        """The box's longer side."""
        return max(self.x1 - self.x0, self.y1 - self.y0)

    def utm(self, x: FloatArray, y: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Easting, northing of grid points."""
        return x + self.frame.origin_utm_m[0], y + self.frame.origin_utm_m[1]


class _FileError(Exception):
    """What is wrong with the file (made a ConfigError naming key and file by the caller)."""


def load_orthophoto(path: Path, frame: SearchFrame, geofence_latlon: FloatArray | None = None,
                    *, key: str = "view.orthophoto", margin_m: float = MARGIN_M,
                    max_side_px: int = MAX_SIDE_PX) -> Orthophoto:
    """The orthophoto of path over the search area and fence of frame; ConfigError names key,
    the file and what is wrong."""
    try:
        target = _target(frame, geofence_latlon, margin_m)
        if not path.exists():
            raise _FileError("no such file")
        if not path.is_file():
            raise _FileError("is not a file")
        suffix = path.suffix.lower()
        if suffix in GEOTIFF_EXT:
            rgba, bounds, res = _geotiff(path, target, max_side_px)
        elif suffix in MBTILES_EXT:
            rgba, bounds, res = _mbtiles(path, target, max_side_px)
        else:
            raise _FileError("is neither a GeoTIFF (.tif, .tiff) nor an MBTiles file (.mbtiles)")
    except _FileError as exc:
        raise ConfigError(key, f"{path}: {exc}") from None
    except MemoryError:
        raise ConfigError(key, f"{path}: too large to read in this memory; crop it to the "
                               "search area first") from None
    except (ValueError, IndexError, TypeError, OverflowError, sqlite3.Error, cv2.error,
            ProjError) as exc:  # a file this reader did not foresee: still one clear line
        raise ConfigError(key, f"{path}: cannot be read ({type(exc).__name__}: {exc})") from None
    ok, png = cv2.imencode(".png", cv2.cvtColor(rgba, cv2.COLOR_RGBA2BGRA))
    if not ok:
        raise ConfigError(key, f"{path}: the image could not be encoded as PNG")
    return Orthophoto(png.tobytes(), bounds, (rgba.shape[1], rgba.shape[0]), res, path.name)


def _target(frame: SearchFrame, fence_latlon: FloatArray | None, margin_m: float) -> _Target:
    """The box around the search area and the fence, margin_m wider on every side."""
    points = [np.asarray(frame.area_xy_m, dtype=np.float64).reshape(-1, 2),
              np.array([[0.0, 0.0], [frame.world.width_m, frame.world.height_m]])]
    if fence_latlon is not None and len(fence_latlon):
        fence = np.asarray(fence_latlon, dtype=np.float64)
        e, n = frame.utm.geodetic_to_utm(fence[:, 0], fence[:, 1])
        points.append(frame.from_utm(np.column_stack([e, n])))
    xy = np.concatenate(points)
    lo, hi = xy.min(axis=0) - margin_m, xy.max(axis=0) + margin_m
    return _Target(frame, float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))


def _crs(epsg: int) -> CRS:
    try:
        return CRS.from_epsg(epsg)
    except CRSError:
        raise _FileError(f"its coordinate reference system EPSG:{epsg} is not known to "
                         "PROJ") from None


def _to_source(target: _Target, crs: CRS) -> Transformer:
    return Transformer.from_crs(CRS.from_epsg(target.frame.utm.epsg), crs, always_xy=True)


def _native_resolution_m(target: _Target, grid: _Grid, crs: CRS) -> float:
    """The ground size of one source pixel near the box's centre."""
    forward, back = _to_source(target, crs), Transformer.from_crs(
        crs, CRS.from_epsg(target.frame.utm.epsg), always_xy=True)
    cx, cy = target.utm(np.array([(target.x0 + target.x1) / 2]),
                        np.array([(target.y0 + target.y1) / 2]))
    sx, sy = forward.transform(cx, cy)
    col, row = grid.pixel(np.asarray(sx), np.asarray(sy))
    cols = np.array([col[0], col[0] + 1.0, col[0]])
    rows = np.array([row[0], row[0], row[0] + 1.0])
    e, n = back.transform(*grid.model(cols, rows))
    e, n = np.asarray(e), np.asarray(n)
    step = [math.hypot(e[k] - e[0], n[k] - n[0]) for k in (1, 2)]
    if not all(math.isfinite(s) and s > 0 for s in step):
        raise _FileError("its georeference does not map to the search area's UTM zone")
    return min(step)


# -- the warp ---------------------------------------------------------------------------------

def _axis(n: int) -> FloatArray:
    """The lattice positions along an axis of n pixels: every LATTICE_PX and the last."""
    return np.unique(np.append(np.arange(0, n, LATTICE_PX), n - 1)).astype(np.float64)


def _between(lattice: NDArray[np.float64], at: NDArray[np.float64]
             ) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """For each position, the lattice interval it lies in and the fraction into it."""
    if len(lattice) == 1:
        return np.zeros(len(at), dtype=np.int64), np.zeros(len(at))
    k = np.clip(np.searchsorted(lattice, at, side="right") - 1, 0, len(lattice) - 2)
    t = (at - lattice[k]) / (lattice[k + 1] - lattice[k])
    return k.astype(np.int64), t


def _interp(values: FloatArray, rk: NDArray[np.int64], rt: FloatArray, ck: NDArray[np.int64],
            ct: FloatArray) -> FloatArray:
    """Bilinear interpolation of lattice values at (row, col) intervals and fractions."""
    if values.shape[0] == 1:
        rows = np.repeat(values, len(rk), axis=0)
    else:
        rows = (1 - rt)[:, None] * values[rk] + rt[:, None] * values[rk + 1]
    if values.shape[1] == 1:
        return np.repeat(rows, len(ck), axis=1)
    out: FloatArray = (1 - ct)[None, :] * rows[:, ck] + ct[None, :] * rows[:, ck + 1]
    return out


def _warp(source: Any, to_rgba: Callable[[Any], NDArray[np.uint8]], grid: _Grid, crs: CRS,
          target: _Target, native_m: float, max_side_px: int
          ) -> tuple[NDArray[np.uint8], tuple[float, float, float, float], float]:
    """The source raster (rows, cols, ...) resampled onto the target box at about its own
    resolution (coarser when the box would exceed max_side_px), cropped to where it has data."""
    res = max(native_m, target.longest_m / max_side_px)
    width = max(1, min(max_side_px, math.ceil((target.x1 - target.x0) / res)))
    height = max(1, min(max_side_px, math.ceil((target.y1 - target.y0) / res)))
    rows_l = _axis(height)
    cols_l = _axis(width)
    gx, gy = np.meshgrid(target.x0 + (cols_l + 0.5) * res, target.y1 - (rows_l + 0.5) * res)
    try:
        sx, sy = _to_source(target, crs).transform(*target.utm(gx, gy))
    except ProjError as exc:
        raise _FileError(f"cannot be reprojected into the run's UTM zone: {exc}") from None
    lat_col, lat_row = grid.pixel(np.asarray(sx), np.asarray(sy))
    if not (np.all(np.isfinite(lat_col)) and np.all(np.isfinite(lat_row))):
        raise _FileError("its coordinate reference system does not reach the search area")
    n_rows, n_cols = int(source.shape[0]), int(source.shape[1])
    c_lo, c_hi = math.floor(lat_col.min()) - 1, math.ceil(lat_col.max()) + 1
    r_lo, r_hi = math.floor(lat_row.min()) - 1, math.ceil(lat_row.max()) + 1
    c_lo, c_hi = max(c_lo, 0), min(c_hi, n_cols - 1)
    r_lo, r_hi = max(r_lo, 0), min(r_hi, n_rows - 1)
    if c_lo > c_hi or r_lo > r_hi:
        raise _FileError("does not overlap the search area (nor the geofence)")
    stride = max(1, int(res / native_m))  # a source much finer than the output: decimated
    window = to_rgba(source[r_lo:r_hi + 1:stride, c_lo:c_hi + 1:stride])
    lat_col, lat_row = (lat_col - c_lo) / stride, (lat_row - r_lo) / stride
    wh, ww = window.shape[:2]
    out = np.zeros((height, width, 4), dtype=np.uint8)
    ck, ct = _between(cols_l, np.arange(width, dtype=np.float64))
    for start in range(0, height, CHUNK_ROWS):
        rows = np.arange(start, min(start + CHUNK_ROWS, height), dtype=np.float64)
        rk, rt = _between(rows_l, rows)
        col = _interp(lat_col, rk, rt, ck, ct)
        row = _interp(lat_row, rk, rt, ck, ct)
        inside = (col >= -0.5) & (col <= ww - 0.5) & (row >= -0.5) & (row <= wh - 0.5)
        c0 = np.floor(col)
        r0 = np.floor(row)
        fc = (col - c0).astype(np.float32)[..., None]
        fr = (row - r0).astype(np.float32)[..., None]
        c0i = np.clip(c0, 0, ww - 1).astype(np.intp)
        c1i = np.clip(c0 + 1, 0, ww - 1).astype(np.intp)
        r0i = np.clip(r0, 0, wh - 1).astype(np.intp)
        r1i = np.clip(r0 + 1, 0, wh - 1).astype(np.intp)
        top = (1 - fc) * window[r0i, c0i] + fc * window[r0i, c1i]
        bottom = (1 - fc) * window[r1i, c0i] + fc * window[r1i, c1i]
        value = (1 - fr) * top + fr * bottom
        value[~inside] = 0.0
        out[start:start + len(rows)] = np.clip(np.rint(value), 0, 255).astype(np.uint8)
    has = out[..., 3] > 0
    if not has.any():
        raise _FileError("does not overlap the search area (nor the geofence): no pixel of it "
                   "falls there")
    used_rows, used_cols = np.flatnonzero(has.any(axis=1)), np.flatnonzero(has.any(axis=0))
    r_a, r_b, c_a, c_b = used_rows[0], used_rows[-1] + 1, used_cols[0], used_cols[-1] + 1
    cropped = np.ascontiguousarray(out[r_a:r_b, c_a:c_b])
    bounds = (target.x0 + c_a * res, target.y1 - r_b * res,
              target.x0 + c_b * res, target.y1 - r_a * res)
    return cropped, (float(bounds[0]), float(bounds[1]), float(bounds[2]), float(bounds[3])), res


# -- GeoTIFF ----------------------------------------------------------------------------------

def _geokeys(values: Any) -> dict[int, int]:
    """The GeoKeyDirectory's keys held in the directory itself (short values)."""
    v = [int(x) for x in values]
    if len(v) < 4:
        raise _FileError("its GeoKeyDirectory is truncated")
    count, keys = v[3], {}
    for k in range(count):
        entry = v[4 + 4 * k: 8 + 4 * k]
        if len(entry) < 4:
            raise _FileError("its GeoKeyDirectory is truncated")
        key_id, location, _, value = entry
        if location == 0:
            keys[key_id] = value
    return keys


def _geotiff_crs(keys: dict[int, int]) -> CRS:
    """The CRS a GeoKeyDirectory names by EPSG code."""
    model = keys.get(KEY_MODEL_TYPE)
    projected, geographic = keys.get(KEY_PROJECTED), keys.get(KEY_GEOGRAPHIC)
    if model == MODEL_PROJECTED or (model is None and projected is not None):
        if projected is None or projected == USER_DEFINED:
            raise _FileError("its projected coordinate system has no EPSG code (user-defined): "
                       "reproject it to a UTM zone or EPSG:3857 first")
        return _crs(projected)
    if model == MODEL_GEOGRAPHIC or (model is None and geographic is not None):
        if geographic is None or geographic == USER_DEFINED:
            raise _FileError("its geographic coordinate system has no EPSG code (user-defined)")
        return _crs(geographic)
    raise _FileError(f"its GeoKeyDirectory names no EPSG coordinate system (model type {model}): "
               "a geocentric or user-defined model is not supported")


def _geotiff_grid(tags: Any, keys: dict[int, int]) -> _Grid:
    """The pixel-centre grid of the pixel scale and tiepoint, or of the transformation."""
    half = 0.0 if keys.get(KEY_RASTER_TYPE) == PIXEL_IS_POINT else 0.5
    if TAG_TRANSFORMATION in tags:
        m = [float(x) for x in tags[TAG_TRANSFORMATION].value]
        if len(m) != 16:
            raise _FileError("its ModelTransformation does not hold 16 numbers")
        a, b, d, e, f, h = m[0], m[1], m[3], m[4], m[5], m[7]
        if abs(b) > 1e-9 * abs(a) or abs(e) > 1e-9 * abs(f):
            raise _FileError("it is rotated or sheared (its ModelTransformation is not north-up): "
                       "warp it to a north-up raster first")
        if a == 0 or f == 0:
            raise _FileError("its ModelTransformation has a zero pixel size")
        return _Grid(d + a * half, a, h + f * half, f)
    if TAG_TIEPOINT in tags and len(tags[TAG_TIEPOINT].value) > 6:
        raise _FileError(f"it has {len(tags[TAG_TIEPOINT].value) // 6} tiepoints (ground "
                         "control points), not one with a pixel scale: warp it to a north-up "
                         "raster first")
    if TAG_PIXEL_SCALE not in tags or TAG_TIEPOINT not in tags:
        raise _FileError("it has no georeference (neither ModelPixelScale with ModelTiepoint nor "
                   "ModelTransformation): not a GeoTIFF")
    scale = [float(x) for x in tags[TAG_PIXEL_SCALE].value]
    tie = [float(x) for x in tags[TAG_TIEPOINT].value]
    if len(scale) < 2 or len(tie) < 6:
        raise _FileError("its ModelPixelScale or ModelTiepoint is truncated")
    sx, sy = scale[0], scale[1]
    if not (sx > 0 and sy > 0 and math.isfinite(sx) and math.isfinite(sy)):
        raise _FileError(f"its pixel scale ({sx}, {sy}) is not positive")
    i, j, x, y = tie[0], tie[1], tie[3], tie[4]
    return _Grid(x + (half - i) * sx, sx, y - (half - j) * sy, -sy)


def _nodata(tags: Any) -> float | None:
    if TAG_GDAL_NODATA not in tags:
        return None
    try:
        return float(str(tags[TAG_GDAL_NODATA].value).strip("\x00 "))
    except ValueError:
        return None


def _rgba_of(photometric: int, colormap: Any, nodata: float | None,
             extra_alpha: bool) -> Callable[[Any], NDArray[np.uint8]]:
    """How a window of the file's samples becomes 8-bit RGBA."""
    def convert(window: Any) -> NDArray[np.uint8]:
        data = np.asarray(window)
        if data.ndim == 2:
            data = data[..., None]
        alpha = np.full(data.shape[:2], 255, dtype=np.uint8)
        if nodata is not None:
            alpha[np.all(data == nodata, axis=-1)] = 0
        if colormap is not None and data.shape[-1] == 1:  # a palette
            cmap = np.asarray(colormap)
            scale = 257 if cmap.max() > 255 else 1
            idx = np.clip(data[..., 0].astype(np.int64), 0, cmap.shape[1] - 1)
            rgb = (cmap[:, idx] // scale).astype(np.uint8).transpose(1, 2, 0)
            return np.dstack([rgb, alpha])
        if data.dtype != np.uint8:  # stretched: 16-bit imagery rarely uses its whole range
            values = data.astype(np.float32)
            valid = np.isfinite(values) & (alpha[..., None] > 0)
            sample = values[valid]
            lo, hi = ((0.0 if np.issubdtype(data.dtype, np.integer)
                       else float(np.percentile(sample, 0.1)), float(np.percentile(sample, 99.9)))
                      if sample.size else (0.0, 1.0))
            values = (np.nan_to_num(values, nan=lo) - lo) * 255.0 / max(hi - lo, 1e-12)
            data = np.clip(np.rint(values), 0, 255).astype(np.uint8)
        bands = data.shape[-1]
        rgb = np.repeat(data[..., :1], 3, axis=-1) if bands in (1, 2) else data[..., :3]
        if bands == 2 or (bands >= 4 and extra_alpha):
            alpha = np.minimum(alpha, data[..., 1 if bands == 2 else 3])
        if photometric == 0 and bands == 1:  # min-is-white grey
            rgb = 255 - rgb
        return np.dstack([rgb, alpha]).astype(np.uint8)

    return convert


def _geotiff(path: Path, target: _Target, max_side_px: int
             ) -> tuple[NDArray[np.uint8], tuple[float, float, float, float], float]:
    try:
        with tifffile.TiffFile(path) as tif:
            if not tif.pages:
                raise _FileError("holds no image")
            page = tif.pages.first
            tags = page.tags
            if TAG_GEOKEYS not in tags:
                raise _FileError("it has no GeoKeyDirectory: a TIFF without georeference, not a "
                           "GeoTIFF")
            keys = _geokeys(tags[TAG_GEOKEYS].value)
            crs = _geotiff_crs(keys)
            grid = _geotiff_grid(tags, keys)
            nodata = _nodata(tags)
            colormap = page.colormap if int(page.photometric) == 3 else None
            convert = _rgba_of(int(page.photometric), colormap, nodata,
                               bool(page.extrasamples))
            shape = page.shape
            native = _native_resolution_m(target, grid, crs)
            if page.is_memmappable:
                data: Any = tifffile.memmap(path, page=0, mode="r")
            else:
                itemsize = 8 if page.dtype is None else page.dtype.itemsize
                if math.prod(shape) * itemsize > MAX_DECODED_BYTES:
                    raise _FileError(f"a compressed image of {shape[1]} x {shape[0]} pixels is too "
                               "large to decode whole; crop it to the search area (or save "
                               "it uncompressed) first")
                data = page.asarray()
    except _FileError:
        raise
    except (tifffile.TiffFileError, ValueError, OSError, KeyError, TypeError) as exc:
        raise _FileError(f"not a readable GeoTIFF: {exc}") from None
    if data.ndim == 3 and int(page.planarconfig) == 2 and data.shape[0] <= 8:
        data = np.moveaxis(data, 0, -1)  # separate planes: (samples, rows, cols)
    if data.ndim not in (2, 3):
        raise _FileError(f"its image has {data.ndim} dimensions: only one plane of grey, RGB or "
                   "RGBA is read")
    return _warp(data, convert, grid, crs, target, native, max_side_px)


# -- MBTiles ----------------------------------------------------------------------------------

def _mercator_res_m(zoom: int, tile_px: int) -> float:
    """Web-mercator metres of one pixel of a zoom level."""
    return float(2 * MERCATOR_HALF_M / (tile_px * 2**zoom))


def _decode_tile(blob: bytes) -> NDArray[np.uint8]:
    """A PNG or JPEG tile as RGBA, or _FileError."""
    image = cv2.imdecode(np.frombuffer(blob, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise _FileError("its tiles are not PNG or JPEG images (vector tiles are not supported)")
    if image.dtype != np.uint8:
        image = (image / 257).astype(np.uint8)
    code = (cv2.COLOR_GRAY2RGBA if image.ndim == 2 else
            cv2.COLOR_BGRA2RGBA if image.shape[2] == 4 else cv2.COLOR_BGR2RGBA)
    rgba: NDArray[np.uint8] = np.asarray(cv2.cvtColor(image, code), dtype=np.uint8)
    return rgba


def _mbtiles(path: Path, target: _Target, max_side_px: int
             ) -> tuple[NDArray[np.uint8], tuple[float, float, float, float], float]:
    try:
        db = sqlite3.connect(f"{path.resolve().as_uri()}?mode=ro", uri=True)
    except sqlite3.Error as exc:
        raise _FileError(f"cannot be opened: {exc}") from None
    try:
        try:
            zooms = [int(z) for (z,) in db.execute(
                "SELECT DISTINCT zoom_level FROM tiles ORDER BY zoom_level")]
            first = db.execute("SELECT tile_data FROM tiles LIMIT 1").fetchone()
        except sqlite3.Error as exc:
            raise _FileError(f"not an MBTiles file (no tiles table: {exc})") from None
        if not zooms or first is None:
            raise _FileError("holds no tile")
        tile = _decode_tile(bytes(first[0]))
        tile_px = int(tile.shape[0])
        if tile.shape[1] != tile_px:
            raise _FileError(f"its tiles are not square ({tile.shape[1]} x {tile.shape[0]})")
        return _mbtiles_warp(db, zooms, tile_px, target, max_side_px)
    finally:
        db.close()


def _mbtiles_warp(db: sqlite3.Connection, zooms: list[int], tile_px: int, target: _Target,
                  max_side_px: int
                  ) -> tuple[NDArray[np.uint8], tuple[float, float, float, float], float]:
    """The tiles of the best zoom over the box, mosaicked and warped onto the grid."""
    mercator = CRS.from_epsg(3857)
    edge = np.linspace(0.0, 1.0, 17)
    bx = np.concatenate([target.x0 + edge * (target.x1 - target.x0), np.full(17, target.x1),
                         target.x1 - edge * (target.x1 - target.x0), np.full(17, target.x0)])
    by = np.concatenate([np.full(17, target.y0), target.y0 + edge * (target.y1 - target.y0),
                         np.full(17, target.y1), target.y1 - edge * (target.y1 - target.y0)])
    mx, my = _to_source(target, mercator).transform(*target.utm(bx, by))
    mx, my = np.asarray(mx), np.asarray(my)
    centre_e, centre_n = target.utm(np.array([(target.x0 + target.x1) / 2]),
                                    np.array([(target.y0 + target.y1) / 2]))
    lat = float(target.frame.utm.utm_to_geodetic(centre_e, centre_n)[0][0])
    ground = math.cos(math.radians(lat))  # ground metres per mercator metre
    wanted_m = target.longest_m / max_side_px
    # the coarsest zoom at least as fine as wanted, then coarser ones, then finer ones
    fine = [z for z in zooms if _mercator_res_m(z, tile_px) * ground <= wanted_m]
    best = min(fine) if fine else max(zooms)
    order = sorted(zooms, key=lambda z: (z > best, -z if z <= best else z))
    for zoom in order:
        res = _mercator_res_m(zoom, tile_px)
        span = tile_px * res
        n = 2**zoom
        tx0 = max(0, math.floor((mx.min() + MERCATOR_HALF_M) / span))
        tx1 = min(n - 1, math.floor((mx.max() + MERCATOR_HALF_M) / span))
        ty0 = max(0, math.floor((MERCATOR_HALF_M - my.max()) / span))
        ty1 = min(n - 1, math.floor((MERCATOR_HALF_M - my.min()) / span))
        if tx0 > tx1 or ty0 > ty1:
            continue
        if max(tx1 - tx0 + 1, ty1 - ty0 + 1) * tile_px > MAX_MOSAIC_SIDE_PX:
            continue  # finer than the page can show: a coarser zoom will do
        rows = db.execute(
            "SELECT tile_column, tile_row, tile_data FROM tiles WHERE zoom_level = ? AND "
            "tile_column BETWEEN ? AND ? AND tile_row BETWEEN ? AND ?",
            (zoom, tx0, tx1, n - 1 - ty1, n - 1 - ty0)).fetchall()
        if not rows:
            continue
        mosaic = np.zeros(((ty1 - ty0 + 1) * tile_px, (tx1 - tx0 + 1) * tile_px, 4),
                          dtype=np.uint8)
        for column, tms_row, blob in rows:
            image = _decode_tile(bytes(blob))
            if image.shape[:2] != (tile_px, tile_px):
                raise _FileError(f"its tiles differ in size ({image.shape[1]} x {image.shape[0]} "
                           f"beside {tile_px} x {tile_px})")
            top = (n - 1 - int(tms_row) - ty0) * tile_px  # TMS rows count from the south
            left = (int(column) - tx0) * tile_px
            mosaic[top:top + tile_px, left:left + tile_px] = image
        grid = _Grid(-MERCATOR_HALF_M + (tx0 * tile_px + 0.5) * res, res,
                     MERCATOR_HALF_M - (ty0 * tile_px + 0.5) * res, -res)
        try:
            return _warp(mosaic, np.asarray, grid, mercator, target,
                         res * ground, max_side_px)
        except _FileError:
            continue  # its tiles there are all transparent: another zoom may have some
    raise _FileError(f"has no tile over the search area (nor the geofence) at any of its zoom "
               f"levels {zooms[0]}..{zooms[-1]}")
