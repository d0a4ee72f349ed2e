"""The mock autopilot behaves as the real firmware was measured to, seen from pymavlink.

ArduPilot master 2023-07 SITL and PX4 v1.15 SIH: start-up (warm-up, GPS fix, PX4's transient
arm refusals as EVENTs), take-off (ArduPilot's GUIDED spool-up, PX4's landed state ahead of its
heartbeat), PX4's mode rules, the estimate errors and the uncertainty the firmware reports, the
resting-height bias and the downward rangefinder.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Iterator

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink
from pymavlink.generator import mavparse

from companion.geo import LocalNed
from companion.sim.scenario import load_scenario, parse_scenario
from sitl import events
from sitl.autopilot import (
    FLAVOUR_DEFAULTS,
    AutopilotConfig,
    Firmware,
    GaussMarkov,
    MockAutopilot,
)
from sitl.cli import sitl_scenarios
from sitl.clock import SimClock
from sitl.link import UdpLink
from sitl.modes import Behaviour, Flavour, decode_custom_mode, encode
from sitl.runner import autopilot_config
from tests.mavlink_client import POSITION_ONLY, Client

pytestmark = pytest.mark.sitl

GEO = LocalNed(37.2, -80.4, 600.0)
ACCEPTED, DENIED = mavlink.MAV_RESULT_ACCEPTED, mavlink.MAV_RESULT_DENIED
REJECTED = mavlink.MAV_RESULT_TEMPORARILY_REJECTED
CUSTOM = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
ARM = mavlink.MAV_CMD_COMPONENT_ARM_DISARM
GUIDED = 4  # Copter's mode number
PREARM = mavlink.MAV_SYS_STATUS_PREARM_CHECK
GPS = mavlink.MAV_SYS_STATUS_SENSOR_GPS


@pytest.fixture
def started() -> Iterator[Callable[..., MockAutopilot]]:
    """Start autopilots on the client's port; every one is stopped afterwards."""
    running: list[MockAutopilot] = []

    def start(client: Client, speedup: float = 10.0, **config: object) -> MockAutopilot:
        cfg = AutopilotConfig(**config)  # type: ignore[arg-type]
        link = UdpLink([("127.0.0.1", client.port)], np.random.default_rng(1))
        autopilot = MockAutopilot(cfg, link, SimClock(speedup), GEO)
        running.append(autopilot)
        autopilot.start()
        client.wait_type("HEARTBEAT")
        return autopilot

    yield start
    for autopilot in running:
        autopilot.stop()


def _send(client: Client, command: int, *params: float) -> None:
    """COMMAND_LONG to the autopilot without waiting for its ack."""
    p = [*params, *[0.0] * (7 - len(params))]
    client.send(client.mav.command_long_encode(1, 1, command, 0, *p))


def _record_until(client: Client, done: Callable[[mavlink.MAVLink_message], bool],
                  timeout_s: float = 10.0) -> list[mavlink.MAVLink_message]:
    """Every message received up to and including the first for which done() holds."""
    got: list[mavlink.MAVLink_message] = []
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        for msg in client.messages(0.01):
            got.append(msg)
            if done(msg):
                return got
    raise AssertionError(f"not done within {timeout_s} s; last: {got[-5:]}")


def _of(messages: list[mavlink.MAVLink_message], kind: str) -> list[mavlink.MAVLink_message]:
    return [m for m in messages if m.get_type() == kind]


def _ack(messages: list[mavlink.MAVLink_message], command: int) -> int:
    return int(next(m.result for m in _of(messages, "COMMAND_ACK") if m.command == command))


def _command(client: Client, command: int, *params: float
             ) -> tuple[int, list[mavlink.MAVLink_message]]:
    """COMMAND_LONG: its ack's result and every message received until the ack."""
    _send(client, command, *params)
    got = _record_until(client, lambda m: m.get_type() == "COMMAND_ACK" and m.command == command)
    return int(got[-1].result), got


def _interval(client: Client, msg_id: int, period_s: float) -> None:
    ack = client.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, period_s * 1e6)
    assert ack.result == ACCEPTED


def _boot_s(client: Client) -> float:
    """The autopilot's boot time now, from its next ATTITUDE."""
    return float(client.wait_type("ATTITUDE").time_boot_ms) / 1e3


def _px4_mode(client: Client, behaviour: Behaviour) -> int:
    return client.set_px4_mode(encode(Flavour.PX4, behaviour))


def _fly_up(client: Client, alt_m: float) -> None:
    """PX4: arm, stream a setpoint above home, OFFBOARD, until there."""
    assert client.command(ARM, 1).result == ACCEPTED
    client.stream_setpoints((0.0, 0.0, -alt_m), 0.3)
    assert _px4_mode(client, Behaviour.OFFBOARD) == ACCEPTED
    client.fly_to((0.0, 0.0, -alt_m), 0.2, 20.0)


# --------------------------------------------------------------------------- configuration


def test_flavour_defaults_follow_the_measured_firmware_and_the_warm_up_given() -> None:
    assert AutopilotConfig(flavour=Flavour.ARDUPILOT).firmware() == Firmware(
        armable_after_s=40.0, gps_fix_after_s=25.0, arm_unstable_s=0.0, takeoff_spoolup_s=1.75,
        rel_alt_bias_m=0.25)
    assert AutopilotConfig().firmware() == FLAVOUR_DEFAULTS[Flavour.PX4]
    assert AutopilotConfig().firmware().arm_unstable_s == 3.0
    # A warm-up given by hand: the fix no later, and no transient unless asked for.
    quick = AutopilotConfig(flavour=Flavour.ARDUPILOT, armable_after_s=1.0).firmware()
    assert (quick.armable_after_s, quick.gps_fix_after_s, quick.arm_unstable_s) == (1.0, 1.0, 0.0)
    assert AutopilotConfig(armable_after_s=1.0).firmware().arm_unstable_s == 0.0
    assert AutopilotConfig(armable_after_s=1.0, arm_unstable_s=2.0).firmware().arm_unstable_s == 2.0
    assert AutopilotConfig(arm_unstable_s=0.0).firmware().armable_after_s == 2.0


def test_vehicle_keys_reach_the_autopilot_and_a_replaced_flavour_gets_its_defaults() -> None:
    s = load_scenario(sitl_scenarios()["field-5-tags"])
    assert s.vehicle.armable_after_s is None and s.vehicle.rel_alt_bias_m is None
    assert autopilot_config(s).firmware() == FLAVOUR_DEFAULTS[Flavour.PX4]
    ardupilot = dataclasses.replace(s, vehicle=dataclasses.replace(s.vehicle, flavour="ardupilot"))
    assert autopilot_config(ardupilot).firmware() == FLAVOUR_DEFAULTS[Flavour.ARDUPILOT]
    keys = {"arm_unstable_s": 0.0, "gps_fix_after_s": 5.0, "takeoff_spoolup_s": 1.0,
            "rel_alt_bias_m": -0.5, "heading_error_deg": 4.0, "attitude_error_deg": 1.5,
            "position_error_m": 0.2, "height_error_m": 1.2, "error_time_constant_s": 20.0,
            "rangefinder": True, "rangefinder_max_m": 12.0}
    config = autopilot_config(parse_scenario({"vehicle": keys}))
    assert {k: getattr(config, k) for k in keys} == keys
    assert config.armable_after_s is None and config.firmware().arm_unstable_s == 0.0


def test_gauss_markov_errors_are_seeded_slow_and_of_their_size() -> None:
    sigmas = np.array([0.2, 1.0, math.radians(5.0)])

    def run(seed: int) -> np.ndarray:
        process = GaussMarkov(sigmas, 2.0, np.random.default_rng(seed))
        return np.array([process.step(0.02).copy() for _ in range(50_000)])  # 1000 s

    a, b = run(7), run(7)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, run(8))
    np.testing.assert_allclose(a.std(axis=0), sigmas, rtol=0.15)
    np.testing.assert_allclose(a.mean(axis=0), 0.0, atol=0.2 * sigmas.max())
    step_std = np.diff(a, axis=0).std(axis=0)  # one 0.02 s step: a tenth of sigma
    np.testing.assert_allclose(step_std, sigmas * math.sqrt(2 * 0.02 / 2.0), rtol=0.1)
    lag_s = 2.0  # the correlation at one time constant is 1/e
    k = int(lag_s / 0.02)
    corr = [np.corrcoef(a[:-k, i], a[k:, i])[0, 1] for i in range(3)]
    np.testing.assert_allclose(corr, math.exp(-1.0), atol=0.1)
    assert np.all(GaussMarkov(np.zeros(3), 2.0, np.random.default_rng(0)).step(0.02) == 0.0)


def test_the_event_message_is_the_one_of_common_xml() -> None:
    xml = """<?xml version="1.0"?><mavlink><version>3</version><messages>
      <message id="410" name="EVENT"><description>Event message.</description>
        <field type="uint8_t" name="destination_component">Component ID</field>
        <field type="uint8_t" name="destination_system">System ID</field>
        <field type="uint32_t" name="id">Event ID</field>
        <field type="uint32_t" name="event_time_boot_ms" units="ms">Timestamp</field>
        <field type="uint16_t" name="sequence">Sequence number.</field>
        <field type="uint8_t" name="log_levels">Log levels</field>
        <field type="uint8_t[40]" name="arguments">Arguments</field>
      </message></messages></mavlink>"""
    import tempfile  # noqa: PLC0415

    with tempfile.NamedTemporaryFile("w", suffix=".xml") as fh:
        fh.write(xml)
        fh.flush()
        spec = mavparse.MAVXML(fh.name, "2.0").message[0]
    cls = events.MAVLink_event_message
    assert (cls.crc_extra, cls.unpacker.size) == (spec.crc_extra, spec.wire_length) == (160, 53)
    assert cls.ordered_fieldnames == [f.name for f in spec.ordered_fields]
    sender = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    frame = events.event_message(events.EVENT_HORIZONTAL_VELOCITY_UNSTABLE, 12_345, 7).pack(
        sender)
    (msg,) = mavlink.MAVLink(None).parse_buffer(frame)
    assert msg.get_type() == "EVENT"
    assert (msg.id, msg.event_time_boot_ms, msg.sequence, msg.log_levels) == (
        events.EVENT_HORIZONTAL_VELOCITY_UNSTABLE, 12_345, 7, events.LOG_LEVELS_ERROR)
    assert (msg.destination_system, msg.destination_component) == (0, 0)
    assert msg.arguments == [0] * 40
    assert events.EVENT_HORIZONTAL_VELOCITY_UNSTABLE >> 24 == events.PX4_NAMESPACE
    assert "horizontal velocity unstable" in events.PX4_EVENT_TEXTS[msg.id]


# --------------------------------------------------------------------------- ArduPilot


def test_ardupilot_guided_takeoff_shows_guided_first_and_in_air_after_the_spool_up(
        client: Client, started: Callable[..., MockAutopilot]) -> None:
    copter = started(client, 5.0, flavour=Flavour.ARDUPILOT, armable_after_s=0.0)
    for msg_id in (mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE,
                   mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT):
        _interval(client, msg_id, 0.05)
    assert client.command(ARM, 1).result == ACCEPTED  # in STABILIZE
    client.wait_type("HEARTBEAT")  # the next one is a second away: the order cannot be luck
    commanded_s = client.wait_type("GLOBAL_POSITION_INT").time_boot_ms / 1e3
    _send(client, mavlink.MAV_CMD_DO_SET_MODE, CUSTOM, GUIDED)  # what action.takeoff() sends
    _send(client, mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 5.0)
    bias_m = copter.firmware.rel_alt_bias_m
    got = _record_until(client, lambda m: m.get_type() == "GLOBAL_POSITION_INT"
                        and m.relative_alt > 4900)
    assert _ack(got, mavlink.MAV_CMD_DO_SET_MODE) == ACCEPTED
    assert _ack(got, mavlink.MAV_CMD_NAV_TAKEOFF) == ACCEPTED
    guided_at = next(i for i, m in enumerate(got) if m.get_type() == "HEARTBEAT"
                     and m.custom_mode == GUIDED)
    in_air_at = next(i for i, m in enumerate(got) if m.get_type() == "EXTENDED_SYS_STATE"
                     and m.landed_state == mavlink.MAV_LANDED_STATE_IN_AIR)
    assert guided_at < in_air_at
    assert all(m.landed_state == mavlink.MAV_LANDED_STATE_ON_GROUND
               for m in _of(got[:in_air_at], "EXTENDED_SYS_STATE"))
    # The motors spool up for 1.5-2 s before it leaves the ground; in the air at 0.2 m.
    lifted = next(m for m in _of(got, "GLOBAL_POSITION_INT")
                  if m.relative_alt / 1e3 - bias_m > 0.02)
    assert 1.5 <= lifted.time_boot_ms / 1e3 - commanded_s <= 2.2
    assert got.index(lifted) > guided_at
    height_then_m = _of(got[:in_air_at], "GLOBAL_POSITION_INT")[-1].relative_alt / 1e3 - bias_m
    assert 0.1 < height_then_m < 0.5
    # ArduPilot flies the climb and holds the take-off altitude in GUIDED. Its relative
    # altitude reads 0.25 m above the true height: it flies that much lower.
    hold = client.wait_for(lambda m: m.get_type() == "GLOBAL_POSITION_INT"
                           and abs(m.relative_alt - 5000) < 30 and abs(m.vz) < 5)
    truth = copter.snapshot()
    assert truth.behaviour is Behaviour.OFFBOARD
    assert -truth.vehicle.position_ned[2] == pytest.approx(hold.relative_alt / 1e3 - 0.25,
                                                           abs=0.05)
    local = client.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL,
                           mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 50_000)
    assert local.result == ACCEPTED
    z_m = client.wait_type("LOCAL_POSITION_NED").z  # about the EKF origin, at home's height
    assert z_m == pytest.approx(truth.vehicle.position_ned[2] - 0.25, abs=0.05)


def test_ardupilot_warm_up_no_position_before_the_fix_no_arming_before_40_s(
        client: Client, started: Callable[..., MockAutopilot]) -> None:
    copter = started(client, 20.0, flavour=Flavour.ARDUPILOT)
    client.send(client.mav.request_data_stream_encode(1, 1, 0, 5, 1))  # every stream, 5 Hz
    early = _record_until(client, lambda m: m.get_type() == "GLOBAL_POSITION_INT"
                          and m.time_boot_ms > 10_000, timeout_s=5.0)
    result, reply = _command(client, ARM, 1)
    assert result == DENIED
    early += reply
    early += _record_until(client, lambda m: m.get_type() == "GLOBAL_POSITION_INT"
                           and m.lat != 0, timeout_s=5.0)
    fixed_at = early.pop()
    assert 25_000 <= fixed_at.time_boot_ms <= 25_400
    early = _sent_before(early, 24.8)
    positions = _of(early, "GLOBAL_POSITION_INT")
    assert len(positions) > 20
    assert all((m.lat, m.lon, m.alt, m.relative_alt) == (0, 0, 0, 0) for m in positions)
    raw = _of(early, "GPS_RAW_INT")
    assert raw and all(m.fix_type == mavlink.GPS_FIX_TYPE_NO_FIX and (m.lat, m.lon) == (0, 0)
                       for m in raw)
    statuses = _of(early, "SYS_STATUS")
    assert statuses and all(m.onboard_control_sensors_present & GPS
                            and not m.onboard_control_sensors_health & GPS for m in statuses)
    assert not _of(early, "LOCAL_POSITION_NED")
    assert "PreArm: GPS 1: Bad fix" in _texts(early)
    # Fixed, but the EKF still settles: position, no arming yet.
    assert fixed_at.lat == round(GEO.lat_deg * 1e7)
    after = _record_until(client, lambda m: m.get_type() == "LOCAL_POSITION_NED")
    result, reply = _command(client, ARM, 1)
    assert result == DENIED
    after += reply
    after += _record_until(client, lambda m: m.get_type() == "SYS_STATUS"
                           and m.onboard_control_sensors_health & PREARM, timeout_s=5.0)
    assert after[-1].onboard_control_sensors_health & GPS
    assert 40_000 <= _boot_s(client) * 1e3 <= 41_500
    gps = _of(after, "GPS_RAW_INT")
    assert gps and all(m.fix_type == mavlink.GPS_FIX_TYPE_3D_FIX for m in gps)
    assert "PreArm: Need Position Estimate" in _texts(after)
    assert client.command(ARM, 1).result == ACCEPTED
    assert copter.snapshot().armed and not copter.events_sent  # ArduPilot: STATUSTEXT only


def _sent_before(messages: list[mavlink.MAVLink_message], t_s: float
                 ) -> list[mavlink.MAVLink_message]:
    """The messages up to the last one stamped before boot time t_s (all sent before it)."""
    def stamp_s(m: mavlink.MAVLink_message) -> float:
        if hasattr(m, "time_boot_ms"):
            return float(m.time_boot_ms) / 1e3
        return float(getattr(m, "time_usec", math.inf)) / 1e6

    last = max(i for i, m in enumerate(messages) if stamp_s(m) < t_s)
    return messages[:last + 1]


def _texts(messages: list[mavlink.MAVLink_message]) -> list[str]:
    return [m.text for m in _of(messages, "STATUSTEXT")]


# --------------------------------------------------------------------------- PX4


def test_px4_arm_is_temporarily_rejected_right_after_healthy_with_events_not_text(
        client: Client, started: Callable[..., MockAutopilot]) -> None:
    px4 = started(client, 5.0)  # PX4's defaults: armable after 2 s, 3 s unstable
    result, got = _command(client, ARM, 1)
    assert result == DENIED  # not ready yet
    got += _record_until(client, lambda m: m.get_type() == "SYS_STATUS"
                         and m.onboard_control_sensors_health & PREARM)  # "healthy"
    attempts: list[int] = []
    for after_s in (0.0, 3.6, 5.05):  # right after healthy, in the second half, after it
        while _boot_s(client) < after_s:
            pass
        result, reply = _command(client, ARM, 1)
        got += reply
        attempts.append(result)
    got += client.messages(0.1)
    assert attempts == [REJECTED, REJECTED, ACCEPTED]
    assert px4.snapshot().armed
    sent = _of(got, "EVENT")
    assert [m.id for m in sent] == px4.events_sent
    assert sent[0].id == events.EVENT_ESTIMATOR_NOT_READY
    unstable = sent[1:]
    assert len(unstable) == 2
    for event in unstable:
        since_s = event.event_time_boot_ms / 1e3 - px4.firmware.armable_after_s
        assert 0.0 <= since_s < 3.0
        assert event.id == (events.EVENT_HORIZONTAL_VELOCITY_UNSTABLE if since_s < 1.5
                            else events.EVENT_VERTICAL_VELOCITY_UNSTABLE)
    assert unstable[1].id == events.EVENT_VERTICAL_VELOCITY_UNSTABLE
    assert "velocity unstable" in events.PX4_EVENT_TEXTS[unstable[0].id]
    assert [m.sequence for m in sent] == list(range(len(sent)))
    assert not _of(got, "STATUSTEXT") and not px4.statustexts  # PX4: no text on the API link


def test_px4_before_its_gps_fix_has_no_position_and_says_why_it_will_not_arm(
        client: Client, started: Callable[..., MockAutopilot]) -> None:
    px4 = started(client, 5.0, gps_fix_after_s=3.0, arm_unstable_s=0.0)
    result, got = _command(client, ARM, 1)
    assert result == DENIED and px4.events_sent == [events.EVENT_NO_GPS_FIX]
    assert [m.id for m in _of(got, "EVENT")] == [events.EVENT_NO_GPS_FIX]
    got += _record_until(client, lambda m: m.get_type() == "ODOMETRY")
    odometry = got.pop()
    assert odometry.time_usec >= 3_000_000
    early = _sent_before(got, 2.9)
    assert not {"ODOMETRY", "LOCAL_POSITION_NED"} & {m.get_type() for m in early}
    assert all((m.lat, m.lon, m.relative_alt) == (0, 0, 0)
               for m in _of(early, "GLOBAL_POSITION_INT"))
    status = _of(early, "ESTIMATOR_STATUS")
    assert status and all(m.flags & mavlink.ESTIMATOR_CONST_POS_MODE
                          and not m.flags & mavlink.ESTIMATOR_POS_HORIZ_ABS
                          and m.pos_horiz_accuracy >= 100.0 for m in status)
    assert client.command(ARM, 1).result == ACCEPTED


def test_px4_arms_at_once_without_the_transient(client: Client,
                                                started: Callable[..., MockAutopilot]) -> None:
    started(client, 5.0, arm_unstable_s=0.0)
    client.wait_for(lambda m: m.get_type() == "SYS_STATUS"
                    and m.onboard_control_sensors_health & PREARM)
    assert client.command(ARM, 1).result == ACCEPTED


def test_px4_takeoff_landed_state_runs_ahead_of_the_heartbeat(
        client: Client, started: Callable[..., MockAutopilot]) -> None:
    started(client, 5.0, armable_after_s=0.0, takeoff_spoolup_s=1.0)
    assert client.command(ARM, 1).result == ACCEPTED
    before = client.wait_type("HEARTBEAT")  # the next one is a second away
    _send(client, mavlink.MAV_CMD_NAV_TAKEOFF, *[math.nan] * 7)
    takeoff = encode(Flavour.PX4, Behaviour.TAKEOFF)
    got = _record_until(client, lambda m: m.get_type() == "HEARTBEAT")
    assert got[-1].custom_mode == takeoff  # the first heartbeat after the command shows it...
    assert _ack(got, mavlink.MAV_CMD_NAV_TAKEOFF) == ACCEPTED
    said_takeoff = [i for i, m in enumerate(got) if m.get_type() == "EXTENDED_SYS_STATE"
                    and m.landed_state == mavlink.MAV_LANDED_STATE_TAKEOFF]
    assert said_takeoff  # ...but the landed state said "taking off" before it,
    on_ground = [m for m in _of(got[:said_takeoff[0]], "GLOBAL_POSITION_INT")]
    assert on_ground and abs(on_ground[-1].relative_alt) < 20  # while still on the ground
    boot_ms = [m.time_boot_ms for m in _of(got, "ATTITUDE")]
    assert boot_ms[-1] - boot_ms[0] >= 800  # no extra heartbeat for the mode change
    assert before.custom_mode != takeoff


def test_px4_posctl_and_altctl_need_manual_control_hold_does_not(
        client: Client, started: Callable[..., MockAutopilot]) -> None:
    px4 = started(client, 10.0, armable_after_s=0.0)
    assert _px4_mode(client, Behaviour.HOLD) == ACCEPTED
    assert _px4_mode(client, Behaviour.POSITION) == REJECTED
    assert _px4_mode(client, Behaviour.ALTITUDE) == REJECTED
    assert px4.events_sent[-2:] == [events.EVENT_POSITION_NOT_AVAILABLE,
                                    events.EVENT_ALTITUDE_NOT_AVAILABLE]
    assert events.PX4_EVENT_TEXTS[px4.events_sent[-2]] == (
        "Switching to Position is currently not available")
    sticks = mavlink.MAVLink(None, srcSystem=42, srcComponent=1)  # any sender will do
    assert client.autopilot is not None
    for _ in range(3):
        centred = sticks.manual_control_encode(1, 0, 0, 500, 0, 0)
        client.sock.sendto(centred.pack(sticks), client.autopilot)
        client.messages(0.01)
    assert _px4_mode(client, Behaviour.POSITION) == ACCEPTED
    assert _px4_mode(client, Behaviour.HOLD) == ACCEPTED
    stopped_s = _boot_s(client)
    while _boot_s(client) < stopped_s + 1.2:  # sticks silent for over a second
        pass
    assert _px4_mode(client, Behaviour.ALTITUDE) == REJECTED
    assert px4.snapshot().behaviour is Behaviour.HOLD
    px4.pilot_set_mode(Behaviour.POSITION)  # the pilot's switch always wins
    hb = client.wait_for(lambda m: m.get_type() == "HEARTBEAT" and m.custom_mode == encode(
        Flavour.PX4, Behaviour.POSITION))
    assert decode_custom_mode(Flavour.PX4, hb.custom_mode) is Behaviour.POSITION


# --------------------------------------------------------------------------- estimate errors


ERRORS = {"heading_error_deg": 5.0, "attitude_error_deg": 1.5, "position_error_m": 0.2,
          "height_error_m": 1.0, "error_time_constant_s": 2.0}


def test_reported_pose_differs_from_the_truth_by_slow_errors_of_their_size(
        client: Client, started: Callable[..., MockAutopilot]) -> None:
    px4 = started(client, 25.0, armable_after_s=0.0, **ERRORS)
    # 75 s of 20 Hz attitude at least (more if the loaded autopilot skips some): on the ground,
    # at rest, at home, heading north
    got = client.messages_until("ATTITUDE", 1500, timeout_s=30.0)
    assert px4.snapshot().vehicle.on_ground
    attitude = _of(got, "ATTITUDE")
    yaw = np.array([m.yaw for m in attitude])
    roll = np.array([m.roll for m in attitude])
    for errors, sigma_deg in ((yaw, 5.0), (roll, 1.5)):
        sigma = math.radians(sigma_deg)
        assert 0.5 * sigma < errors.std() < 1.6 * sigma
        assert np.diff(errors).std() < 0.5 * sigma  # slowly varying, not white
    quaternions = {m.time_boot_ms: m for m in _of(got, "ATTITUDE_QUATERNION")}
    positions = {m.time_boot_ms: m for m in _of(got, "GLOBAL_POSITION_INT")}
    same_time = [m for m in attitude if m.time_boot_ms in quaternions]
    assert same_time
    for m in same_time:  # ATTITUDE and ATTITUDE_QUATERNION report the same attitude
        q = quaternions[m.time_boot_ms]
        yaw_q = math.atan2(2 * (q.q1 * q.q4 + q.q2 * q.q3), 1 - 2 * (q.q3 ** 2 + q.q4 ** 2))
        assert yaw_q == pytest.approx(m.yaw, abs=1e-5)
        if m.time_boot_ms in positions:  # and GLOBAL_POSITION_INT's heading
            hdg = positions[m.time_boot_ms].hdg / 100.0
            assert (hdg - math.degrees(m.yaw) + 180.0) % 360.0 - 180.0 == pytest.approx(
                0.0, abs=0.02)
    local = _of(got, "LOCAL_POSITION_NED")
    xyz = np.array([(m.x, m.y, m.z) for m in local])
    for axis, sigma in ((0, 0.2), (1, 0.2), (2, 1.0)):
        assert 0.5 * sigma < xyz[:, axis].std() < 1.6 * sigma
        assert np.diff(xyz[:, axis]).std() < 0.5 * sigma
    for m in local:  # the same position in GLOBAL_POSITION_INT and LOCAL_POSITION_NED
        g = positions.get(m.time_boot_ms)
        if g is not None:
            north, east, _ = GEO.geodetic_to_ned(g.lat / 1e7, g.lon / 1e7, g.alt / 1e3)
            assert (float(north), float(east)) == pytest.approx((m.x, m.y), abs=0.02)
            assert g.relative_alt / 1e3 == pytest.approx(-m.z, abs=0.002)


def test_the_vehicle_flies_on_its_estimate(client: Client,
                                           started: Callable[..., MockAutopilot]) -> None:
    px4 = started(client, 10.0, armable_after_s=0.0, position_error_m=2.0, height_error_m=2.0,
                  heading_error_deg=10.0, error_time_constant_s=600.0, seed=3)
    _fly_up(client, 5.0)  # the reported position reaches the setpoint...
    target = (4.0, -3.0, -6.0)
    client.fly_to(target, 0.15, 20.0)
    # ...and, while the setpoint still streams, the truth is off by the estimate's error (a
    # vehicle that flew on the truth would stay off by all of it, more than 0.5 m).
    end = time.monotonic() + 10.0
    while True:
        snap = px4.snapshot()
        error = np.array(snap.estimate_error[:3])
        off = snap.vehicle.position_ned - (np.array(target) - error)
        if np.abs(off).max() <= 0.25 or time.monotonic() > end:
            break
        client.stream_setpoints(target, 0.1)
    assert np.linalg.norm(error) > 0.5
    np.testing.assert_allclose(off, 0.0, atol=0.25)


def test_uncertainty_is_reported_as_the_firmware_does(
        client: Client, started: Callable[..., MockAutopilot]) -> None:
    started(client, 10.0, armable_after_s=0.0, **ERRORS)
    got = client.messages(1.0)  # 10 s
    gps = _of(got, "GPS_RAW_INT")
    assert gps and all((m.h_acc, m.v_acc) == (200, 1000) for m in gps)
    status = _of(got, "ESTIMATOR_STATUS")
    span_s = (status[-1].time_usec - status[0].time_usec) / 1e6
    assert 0.8 <= (len(status) - 1) / span_s <= 1.2  # 1 Hz
    for m in status:
        assert (m.pos_horiz_accuracy, m.pos_vert_accuracy) == pytest.approx((0.2, 1.0))
        assert m.flags & mavlink.ESTIMATOR_POS_HORIZ_ABS and m.flags & mavlink.ESTIMATOR_ATTITUDE
        assert not m.flags & mavlink.ESTIMATOR_CONST_POS_MODE
    odometry = _of(got, "ODOMETRY")
    span_s = (odometry[-1].time_usec - odometry[0].time_usec) / 1e6
    assert 27.0 <= (len(odometry) - 1) / span_s <= 33.0  # 30 Hz
    local = {m.time_boot_ms: m for m in _of(got, "LOCAL_POSITION_NED")}
    quaternions = {m.time_boot_ms: m for m in _of(got, "ATTITUDE_QUATERNION")}
    matched = 0
    for m in odometry:
        assert (m.frame_id, m.child_frame_id) == (mavlink.MAV_FRAME_LOCAL_NED,
                                                  mavlink.MAV_FRAME_BODY_FRD)
        assert (m.reset_counter, m.estimator_type) == (0, mavlink.MAV_ESTIMATOR_TYPE_GPS_INS)
        variances = [m.pose_covariance[i] for i in (0, 6, 11, 15, 18, 20)]
        expected = [0.04, 0.04, 1.0, *[math.radians(d) ** 2 for d in (1.5, 1.5, 5.0)]]
        assert variances == pytest.approx(expected, rel=1e-5)
        assert sum(abs(c) for c in m.pose_covariance) == pytest.approx(sum(expected), rel=1e-5)
        assert math.isnan(m.velocity_covariance[0])
        t_ms = m.time_usec // 1000  # the boot clock of the other messages
        if t_ms in local and t_ms in quaternions:
            matched += 1
            p, q = local[t_ms], quaternions[t_ms]
            assert (m.x, m.y, m.z) == pytest.approx((p.x, p.y, p.z), abs=1e-4)
            assert list(m.q) == pytest.approx([q.q1, q.q2, q.q3, q.q4], abs=1e-6)
    assert matched > 10


def test_uncertainty_is_never_zero_and_only_px4_streams_the_estimator(
        client: Client, started: Callable[..., MockAutopilot]) -> None:
    started(client, 10.0, flavour=Flavour.ARDUPILOT, armable_after_s=0.0)
    _interval(client, mavlink.MAVLINK_MSG_ID_GPS_RAW_INT, 0.1)
    gps = client.wait_type("GPS_RAW_INT")
    assert (gps.h_acc, gps.v_acc) == (20, 20)  # the 2 cm floor
    for msg_id in (mavlink.MAVLINK_MSG_ID_ODOMETRY, mavlink.MAVLINK_MSG_ID_ESTIMATOR_STATUS):
        ack = client.command(mavlink.MAV_CMD_REQUEST_MESSAGE, msg_id)
        assert ack.result == mavlink.MAV_RESULT_UNSUPPORTED
    assert not {"ODOMETRY", "ESTIMATOR_STATUS"} & {m.get_type() for m in client.messages(0.3)}


def test_px4_odometry_floor_and_velocity_in_the_body_frame(
        client: Client, started: Callable[..., MockAutopilot]) -> None:
    px4 = started(client, 10.0, armable_after_s=0.0)
    odometry = client.wait_type("ODOMETRY")
    floor = [0.02 ** 2] * 3 + [math.radians(0.1) ** 2] * 3
    assert [odometry.pose_covariance[i] for i in (0, 6, 11, 15, 18, 20)] == pytest.approx(floor)
    _fly_up(client, 5.0)
    velocity_and_yaw = 0b111 | 0b111000000 | (1 << 11)
    end = time.monotonic() + 20.0
    while time.monotonic() < end:  # east at 2 m/s, heading east: forward in the body frame
        client.send(client.mav.set_position_target_local_ned_encode(
            0, 1, 1, mavlink.MAV_FRAME_LOCAL_NED, velocity_and_yaw, 0, 0, 0, 0.0, 2.0, 0.0,
            0, 0, 0, math.pi / 2, 0.0))
        odometry = next((m for m in client.messages(0.02) if m.get_type() == "ODOMETRY"),
                        odometry)
        v = px4.snapshot().vehicle
        if abs(v.velocity_ned[1] - 2.0) < 0.02 and abs(v.yaw_rad - math.pi / 2) < 0.005:
            break
    odometry = client.wait_type("ODOMETRY")
    assert (odometry.vx, odometry.vy, odometry.vz) == pytest.approx((2.0, 0.0, 0.0), abs=0.1)


# --------------------------------------------------------------------------- rangefinder


def test_px4_rangefinder_measures_the_height_at_10_hz(
        client: Client, started: Callable[..., MockAutopilot]) -> None:
    started(client, 10.0, armable_after_s=0.0, rangefinder=True, rangefinder_max_m=4.0)
    got = client.messages(0.5)
    ranges = _of(got, "DISTANCE_SENSOR")
    attitude_ms = [m.time_boot_ms for m in _of(got, "ATTITUDE")]
    span_s = (ranges[-1].time_boot_ms - ranges[0].time_boot_ms) / 1e3
    assert 8.0 <= (len(ranges) - 1) / span_s <= 12.0
    first = ranges[0]
    assert (first.orientation, first.type) == (mavlink.MAV_SENSOR_ROTATION_PITCH_270,
                                               mavlink.MAV_DISTANCE_SENSOR_LASER)
    assert (first.min_distance, first.max_distance) == (10, 400)
    assert all(m.current_distance <= 5 for m in ranges)  # on the ground
    assert min(attitude_ms) - 200 <= first.time_boot_ms <= max(attitude_ms) + 200  # boot clock
    status = client.wait_type("ESTIMATOR_STATUS")
    assert status.flags & mavlink.ESTIMATOR_POS_VERT_AGL
    assert client.command(ARM, 1).result == ACCEPTED
    client.stream_setpoints((0.0, 0.0, -5.0), 0.3)
    assert _px4_mode(client, Behaviour.OFFBOARD) == ACCEPTED
    climb: list[tuple[int, int]] = []  # (range, relative altitude) in the climb, cm and mm
    height_ms: dict[int, int] = {}
    end = time.monotonic() + 20.0
    while time.monotonic() < end and not (climb and climb[-1][1] > 4900):
        for m in client.stream_setpoints((0.0, 0.0, -5.0), 0.05, POSITION_ONLY):
            if m.get_type() == "GLOBAL_POSITION_INT":
                height_ms[m.time_boot_ms] = m.relative_alt
            elif m.get_type() == "DISTANCE_SENSOR" and m.time_boot_ms in height_ms:
                climb.append((m.current_distance, height_ms[m.time_boot_ms]))
    in_range = [(r, h) for r, h in climb if h < 3800]
    assert len(in_range) > 5
    for range_cm, height_mm in in_range:  # level flight up: the range is the height
        assert range_cm == pytest.approx(height_mm / 10, abs=5)
    assert climb[-1][0] == 401  # beyond its 4 m: out of range


def test_rangefinder_is_off_by_default(client: Client,
                                       started: Callable[..., MockAutopilot]) -> None:
    started(client, 10.0, armable_after_s=0.0)
    assert "DISTANCE_SENSOR" not in {m.get_type() for m in client.messages(0.3)}
    ack = client.command(mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_DISTANCE_SENSOR)
    assert ack.result == mavlink.MAV_RESULT_UNSUPPORTED


def test_ardupilot_sends_the_rangefinder_when_asked(
        client: Client, started: Callable[..., MockAutopilot]) -> None:
    started(client, 10.0, flavour=Flavour.ARDUPILOT, armable_after_s=0.0, rangefinder=True)
    assert "DISTANCE_SENSOR" not in {m.get_type() for m in client.messages(0.3)}
    client.send(client.mav.request_data_stream_encode(1, 1, mavlink.MAV_DATA_STREAM_EXTRA3, 10, 1))
    reading = client.wait_type("DISTANCE_SENSOR")
    assert reading.orientation == mavlink.MAV_SENSOR_ROTATION_PITCH_270
    assert (reading.min_distance, reading.max_distance) == (10, 4000)
    assert reading.current_distance <= 5  # on the ground
    client.send(client.mav.request_data_stream_encode(1, 1, mavlink.MAV_DATA_STREAM_EXTRA3, 0, 0))
    client.messages(0.1)
    assert "DISTANCE_SENSOR" not in {m.get_type() for m in client.messages(0.3)}
    _interval(client, mavlink.MAVLINK_MSG_ID_DISTANCE_SENSOR, 0.1)  # or on SET_MESSAGE_INTERVAL
    client.wait_type("DISTANCE_SENSOR")
