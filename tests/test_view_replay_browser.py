"""The replay page in a real headless Chromium over small synthetic run folders (no SITL): the
orthophoto lies under the map where its bounds say, with its toggle, and the status bar shows
the mission state, link and camera health each step recorded ("not recorded" for a folder of
an earlier version)."""

from __future__ import annotations

from pathlib import Path

import pytest
from playwright.sync_api import Page

from companion.config import parse_config
from tests.browser import chromium, serving, set_slider
from tests.test_view_model import sitl_data
from tests.test_view_recorded import STATES, field_geotiff, write_run

pytestmark = pytest.mark.browser

# where Leaflet put the overlay's corners, against where the map projects its bounds
PLACED_JS = """() => {
    const v = window.companionView, img = document.querySelector("img.orthophoto");
    const [[w, s], [e, n]] = v.ortho.bounds;
    const box = img.getBoundingClientRect(), map = v.map.getContainer().getBoundingClientRect();
    const nw = v.map.latLngToContainerPoint([n, w]), se = v.map.latLngToContainerPoint([s, e]);
    return {img: [box.left - map.left, box.top - map.top, box.right - map.left,
                  box.bottom - map.top], want: [nw.x, nw.y, se.x, se.y],
            data: [img.dataset.west, img.dataset.south, img.dataset.east, img.dataset.north]
                  .map(Number),
            pane: img.parentElement.classList.contains("leaflet-ortho-pane"),
            paneZ: Number(getComputedStyle(img.parentElement).zIndex),
            overlayZ: Number(getComputedStyle(v.map.getPane("overlayPane")).zIndex),
            loaded: img.complete && img.naturalWidth > 0, natural: [img.naturalWidth,
                                                                   img.naturalHeight]};
}"""


def _chips(page: Page) -> tuple[str, str, str]:
    return (page.inner_text("#mission"), page.inner_text("#link"), page.inner_text("#camera"))


def test_the_orthophoto_lies_under_the_map_at_its_bounds_and_the_state_is_shown(
        tmp_path: Path) -> None:
    config = parse_config(sitl_data(orthophoto=str(field_geotiff(tmp_path / "field.tif",
                                                                 parse_config(sitl_data())))))
    write_run(tmp_path / "run", config)
    with serving(tmp_path / "run") as url, chromium() as context:
        page = context.new_page()
        page.goto(url)
        page.wait_for_selector(f"body[data-seq='{len(STATES)}']", timeout=60_000)
        page.wait_for_function("() => { const i = document.querySelector('img.orthophoto');"
                               " return i && i.complete && i.naturalWidth > 0; }",
                               timeout=30_000)
        scene = page.evaluate("() => window.companionView.scene")
        placed = page.evaluate(PLACED_JS)
        (w, s), (e, n) = scene["orthophoto"]["bounds"]
        assert placed["data"] == [w, s, e, n]
        assert placed["natural"] == scene["orthophoto"]["size_px"]
        for got, want in zip(placed["img"], placed["want"], strict=True):
            assert abs(got - want) <= 2.0, placed  # Leaflet laid it where its bounds are
        assert placed["pane"] and placed["paneZ"] < placed["overlayZ"]  # under every layer
        assert page.locator("#ortho-toggle").is_visible()
        assert _chips(page) == ("done", "link ok", "camera ok")
        set_slider(page, 2)
        assert _chips(page) == ("taking_off", "link lost", "camera ok")
        set_slider(page, 4)
        assert _chips(page) == ("searching", "link ok", "camera: no picture")
        page.uncheck("#ortho-on")
        page.wait_for_selector("img.orthophoto", state="detached", timeout=10_000)
        page.check("#ortho-on")
        page.wait_for_selector("img.orthophoto", state="attached", timeout=10_000)


def test_a_folder_of_an_earlier_version_says_not_recorded(tmp_path: Path) -> None:
    config = parse_config(sitl_data())
    write_run(tmp_path / "old", config, status=False)
    with serving(tmp_path / "old") as url, chromium() as context:
        page = context.new_page()
        page.goto(url)
        page.wait_for_selector(f"body[data-seq='{len(STATES)}']", timeout=60_000)
        assert _chips(page) == ("mission not recorded", "link not recorded",
                                "camera not recorded")
        assert not page.locator("#ortho-toggle").is_visible()
        assert page.locator("img.orthophoto").count() == 0


def test_an_orthophoto_given_on_the_command_line_is_shown(tmp_path: Path) -> None:
    config = parse_config(sitl_data())
    write_run(tmp_path / "run", config, snapshot=False)  # no configuration: the steps' grid
    photo = field_geotiff(tmp_path / "given.tif", config)
    with serving(tmp_path / "run", "--orthophoto", str(photo)) as url, \
            chromium() as context:
        page = context.new_page()
        page.goto(url)
        page.wait_for_function("() => { const i = document.querySelector('img.orthophoto');"
                               " return i && i.complete && i.naturalWidth > 0; }",
                               timeout=60_000)
        assert page.get_attribute("img.orthophoto", "alt") == "orthophoto given.tif"
