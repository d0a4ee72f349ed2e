"""Run folders: a new folder per start (suffixed within a second), compact flushed JSON lines,
a torn last line read with a warning and a bad line inside refused, the reports written with
or without plots."""

from __future__ import annotations

import json
import sys
from datetime import UTC, datetime
from pathlib import Path

import pytest

from companion.errors import CompanionError, InputError
from companion.report import TrackRecord
from companion.run_folder import (
    RunFolder,
    new_run_dir,
    read_camera,
    read_config,
    read_records,
    read_steps,
)

NOW = datetime(2026, 5, 4, 3, 2, 1, tzinfo=UTC)


def test_a_second_run_in_the_same_second_gets_a_suffix(tmp_path: Path) -> None:
    first, second = new_run_dir(tmp_path, NOW), new_run_dir(tmp_path, NOW)
    assert first.name == "run-20260504T030201Z" and second.name == "run-20260504T030201Z-2"
    assert first.is_dir() and second.is_dir()


def test_steps_and_events_are_compact_lines_readable_before_close(tmp_path: Path) -> None:
    folder = RunFolder.create(tmp_path, NOW)
    folder.write_step({"t_s": 1.0, "blind": None})
    folder.write_event({"t_s": 0.5, "event": "start"})
    assert (folder.path / "steps.jsonl").read_text() == '{"t_s":1.0,"blind":null}\n'
    assert (folder.path / "events.jsonl").read_text() == '{"t_s":0.5,"event":"start"}\n'
    folder.close()
    assert read_steps(folder.path) == [{"t_s": 1.0, "blind": None}]


def test_a_replay_folder_has_no_events_and_starts_its_steps_afresh(tmp_path: Path) -> None:
    (tmp_path / "steps.jsonl").write_text('{"old":1}\n')
    folder = RunFolder(tmp_path)
    folder.write_event({"event": "dropped"})
    folder.write_step({"new": 1})
    folder.close()
    assert read_steps(tmp_path) == [{"new": 1}] and not (tmp_path / "events.jsonl").exists()


def test_a_torn_last_line_ends_the_records_with_a_warning(tmp_path: Path) -> None:
    path = tmp_path / "steps.jsonl"
    path.write_text('{"a":1}\n{"a":2}\n{"a":')
    warnings: list[str] = []
    assert list(read_records(path, warnings)) == [{"a": 1}, {"a": 2}]
    assert warnings == ["steps.jsonl: line 3 is cut short (a crash?): replayed up to line 2"]
    path.write_text('{"a":1}\n{"a":\n{"a":3}\n')
    with pytest.raises(InputError, match="line 2 is not JSON"):
        list(read_records(path, []))


def _track() -> TrackRecord:
    return TrackRecord(id=7, lat_deg=47.0, lon_deg=8.0, easting_m=1.0, northing_m=2.0,
                       utm_epsg=32632, cov_ee_m2=0.1, cov_en_m2=0.0, cov_nn_m2=0.2,
                       first_seen_s=1.0, last_seen_s=2.0, last_detected_s=2.0, coasting=False)


def test_reports_without_plots(tmp_path: Path) -> None:
    folder = RunFolder(tmp_path)
    folder.close()
    folder.write_reports([_track()], {"confirmed": 1}, plots=False)
    assert json.loads((tmp_path / "summary.json").read_text()) == {"confirmed": 1}
    assert (tmp_path / "tracks.csv").read_text().splitlines()[1].startswith("7,")
    assert json.loads((tmp_path / "tracks.geojson").read_text())["features"][0][
        "geometry"]["coordinates"] == [8.0, 47.0]
    assert not list(tmp_path.glob("*.png"))


def test_plots_that_cannot_be_drawn_are_reported_or_raised(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    folder = RunFolder(tmp_path)
    folder.close()
    skipped: list[str] = []
    folder.write_reports([], {"confirmed": 0}, plots=True, on_plots_skipped=skipped.append)
    assert skipped and "matplotlib" in skipped[0] and (tmp_path / "summary.json").is_file()
    with pytest.raises(CompanionError, match="matplotlib"):
        folder.write_reports([], {"confirmed": 0}, plots=True)


def test_the_snapshot_reads_back_as_the_configuration_and_camera(tmp_path: Path) -> None:
    from companion.config import load_config  # noqa: PLC0415
    from companion.pipeline import camera_model  # noqa: PLC0415

    config = load_config(Path(__file__).resolve().parent.parent / "sitl" / "service.toml")
    camera = camera_model(config.camera)
    folder = RunFolder(tmp_path)
    folder.write_snapshot(config, camera)
    folder.close()
    assert read_camera(tmp_path) == camera
    assert read_config(tmp_path).data == config.data
    assert (tmp_path / "version.txt").read_text().startswith("companion ")
    (tmp_path / "camera.json").write_text('{"nope": 1}')
    with pytest.raises(InputError, match="not a camera model"):
        read_camera(tmp_path)
