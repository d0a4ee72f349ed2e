"""The operator's page in a real headless Chromium: live during a SITL mission, then the replay.

One whole field mission (the real service and MAVSDK against the SITL over loopback) is watched
by a page with its access token while the test checks what the page shows against what the
service reported; its run folder then opens in `companion view` for the time slider. The
screenshots in docs/ are taken here.
"""

from __future__ import annotations

import asyncio
import dataclasses
import json
import queue
import shutil
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from playwright.sync_api import Page

from companion.run_folder import read_steps
from companion.sim.scenario import load_scenario
from sitl.cli import sitl_scenarios
from sitl.demo import DemoResult, _latlon, fly
from tests.browser import DOCS, InThread, chromium, serving, set_slider
from tests.orthophotos import grass, write_geotiff

pytestmark = [pytest.mark.sitl, pytest.mark.browser]

SPEEDUP = 4.0
TOKEN = "field-token-7f3a9c2e41d84b6f"  # a test's token; a real one comes from a secret file
ROWS_JS = """rows => rows.map(r => ({id: Number(r.dataset.trackId), lat: Number(r.dataset.lat),
                                     lon: Number(r.dataset.lon), state: r.dataset.state}))"""
WS_REFUSED_JS = """url => new Promise(done => {
    const ws = new WebSocket(url);
    ws.onopen = () => { ws.close(); done("open"); };
    ws.onerror = () => done("refused");
})"""
LAT_LON_DEG = 2e-7  # the table's precision (7 decimals, about 1 cm)


@dataclass(frozen=True)
class Watched:
    """What the page showed during the mission."""

    missing_token_status: int
    wrong_token_status: int
    stream_with_wrong_token: str
    first_vehicle: tuple[float, float]
    moved_vehicle: tuple[float, float]
    stale_while_streaming: bool
    rows_at_end: list[dict[str, Any]]
    orthophoto: dict[str, Any]  # the scene's, and the image's size as loaded


def _vehicle(page: Page) -> tuple[float, float]:
    pos = page.locator("#vehicle-pos")
    return float(pos.get_attribute("data-x") or "nan"), float(pos.get_attribute("data-y") or "nan")


def _watch(urls: queue.Queue[str]) -> Watched:
    url = urls.get(timeout=180)
    with chromium() as context:
        page = context.new_page()
        missing = page.goto(url)
        wrong = page.goto(url + "?token=" + TOKEN[:-1] + "x")
        assert missing is not None and wrong is not None
        page.goto(url + "?token=" + TOKEN)
        ws_url = url.replace("http://", "ws://") + "api/stream?token=not-the-token"
        stream_refused = page.evaluate(WS_REFUSED_JS, ws_url)
        page.wait_for_function("() => { const i = document.querySelector('img.orthophoto');"
                               " return i && i.complete && i.naturalWidth > 0; }",
                               timeout=120_000)  # fetched with the token, like the data
        ortho = page.evaluate("""() => ({scene: window.companionView.scene.orthophoto,
            natural: [document.querySelector('img.orthophoto').naturalWidth,
                      document.querySelector('img.orthophoto').naturalHeight]})""")
        page.wait_for_selector("#vehicle-pos[data-x]", timeout=120_000)
        first = _vehicle(page)
        page.wait_for_function(
            """([x0, y0]) => { const e = document.getElementById("vehicle-pos");
                               return Math.hypot(e.dataset.x - x0, e.dataset.y - y0) > 3; }""",
            arg=list(first), timeout=120_000)
        moved = _vehicle(page)
        page.wait_for_function(
            "() => document.querySelectorAll('tr[data-track-id]').length >= 3",
            timeout=240_000)
        stale = page.locator("#stale").is_visible()
        page.screenshot(path=str(DOCS / "view-live.png"))
        # the mission ends, the service stops streaming: the page must say its data is stale
        page.wait_for_selector("#stale", state="visible", timeout=300_000)
        rows = page.eval_on_selector_all("tr[data-track-id]", ROWS_JS)
        return Watched(missing.status, wrong.status, stream_refused, first, moved, stale, rows,
                       ortho)


@pytest.fixture(scope="module")
def mission(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[DemoResult, Watched]]:
    """One field mission flown by the service with a page watching it."""
    out = tmp_path_factory.mktemp("view-mission")
    token_file = out / "view.token"
    token_file.write_text(TOKEN + "\n")
    token_file.chmod(0o600)
    urls: queue.Queue[str] = queue.Queue()

    def announce(text: str) -> None:
        if text.startswith("view: serving the operator's page at "):
            urls.put(text.rsplit(" ", 1)[1])

    watcher = InThread(lambda: _watch(urls)).start()
    s = load_scenario(sitl_scenarios()["field-5-tags"])
    scenario = dataclasses.replace(s, vehicle=dataclasses.replace(s.vehicle, flavour="px4"))
    w, h = scenario.world.size_m
    (lat, lon), = _latlon(scenario, np.array([[w / 2, h / 2]]))
    step_deg = 3e-6  # about 0.23 m east, 0.33 m north: 136 m by 200 m of grass
    photo = write_geotiff(out / "field.tif", grass(600, 600), 4326, lon - 300 * step_deg,
                          lat + 300 * step_deg, step_deg, geographic=True)
    result = asyncio.run(fly(scenario, speedup=SPEEDUP, out_dir=out, announce=announce,
                             view={"port": 0, "token_file": str(token_file),
                                   "orthophoto": str(photo)}))
    yield result, watcher.result(120)


def test_the_live_page_shows_the_service_s_targets_and_refuses_a_wrong_token(
        mission: tuple[DemoResult, Watched]) -> None:
    result, watched = mission
    assert (watched.missing_token_status, watched.wrong_token_status) == (401, 401)
    assert watched.stream_with_wrong_token == "refused"
    assert result.run.counters["view_refused_token"] >= 3
    assert result.run.counters["view_pages"] >= 1
    assert not watched.stale_while_streaming
    service = {t.id: t for t in result.run.tracks}
    assert len(service) >= 3
    assert sorted(r["id"] for r in watched.rows_at_end) == sorted(service)
    for row in watched.rows_at_end:
        track = service[row["id"]]
        assert abs(row["lat"] - track.lat_deg) <= LAT_LON_DEG, row
        assert abs(row["lon"] - track.lon_deg) <= LAT_LON_DEG, row
        assert row["state"] == ("coasting" if track.coasting else "seen")


def test_the_live_page_lays_the_orthophoto_under_the_map(
        mission: tuple[DemoResult, Watched]) -> None:
    _, watched = mission
    scene = watched.orthophoto["scene"]
    assert scene["name"] == "field.tif" and scene["url"] == "api/orthophoto.png"
    assert watched.orthophoto["natural"] == scene["size_px"]
    (west, south), (east, north) = scene["bounds"]
    assert west < 0 and south < 0 and east > 20 and north > 20  # the area and its margin


def test_the_vehicle_moves_on_the_page(mission: tuple[DemoResult, Watched]) -> None:
    _, watched = mission
    (x0, y0), (x1, y1) = watched.first_vehicle, watched.moved_vehicle
    assert ((x1 - x0) ** 2 + (y1 - y0) ** 2) ** 0.5 > 3.0


def _ids(page: Page) -> list[int]:
    return sorted(r["id"] for r in page.eval_on_selector_all("tr[data-track-id]", ROWS_JS))


def test_the_replay_view_opens_at_the_end_and_its_slider_shows_a_chosen_time(
        mission: tuple[DemoResult, Watched]) -> None:
    result, _ = mission
    run_dir = result.run.out_dir
    steps = read_steps(run_dir)
    final = {t.id: t for t in result.run.tracks}
    # a time in the middle of the flight: some targets confirmed, not all yet
    chosen = next(k for k, s in enumerate(steps) if 0 < len(s["confirmed_ids"]) < len(final))
    with serving(run_dir) as url, chromium() as context:
        page = context.new_page()
        page.goto(url)
        page.wait_for_selector(f"body[data-seq='{len(steps)}']", timeout=60_000)
        assert page.locator("#slider").input_value() == str(len(steps) - 1)
        rows = page.eval_on_selector_all("tr[data-track-id]", ROWS_JS)
        assert sorted(r["id"] for r in rows) == sorted(final)
        for row in rows:  # the estimate again over the recorded detections: the live one
            assert abs(row["lat"] - final[row["id"]].lat_deg) <= LAT_LON_DEG, row
            assert abs(row["lon"] - final[row["id"]].lon_deg) <= LAT_LON_DEG, row
        assert not page.locator("#stale").is_visible()
        page.screenshot(path=str(DOCS / "view-replay.png"))
        set_slider(page, chosen)
        assert _ids(page) == sorted(steps[chosen]["confirmed_ids"])  # what the service had
        page.select_option("#speed", "16")
        page.click("#play")
        page.wait_for_function(f"() => Number(document.body.dataset.seq) > {chosen + 4}",
                               timeout=30_000)
        page.click("#play")  # pause
        assert page.get_attribute("#play", "aria-label") == "play"
        paused_at = page.locator("#slider").input_value()
        page.wait_for_timeout(500)  # nothing may move while paused
        assert page.locator("#slider").input_value() == paused_at
        set_slider(page, len(steps) - 1)
        page.set_viewport_size({"width": 390, "height": 844})
        page.wait_for_function("() => document.getElementById('side').getBoundingClientRect()"
                               ".top > document.getElementById('map').getBoundingClientRect().top")
        page.screenshot(path=str(DOCS / "view-phone.png"), full_page=True)


def test_a_run_folder_of_an_earlier_version_opens(mission: tuple[DemoResult, Watched],
                                                 tmp_path: Path) -> None:
    result, _ = mission
    old = tmp_path / "run-old"
    shutil.copytree(result.run.out_dir, old)
    for name in ("config.json", "camera.json", "version.txt", "checkpoint.pkl", "events.jsonl"):
        (old / name).unlink(missing_ok=True)
    steps = [{k: v for k, v in s.items() if k not in ("input", "confirmed_ids", "coasting_ids")}
             for s in read_steps(old)]
    (old / "steps.jsonl").write_text("".join(json.dumps(s) + "\n" for s in steps))
    with serving(old) as url, chromium() as context:
        page = context.new_page()
        page.goto(url)
        page.wait_for_selector(f"body[data-seq='{len(steps)}']", timeout=60_000)
        assert page.locator("#notes").is_visible()
        assert "configuration or camera cannot be read" in page.inner_text("#notes")
        assert _ids(page) == sorted(t.id for t in result.run.tracks)
        set_slider(page, len(steps) // 2)
        assert page.locator("#vehicle-pos").get_attribute("data-x") is not None


def test_replay_with_view_replays_then_serves_the_slider(mission: tuple[DemoResult, Watched],
                                                        tmp_path: Path) -> None:
    result, _ = mission
    run_dir = result.run.out_dir
    err = tmp_path / "stderr.txt"
    with err.open("w") as err_file:
        proc = subprocess.Popen([sys.executable, "-m", "companion", "replay", str(run_dir),
                                 "--recorded-detections", "--out", str(tmp_path / "replay"),
                                 "--view", "--port", "0"],
                                stdout=subprocess.PIPE, stderr=err_file, text=True)
    try:
        assert proc.stdout is not None
        lines = [proc.stdout.readline() for _ in range(2)]
        assert lines[0].startswith("replayed "), [*lines, err.read_text()]
        url = json.loads(lines[1])["url"]
        with chromium() as context:
            page = context.new_page()
            page.goto(url)
            steps = len(read_steps(run_dir))
            page.wait_for_selector(f"body[data-seq='{steps}']", timeout=60_000)
            assert page.locator("#replay").is_visible()
            assert _ids(page) == sorted(t.id for t in result.run.tracks)
    finally:
        proc.terminate()
        proc.wait(10)
    assert (tmp_path / "replay" / "tracks.csv").is_file()
