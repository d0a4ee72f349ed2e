"""The SITL mission as a whole: world, fault plans, the rendered camera stream and the command."""

from __future__ import annotations

import dataclasses
import math
import subprocess
import sys
import time
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.errors import ConfigError
from companion.sim.scenario import Scenario, load_scenario
from companion.vision.camera import BodyPose, ground_footprint, project_points
from companion.vision.tags import TagDetector, detect_centres
from sitl.cli import sitl_scenarios
from sitl.faults import FaultEvent, FaultKind, parse_faults
from sitl.modes import Behaviour, Flavour, encode
from sitl.runner import Sitl
from sitl.stream import MjpegReader
from sitl.world import TargetWorld, clutter_tags
from tests.mavlink_client import Client

pytestmark = pytest.mark.sitl

SPEEDUP = 4.0


def _scenario(name: str, **vehicle: Any) -> Scenario:
    s = load_scenario(sitl_scenarios()[name])
    return dataclasses.replace(s, vehicle=dataclasses.replace(s.vehicle, **vehicle))


# --------------------------------------------------------------------------- fault plans


def test_fault_plan_parses_steady_and_timed_faults() -> None:
    plan = parse_faults("loss=5, latency=0.05,drop=10,cut@60+10,freeze@30+5,gps@120+20:5/-2,"
                        "battery@300:15,pilot@200:posctl,reboot@400+3")
    assert (plan.loss_to_autopilot, plan.loss_from_autopilot) == (0.05, 0.05)
    assert (plan.latency_s, plan.frame_drop) == (0.05, 0.1)
    assert [e.kind for e in plan.events] == ["freeze", "cut", "gps", "pilot", "battery",
                                             "reboot"]
    assert plan.events[2].gps_offset_ne_m() == (5.0, -2.0)
    assert plan.camera_fault(32.0) == "freeze" and plan.camera_fault(35.0) is None
    assert parse_faults("loss=2/10").loss_from_autopilot == pytest.approx(0.1)
    assert parse_faults("") == parse_faults(" , ")


@pytest.mark.parametrize(("spec", "message"), [
    ("loss=150", "--faults: 'loss=150': loss must be a number in [0, 100], got '150'"),
    ("speed=3", "--faults: 'speed=3': unknown steady fault 'speed' (known: loss, latency, drop)"),
    ("cut@60", "--faults: 'cut@60': write cut@T+D"),
    ("battery@10+5:20", "--faults: 'battery@10+5:20': write battery@T:P"),
    ("gps@1+2", "--faults: 'gps@1+2': gps takes the argument :N/E"),
    ("pilot@5:offboard", "--faults: 'pilot@5:offboard': the pilot action must be one of posctl, "
                         "altctl, manual, hold, land, rtl, arm, disarm, got 'offboard'"),
    ("freeze@-1+2", "--faults: 'freeze@-1+2': the start time T (seconds) must be a number >= 0, "
                    "got '-1'"),
    ("explode", "--faults: 'explode': not a fault; write NAME=VALUE or KIND@T[+D][:ARG]"),
])
def test_bad_fault_plans_name_the_item(spec: str, message: str) -> None:
    with pytest.raises(ConfigError) as info:
        parse_faults(spec)
    assert str(info.value) == message


# --------------------------------------------------------------------------- the world


def test_world_tags_are_the_scenario_targets_and_move_continuously() -> None:
    field = TargetWorld(_scenario("field-5-tags"), np.random.default_rng(0))
    tags = field.tags(12.3)
    assert [t.tag_id for t in tags] == [0, 1, 2, 3, 4]
    assert [(t.east_m, t.north_m) for t in tags] == [(5.0, 4.0), (22.0, 6.0), (14.0, 12.0),
                                                    (6.0, 19.0), (25.0, 20.0)]
    moving = _scenario("moving-5-targets")
    world = TargetWorld(moving, np.random.default_rng(0))
    times = np.arange(0.0, 300.0, 0.1)
    tracks = np.array([world.positions_xy(t)[1] for t in times])  # (time, target, xy)
    speeds = np.linalg.norm(np.diff(tracks, axis=0), axis=2) / 0.1
    assert speeds.max() <= moving.targets.speed_m_s * (1 + 1e-9)
    assert np.median(speeds) == pytest.approx(moving.targets.speed_m_s)
    assert (tracks >= 0.0).all() and (tracks <= 60.0).all()


def test_clutter_tags_fall_in_the_footprint_with_ids_above_the_targets() -> None:
    s = _scenario("field-5-tags")
    pose = BodyPose.from_euler(0.0, 10.0, 10.0, -8.0, yaw_rad=0.4)
    rng = np.random.default_rng(5)
    tags = [t for _ in range(200) for t in clutter_tags(s.camera, pose, 5, 0.5, 0.5, 0.5, rng)]
    assert 150 < len(tags) < 250  # 0.5 + 0.5 per frame
    assert all(5 <= t.tag_id < 587 for t in tags)
    ne = np.array([[t.north_m, t.east_m] for t in tags])
    pixels, in_front = project_points(s.camera, pose, np.column_stack([ne, np.zeros(len(ne))]))
    assert in_front.all()
    assert (pixels >= -0.5).all() and (pixels[:, 0] <= 639.5).all()
    assert (pixels[:, 1] <= 479.5).all()
    footprint = ground_footprint(s.camera, pose)
    assert ne[:, 0].min() >= footprint[:, 0].min() - 1e-9


# --------------------------------------------------------------------------- the mission


# The telemetry equals the truth: what the camera shows is where the telemetry says.
PERFECT_POSE = {"heading_error_deg": 0.0, "attitude_error_deg": 0.0, "position_error_m": 0.0,
                "height_error_m": 0.0}


@pytest.fixture
def field(client: Client) -> Iterator[Sitl]:
    scenario = _scenario("field-5-tags", armable_after_s=0.0, **PERFECT_POSE)
    with Sitl(scenario, speedup=SPEEDUP, mavlink_port=client.port) as sitl:
        client.wait_type("HEARTBEAT")
        yield sitl


def _take_off_to(client: Client, ned: tuple[float, float, float]) -> mavlink.MAVLink_message:
    assert client.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1).result == 0
    client.stream_setpoints(ned, 0.3)
    assert client.set_px4_mode(encode(Flavour.PX4, Behaviour.OFFBOARD)) == 0
    return client.fly_to(ned, 0.1, 20.0)


def _frames_after(frames: Iterator[tuple[np.ndarray, float]], t_s: float, n: int
                  ) -> list[tuple[np.ndarray, float]]:
    """The next n frames captured after t_s (one stream: each iter(reader) reconnects)."""
    out = []
    for image, capture_s in frames:
        if capture_s > t_s:
            out.append((image, capture_s))
            if len(out) == n:
                break
    return out


def test_camera_sees_the_tag_below_where_the_telemetry_says(field: Sitl, client: Client
                                                           ) -> None:
    # Tag 2 lies at x 14, y 12: north 12, east 14 of the corner, which is home.
    hover = _take_off_to(client, (12.0, 14.0, -8.0))
    attitude = client.wait_type("ATTITUDE_QUATERNION")
    pose = BodyPose(hover.time_boot_ms / 1e3, hover.x, hover.y, hover.z,
                    (attitude.q1, attitude.q2, attitude.q3, attitude.q4))
    detector = TagDetector(families="tag36h11", quad_decimate=1.0)
    tag = field.world.tags(0.0)[2]
    expected, _ = project_points(field.scenario.camera, pose,
                                 np.array([[tag.north_m, tag.east_m, 0.0]]))
    with MjpegReader(field.camera_url) as reader:
        frames = _frames_after(iter(reader), hover.time_boot_ms / 1e3, 5)
    boot_time_now_s = field.autopilot.snapshot().t_s
    seen = 0
    for image, capture_s in frames:
        # Stamped on the autopilot's boot time: after the hover report, not after now.
        assert hover.time_boot_ms / 1e3 < capture_s <= boot_time_now_s + 1e-6  # sent in µs
        ids, centres = detect_centres(detector, image)
        assert all(i == 2 or i >= 5 for i in ids)  # the one below, or clutter
        if 2 in ids:
            seen += 1
            assert np.linalg.norm(centres[ids == 2][0] - expected[0]) < 3.0
    assert seen >= 4  # p_detect 0.98 per frame


def test_camera_faults_freeze_black_drop_and_corrupt(field: Sitl) -> None:
    with MjpegReader(field.camera_url) as reader:
        frames = iter(reader)
        next(frames)
        field.inject(FaultKind.FREEZE, 1.0)
        frozen = [next(frames) for _ in range(3)]
        assert all(np.array_equal(frozen[0][0], image) for image, _ in frozen[1:])
        assert [t for _, t in frozen] == sorted({t for _, t in frozen})  # new time stamps
        field.inject(FaultKind.BLACK, 1.0)
        assert _frames_after(frames, field.clock.now_s() - 1e9, 1)  # drain what was queued
        black = [image for image, _ in _frames_after(frames, 0.0, 12)]
        assert any(image.max() == 0 for image in black)
        start_s = field.autopilot.snapshot().t_s
        field.inject(FaultKind.DROP, 2.0)
        gaps = np.diff([t for _, t in _frames_after(frames, start_s, 3)])
        _, last_s = next(frames)
        assert last_s - start_s > 1.9 or gaps.max() > 1.9  # two seconds without a frame
        field.inject(FaultKind.CORRUPT, 2.0)
        deadline = time.monotonic() + 2.0 / SPEEDUP + 2.0
        while reader.corrupt_frames == 0 and time.monotonic() < deadline:
            next(frames)
        assert reader.corrupt_frames > 0
    assert field.frames.dropped >= 15


def test_scheduled_faults_reach_the_autopilot(client: Client) -> None:
    plan = parse_faults("battery@0.5:50,gps@0.5+1000:30/0,pilot@1.0:land")
    scenario = _scenario("field-5-tags")
    with Sitl(scenario, speedup=SPEEDUP, mavlink_port=client.port, faults=plan) as sitl:
        battery = client.wait_for(lambda m: m.get_type() == "BATTERY_STATUS"
                                  and m.battery_remaining <= 50, timeout_s=5.0)
        assert battery.battery_remaining == 50
        jumped = client.wait_for(lambda m: m.get_type() == "LOCAL_POSITION_NED" and m.x > 25.0)
        assert jumped.x == pytest.approx(30.0, abs=0.5)
        assert sitl.autopilot.snapshot().vehicle.position_ned[0] == pytest.approx(0.0)
        client.wait_for(lambda m: m.get_type() == "HEARTBEAT" and m.custom_mode == encode(
            Flavour.PX4, Behaviour.LAND))
    assert sitl.frames.published > 0


def test_link_faults_come_from_the_plan(client: Client) -> None:
    plan = parse_faults("loss=100/0,latency=0.2")
    with Sitl(_scenario("field-5-tags"), speedup=SPEEDUP, mavlink_port=client.port,
              faults=plan) as sitl:
        client.wait_type("HEARTBEAT")
        faults = sitl.autopilot.link.faults
        assert (faults.loss_in, faults.loss_out, faults.latency_s) == (1.0, 0.0, 0.2)
        client.send(client.mav.command_long_encode(1, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM,
                                                   0, 1, 0, 0, 0, 0, 0, 0))
        assert not any(m.get_type() == "COMMAND_ACK" for m in client.messages(0.5))
        assert not sitl.autopilot.snapshot().armed


# --------------------------------------------------------------------------- the command


def test_command_prints_where_to_connect_serves_and_stops(client: Client) -> None:
    cmd = [sys.executable, "-m", "sitl", "field-5-tags-ardupilot", "--speedup", "5",
           "--duration", "6", "--mavlink-port", str(client.port), "--status-every", "2",
           "--faults", "drop=10"]
    with subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) as proc:
        assert proc.stdout is not None
        lines = [proc.stdout.readline().strip() for _ in range(3)]
        assert lines[0] == "scenario field-5-tags-ardupilot (ardupilot), speed-up 5x"
        assert lines[1] == f"mavlink udpin://127.0.0.1:{client.port}"
        assert lines[2].startswith("camera http://127.0.0.1:")
        heartbeat = client.wait_type("HEARTBEAT")
        assert heartbeat.autopilot == mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
        with MjpegReader(lines[2].split()[1]) as reader:
            image, _ = next(iter(reader))
        assert image.shape == (480, 640)
        _, err = proc.communicate(timeout=30)
    assert proc.returncode == 0
    status = [line for line in err.splitlines() if line.startswith("t ")]
    assert len(status) >= 2 and "manual" in status[0]


@pytest.mark.parametrize(("args", "message"), [
    (["nowhere"], "companion-sitl: nowhere: no such scenario file"),
    (["field-5-tags", "--faults", "cut@5"], "companion-sitl: --faults: 'cut@5': write cut@T+D"),
])
def test_command_rejects_bad_input_in_one_line(args: list[str], message: str) -> None:
    done = subprocess.run([sys.executable, "-m", "sitl", *args], capture_output=True, text=True,
                          timeout=60, check=False)
    assert done.returncode == 2
    assert done.stderr.startswith(message) and done.stderr.count("\n") == 1
    assert done.stdout == ""


def test_fault_events_are_ordered_and_active_in_their_window() -> None:
    event = FaultEvent(FaultKind.CUT, 10.0, 5.0)
    assert not event.active(9.99) and event.active(10.0) and not event.active(15.0)
    assert math.isclose(parse_faults("cut@3+1,freeze@1+1").events[0].at_s, 1.0)
