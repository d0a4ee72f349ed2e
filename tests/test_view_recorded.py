"""The replay view of small synthetic run folders: the mission state, link and camera health the
service recorded with each step, folders of earlier versions without them, and the orthophoto
(the run's own, a missing one, one given on the command line)."""

from __future__ import annotations

import json
import subprocess
import sys
import zlib
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from companion.config import ServiceConfig, parse_config
from companion.errors import ConfigError
from companion.pipeline import SearchFrame, camera_model
from companion.replay import replay_run
from companion.run_folder import STEP_STATUS_KEYS, RunFolder, read_config, read_steps
from companion.service import Service
from companion.view.recorded import recorded_view
from tests.orthophotos import ramp, write_geotiff
from tests.test_view_model import ROOT, sitl_data

STATES = ["waiting_for_vehicle", "arming", "taking_off", "searching", "searching", "done"]


def field_geotiff(path: Path, config: ServiceConfig) -> Path:
    """A 1 m ramp GeoTIFF in the run's UTM zone over its search area."""
    frame = SearchFrame.from_config(config.search)
    e, n = frame.to_utm(np.array([frame.world.width_m / 2, frame.world.height_m / 2]))
    return write_geotiff(path, ramp(200, 200), frame.utm.epsg, float(e) - 100.0,
                         float(n) + 100.0, 1.0)


def write_run(run_dir: Path, config: ServiceConfig, *, status: bool = True,
              snapshot: bool = True) -> list[dict[str, Any]]:
    """A run folder of len(STATES) steps flying west to east over the area (no detection), as
    the service writes it (status: with this version's status fields); its step records."""
    folder = RunFolder(run_dir)
    frame = SearchFrame.from_config(config.search)
    if snapshot:
        folder.write_snapshot(config, camera_model(config.camera))
    else:
        (run_dir / "summary.json").write_text(json.dumps({"utm_epsg": frame.utm.epsg}))
    home = frame.to_utm(np.array([2.0, 3.0]))
    records = []
    for k, mission in enumerate(STATES):
        xy = np.array([2.0 + 5.0 * k, frame.world.height_m / 2])
        e, n = frame.to_utm(xy)
        lat, lon = frame.to_latlon(xy[None])[0]
        record: dict[str, Any] = {
            "t_s": 10.0 + k, "blind": None, "detections": 0, "measurements_utm": [],
            "region_utm": None, "vehicle_utm": [[round(float(e), 3), round(float(n), 3)]],
            "r_cov_m2": [], "components": 0, "weight_sum": 0.0, "confirmed": 0,
            "input": {"boot_t_s": 10.0 + k, "pose": [float(lat), float(lon), 500.0, 8.0,
                                                     1.0, 0.0, 0.0, 0.0], "pixels": []}}
        if status:
            record.update({"mission": mission, "link_ok": k != 2, "camera_ok": k != 4,
                           "home_utm": [round(float(home[0]), 3), round(float(home[1]), 3)]})
        folder.write_step(record)
        records.append(record)
    folder.close()
    return records


def _messages(steps: list[bytes]) -> list[dict[str, Any]]:
    return [json.loads(zlib.decompress(s)) for s in steps]


def test_the_replay_view_shows_the_recorded_mission_state(tmp_path: Path) -> None:
    config = parse_config(sitl_data())
    write_run(tmp_path / "run", config)
    view = recorded_view(tmp_path / "run")
    messages = _messages(view.steps)
    assert [m["mission"] for m in messages] == STATES
    assert [m["link_ok"] for m in messages] == [k != 2 for k in range(len(STATES))]
    assert [m["camera_ok"] for m in messages] == [k != 4 for k in range(len(STATES))]
    assert all(m["home"] == [2.0, 3.0] for m in messages)
    assert view.scene["orthophoto"] is None and view.orthophoto is None


def test_a_folder_without_a_configuration_shows_the_recorded_state_too(tmp_path: Path) -> None:
    config = parse_config(sitl_data())
    write_run(tmp_path / "run", config, snapshot=False)
    view = recorded_view(tmp_path / "run")
    assert any("cannot be read" in w for w in view.warnings)
    assert [m["mission"] for m in _messages(view.steps)] == STATES


def test_a_folder_of_an_earlier_version_has_no_status(tmp_path: Path) -> None:
    config = parse_config(sitl_data())
    write_run(tmp_path / "run", config, status=False)
    messages = _messages(recorded_view(tmp_path / "run").steps)
    assert all(m[k] is None for m in messages for k in ("mission", "link_ok", "camera_ok"))
    assert messages[-1]["vehicle"] is not None  # the steps themselves are all there


def test_the_service_records_its_status_with_a_step() -> None:
    service = Service(parse_config(sitl_data()))
    def recorded(t_s: float, blind: str) -> dict[str, object]:
        return service._step_status(service._view_status(service.pipeline.blind(t_s, blind), 0))

    no_frame = recorded(1.0, "no frame")
    assert no_frame == {"mission": "waiting_for_vehicle", "link_ok": False,
                        "camera_ok": False, "home_utm": None}
    assert recorded(2.0, "no pose")["camera_ok"] is True
    assert tuple(no_frame) == STEP_STATUS_KEYS


def test_the_run_s_orthophoto_is_recorded_by_absolute_path_and_shown(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    base = parse_config(sitl_data())
    field_geotiff(tmp_path / "field.tif", base)
    monkeypatch.chdir(tmp_path)
    config = parse_config(sitl_data(orthophoto="field.tif"))  # relative to the working folder
    write_run(tmp_path / "run", config)
    assert read_config(tmp_path / "run").view.orthophoto == str(tmp_path / "field.tif")
    monkeypatch.chdir(ROOT)
    view = recorded_view(tmp_path / "run")
    assert view.orthophoto is not None and view.warnings == []
    assert view.scene["orthophoto"]["bounds"] == view.orthophoto.scene()["bounds"]
    assert view.scene["orthophoto"]["url"] == "api/orthophoto.png"
    (tmp_path / "field.tif").unlink()  # the folder on another laptop, without the file
    view = recorded_view(tmp_path / "run")
    assert view.orthophoto is None and view.scene["orthophoto"] is None
    assert any("orthophoto is not shown" in n and "no such file" in n
               for n in view.scene["notes"])


def test_a_bad_orthophoto_given_is_an_error_naming_the_flag(tmp_path: Path) -> None:
    config = parse_config(sitl_data())
    write_run(tmp_path / "run", config)
    with pytest.raises(ConfigError, match=r"^--orthophoto: .*nothing\.tif: no such file"):
        recorded_view(tmp_path / "run", orthophoto=tmp_path / "nothing.tif")
    good = field_geotiff(tmp_path / "given.tif", config)
    view = recorded_view(tmp_path / "run", orthophoto=good)
    assert view.orthophoto is not None and view.orthophoto.name == "given.tif"
    done = subprocess.run([sys.executable, "-m", "companion", "view", str(tmp_path / "run"),
                           "--port", "0", "--orthophoto", str(tmp_path / "nothing.tif")],
                          capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 2, done.stderr
    assert "--orthophoto" in done.stderr and "no such file" in done.stderr
    assert "Traceback" not in done.stderr


def test_check_config_reads_the_orthophoto(tmp_path: Path) -> None:
    config = parse_config(sitl_data())
    field_geotiff(tmp_path / "field.tif", config)
    data = sitl_data(orthophoto="field.tif")
    data["output"] = {"dir": str(tmp_path / "runs")}
    for name, ortho in (("good", "field.tif"), ("bad", "missing.tif")):
        data["view"] = {"orthophoto": ortho}
        path = tmp_path / f"{name}.json"
        path.write_text(json.dumps(data, default=lambda a: a.tolist()))
        done = subprocess.run([sys.executable, "-m", "companion", "check-config", str(path)],
                              capture_output=True, text=True, timeout=120, check=False)
        if name == "good":
            assert done.returncode == 0, done.stderr
            assert "orthophoto field.tif of" in done.stdout
        else:
            assert done.returncode == 2
            assert f"view.orthophoto: {tmp_path / 'missing.tif'}: no such file" in done.stderr
            assert "Traceback" not in done.stderr


def test_a_replay_of_a_run_folder_keeps_the_recorded_status(tmp_path: Path) -> None:
    config = parse_config(sitl_data())
    live = write_run(tmp_path / "run", config)
    replay_run(tmp_path / "run", tmp_path / "replayed", redetect=False)
    steps = read_steps(tmp_path / "replayed")
    assert [{k: s[k] for k in STEP_STATUS_KEYS} for s in steps] == [
        {k: r[k] for k in STEP_STATUS_KEYS} for r in live]
    view = recorded_view(tmp_path / "replayed", config, camera_model(config.camera))
    assert [m["mission"] for m in _messages(view.steps)] == STATES
