"""Small synthetic orthophotos for the view's tests: GeoTIFFs and MBTiles whose colours say where
each pixel is (red: column, green: row, within 256), so a test can read a position back."""

from __future__ import annotations

import math
import sqlite3
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import tifffile
from numpy.typing import NDArray

EARTH_R_M = 6378137.0
BLUE = 100


def ramp(rows: int, cols: int) -> NDArray[np.uint8]:
    """An RGB image whose red is the column and green the row (both below 256)."""
    assert rows <= 256 and cols <= 256
    r, c = np.mgrid[0:rows, 0:cols]
    return np.dstack([c, r, np.full_like(c, BLUE)]).astype(np.uint8)


def geokeys(epsg: int, *, geographic: bool = False, point: bool = False) -> list[int]:
    """A GeoKeyDirectory naming one EPSG code (projected, or geographic)."""
    return [1, 1, 0, 3,
            1024, 0, 1, 2 if geographic else 1,
            1025, 0, 1, 2 if point else 1,
            2048 if geographic else 3072, 0, 1, epsg]


def write_geotiff(path: Path, image: NDArray[np.generic], epsg: int | None, left: float,
                  top: float, pixel: float, *, geographic: bool = False,
                  transformation: list[float] | None = None,
                  keys: list[int] | None = None, compress: bool = False) -> Path:
    """A GeoTIFF of image whose top-left corner is (left, top) in EPSG:epsg, pixel units square;
    with transformation, a ModelTransformation instead of scale and tiepoint."""
    tags: list[tuple[int | str, int | str, int | None, Any, bool]] = []
    if transformation is not None:
        tags.append((34264, "d", 16, tuple(transformation), False))
    else:
        tags += [(33550, "d", 3, (pixel, pixel, 0.0), False),
                 (33922, "d", 6, (0.0, 0.0, 0.0, left, top, 0.0), False)]
    directory = keys if keys is not None else (
        None if epsg is None else geokeys(epsg, geographic=geographic))
    if directory is not None:
        tags.append((34735, "H", len(directory), tuple(directory), False))
    tifffile.imwrite(path, image, photometric="rgb" if image.ndim == 3 else "minisblack",
                     extratags=tags, compression="zlib" if compress else None)
    return path


def mercator(lat_deg: float, lon_deg: float) -> tuple[float, float]:
    """Web-mercator metres of a WGS84 point (spherical formula)."""
    x = EARTH_R_M * math.radians(lon_deg)
    y = EARTH_R_M * math.log(math.tan(math.pi / 4 + math.radians(lat_deg) / 2))
    return x, y


def tile_of(lat_deg: float, lon_deg: float, zoom: int) -> tuple[float, float]:
    """The (x, y) tile coordinates (XYZ: y from the north, fractional) of a point."""
    x, y = mercator(lat_deg, lon_deg)
    span = 2 * math.pi * EARTH_R_M / 2**zoom
    return (x + math.pi * EARTH_R_M) / span, (math.pi * EARTH_R_M - y) / span


def tile_image(tx: int, ty: int, size: int = 256) -> NDArray[np.uint8]:
    """A tile whose red is the pixel's column, green its row and blue says which tile it is."""
    r, c = np.mgrid[0:size, 0:size]
    tag = (ty % 16) * 16 + tx % 16
    return np.dstack([c, r, np.full_like(c, tag)]).astype(np.uint8)


def write_mbtiles(path: Path, tiles: Iterable[tuple[int, int, int]], *, fmt: str = "png",
                  blob: bytes | None = None) -> Path:
    """An MBTiles file of the given (zoom, x, y) tiles (XYZ y; stored as TMS rows)."""
    db = sqlite3.connect(path)
    try:
        db.execute("CREATE TABLE metadata (name TEXT, value TEXT)")
        db.execute("CREATE TABLE tiles (zoom_level INTEGER, tile_column INTEGER, "
                   "tile_row INTEGER, tile_data BLOB)")
        db.executemany("INSERT INTO metadata VALUES (?, ?)",
                       [("name", "test"), ("format", fmt)])
        for zoom, tx, ty in tiles:
            if blob is None:
                rgb = tile_image(tx, ty)
                ok, data = cv2.imencode(f".{fmt}", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
                assert ok
                content = data.tobytes()
            else:
                content = blob
            db.execute("INSERT INTO tiles VALUES (?, ?, ?, ?)",
                       (zoom, tx, 2**zoom - 1 - ty, content))
        db.commit()
    finally:
        db.close()
    return path


def decode_png(png: bytes) -> NDArray[np.uint8]:
    """A served PNG as RGBA."""
    image = cv2.imdecode(np.frombuffer(png, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    assert image is not None and image.shape[2] == 4
    rgba: NDArray[np.uint8] = np.asarray(cv2.cvtColor(image, cv2.COLOR_BGRA2RGBA), np.uint8)
    return rgba


def grass(rows: int, cols: int, seed: int = 7) -> NDArray[np.uint8]:
    """An RGB field of grass (seeded noise at two scales), for a page that looks like one."""
    rng = np.random.default_rng(seed)
    blurred = np.asarray(cv2.GaussianBlur(rng.normal(0.0, 1.0, (rows, cols)), (0, 0), 25),
                         dtype=np.float64)
    coarse = blurred / max(float(np.abs(blurred).max()), 1e-9)
    fine = rng.normal(0.0, 1.0, (rows, cols))
    shade = 0.8 + 0.15 * coarse + 0.05 * fine
    base = np.array([104.0, 138.0, 72.0])
    field: NDArray[np.uint8] = np.clip(shade[..., None] * base, 0, 255).astype(np.uint8)
    return field
