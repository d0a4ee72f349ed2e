"""The mock autopilot's MAVLink protocol, seen from a plain pymavlink ground station."""

from __future__ import annotations

import time
from collections.abc import Iterator

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.geo import LocalNed
from sitl.autopilot import FORCE_MAGIC, AutopilotConfig, Failsafe, MockAutopilot
from sitl.clock import SimClock
from sitl.link import UdpLink
from sitl.modes import Behaviour, Flavour, decode_custom_mode, encode
from tests.mavlink_client import Client

pytestmark = pytest.mark.sitl

SPEEDUP = 10.0
GEO = LocalNed(37.2, -80.4, 600.0)
ACCEPTED, DENIED = mavlink.MAV_RESULT_ACCEPTED, mavlink.MAV_RESULT_DENIED
CUSTOM = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED


def _start(client: Client, **config: object) -> MockAutopilot:
    cfg = AutopilotConfig(**config)  # type: ignore[arg-type]
    link = UdpLink([("127.0.0.1", client.port)], np.random.default_rng(1))
    autopilot = MockAutopilot(cfg, link, SimClock(SPEEDUP), GEO)
    autopilot.start()
    client.wait_type("HEARTBEAT")
    return autopilot


@pytest.fixture
def px4(client: Client) -> Iterator[MockAutopilot]:
    autopilot = _start(client, armable_after_s=0.0)
    yield autopilot
    autopilot.stop()


@pytest.fixture
def copter(client: Client) -> Iterator[MockAutopilot]:
    autopilot = _start(client, flavour=Flavour.ARDUPILOT, armable_after_s=0.0)
    yield autopilot
    autopilot.stop()


def _mode(client: Client, flavour: Flavour = Flavour.PX4) -> Behaviour | None:
    hb = client.wait_type("HEARTBEAT")
    return decode_custom_mode(flavour, hb.custom_mode)


def _px4_mode(client: Client, behaviour: Behaviour) -> int:
    return client.set_px4_mode(encode(Flavour.PX4, behaviour))


def _fly_up(client: Client, autopilot: MockAutopilot, alt_m: float = 5.0) -> None:
    assert client.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1).result == ACCEPTED
    client.stream_setpoints((0.0, 0.0, -alt_m), 0.3)
    assert _px4_mode(client, Behaviour.OFFBOARD) == ACCEPTED
    client.fly_to((0.0, 0.0, -alt_m), 0.3, 20.0)
    assert -autopilot.snapshot().vehicle.position_ned[2] > alt_m - 0.3


def test_heartbeat_identifies_a_px4_quadrotor_at_one_hertz(client: Client, px4: MockAutopilot
                                                           ) -> None:
    received = client.messages(1.0)
    beats = [m for m in received if m.get_type() == "HEARTBEAT"]
    boot_ms = [m.time_boot_ms for m in received if m.get_type() == "ATTITUDE"]
    rate_hz = len(beats) / ((max(boot_ms) - min(boot_ms)) / 1e3)  # per simulated second
    assert 0.7 <= rate_hz <= 1.4
    hb = beats[-1]
    assert (hb.get_srcSystem(), hb.get_srcComponent()) == (1, 1)
    assert hb.autopilot == mavlink.MAV_AUTOPILOT_PX4
    assert hb.type == mavlink.MAV_TYPE_QUADROTOR
    assert hb.base_mode & CUSTOM
    assert not hb.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED
    assert hb.custom_mode == (3 << 16)  # POSCTL at boot
    raw, _ = client.sock.recvfrom(65535)
    assert raw[0] == 0xFD  # MAVLink 2 framing


def test_px4_mode_encoding_and_acks(client: Client, px4: MockAutopilot) -> None:
    assert _px4_mode(client, Behaviour.HOLD) == ACCEPTED
    hb = client.wait_for(lambda m: m.get_type() == "HEARTBEAT" and m.custom_mode != (3 << 16))
    assert hb.custom_mode == (4 << 16) | (3 << 24)  # AUTO.LOITER
    ack = client.command(mavlink.MAV_CMD_DO_SET_MODE, CUSTOM, 42, 0)
    assert ack.result == DENIED  # no such mode
    assert client.command(mavlink.MAV_CMD_DO_SET_MODE, 0, 4, 3).result == (
        mavlink.MAV_RESULT_UNSUPPORTED)  # without CUSTOM_MODE_ENABLED
    assert client.command(mavlink.MAV_CMD_DO_FENCE_ENABLE, 1).result == (
        mavlink.MAV_RESULT_UNSUPPORTED)
    assert client.command(mavlink.MAV_CMD_NAV_TAKEOFF).result == DENIED  # not armed
    assert client.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1).result == ACCEPTED
    assert client.wait_for(lambda m: m.get_type() == "HEARTBEAT"
                           and m.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)


def test_request_message_and_parameters(client: Client, px4: MockAutopilot) -> None:
    ack = client.command(mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
    assert ack.result == ACCEPTED
    version = client.wait_type("AUTOPILOT_VERSION")
    assert version.capabilities & mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
    assert version.capabilities & mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
    client.send(client.mav.param_request_read_encode(1, 1, b"MIS_TAKEOFF_ALT", -1))
    value = client.wait_type("PARAM_VALUE")
    assert value.param_id == "MIS_TAKEOFF_ALT" and value.param_value == pytest.approx(2.5)
    client.send(client.mav.param_set_encode(1, 1, b"MIS_TAKEOFF_ALT", 8.0,
                                            mavlink.MAV_PARAM_TYPE_REAL32))
    assert client.wait_type("PARAM_VALUE").param_value == pytest.approx(8.0)


def test_offboard_is_refused_without_a_setpoint_stream(client: Client, px4: MockAutopilot
                                                       ) -> None:
    assert _px4_mode(client, Behaviour.OFFBOARD) == DENIED
    client.stream_setpoints((0.0, 0.0, -3.0), 0.3)
    assert _px4_mode(client, Behaviour.OFFBOARD) == ACCEPTED


def _await_behaviour(client: Client, autopilot: MockAutopilot, behaviour: Behaviour,
                     setpoint_ned: tuple[float, float, float] | None = None,
                     timeout_wall_s: float = 5.0) -> None:
    """Read (and, with setpoint_ned, stream that setpoint) until the autopilot is in behaviour."""
    deadline = time.monotonic() + timeout_wall_s
    while autopilot.snapshot().behaviour is not behaviour:
        assert time.monotonic() < deadline, f"not in {behaviour.value}: {autopilot.snapshot()}"
        if setpoint_ned is None:
            client.messages(0.02)
        else:
            client.stream_setpoints(setpoint_ned, 0.02)


def test_px4_falls_back_to_position_mode_by_default(client: Client, px4: MockAutopilot) -> None:
    client.send(client.mav.param_request_read_encode(1, 1, b"COM_OBL_RC_ACT", -1))
    assert client.wait_type("PARAM_VALUE").param_value == 0.0  # PX4's 0: Position mode
    _fly_up(client, px4)
    hb = client.wait_for(lambda m: m.get_type() == "HEARTBEAT" and m.custom_mode != (6 << 16))
    assert hb.custom_mode == (3 << 16)  # OFFBOARD -> POSCTL, no setpoints for COM_OF_LOSS_T
    assert px4.snapshot().armed
    assert "failsafe: offboard setpoints lost, position" in px4.statustexts


@pytest.mark.parametrize(
    ("failsafe", "expected"),
    [
        (Failsafe.POSITION, Behaviour.POSITION),
        (Failsafe.HOLD, Behaviour.HOLD),
        (Failsafe.LAND, Behaviour.LAND),
        (Failsafe.RTL, Behaviour.RTL),
    ],
)
def test_offboard_loss_falls_back_and_returns_to_offboard_when_the_setpoints_come_back(
    client: Client, failsafe: Failsafe, expected: Behaviour
) -> None:
    autopilot = _start(client, armable_after_s=0.0, offboard_failsafe=failsafe)
    try:
        _fly_up(client, autopilot)
        _await_behaviour(client, autopilot, expected)
        assert any("offboard setpoints lost" in t for t in autopilot.statustexts)
        _await_behaviour(client, autopilot, Behaviour.OFFBOARD, setpoint_ned=(3.0, 0.0, -5.0))
        assert autopilot.snapshot().armed
        assert "failsafe: offboard setpoints back, offboard" in autopilot.statustexts
        client.fly_to((3.0, 0.0, -5.0), 0.3, 20.0)  # it flies the setpoints again
    finally:
        autopilot.stop()


@pytest.mark.parametrize(("value", "expected"), [
    (3.0, Behaviour.RTL), (4.0, Behaviour.LAND), (5.0, Behaviour.HOLD),
])
def test_com_obl_rc_act_takes_px4s_values(client: Client, px4: MockAutopilot, value: float,
                                          expected: Behaviour) -> None:
    client.send(client.mav.param_set_encode(1, 1, b"COM_OBL_RC_ACT", value,
                                            mavlink.MAV_PARAM_TYPE_REAL32))
    assert client.wait_type("PARAM_VALUE").param_value == value
    _fly_up(client, px4)
    _await_behaviour(client, px4, expected)


@pytest.mark.parametrize("change", ["mode request", "pilot switch"])
def test_a_mode_change_during_the_fallback_means_no_return_to_offboard(
    client: Client, px4: MockAutopilot, change: str
) -> None:
    _fly_up(client, px4)
    _await_behaviour(client, px4, Behaviour.POSITION)
    if change == "mode request":
        assert _px4_mode(client, Behaviour.HOLD) == ACCEPTED
        expected = Behaviour.HOLD
    else:  # the switch to the mode it is already in still replaces the intended mode
        px4.pilot_set_mode(Behaviour.POSITION)
        expected = Behaviour.POSITION
    client.stream_setpoints((3.0, 0.0, -5.0), 0.5)  # 5 s of setpoints again: ignored
    assert px4.snapshot().behaviour is expected
    assert _mode(client) is expected
    assert "failsafe: offboard setpoints back, offboard" not in px4.statustexts


def test_a_fallback_that_landed_and_disarmed_does_not_return(client: Client) -> None:
    autopilot = _start(client, armable_after_s=0.0, offboard_failsafe=Failsafe.LAND)
    try:
        _fly_up(client, autopilot, alt_m=2.0)
        client.wait_for(lambda m: m.get_type() == "HEARTBEAT"
                        and not m.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED, 10.0)
        client.stream_setpoints((0.0, 0.0, -2.0), 0.5)
        snap = autopilot.snapshot()
        assert snap.behaviour is Behaviour.LAND and not snap.armed
    finally:
        autopilot.stop()


def test_a_disarm_ends_the_fallback(client: Client, px4: MockAutopilot) -> None:
    _fly_up(client, px4)
    _await_behaviour(client, px4, Behaviour.POSITION)
    assert client.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, FORCE_MAGIC).result == ACCEPTED
    assert client.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1).result == ACCEPTED
    client.stream_setpoints((0.0, 0.0, -2.0), 0.5)
    snap = px4.snapshot()
    assert snap.behaviour is Behaviour.POSITION and snap.armed


def test_ardupilot_guided_has_no_offboard_loss_failsafe(client: Client, copter: MockAutopilot
                                                       ) -> None:
    assert client.command(mavlink.MAV_CMD_DO_SET_MODE, CUSTOM, 4).result == ACCEPTED  # GUIDED
    assert client.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1).result == ACCEPTED
    assert client.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 4.0).result == ACCEPTED
    client.stream_setpoints((-4.0, 3.0, -4.0), 0.3)  # above home (local NED: the EKF origin)
    client.messages(0.3)  # 3 s without setpoints: GUIDED holds the last one
    snap = copter.snapshot()
    assert snap.behaviour is Behaviour.OFFBOARD and snap.armed and not snap.vehicle.on_ground
    assert not [t for t in copter.statustexts if t.startswith("failsafe")]


def test_type_mask_position_velocity_and_yaw(client: Client, px4: MockAutopilot) -> None:
    _fly_up(client, px4)
    client.fly_to((6.0, -4.0, -5.0), 0.3, 20.0)  # position, yaw ignored by 0xDF8
    snap = px4.snapshot().vehicle
    np.testing.assert_allclose(snap.position_ned, [6.0, -4.0, -5.0], atol=0.3)
    assert snap.yaw_rad == pytest.approx(0.0, abs=1e-6)
    ignore_position = 0b111 | 0b111000000 | (1 << 11)  # velocity + yaw
    end = time.monotonic() + 20.0
    while time.monotonic() < end:  # until the vehicle flies east at 2 m/s, heading 1 rad
        client.send(client.mav.set_position_target_local_ned_encode(
            0, 1, 1, mavlink.MAV_FRAME_LOCAL_NED, ignore_position, 0, 0, 0, 0.0, 2.0, 0.0,
            0, 0, 0, 1.0, 0.0))
        client.messages(0.02)
        snap = px4.snapshot().vehicle
        if abs(snap.velocity_ned[1] - 2.0) < 0.05 and abs(snap.yaw_rad - 1.0) < 0.01:
            break
    assert snap.velocity_ned[1] == pytest.approx(2.0, abs=0.3)
    assert snap.velocity_ned[0] == pytest.approx(0.0, abs=0.3)
    assert snap.yaw_rad == pytest.approx(1.0, abs=0.05)


def test_pilot_override_wins_and_offboard_is_not_reentered(client: Client, px4: MockAutopilot
                                                           ) -> None:
    _fly_up(client, px4)
    px4.pilot_set_mode(Behaviour.POSITION)
    client.stream_setpoints((10.0, 0.0, -5.0), 0.5)  # setpoints keep coming: ignored
    assert px4.snapshot().behaviour is Behaviour.POSITION
    assert _mode(client) is Behaviour.POSITION
    assert abs(px4.snapshot().vehicle.position_ned[0]) < 1.0


def test_disarm_is_refused_in_the_air_unless_forced(client: Client, px4: MockAutopilot) -> None:
    _fly_up(client, px4)
    assert client.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0).result == DENIED
    assert client.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 21196).result == ACCEPTED


def test_ardupilot_streams_nothing_until_asked(client: Client, copter: MockAutopilot) -> None:
    kinds = {m.get_type() for m in client.messages(0.4)}
    assert kinds == {"HEARTBEAT"}
    hb = client.wait_type("HEARTBEAT")
    assert hb.autopilot == mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
    assert hb.custom_mode == 0  # STABILIZE
    interval_us = 100_000
    ack = client.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL,
                         mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, interval_us)
    assert ack.result == ACCEPTED
    local = client.wait_type("LOCAL_POSITION_NED")
    # Local NED is about the EKF origin, not the take-off point: (4, -3) m away by default.
    assert (local.x, local.y) == pytest.approx((-4.0, 3.0), abs=1e-3)
    client.send(client.mav.request_data_stream_encode(1, 1, mavlink.MAV_DATA_STREAM_EXTRA1, 5, 1))
    client.wait_type("ATTITUDE")


def test_ardupilot_arming_rules_and_guided(client: Client, copter: MockAutopilot) -> None:
    def set_mode(number: int) -> int:
        return int(client.command(mavlink.MAV_CMD_DO_SET_MODE, CUSTOM, number).result)

    assert set_mode(9) == ACCEPTED  # LAND
    assert client.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1).result == DENIED
    assert set_mode(4) == ACCEPTED  # GUIDED: no setpoint stream needed
    assert client.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1).result == ACCEPTED
    assert client.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 6.0).result == ACCEPTED
    client.messages(0.6)
    assert -copter.snapshot().vehicle.position_ned[2] == pytest.approx(6.0, abs=0.5)


def test_gps_glitch_moves_the_report_not_the_vehicle(client: Client, px4: MockAutopilot) -> None:
    before = client.wait_type("LOCAL_POSITION_NED")
    px4.gps_glitch((20.0, 0.0, 0.0), duration_s=3.0)
    during = client.wait_type("LOCAL_POSITION_NED")
    assert during.x - before.x == pytest.approx(20.0, abs=0.1)
    assert px4.snapshot().vehicle.position_ned[0] == pytest.approx(0.0, abs=1e-9)
    client.messages(0.35)
    assert client.wait_type("LOCAL_POSITION_NED").x == pytest.approx(before.x, abs=0.1)


def test_link_faults(client: Client, px4: MockAutopilot) -> None:
    px4.link.faults.cut_until_s = px4.clock.now_s() + 3.0
    assert not [m for m in client.messages(0.2) if m.get_type() == "HEARTBEAT"]
    client.wait_type("HEARTBEAT", timeout_s=1.0)  # back after 3 simulated seconds
    px4.link.faults.loss_in = 1.0
    client.send(client.mav.command_long_encode(1, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0,
                                               1, 0, 0, 0, 0, 0, 0))
    assert not [m for m in client.messages(0.2) if m.get_type() == "COMMAND_ACK"]
    px4.link.faults.loss_in = 0.0
    px4.link.faults.loss_out = 0.3
    sent, dropped = px4.link.sent, px4.link.dropped_out
    beats = [m for m in client.messages(1.0) if m.get_type() == "HEARTBEAT"]
    assert len(beats) >= 2  # the link still carries heartbeats
    # ~30 % of what the autopilot sent is lost, counted over every packet of the second (a
    # thousand) rather than its ~10 heartbeats, of which all 10 arrive now and then
    sent, dropped = px4.link.sent - sent, px4.link.dropped_out - dropped
    assert 0.15 <= dropped / (sent + dropped) <= 0.45, (sent, dropped)


def test_reboot_goes_silent_and_comes_back_disarmed(client: Client, px4: MockAutopilot) -> None:
    assert client.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1).result == ACCEPTED
    px4.reboot(downtime_s=2.0)
    assert not [m for m in client.messages(0.1) if m.get_type() == "HEARTBEAT"]
    hb = client.wait_type("HEARTBEAT", timeout_s=1.0)
    assert not hb.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED
    assert px4.snapshot().boot == 1
    assert client.wait_type("ATTITUDE").time_boot_ms < 2000
