"""The view's data model (pure) and its configuration keys."""

from __future__ import annotations

import base64
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from companion.cli import main
from companion.config import parse_config
from companion.errors import AggregateConfigError, ConfigError
from companion.keys import load_toml
from companion.pipeline import SearchFrame
from companion.sat.filter import SatState
from companion.sat.mixture import Mixture
from companion.sat.tracks import TrackParams, Tracks
from companion.view.model import (
    HISTORY_POINTS,
    MAX_MESSAGE_BYTES,
    PATH_POINTS,
    Status,
    Trails,
    Vehicle,
    encode,
    heat_map,
    scene_message,
    step_message,
    utm_zone_name,
    yaw_deg,
)

ROOT = Path(__file__).resolve().parents[1]


def sitl_data(**view: Any) -> dict[str, Any]:
    data = load_toml(ROOT / "sitl" / "service.toml", "configuration")
    data["view"] = view
    return data


def state_with(weights: list[float], means: list[list[float]], sd_m: float = 1.0) -> SatState:
    n = len(weights)
    mixture = Mixture(np.array(weights), np.array(means, dtype=np.float64),
                      np.tile(np.eye(2) * sd_m**2, (n, 1, 1)), np.full(n, -1, dtype=np.int64))
    return SatState(10.0, mixture, Tracks.empty(2, 30))


def test_view_keys_default_to_a_loopback_page() -> None:
    v = parse_config(sitl_data()).view
    assert (v.enabled, v.bind, v.port, v.token_file, v.max_clients) == (
        True, "127.0.0.1", 8090, None, 8)


@pytest.mark.parametrize("bind", ["0.0.0.0", "192.168.1.20", "::", "drone.local"])
def test_a_page_beyond_loopback_needs_a_token(bind: str) -> None:
    with pytest.raises(ConfigError, match=r"view\.token_file: is required when view\.bind"):
        parse_config(sitl_data(bind=bind))
    assert parse_config(sitl_data(bind=bind, token_file="token")).view.token_file is not None
    assert not parse_config(sitl_data(bind=bind, enabled=False)).view.enabled


@pytest.mark.parametrize(("view", "message"), [
    ({"port": 70000}, "view.port"), ({"max_clients": 0}, "view.max_clients"),
    ({"enabled": "yes"}, "view.enabled"), ({"colour": "red"}, "view.colour"),
])
def test_bad_view_values_name_the_key(view: dict[str, Any], message: str) -> None:
    with pytest.raises((ConfigError, AggregateConfigError), match=message):
        parse_config(sitl_data(**view))


def test_heat_map_peaks_where_the_weight_is() -> None:
    heat = heat_map(state_with([1.0, 0.5], [[5.0, 5.0], [25.0, 15.0]]), 30.0, 20.0, cells=30)
    assert heat is not None
    cells = np.frombuffer(base64.b64decode(heat["cells"]), dtype=np.uint8)
    grid = cells.reshape(heat["ny"], heat["nx"])  # rows from the south
    assert (heat["nx"], heat["ny"]) == (30, 20)
    row, col = (int(i) for i in np.unravel_index(np.argmax(grid), grid.shape))
    assert (row, col) in {(4, 4), (4, 5), (5, 4), (5, 5)}
    assert grid[15, 25] > 100 and grid[15, 10] == 0
    # the nearest cell centres are half a cell (0.5 m) off the mean in x and y
    assert math.isclose(heat["peak"], math.exp(-0.25) / (2 * math.pi), rel_tol=0.01)
    assert heat_map(state_with([], []), 30.0, 20.0) is None


def test_trails_are_bounded_and_keep_what_was_seen() -> None:
    trails = Trails()
    state = state_with([1.0], [[1.0, 1.0]])
    for k in range(PATH_POINTS + 50):
        trails = trails.after(0.5 * k, (0.1 * k, 0.0), np.array([[1.0, 2.0]]),
                              "no frame" if k % 3 == 0 else None, state)
    assert len(trails.path) == PATH_POINTS
    assert trails.path[-1] == (round(0.1 * (PATH_POINTS + 49), 2), 0.0)
    assert len(trails.scans) == 5 and len(trails.blind) == 5
    assert all(reason == "no frame" for _, reason in trails.blind)
    assert all(len(h) <= HISTORY_POINTS for h in trails.history.values())


def test_a_step_message_is_json_with_the_vehicle_and_a_bounded_size() -> None:
    frame = SearchFrame.from_config(parse_config(sitl_data()).search)
    state = state_with([0.9] * 3, [[2.0, 3.0], [10.0, 10.0], [20.0, 5.0]])
    trails = Trails().after(10.0, (4.0, 5.0), np.zeros((0, 2)), None, state)
    message = step_message(7, frame, state, {"t_s": 10.0, "blind": None}, trails, TrackParams(),
                           Vehicle((4.0, 5.0), 90.0, 8.0), Status("searching", True, True,
                                                                   {"steps": 7}, (0.5, 0.5)))
    decoded = json.loads(encode(message))
    assert decoded["vehicle"] == {"x": 4.0, "y": 5.0, "heading_deg": 90.0, "alt_m": 8.0}
    assert decoded["mission"] == "searching" and decoded["home"] == [0.5, 0.5]
    assert len(decoded["components"]) == 3 and decoded["components"][0][5] == 0.9
    assert math.isclose(decoded["expected_targets"], 2.7)
    assert decoded["heat"]["nx"] > 0
    huge = {**message, "path": [[float(k), 0.0] for k in range(100_000)]}
    assert len(encode(huge)) <= MAX_MESSAGE_BYTES
    assert json.loads(encode({**message, "t_s": float("nan")}))["t_s"] is None


def test_scene_has_the_grid_and_its_utm_zone() -> None:
    config = parse_config(sitl_data())
    frame = SearchFrame.from_config(config.search)
    scene = scene_message(frame, config.safety.geofence_latlon, mode="live", rate_hz=2.0,
                          expected_targets=5)
    assert scene["utm_zone"] == "32N" and scene["utm_epsg"] == 32632
    assert scene["geofence"] == scene["area"]  # the SITL's fence is its search area
    assert np.array(scene["area"]).min() == 0.0  # the grid starts at the area's corner
    assert utm_zone_name(32733) == "33S"
    assert yaw_deg((math.cos(math.pi / 4), 0.0, 0.0, math.sin(math.pi / 4))) == pytest.approx(90)


def test_view_of_a_folder_that_is_no_run_is_one_clear_line(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["view", str(tmp_path / "missing")]) == 1
    assert "no such run folder" in capsys.readouterr().err
    assert main(["view", str(tmp_path)]) == 1
    err = capsys.readouterr().err
    assert "not a run folder" in err and "Traceback" not in err
    (tmp_path / "steps.jsonl").write_text("")
    assert main(["view", str(tmp_path)]) == 1
    assert "holds no step" in capsys.readouterr().err
    assert main(["view", str(tmp_path), "--bind", "0.0.0.0"]) == 2
    assert "--token-file" in capsys.readouterr().err


def test_check_config_refuses_a_token_file_others_can_read(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    text = (ROOT / "sitl" / "service.toml").read_text().replace(
        "[view]", '[view]\nbind = "0.0.0.0"\ntoken_file = "view.token"')
    (tmp_path / "service.toml").write_text(text.replace('dir = "../out/sitl"', 'dir = "out"'))
    token = tmp_path / "view.token"
    token.write_text("a-token-long-enough-1234\n")
    token.chmod(0o644)
    assert main(["check-config", str(tmp_path / "service.toml")]) == 2
    assert "view.token_file" in capsys.readouterr().err
    token.chmod(0o600)
    assert main(["check-config", str(tmp_path / "service.toml")]) == 0
