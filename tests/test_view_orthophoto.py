"""The operator's orthophoto: synthetic GeoTIFFs (UTM, another zone, web mercator, degrees) and
MBTiles put known ground points on the right pixels of the served image; bad files are refused
with one clear line naming the file."""

from __future__ import annotations

import asyncio
import math
from pathlib import Path

import numpy as np
import pytest
import tifffile
from pyproj import Transformer

import companion.view.orthophoto as orthophoto_module
from companion.config import parse_config
from companion.errors import ConfigError
from companion.pipeline import SearchFrame
from companion.service import Service
from companion.view.live import LiveView
from companion.view.orthophoto import MARGIN_M, Orthophoto, load_orthophoto
from tests.orthophotos import (
    BLUE,
    decode_png,
    geokeys,
    mercator,
    ramp,
    tile_of,
    write_geotiff,
    write_mbtiles,
)
from tests.test_view_model import sitl_data

CONFIG = parse_config(sitl_data())
FRAME = SearchFrame.from_config(CONFIG.search)
FENCE = CONFIG.safety.geofence_latlon
W, H = FRAME.world.width_m, FRAME.world.height_m
# ground points on the grid: the area's corners and centre, and one in the margin
POINTS = [(0.0, 0.0), (W, 0.0), (W, H), (0.0, H), (W / 2, H / 2), (-20.0, H + 15.0)]


def _pixel(ortho: Orthophoto, x: float, y: float) -> tuple[int, int]:
    """The served image's (col, row) under a grid point."""
    west, south, east, north = ortho.bounds_m
    width, height = ortho.size_px
    col = math.floor((x - west) / (east - west) * width)
    row = math.floor((north - y) / (north - south) * height)
    assert 0 <= col < width and 0 <= row < height, (x, y, ortho.bounds_m)
    return col, row


def _utm_to(epsg: int, x: float, y: float) -> tuple[float, float]:
    """A grid point in another CRS."""
    e, n = FRAME.to_utm(np.array([x, y]))
    t = Transformer.from_crs(FRAME.utm.epsg, epsg, always_xy=True)
    a, b = t.transform(e, n)
    return float(a), float(b)


def _check_ramp(ortho: Orthophoto, epsg: int, left: float, top: float, pixel: float,
                tolerance_px: float = 1.5) -> None:
    """Each point's served pixel has the colour of the source pixel over it."""
    image = decode_png(ortho.png)
    assert image.shape[:2] == (ortho.size_px[1], ortho.size_px[0])
    for x, y in POINTS:
        col, row = _pixel(ortho, x, y)
        r, g, b, a = (int(v) for v in image[row, col])
        sx, sy = _utm_to(epsg, x, y)
        want_col, want_row = (sx - left) / pixel - 0.5, (top - sy) / pixel - 0.5
        assert a == 255 and abs(b - BLUE) <= 1, (x, y, r, g, b, a)
        assert abs(r - want_col) <= tolerance_px, (x, y, r, want_col)
        assert abs(g - want_row) <= tolerance_px, (x, y, g, want_row)


def _geotiff_over_area(tmp_path: Path, epsg: int, pixel: float, name: str = "ortho.tif",
                       **kwargs: object) -> tuple[Path, float, float]:
    """A 256 x 256 ramp in EPSG:epsg centred on the search area; its path and top-left."""
    cx, cy = _utm_to(epsg, W / 2, H / 2)
    left, top = cx - 128 * pixel, cy + 128 * pixel
    path = write_geotiff(tmp_path / name, ramp(256, 256), epsg, left, top, pixel,
                         **kwargs)  # type: ignore[arg-type]
    return path, left, top


@pytest.mark.parametrize(("epsg", "pixel"), [
    (32632, 1.0),  # the run's own zone
    (32631, 1.0),  # the zone to the west: the grid is turned by some degrees
    (3857, 1.5),  # web mercator, about 1 m on the ground at 47.4 degrees
])
def test_a_geotiff_puts_ground_points_on_their_pixels(tmp_path: Path, epsg: int,
                                                       pixel: float) -> None:
    path, left, top = _geotiff_over_area(tmp_path, epsg, pixel)
    ortho = load_orthophoto(path, FRAME, FENCE)
    _check_ramp(ortho, epsg, left, top, pixel)
    west, south, east, north = ortho.bounds_m
    # cropped to the area and fence plus the margin, which the source covers whole
    assert west == pytest.approx(-MARGIN_M, abs=2.0) and south == pytest.approx(-MARGIN_M, abs=2)
    assert east == pytest.approx(W + MARGIN_M, abs=2.0)
    assert north == pytest.approx(H + MARGIN_M, abs=2.0)
    assert ortho.resolution_m == pytest.approx(1.0, rel=0.05)
    assert ortho.scene()["bounds"] == [[round(west, 3), round(south, 3)],
                                       [round(east, 3), round(north, 3)]]


def test_a_geotiff_in_degrees_and_a_compressed_one(tmp_path: Path) -> None:
    pixel = 1e-5  # degrees: about 0.75 m east and 1.1 m north
    lat, lon = FRAME.to_latlon(np.array([[W / 2, H / 2]]))[0]
    left, top = lon - 128 * pixel, lat + 128 * pixel
    path = write_geotiff(tmp_path / "degrees.tif", ramp(256, 256), 4326, left, top, pixel,
                         geographic=True, compress=True)
    ortho = load_orthophoto(path, FRAME, FENCE)
    _check_ramp(ortho, 4326, left, top, pixel)


def test_the_served_image_is_bounded_in_pixels(tmp_path: Path) -> None:
    path, left, top = _geotiff_over_area(tmp_path, 32632, 0.5)
    ortho = load_orthophoto(path, FRAME, FENCE, max_side_px=40)
    assert max(ortho.size_px) <= 40
    assert ortho.resolution_m >= (W + 2 * MARGIN_M) / 40 - 1e-9
    # coarser, still in place: within one served pixel (in source pixels of 0.5 m)
    _check_ramp(ortho, 32632, left, top, 0.5, tolerance_px=ortho.resolution_m / 0.5 + 1)


def test_a_model_transformation_without_rotation_is_read(tmp_path: Path) -> None:
    cx, cy = _utm_to(32632, W / 2, H / 2)
    left, top = cx - 128.0, cy + 128.0
    matrix = [1.0, 0.0, 0.0, left, 0.0, -1.0, 0.0, top, 0, 0, 0, 0, 0, 0, 0, 1]
    path = write_geotiff(tmp_path / "affine.tif", ramp(256, 256), 32632, 0, 0, 1,
                         transformation=matrix)
    _check_ramp(load_orthophoto(path, FRAME, FENCE), 32632, left, top, 1.0)


def _z18_tiles() -> tuple[int, set[tuple[int, int]]]:
    """The zoom-18 tiles over the area and its margin."""
    zoom = 18
    corners = FRAME.to_latlon(np.array([[-MARGIN_M - 5, -MARGIN_M - 5],
                                        [W + MARGIN_M + 5, H + MARGIN_M + 5]]))
    (x0, y0), (x1, y1) = (tile_of(float(lat), float(lon), zoom) for lat, lon in corners)
    tiles = {(tx, ty) for tx in range(math.floor(min(x0, x1)), math.floor(max(x0, x1)) + 1)
             for ty in range(math.floor(min(y0, y1)), math.floor(max(y0, y1)) + 1)}
    return zoom, tiles


def test_mbtiles_put_ground_points_on_their_pixels_and_the_finest_zoom_is_taken(
        tmp_path: Path) -> None:
    zoom, tiles = _z18_tiles()
    coarse = {(15, tx >> 3, ty >> 3) for tx, ty in tiles}
    path = write_mbtiles(tmp_path / "tiles.mbtiles",
                         [(zoom, tx, ty) for tx, ty in tiles] + sorted(coarse))
    ortho = load_orthophoto(path, FRAME, FENCE)
    ground_res = 2 * math.pi * 6378137.0 / (256 * 2**zoom) * math.cos(math.radians(47.3978))
    assert ortho.resolution_m == pytest.approx(ground_res, rel=0.01)
    image = decode_png(ortho.png)
    checked = 0
    for x, y in [*POINTS, (3.0, 4.0), (W - 7.0, 2.0), (11.0, H - 5.0), (-12.0, -9.0)]:
        lat, lon = FRAME.to_latlon(np.array([[x, y]]))[0]
        fx, fy = tile_of(float(lat), float(lon), zoom)
        px, py = (fx % 1) * 256 - 0.5, (fy % 1) * 256 - 0.5  # pixel-centre coordinates
        if not (2 <= px <= 253 and 2 <= py <= 253):
            continue  # beside a tile's edge the colours of two tiles are blended
        col, row = _pixel(ortho, x, y)
        r, g, b, a = (int(v) for v in image[row, col])
        assert a == 255
        assert b == (math.floor(fy) % 16) * 16 + math.floor(fx) % 16, (x, y)  # the right tile
        assert abs(r - px) <= 1.5 and abs(g - py) <= 1.5, (x, y, r, g, px, py)
        checked += 1
    assert checked >= 5


def test_mbtiles_of_only_a_coarse_zoom_are_used(tmp_path: Path) -> None:
    _, tiles = _z18_tiles()
    path = write_mbtiles(tmp_path / "coarse.mbtiles",
                         sorted({(16, tx >> 2, ty >> 2) for tx, ty in tiles}))
    ortho = load_orthophoto(path, FRAME, FENCE)
    assert ortho.resolution_m == pytest.approx(
        2 * math.pi * 6378137.0 / (256 * 2**16) * math.cos(math.radians(47.3978)), rel=0.01)


# -- bad files -----------------------------------------------------------------------------------

def _refused(path: Path, match: str) -> None:
    with pytest.raises(ConfigError, match=match) as caught:
        load_orthophoto(path, FRAME, FENCE)
    assert str(caught.value).startswith(f"view.orthophoto: {path}: "), caught.value
    assert "\n" not in str(caught.value)


def test_a_missing_file_or_an_unknown_kind(tmp_path: Path) -> None:
    _refused(tmp_path / "nothing.tif", "no such file")
    (tmp_path / "photo.png").write_bytes(b"\x89PNG")
    _refused(tmp_path / "photo.png", "neither a GeoTIFF")
    (tmp_path / "folder.tif").mkdir()
    _refused(tmp_path / "folder.tif", "not a file")


def test_not_a_tiff_or_a_tiff_without_georeference(tmp_path: Path) -> None:
    (tmp_path / "text.tif").write_text("not an image\n")
    _refused(tmp_path / "text.tif", "not a readable GeoTIFF")
    plain = write_geotiff(tmp_path / "plain.tif", ramp(16, 16), None, 0, 0, 1)
    _refused(plain, "no GeoKeyDirectory")
    keys_only = tmp_path / "keys.tif"  # a GeoKeyDirectory, but neither scale nor transformation
    tifffile.imwrite(keys_only, ramp(16, 16), photometric="rgb",
                     extratags=[(34735, "H", 16, tuple(geokeys(32632)), False)])
    _refused(keys_only, "no georeference")


@pytest.mark.parametrize(("keys", "match"), [
    (geokeys(32767), "no EPSG code"),
    (geokeys(60000), "EPSG:60000 is not known"),
    ([1, 1, 0, 1, 1024, 0, 1, 3], "geocentric or user-defined"),
])
def test_an_unsupported_crs(tmp_path: Path, keys: list[int], match: str) -> None:
    path = write_geotiff(tmp_path / "crs.tif", ramp(16, 16), None, 0, 0, 1, keys=keys)
    _refused(path, match)


def test_a_rotated_raster(tmp_path: Path) -> None:
    cx, cy = _utm_to(32632, W / 2, H / 2)
    a, b = math.cos(0.3), math.sin(0.3)
    matrix = [a, b, 0.0, cx, b, -a, 0.0, cy, 0, 0, 0, 0, 0, 0, 0, 1]
    path = write_geotiff(tmp_path / "rotated.tif", ramp(64, 64), 32632, 0, 0, 1,
                         transformation=matrix)
    _refused(path, "rotated or sheared")


def test_a_geotiff_elsewhere(tmp_path: Path) -> None:
    cx, cy = _utm_to(32632, W / 2, H / 2)
    path = write_geotiff(tmp_path / "far.tif", ramp(64, 64), 32632, cx + 5000, cy, 1.0)
    _refused(path, "does not overlap the search area")


def test_mbtiles_without_tiles_over_the_area_or_not_mbtiles(tmp_path: Path) -> None:
    zoom, tiles = _z18_tiles()
    far = write_mbtiles(tmp_path / "far.mbtiles", [(zoom, tx + 50, ty) for tx, ty in tiles])
    _refused(far, "no tile over the search area")
    empty = write_mbtiles(tmp_path / "empty.mbtiles", [])
    _refused(empty, "holds no tile")
    vector = write_mbtiles(tmp_path / "vector.mbtiles", [(zoom, *next(iter(tiles)))],
                           blob=b"\x1f\x8b\x08\x00 not an image")
    _refused(vector, "not PNG or JPEG")
    (tmp_path / "text.mbtiles").write_text("not a database at all, just text\n" * 20)
    _refused(tmp_path / "text.mbtiles", "not an MBTiles file")


def test_the_key_resolves_beside_the_configuration(tmp_path: Path) -> None:
    data = sitl_data(orthophoto="maps/field.tif")
    assert parse_config(data, base=tmp_path).view.orthophoto == str(tmp_path / "maps/field.tif")
    assert parse_config(sitl_data(orthophoto="")).view.orthophoto is None
    assert parse_config(sitl_data()).view.orthophoto is None


def test_mercator_helper_agrees_with_pyproj() -> None:  # the tests' own oracle
    t = Transformer.from_crs(4326, 3857, always_xy=True)
    x, y = t.transform(8.5457, 47.3978)
    assert mercator(47.3978, 8.5457) == pytest.approx((x, y), abs=1e-6)


def test_the_live_page_names_the_orthophoto_and_a_bad_one_only_disables_it(
        tmp_path: Path) -> None:
    path, _, _ = _geotiff_over_area(tmp_path, 32632, 1.0)
    lines: list[str] = []
    config = parse_config(sitl_data(orthophoto=str(path)))
    service = Service(config, announce=lines.append)
    ortho, notes = asyncio.run(service._load_orthophoto())
    assert ortho is not None and notes == []
    assert lines[-1].startswith("view: orthophoto ortho.tif: ")
    live = LiveView(config, service.pipeline.frame, service.pipeline.params.tracks,
                    orthophoto=ortho, notes=notes)
    assert live.server.scene["orthophoto"] == ortho.scene()
    assert live.server.scene["orthophoto"]["url"] == "api/orthophoto.png"
    bad = Service(parse_config(sitl_data(orthophoto=str(tmp_path / "none.tif"))),
                  announce=lines.append)
    ortho, notes = asyncio.run(bad._load_orthophoto())
    assert ortho is None and len(notes) == 1 and "none.tif: no such file" in notes[0]
    assert lines[-1] == ("view: warning: the orthophoto is not shown: view.orthophoto: "
                         f"{tmp_path / 'none.tif'}: no such file")


def test_a_16_bit_grey_geotiff_with_nodata(tmp_path: Path) -> None:
    cx, cy = _utm_to(32632, W / 2, H / 2)
    grey = np.full((200, 200), 1000, dtype=np.uint16)
    grey[:, 100:] = 4000  # the east half brighter
    grey[:, :80] = 0  # nodata west of 20 m before the area's centre: transparent
    path = tmp_path / "grey.tif"
    tifffile.imwrite(path, grey, photometric="minisblack", extratags=[
        (33550, "d", 3, (1.0, 1.0, 0.0), False),
        (33922, "d", 6, (0.0, 0.0, 0.0, cx - 100.0, cy + 100.0, 0.0), False),
        (34735, "H", 16, tuple(geokeys(32632)), False), (42113, "s", 2, "0", False)])
    ortho = load_orthophoto(path, FRAME, FENCE)
    image = decode_png(ortho.png)
    west, _, _, _ = ortho.bounds_m
    assert west == pytest.approx(W / 2 - 20.0, abs=1.5)  # the nodata is cropped off
    col, row = _pixel(ortho, W / 2 - 10, H / 2)
    dark = image[row, col]
    col, row = _pixel(ortho, W / 2 + 10, H / 2)
    bright = image[row, col]
    assert dark[3] == bright[3] == 255
    assert dark[0] == dark[1] == dark[2] and bright[0] > 200 and 30 < dark[0] < 80


def test_ground_control_points_and_a_compressed_file_too_large(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    gcps = tmp_path / "gcps.tif"
    tifffile.imwrite(gcps, ramp(16, 16), photometric="rgb", extratags=[
        (33922, "d", 12, (0, 0, 0, 465700.0, 5249500.0, 0, 16, 16, 0, 465716.0, 5249484.0, 0),
         False), (34735, "H", 16, tuple(geokeys(32632)), False)])
    _refused(gcps, "2 tiepoints")
    path, _, _ = _geotiff_over_area(tmp_path, 32632, 1.0, compress=True)
    assert load_orthophoto(path, FRAME, FENCE).size_px[0] > 0
    monkeypatch.setattr(orthophoto_module, "MAX_DECODED_BYTES", 256 * 256 * 3 - 1)
    _refused(path, "too large to decode whole")
