"""The service flies SITL missions over the real MAVSDK: targets, geofence, pilot, camera."""

from __future__ import annotations

import asyncio
import dataclasses
import json
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pytest
from numpy.typing import ArrayLike
from pymavlink import mavutil

from companion.mission import TAKEOFF_REACHED_M
from companion.sat.filter import FilterKind
from companion.sim.scenario import Scenario, load_scenario
from sitl.cli import sitl_scenarios
from sitl.demo import FENCE_MARGIN_M, DemoResult, fly
from sitl.figures import record_figure
from sitl.modes import Behaviour
from sitl.runner import Sitl, autopilot_config

pytestmark = pytest.mark.sitl

SPEEDUP = 4.0
HEARTBEAT_PERIOD_S = 1.0  # the mode reaches the service in the autopilot's heartbeat
SITL_LATE_S = 0.1  # how late the SITL autopilot's loop may send what is due, on a loaded machine
WALKER_GAP_M = 5.0  # how far a walker's confirmation may lie from it (see the walkers mission)


def _scenario(flavour: Literal["px4", "ardupilot"] = "px4") -> Scenario:
    s = load_scenario(sitl_scenarios()["field-5-tags"])
    return dataclasses.replace(s, vehicle=dataclasses.replace(s.vehicle, flavour=flavour))


def _lines(path: Path) -> list[dict[str, Any]]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def _fly(scenario: Scenario, tmp_path: Path, **kwargs: Any) -> DemoResult:
    return asyncio.run(fly(scenario, speedup=SPEEDUP, out_dir=tmp_path, **kwargs))


def _assert_every_tag_found(result: DemoResult) -> None:
    """The mission ended, every tag has a track within 1 m, and no track is far from every tag."""
    assert result.run.mission_state == "done"
    assert result.score.missed == 0, result.score.errors_m
    assert np.all(result.score.errors_m < 1.0), result.score.errors_m
    gaps = np.linalg.norm(result.tracks_xy_m[:, None] - result.truth_xy_m[None], axis=2)
    assert np.all(gaps.min(axis=1) <= 3.0)  # no confirmed track far from every target


def _assert_inside_the_fence(scenario: Scenario, setpoints: list[dict[str, Any]],
                             flavour: Literal["px4", "ardupilot"]) -> None:
    """Every setpoint sent, in the autopilot's local frame, lies inside the geofence: the search
    area grown by FENCE_MARGIN_M, checked in the world frame the scenario defines."""
    config = autopilot_config(scenario)
    origin_ne = np.array(config.home_ned) + (
        np.array(config.ekf_origin_offset_ned) if flavour == "ardupilot" else 0.0)
    world_ne = np.array([[e["north_m"], e["east_m"]] for e in setpoints]) + origin_ne
    w_m, h_m = scenario.world.size_m
    margin = FENCE_MARGIN_M + 1e-6
    assert np.all((world_ne[:, 0] >= -margin) & (world_ne[:, 0] <= h_m + margin))
    assert np.all((world_ne[:, 1] >= -margin) & (world_ne[:, 1] <= w_m + margin))


def _assert_let_go_at_once(events: list[dict[str, Any]], reported_s: float,
                           released_s: float) -> None:
    """The service let go (released_s) on the first heartbeat that reported the pilot's mode
    (reported_s, the autopilot's clock) and at once: no setpoint after the mode it saw but the
    one that may have been on its way.

    Counted in setpoints, not seconds: at 4x a 110 ms stall of this 2-core machine is 0.44 s of
    the run's clock, and the service's loop stalls with the rest of it."""
    assert 0.0 <= released_s - reported_s < HEARTBEAT_PERIOD_S
    seen = [e for e in events if e["event"] == "mode" and e["t_s"] <= released_s][-1]
    assert seen["mode"] != "OFFBOARD"
    late = [e for e in events if e["event"] == "setpoint" and seen["t_s"] <= e["t_s"] <= released_s]
    assert len(late) <= 1, late


@pytest.mark.parametrize("flavour", ["px4", "ardupilot"])
def test_field_experiment_mission(flavour: Literal["px4", "ardupilot"], tmp_path: Path) -> None:
    scenario = _scenario(flavour)
    result = _fly(scenario, tmp_path)
    _assert_every_tag_found(result)
    assert not result.autopilot.armed and result.autopilot.vehicle.on_ground  # it landed

    setpoints = [e for e in _lines(result.run.out_dir / "events.jsonl")
                 if e["event"] == "setpoint"]
    assert len(setpoints) > 500
    _assert_inside_the_fence(scenario, setpoints, flavour)
    altitudes = -np.array([e["down_m"] for e in setpoints])
    assert np.all((altitudes >= 3.0 - 1e-6) & (altitudes <= 15.0 + 1e-6))  # the safety band

    # As the firmware does it: ArduPilot's GUIDED take-off (MAVSDK's "OFFBOARD" before "in
    # air") ends in the search with no mode request and no setpoint during the climb; PX4's
    # transient arm refusals are outlasted.
    events = _lines(result.run.out_dir / "events.jsonl")
    texts = [e["text"] for e in events if e["event"] == "command" and e["kind"] == "statustext"]
    commands = [e["kind"] for e in events if e["event"] == "command"]
    assert not [e for e in setpoints if e["mode"] in ("arming", "taking_off")]
    if flavour == "ardupilot":
        assert "airborne in guided: searching" in texts and "start_offboard" not in commands
    else:
        # each refused arm (none when the service was healthy after the warm-up) asked again
        refused = [e for e in events if e["event"] == "command_failed" and e["kind"] == "arm"]
        assert commands.count("arm") == len(refused) + 1
        assert commands.count("start_offboard") == 1
    # Airborne means at the take-off altitude: the first setpoint holds the vehicle there.
    assert altitudes[0] >= scenario.vehicle.altitude_m - TAKEOFF_REACHED_M - 0.1

    steps = _lines(result.run.out_dir / "steps.jsonl")
    assert sum(s["blind"] is None for s in steps) > 100
    # Once down after the search, every step is blind: a camera at rest near the ground (its
    # altitude drifting a metre above it) would count misses in view against the tags.
    first_seen = next(i for i, s in enumerate(steps) if s["blind"] is None)
    down = next(i for i in range(first_seen, len(steps)) if steps[i]["blind"] == "on the ground")
    assert all(s["blind"] == "on the ground" for s in steps[down:])
    geojson = json.loads((result.run.out_dir / "tracks.geojson").read_text())
    assert len(geojson["features"]) == len(result.run.tracks) == 5

    # The MAVLink traffic the service saw, as a .tlog that pymavlink reads back.
    log = mavutil.mavlink_connection(str(result.run.out_dir / "flight.tlog"))
    kinds: dict[str, int] = {}
    while (msg := log.recv_match()) is not None:
        kinds[msg.get_type()] = kinds.get(msg.get_type(), 0) + 1
    log.close()
    assert kinds.get("BAD_DATA", 0) == 0
    assert kinds["HEARTBEAT"] > 20 and kinds["GLOBAL_POSITION_INT"] > 500


def test_a_fence_along_the_search_area_is_flown_without_the_gate_moving_a_setpoint(
        tmp_path: Path) -> None:
    """safety.geofence at its default, the search area itself: the lanes keep
    safety.fence_clearance_m inside it and the setpoints ramp within the speed limits, so the
    gate moves none but while the vehicle, at home on the area's corner, is just outside it."""
    scenario = _scenario("px4")
    w, h = scenario.world.size_m
    north, east = np.array([0.0, 0.0, h, h]), np.array([0.0, w, w, 0.0])
    lat, lon, _ = scenario.geo.local_ned().ned_to_geodetic(north, east, np.zeros(4))
    area = np.column_stack([lat, lon]).tolist()
    result = _fly(scenario, tmp_path, safety={"geofence": area})
    _assert_every_tag_found(result)
    events = _lines(result.run.out_dir / "events.jsonl")
    moved = [e["reasons"] for e in events if e["event"] == "gate"]
    assert all(any(r.startswith("vehicle ") and "outside geofence" in r for r in rs)
               for rs in moved), moved
    assert result.run.counters["setpoints_clamped"] < 0.02 * result.run.counters["setpoints"]


def test_field_experiment_mission_with_the_lmb(tmp_path: Path) -> None:
    """The field experiment flown by the service with filter.kind = "lmb"."""
    s = _scenario("px4")
    scenario = dataclasses.replace(s, filter=dataclasses.replace(s.filter, kind=FilterKind.LMB))
    result = _fly(scenario, tmp_path)
    _assert_every_tag_found(result)
    assert 5 <= len(result.run.tracks) <= 6  # one duplicate near a tag in 1 of 3 runs
    config = json.loads((result.run.out_dir / "config.json").read_text())
    assert config["filter"]["kind"] == "lmb"
    steps = _lines(result.run.out_dir / "steps.jsonl")
    assert steps and all("confirmed" in s for s in steps)


def test_pilot_takeover_stops_commanding_and_estimating_goes_on(tmp_path: Path) -> None:
    takeover_s = 70.0
    result = _fly(_scenario(), tmp_path, faults=f"pilot@{takeover_s:g}:posctl",
                  stop_after_s=takeover_s + 25.0, mission={"resume_on_pilot_offboard": False})
    events = _lines(result.run.out_dir / "events.jsonl")
    released = [e for e in events if e["event"] == "command" and e["kind"] == "stop_setpoints"]
    assert len(released) == 1
    snap = result.autopilot
    reported_s = snap.behaviour_reported_clock_s
    assert reported_s is not None
    assert takeover_s <= reported_s <= takeover_s + HEARTBEAT_PERIOD_S + SITL_LATE_S
    release_s = released[0]["t_s"] - reported_s
    record_figure("fault-pilot-mode", release_after_heartbeat_s=round(release_s, 3),
                  release_after_switch_s=round(released[0]["t_s"] - takeover_s, 3),
                  autopilot=snap.behaviour.value, state=result.run.mission_state)
    _assert_let_go_at_once(events, reported_s, released[0]["t_s"])
    assert not [e for e in events if e["event"] == "setpoint" and e["t_s"] > released[0]["t_s"]]
    assert snap.behaviour is Behaviour.POSITION  # never taken back
    assert result.run.mission_state == "pilot_has_control"
    assert not [e for e in events if e["event"] == "command" and e["kind"] == "start_offboard"
                and e["t_s"] > takeover_s]
    steps = _lines(result.run.out_dir / "steps.jsonl")
    seeing = [s for s in steps if s["t_s"] > released[0]["t_s"] + 1.0 and s["blind"] is None]
    assert len(seeing) > 30  # still estimating from the camera while the pilot flies


@pytest.mark.parametrize(("mode", "at_s", "phase"), [
    ("hold", 44.0, "taking_off"), ("land", 70.0, "searching")], ids=["loiter-takeoff",
                                                                  "land-search"])
def test_ardupilot_pilot_mode_is_never_overridden(mode: str, at_s: float, phase: str,
                                                   tmp_path: Path) -> None:
    """A pilot's LOITER in ArduPilot's GUIDED take-off, or LAND mid-search: the service never
    asks for a mode, arms or takes off after it, and its planner setpoints stop at once."""
    result = _fly(_scenario("ardupilot"), tmp_path, faults=f"pilot@{at_s:g}:{mode}",
                  stop_after_s=at_s + 30.0)
    events = _lines(result.run.out_dir / "events.jsonl")
    states = [e["text"] for e in events if e["event"] == "command" and e["kind"] == "statustext"]
    takeover = next(e for e in events if e["event"] == "command" and e["kind"] == "statustext"
                    and e["text"].endswith("pilot has control"))
    if phase == "taking_off":
        assert "airborne in guided: searching" not in states  # still climbing when it came
    else:
        assert "airborne in guided: searching" in states
    after = [e for e in events if e["t_s"] >= takeover["t_s"]]
    assert not [e for e in after if e["event"] == "command" and e["kind"] in (
        "arm", "takeoff", "start_offboard", "hold", "land", "rtl")]
    planner = [e for e in after if e["event"] == "setpoint" and e["mode"] == "searching"]
    assert not planner
    snap = result.autopilot
    assert snap.behaviour is Behaviour(mode)  # never taken back
    assert snap.behaviour_reported_clock_s is not None
    _assert_let_go_at_once(events, snap.behaviour_reported_clock_s, takeover["t_s"])
    assert result.run.mission_state == "pilot_has_control"


def test_a_black_camera_loses_no_confirmed_track(tmp_path: Path) -> None:
    """Also: kept frames stop at their disk budget, and old runs make room for the new one."""
    for day in (1, 2):  # two old runs of 2 MB each; all runs may take 3 MB
        old = tmp_path / f"run-200001{day:02d}T000000Z"
        old.mkdir()
        (old / "steps.jsonl").write_bytes(bytes(2_000_000))
    black_s, black_for_s = 90.0, 10.0
    result = _fly(_scenario(), tmp_path, faults=f"black@{black_s:g}+{black_for_s:g}",
                  stop_after_s=black_s + black_for_s + 10.0,
                  output={"frames": "jpg", "frames_budget_mb": 1.0, "max_runs_mb": 3.0})
    logged = [e["message"] for e in _lines(result.run.out_dir / "events.jsonl")
              if e["event"] == "log"]
    assert logged[0] == ("runs: removed run-20000101T000000Z (2.0 MB) to keep the runs under "
                         "3 MB and 500 MB free")
    assert not (tmp_path / "run-20000101T000000Z").exists()
    assert (tmp_path / "run-20000102T000000Z").exists()
    stopped = [m for m in logged if m.startswith("frames: no longer kept")]
    assert stopped == [stopped[0]] and "the budget of 1.0 MB is reached" in stopped[0]
    kept = sorted((result.run.out_dir / "frames").glob("*.jpg"))
    assert 3 < len(kept) == result.run.counters["frames_kept"]
    assert sum(f.stat().st_size for f in kept) <= 1_000_000
    steps = _lines(result.run.out_dir / "steps.jsonl")
    before = [s for s in steps if s["t_s"] < black_s]
    during = [s for s in steps if black_s + 0.5 < s["t_s"] < black_s + black_for_s]
    after = [s for s in steps if s["t_s"] > black_s + black_for_s + 0.5]
    confirmed_before = set(before[-1]["confirmed_ids"])
    assert len(confirmed_before) >= 2
    assert during and all(s["blind"] == "blank frame" for s in during)
    assert all(confirmed_before <= set(s["confirmed_ids"]) for s in during + after)


def test_moving_targets_are_followed(tmp_path: Path) -> None:
    # After two passes the lawn mower ends over the middle of the yard, where the vehicle holds
    # and keeps tracking what it sees.
    scenario = load_scenario(sitl_scenarios()["moving-5-targets"])
    result = _fly(scenario, tmp_path, stop_after_s=100.0, mission={"end_action": "hold"})
    assert result.run.mission_state == "done"
    assert result.score.missed == 0, result.score.errors_m
    assert np.all(result.score.errors_m < 2.0), result.score.errors_m


def _frame_xy(result: DemoResult, lat_deg: ArrayLike, lon_deg: ArrayLike) -> np.ndarray:
    """(n, 2) search-frame points of WGS84 ones."""
    easting, northing = result.frame.utm.geodetic_to_utm(lat_deg, lon_deg)
    return result.frame.from_utm(np.column_stack([easting, northing]))


def test_the_search_track_planner_finds_every_walker_in_the_walkers_mission(
        tmp_path: Path) -> None:
    """walkers-6-targets: six walkers at 0.5 m/s among decoys in 60 m x 40 m, a camera that sees
    a sixth of it, the search-and-track planner. Every walker is confirmed, each where it was
    then, and nothing else is; the mission ends by the planner's stop rule or the time limit and
    lands; no setpoint leaves the fence or needs the gate."""
    scenario = load_scenario(sitl_scenarios()["walkers-6-targets"])
    assert scenario.robot.planner.value == "search-track"
    sitls: list[Sitl] = []
    result = _fly(scenario, tmp_path, on_sitl=sitls.append)
    assert result.run.mission_state == "done"
    config_data = json.loads((result.run.out_dir / "config.json").read_text())
    assert config_data["search"]["expected_targets"] == 6  # robot.unseen_targets
    events = _lines(result.run.out_dir / "events.jsonl")
    texts = [e["text"] for e in events if e["event"] == "command" and e["kind"] == "statustext"]
    # The stop rule usually ends the search first (at 359 s of the 600 s limit in one run); how
    # fast the walkers are found again decides it, so either end is a pass here.
    assert {"area covered 1x: land", "time limit reached: land"} & set(texts), texts

    # Each confirmation (a "target" event, where the new track was) against the walkers then,
    # converted as the service converts: scenario NED -> WGS84 -> its search frame. A walker's
    # detections carry the PX4 estimate's errors this mission flies (heading 1.5, attitude 1
    # degree, height 0.5 m, correlated for tens of seconds): at the image's edge they move a walker
    # 1.5 to 2.6 m for seconds at a time (measured in this mission's steps), and a track confirmed
    # on a few such looks, or between two walkers a few metres apart, carries that. Within 5 m is
    # a walker's; four fifths of the field, where a decoy confirmed on its own would most likely
    # lie, is farther than that from every walker. The goal allows one confirmed track near
    # no walker: 2.5 m was the largest gap in 7 local flights (121 confirmations; 2.8 m in 3 more
    # with the GP of the walkers' own class), and one CI run had one confirmation 5.2 m from the
    # nearest walker (and 18 m or more from the others).
    ned = scenario.geo.local_ned()
    confirmed = [e for e in events if e["event"] == "target"]
    walkers_found: set[int] = set()
    off_walkers = []
    for e in confirmed:
        ids, xy = sitls[0].world.positions_xy(e["t_s"])
        lat, lon, _ = ned.ned_to_geodetic(xy[:, 1], xy[:, 0], np.zeros(len(ids)))
        gaps = np.hypot(*(_frame_xy(result, lat, lon)
                          - _frame_xy(result, e["lat_deg"], e["lon_deg"])).T)
        if gaps.min() <= WALKER_GAP_M:
            walkers_found.add(int(ids[np.argmin(gaps)]))
        else:
            off_walkers.append((e, gaps))
    assert len(off_walkers) <= 1, off_walkers  # walkers, not decoys
    assert walkers_found == set(range(scenario.targets.count))

    counters = json.loads((result.run.out_dir / "summary.json").read_text())["counters"]
    assert counters["setpoints_clamped"] == counters["setpoints_refused"] == 0
    _assert_inside_the_fence(scenario, [e for e in events if e["event"] == "setpoint"],
                             scenario.vehicle.flavour)
