"""The service configuration: the examples load, every bad key is named, the CLI checks files."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from companion.cli import main
from companion.config import SECTIONS, load_config, parse_config, schema_markdown
from companion.errors import ConfigError

ROOT = Path(__file__).resolve().parent.parent
AREA = [[47.3977420, 8.5455940], [47.3977420, 8.5459914], [47.3979579, 8.5459914],
        [47.3979579, 8.5455940]]


def _minimal(**tables: dict[str, Any]) -> dict[str, Any]:
    data: dict[str, Any] = {"camera": {"source": "0"}, "search": {"area": AREA}}
    for name, table in tables.items():
        data[name] = {**data.get(name, {}), **table}
    return data


def test_shipped_examples_load() -> None:
    real = load_config(ROOT / "systemd" / "companion.toml")
    assert real.vehicle.connection.startswith("serial://")
    assert real.camera.calibration == str(ROOT / "systemd" / "camera.yaml")  # next to the file
    assert not real.mission.auto_arm_takeoff and not real.mission.auto_offboard
    sitl = load_config(ROOT / "sitl" / "service.toml")
    assert sitl.mission.auto_arm_takeoff and sitl.camera.kind == "mjpeg"


def test_defaults_and_derived_values() -> None:
    config = parse_config(_minimal())
    assert config.search.utm_epsg == 32632  # Zurich: zone 32 north
    assert (config.safety.geofence_latlon == config.search.area_latlon).all()
    assert config.mission.setpoint_rate_hz == 10.0 and config.mission.end_action == "land"
    assert config.detector.allowed_ids == () and config.camera.calibration is None
    assert config.filter.motion == "gp"
    south = parse_config(_minimal(search={"area": [[-33.9, 18.4], [-33.9, 18.5], [-33.8, 18.5]]}))
    assert south.search.utm_epsg == 32734


@pytest.mark.parametrize(("tables", "message"), [
    ({"camera": {"source": ""}}, "camera.source: must be a non-empty string"),
    ({"vehicle": {"conection": "x"}}, "vehicle.conection: unknown key (did you mean 'connection'"),
    ({"detector": {"family": "tag99"}}, "detector.family: must be one of"),
    ({"detector": {"allowed_ids": [1, -2]}}, "detector.allowed_ids[1]: must be >= 0"),
    ({"search": {"area": [[47.0, 8.0], [47.1, 8.0]]}}, "search.area: must have at least 3"),
    ({"search": {"area": [[8.5, 147.4], [8.6, 147.4], [8.6, 247.4]]}},
     "search.area: latitudes must be in [-90, 90] and longitudes in [-180, 180]"),
    ({"search": {"utm_epsg": 4326}}, "search.utm_epsg: must be a WGS84 / UTM zone"),
    ({"search": {"altitude_m": 50.0}}, "search.altitude_m: must lie in the safety band"),
    ({"safety": {"min_alt_m": 40.0}}, "safety.max_alt_m: must be above safety.min_alt_m"),
    ({"mission": {"end": "targets"}}, "search.expected_targets: is required when mission.end"),
    ({"mission": {"setpoint_rate_hz": 2.0}}, "mission.setpoint_rate_hz: must be in (2, 50]"),
    ({"filter": {"gp_window": 0}}, "filter.gp_window: must be >= "),
    ({"estimator": {"rate_hz": "fast"}}, "estimator.rate_hz: must be a number"),
])
def test_bad_values_name_the_key(tables: dict[str, dict[str, Any]], message: str) -> None:
    with pytest.raises(ConfigError) as info:
        parse_config(_minimal(**tables))
    assert str(info.value).startswith(message), str(info.value)


def test_unknown_section_and_unreadable_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"^misson: unknown key \(did you mean 'mission'"):
        parse_config({**_minimal(), "misson": {}})
    with pytest.raises(ConfigError, match="no such configuration file"):
        load_config(tmp_path / "missing.toml")
    broken = tmp_path / "broken.toml"
    broken.write_text("[camera\nsource = 0\n")
    with pytest.raises(ConfigError, match="invalid TOML"):
        load_config(broken)


def test_every_key_is_documented() -> None:
    text = schema_markdown()
    for section, keys in SECTIONS.items():
        if section != "filter":
            for key in keys:
                assert f"`{section}.{key.leaf}`" in text
    assert (ROOT / "docs" / "configuration.md").read_text() == text


def test_check_config_command(tmp_path: Path) -> None:
    ok = subprocess.run([sys.executable, "-m", "companion", "check-config",
                         str(ROOT / "sitl" / "service.toml")], capture_output=True, text=True,
                        timeout=60, check=False)
    assert ok.returncode == 0 and ": ok (vehicle udpin://127.0.0.1:14540" in ok.stdout
    bad = tmp_path / "bad.toml"
    bad.write_text('[camera]\nsource = "0"\n[search]\narea = [[47.0, 8.0]]\n')
    done = subprocess.run([sys.executable, "-m", "companion", "check-config", str(bad)],
                          capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 2
    assert done.stderr == "companion: search.area: must have at least 3 [lat, lon] vertices, " \
                          "got 1\n"


def test_check_config_lists_every_error_of_a_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A wrong type, an unknown key and an out-of-range value: all three, in one run, exit 2."""
    bad = tmp_path / "three.toml"
    bad.write_text('[camera]\nsource = "0"\n[search]\narea = ' + repr(AREA) + "\n"
                   'speed_m_s = 99.0\n[detector]\nthreads = "two"\n[mission]\nauto_land = true\n')
    assert main(["check-config", str(bad)]) == 2
    err = capsys.readouterr().err
    assert 'detector.threads: must be an integer, got string "two"' in err
    assert "mission.auto_land: unknown key" in err
    assert "search.speed_m_s: must be " in err and "got 99.0" in err
    assert err.count("\n") == 3, err


def test_every_error_is_reported_within_and_across_tables() -> None:
    with pytest.raises(ConfigError) as info:
        parse_config(_minimal(pose={"max_gap_s": 0, "vertical_std_m": "x"},
                              safety={"min_alt_m": 40.0}, nonsense={}))
    keys = [e.key for e in info.value.errors]
    assert keys == ["nonsense", "pose.vertical_std_m", "pose.max_gap_s", "safety.max_alt_m"]
    assert str(info.value).splitlines() == [str(e) for e in info.value.errors]
    assert str(info.value).startswith(f"{info.value.key}: {info.value.problem}")


def test_a_clearance_no_point_of_the_fence_keeps_is_named_by_its_key() -> None:
    """A plan kept that far inside the fence would have nowhere to fly."""
    config = parse_config(_minimal())
    assert config.safety.fence_clearance_m == 3.0  # the default
    with pytest.raises(ConfigError) as info:
        parse_config(_minimal(safety={"fence_clearance_m": 100.0}))
    assert info.value.key == "safety.fence_clearance_m"
    assert "no point of safety.geofence is that far inside it" in str(info.value)


def test_a_geofence_the_gate_refuses_is_named_by_its_key() -> None:
    """The gate's own reason (a symmetric bow tie has no signed area), under the config's key."""
    bow_tie = [AREA[0], AREA[2], AREA[1], AREA[3]]
    with pytest.raises(ConfigError) as info:
        parse_config(_minimal(safety={"geofence": bow_tie}))
    assert info.value.key == "safety.geofence"
    assert str(info.value) == "safety.geofence: has no area (all vertices on a line)"
