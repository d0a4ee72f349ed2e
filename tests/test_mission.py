"""The mission state machine: every path, and the rules that hold over any input sequence."""

from __future__ import annotations

from dataclasses import replace

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.errors import ConfigError
from companion.mission import (
    Autopilot,
    Command,
    CommandKind,
    FlightMode,
    Mission,
    MissionConfig,
    MissionInputs,
    Severity,
    State,
    Stream,
    advance,
)

K = CommandKind
OK = MissionInputs(
    connected=True, health_ok=True, armed=True, in_air=True, flight_mode=FlightMode.POSCTL,
    battery_low=False, position_ok=True, coverage_passes=0, confirmed_targets=0,
    expected_targets=None, setpoints_streaming=False, alt_rel_m=10.0,
)
ON_GROUND = replace(OK, armed=False, in_air=False, flight_mode=FlightMode.HOLD, alt_rel_m=0.0)
STREAMING = replace(OK, setpoints_streaming=True)
OFFBOARD = replace(STREAMING, flight_mode=FlightMode.OFFBOARD)
HOLD_HERE = Command(K.START_SETPOINTS, stream=Stream.HOLD_HERE)
PLANNER = Command(K.START_SETPOINTS, stream=Stream.PLANNER)


def kinds(commands: list[Command]) -> list[CommandKind]:
    """The commands without their STATUSTEXTs."""
    return [c.kind for c in commands if c.kind is not K.STATUSTEXT]


def texts(commands: list[Command]) -> list[str]:
    return [c.text for c in commands if c.kind is K.STATUSTEXT]


def run(
    m: Mission, steps: list[MissionInputs], t0_s: float = 0.0
) -> tuple[Mission, list[list[Command]]]:
    """Advance one second per step; every tick's commands."""
    out = []
    for n, inputs in enumerate(steps):
        m, commands = advance(m, inputs, t0_s + n)
        out.append(commands)
    return m, out


def searching(**config: object) -> Mission:
    """A mission flown by the pilot into SEARCHING (manual OFFBOARD)."""
    m, _ = run(Mission(MissionConfig(**config)), [OK, OK, STREAMING, OFFBOARD])  # type: ignore[arg-type]
    assert m.state is State.SEARCHING and m.stream is Stream.PLANNER
    return m


def test_manual_path_waits_for_the_pilot_to_select_offboard() -> None:
    m = Mission(MissionConfig())
    m, ticks = run(m, [replace(OK, connected=False), OK, replace(OK, health_ok=False), OK])
    assert m.state is State.READY and m.stream is Stream.HOLD_HERE
    assert ticks[0] == [] and texts(ticks[1]) == ["vehicle connected: checking health"]
    assert ticks[2] == [] and kinds(ticks[3]) == [K.START_SETPOINTS] and ticks[3][0] == HOLD_HERE
    m, ticks = run(m, [STREAMING] * 30, 4.0)
    assert m.state is State.READY and all(t == [] for t in ticks)  # no START_OFFBOARD, ever
    m, commands = advance(m, OFFBOARD, 40.0)
    assert m.state is State.SEARCHING and commands[0] == PLANNER
    assert commands[-1].text == "offboard: searching" and m.search_started_s == 40.0


@pytest.mark.parametrize(
    "unhealthy",
    [replace(OK, health_ok=False), replace(OK, position_ok=False), replace(OK, battery_low=True)],
)
def test_waits_for_health(unhealthy: MissionInputs) -> None:
    m, ticks = run(Mission(MissionConfig(auto_arm_takeoff=True)), [unhealthy] * 10)
    assert m.state is State.WAITING_FOR_HEALTH and sum(map(len, ticks)) == 1
    ready, commands = advance(m, OK, 10.0)  # in the air already: no arming
    assert ready.state is State.READY and kinds(commands) == [K.START_SETPOINTS]
    # Bad health in READY: stop streaming and wait for it again.
    back, commands = advance(ready, unhealthy, 11.0)
    assert back.state is State.WAITING_FOR_HEALTH and kinds(commands) == [K.STOP_SETPOINTS]
    assert back.stream is None


def test_auto_arm_takeoff_and_offboard() -> None:
    cfg = MissionConfig(auto_arm_takeoff=True, auto_offboard=True, takeoff_alt_m=7.5)
    m, ticks = run(Mission(cfg), [
        ON_GROUND, ON_GROUND,                                   # connect, arm
        ON_GROUND,                                              # not armed yet
        replace(ON_GROUND, armed=True),                         # armed: take off
        replace(OK, in_air=False, flight_mode=FlightMode.TAKEOFF),
        replace(OK, flight_mode=FlightMode.TAKEOFF),            # climbing
        replace(OK, flight_mode=FlightMode.HOLD),               # takeoff done: READY
        replace(OK, flight_mode=FlightMode.HOLD),               # shell not streaming yet
        replace(STREAMING, flight_mode=FlightMode.HOLD),        # now: request OFFBOARD
        replace(STREAMING, flight_mode=FlightMode.HOLD),        # not granted yet: no repeat
        OFFBOARD,
    ])
    assert [kinds(t) for t in ticks] == [
        [], [K.ARM], [], [K.TAKEOFF], [], [], [K.START_SETPOINTS], [], [K.START_OFFBOARD], [],
        [K.START_SETPOINTS],
    ]
    assert ticks[3][0].takeoff_alt_m == 7.5 and ticks[10][0] == PLANNER
    assert m.state is State.SEARCHING


def test_no_auto_arm_unless_configured_and_arming_timeout_hands_over() -> None:
    m, ticks = run(Mission(MissionConfig(auto_offboard=True)), [ON_GROUND] * 50)
    assert m.state is State.READY and not any(
        k in (K.ARM, K.TAKEOFF, K.START_OFFBOARD) for t in ticks for k in kinds(t))
    m, ticks = run(Mission(MissionConfig(auto_arm_takeoff=True, arm_retry_s=5.0)),
                   [ON_GROUND] * 30)
    flat = [k for t in ticks for k in kinds(t)]
    assert m.state is State.READY and flat == [K.ARM] * 3 + [K.START_SETPOINTS]  # every 2 s
    assert "arming failed: pilot's turn" in [x for t in ticks for x in texts(t)]
    # Already armed on the ground: straight to the takeoff; in the air: no takeoff at all.
    m, ticks = run(Mission(MissionConfig(auto_arm_takeoff=True)), [OK, replace(OK, in_air=False)])
    assert m.state is State.TAKING_OFF and kinds(ticks[1]) == [K.TAKEOFF]
    m, _ = run(Mission(MissionConfig(auto_arm_takeoff=True)), [OK, OK])
    assert m.state is State.READY


def test_failed_takeoff_hands_over() -> None:
    cfg = MissionConfig(auto_arm_takeoff=True, takeoff_timeout_s=5.0)
    on_pad = replace(OK, in_air=False, flight_mode=FlightMode.HOLD)
    climbing = replace(on_pad, flight_mode=FlightMode.TAKEOFF)
    m, ticks = run(Mission(cfg), [on_pad, on_pad] + [climbing] * 10)
    assert m.state is State.READY and texts(ticks[6]) == ["takeoff failed: pilot's turn"]
    m, _ = run(Mission(cfg), [on_pad, on_pad, replace(on_pad, armed=False)])  # disarmed
    assert m.state is State.READY


@pytest.mark.parametrize("mode", [m for m in FlightMode if m is not FlightMode.OFFBOARD])
def test_pilot_takeover_stops_at_once_and_never_starts_offboard(mode: FlightMode) -> None:
    m = searching(auto_offboard=True)
    m, commands = advance(m, replace(OFFBOARD, flight_mode=mode), 10.0)
    assert m.state is State.PILOT_HAS_CONTROL and kinds(commands) == [K.STOP_SETPOINTS]
    assert commands[-1].severity is Severity.WARNING and mode.name in commands[-1].text
    flying = replace(STREAMING, flight_mode=mode)
    m, ticks = run(m, [flying] * 5 + [replace(flying, setpoints_streaming=False)] * 200, 11.0)
    flat = [k for t in ticks for k in kinds(t)]
    assert flat == [K.START_SETPOINTS] and K.START_OFFBOARD not in flat  # hold stream only
    assert ticks[5] == [HOLD_HERE]  # once the shell reports the planner stream stopped
    m, commands = advance(m, OFFBOARD, 300.0)  # the pilot selects OFFBOARD again
    assert m.state is State.SEARCHING and commands[0] == PLANNER


def test_without_resume_a_takeover_is_final_for_the_service() -> None:
    m = searching(auto_offboard=True, resume_on_pilot_offboard=False)
    m, _ = advance(m, STREAMING, 10.0)
    m, ticks = run(m, [OK] * 10 + [OFFBOARD] * 10 + [replace(OK, connected=False), OK, OK, OK]
                   + [OFFBOARD, OK, OFFBOARD] * 10, 11.0)
    flat = [k for t in ticks for k in kinds(t)]
    assert K.START_SETPOINTS not in flat and K.START_OFFBOARD not in flat
    assert m.state is State.READY and m.stream is None


def test_low_battery_stops_and_requests_rtl_lost_position_pauses() -> None:
    m, commands = advance(searching(), replace(OFFBOARD, battery_low=True), 10.0)
    assert m.state is State.FAILSAFE and kinds(commands) == [K.RTL, K.STOP_SETPOINTS]
    assert commands[-1].severity is Severity.CRITICAL
    assert run(m, [OFFBOARD, OK, replace(OK, connected=False)] * 10)[1] == [[]] * 30  # final
    for lost in (replace(OFFBOARD, position_ok=False), replace(OFFBOARD, health_ok=False)):
        m, commands = advance(searching(), lost, 10.0)
        assert m.state is State.PAUSED and kinds(commands) == [K.STOP_SETPOINTS]
        m, ticks = run(m, [lost] * 5, 11.0)
        assert m.state is State.PAUSED and ticks == [[]] * 5  # nothing commanded meanwhile
        back, commands = advance(m, OFFBOARD, 16.0)  # still in our OFFBOARD: carry on
        assert back.state is State.SEARCHING and commands[0] == PLANNER
        assert back.search_started_s == 3.0  # the time limit counts from the first start
        gone, commands = advance(m, replace(OFFBOARD, flight_mode=FlightMode.HOLD), 16.0)
        assert gone.state is State.PILOT_HAS_CONTROL and kinds(commands) == []  # a takeover
    # The mode changed in the same tick (the pilot or the autopilot reacted): no RTL over it.
    m, commands = advance(searching(), replace(OK, battery_low=True), 10.0)
    assert m.state is State.PILOT_HAS_CONTROL and kinds(commands) == [K.STOP_SETPOINTS]


@pytest.mark.parametrize(
    ("config", "inputs", "when_s"),
    [
        ({"end": "covered", "sweeps": 2}, replace(OFFBOARD, coverage_passes=2), 10.0),
        ({"end": "targets"}, replace(OFFBOARD, expected_targets=3, confirmed_targets=3), 10.0),
        ({"end": "time", "time_limit_s": 60.0}, OFFBOARD, 63.0),
        # The time limit always applies.
        ({"end": "covered", "sweeps": 2, "time_limit_s": 60.0}, OFFBOARD, 63.0),
    ],
)
@pytest.mark.parametrize(("action", "kind"), [("hold", K.HOLD), ("land", K.LAND), ("rtl", K.RTL)])
def test_end_action_is_issued_exactly_once(
    config: dict[str, object], inputs: MissionInputs, when_s: float, action: str, kind: CommandKind
) -> None:
    m = searching(end_action=action, **config)  # SEARCHING since t = 3 s
    not_yet = replace(OFFBOARD, coverage_passes=1, expected_targets=3, confirmed_targets=2)
    m, ticks = run(m, [not_yet] * 5, 4.0)
    assert m.state is State.SEARCHING and ticks == [[]] * 5
    m, commands = advance(m, inputs, when_s)
    assert m.state is State.DONE and kinds(commands) == [kind, K.STOP_SETPOINTS]
    assert commands[-1].text.endswith(f": {action}")
    m, ticks = run(m, [inputs, OK, replace(OK, connected=False), OFFBOARD] * 20, when_s + 1)
    assert ticks == [[]] * 80


def test_zero_or_unknown_expected_targets_never_end_the_search() -> None:
    m = searching(end="targets")
    m, ticks = run(m, [replace(OFFBOARD, expected_targets=None, confirmed_targets=5),
                       replace(OFFBOARD, expected_targets=0)] * 5, 4.0)
    assert m.state is State.SEARCHING and ticks == [[]] * 10


def test_reconnection_after_link_loss_does_not_take_control() -> None:
    m = searching(auto_offboard=True, auto_arm_takeoff=True)
    m, commands = advance(m, replace(OFFBOARD, connected=False), 10.0)
    assert m.state is State.WAITING_FOR_VEHICLE and kinds(commands) == [K.STOP_SETPOINTS]
    # Back after a short cut, still in OFFBOARD (stale: the autopilot's failsafe is due): we
    # neither stream nor request anything until the mode has left OFFBOARD.
    m, ticks = run(m, [OFFBOARD] * 10, 11.0)
    assert m.state is State.READY and m.stream is None
    assert [k for t in ticks for k in kinds(t)] == []
    m, ticks = run(m, [replace(STREAMING, flight_mode=FlightMode.HOLD)] * 50
                   + [replace(ON_GROUND, setpoints_streaming=True)] * 50, 21.0)
    flat = [k for t in ticks for k in kinds(t)]
    assert flat == [K.START_SETPOINTS] and m.state is State.READY  # hold stream, no ARM/OFFBOARD
    m, commands = advance(m, OFFBOARD, 200.0)  # the pilot may take it from there
    assert m.state is State.SEARCHING and commands[0] == PLANNER


def test_link_cut_after_arming_or_ready_spends_the_automatic_steps() -> None:
    cfg = MissionConfig(auto_arm_takeoff=True, auto_offboard=True)
    cut = replace(ON_GROUND, connected=False)
    m, ticks = run(Mission(cfg), [ON_GROUND, ON_GROUND, cut, ON_GROUND, ON_GROUND, STREAMING,
                                  STREAMING, OFFBOARD])
    assert [k for t in ticks for k in kinds(t)] == [K.ARM, K.START_SETPOINTS, K.START_SETPOINTS]
    assert m.state is State.SEARCHING  # only because the pilot selected OFFBOARD
    # READY on the ground, auto_offboard waiting for the takeoff: a cut spends it too.
    m, ticks = run(Mission(MissionConfig(auto_offboard=True)),
                   [ON_GROUND, ON_GROUND, cut, ON_GROUND, ON_GROUND] + [STREAMING] * 20)
    assert m.state is State.READY and K.START_OFFBOARD not in [k for t in ticks for k in kinds(t)]


def test_link_cut_before_anything_was_commanded_keeps_auto_offboard() -> None:
    m, ticks = run(Mission(MissionConfig(auto_offboard=True)),
                   [replace(OK, health_ok=False), replace(OK, connected=False), OK, OK, STREAMING])
    assert m.state is State.READY and kinds(ticks[-1]) == [K.START_OFFBOARD]


# ---------------------------------------------------------------------------------------------
# Real firmware: the orders of events ArduPilot and PX4 were seen to produce
# ---------------------------------------------------------------------------------------------

AUTO = MissionConfig(auto_arm_takeoff=True, auto_offboard=True, takeoff_alt_m=8.0)
AP_GROUND = replace(ON_GROUND, flight_mode=FlightMode.MANUAL, autopilot=Autopilot.ARDUPILOT)
AP_ARMED = replace(AP_GROUND, armed=True)
AP_GUIDED = replace(AP_ARMED, flight_mode=FlightMode.OFFBOARD)  # MAVSDK: GUIDED is "OFFBOARD"
NEVER_AGAIN = (K.ARM, K.TAKEOFF, K.START_OFFBOARD)


def climbing(base: MissionInputs, alt_m: float) -> MissionInputs:
    return replace(base, in_air=True, alt_rel_m=alt_m)


def ardupilot_taking_off() -> tuple[Mission, list[list[Command]]]:
    """The automatic flight on ArduPilot up to the GUIDED take-off under way (in air at 3 m)."""
    m, ticks = run(Mission(AUTO), [AP_GROUND, AP_GROUND, AP_ARMED, AP_GUIDED, AP_GUIDED,
                                   climbing(AP_GUIDED, 1.0), climbing(AP_GUIDED, 3.0)])
    assert [kinds(t) for t in ticks] == [[], [K.ARM], [K.TAKEOFF], [], [], [], []]
    assert m.state is State.TAKING_OFF
    return m, ticks


def test_ardupilot_guided_takeoff_searches_by_itself_once_at_altitude() -> None:
    m, _ = ardupilot_taking_off()
    # GUIDED from the heartbeat before "in air": nothing streams while ArduPilot climbs.
    m, ticks = run(m, [climbing(AP_GUIDED, 5.0), climbing(replace(AP_GUIDED,
                                                                  setpoints_streaming=True), 6.8)])
    assert ticks == [[], []] and m.state is State.TAKING_OFF
    m, commands = advance(m, climbing(AP_GUIDED, 7.6), 20.0)
    assert m.state is State.SEARCHING and commands[0] == PLANNER
    assert kinds(commands) == [K.START_SETPOINTS]  # no mode request: the take-off chose GUIDED
    assert texts(commands) == ["airborne in guided: searching"]


def test_ardupilot_guided_takeoff_without_auto_offboard_waits_for_the_pilot() -> None:
    m, _ = run(Mission(replace(AUTO, auto_offboard=False)),
               [AP_GROUND, AP_GROUND, AP_ARMED, AP_GUIDED, climbing(AP_GUIDED, 8.0)])
    assert m.state is State.READY and m.stream is None  # no stream into GUIDED
    loiter = climbing(replace(AP_GUIDED, flight_mode=FlightMode.HOLD), 8.0)
    m, ticks = run(m, [loiter] * 5 + [climbing(AP_GUIDED, 8.0)], 5.0)  # the pilot: LOITER, GUIDED
    assert [kinds(t) for t in ticks] == [[K.START_SETPOINTS], [], [], [], [], [K.START_SETPOINTS]]
    assert m.state is State.SEARCHING and ticks[-1][0] == PLANNER


@pytest.mark.parametrize("mode", [FlightMode.HOLD, FlightMode.LAND], ids=["loiter", "land"])
@pytest.mark.parametrize("when", ["taking-off", "at-altitude-stalled", "searching"])
def test_ardupilot_pilot_mode_is_never_overridden(mode: FlightMode, when: str) -> None:
    """The pilot's LOITER or LAND at any point: no mode request, arm or take-off after it."""
    m, ticks = ardupilot_taking_off()
    if when == "at-altitude-stalled":  # the old stall: in READY in our own GUIDED
        m, _ = run(Mission(replace(AUTO, auto_offboard=False)),
                   [AP_GROUND, AP_GROUND, AP_ARMED, AP_GUIDED, climbing(AP_GUIDED, 8.0)])
    elif when == "searching":
        m, _ = run(m, [climbing(AP_GUIDED, 8.0)], 10.0)
        assert m.state is State.SEARCHING
    pilot = climbing(replace(AP_ARMED, flight_mode=mode, setpoints_streaming=True), 6.0)
    m, commands = advance(m, pilot, 30.0)
    assert m.state is State.PILOT_HAS_CONTROL or (m.state is State.READY
                                                 and when == "at-altitude-stalled")
    later = [pilot] * 5 + [replace(pilot, setpoints_streaming=False)] * 100
    later += [replace(AP_ARMED, flight_mode=mode)] * 20  # landed, still armed
    m, ticks = run(m, later, 31.0)
    flat = [k for t in [commands, *ticks] for k in kinds(t)]
    assert not set(flat) & set(NEVER_AGAIN)


def test_px4_landed_state_ahead_of_the_heartbeat_is_not_airborne() -> None:
    on_pad = replace(ON_GROUND, flight_mode=FlightMode.HOLD)
    m, _ = run(Mission(AUTO), [on_pad, on_pad, replace(on_pad, armed=True)])
    assert m.state is State.TAKING_OFF
    # "taking off" (in air) arrives before the AUTO.TAKEOFF heartbeat: still Hold, at 0 m.
    m, ticks = run(m, [climbing(replace(on_pad, armed=True), -0.01),
                       climbing(replace(on_pad, armed=True, flight_mode=FlightMode.TAKEOFF), 0.3),
                       climbing(replace(on_pad, armed=True, flight_mode=FlightMode.TAKEOFF), 5.0)],
                   3.0)
    assert ticks == [[], [], []] and m.state is State.TAKING_OFF
    # PX4 ends its take-off in Hold within NAV_MC_ALT_RAD (0.8 m) of the altitude: ours.
    m, ticks = run(m, [climbing(replace(STREAMING, flight_mode=FlightMode.HOLD), 7.2)] * 2
                   + [climbing(OFFBOARD, 8.0)], 6.0)
    assert [kinds(t) for t in ticks] == [[K.START_SETPOINTS], [K.START_OFFBOARD],
                                         [K.START_SETPOINTS]]
    assert m.state is State.SEARCHING


def test_px4_pilot_hold_during_the_takeoff_is_a_takeover() -> None:
    on_pad = replace(ON_GROUND, flight_mode=FlightMode.HOLD)
    taking_off = climbing(replace(on_pad, armed=True, flight_mode=FlightMode.TAKEOFF), 3.0)
    m, _ = run(Mission(AUTO), [on_pad, on_pad, replace(on_pad, armed=True), taking_off])
    hold = climbing(replace(STREAMING, flight_mode=FlightMode.HOLD), 3.2)  # low: not ours
    m, ticks = run(m, [hold] * 3 + [replace(hold, setpoints_streaming=False)] * 50, 4.0)
    assert m.state is State.PILOT_HAS_CONTROL
    assert not {k for t in ticks for k in kinds(t)} & set(NEVER_AGAIN)


def test_px4_hold_high_in_the_takeoff_that_never_reaches_the_altitude_asks_for_nothing() -> None:
    on_pad = replace(ON_GROUND, flight_mode=FlightMode.HOLD)
    taking_off = climbing(replace(on_pad, armed=True, flight_mode=FlightMode.TAKEOFF), 5.0)
    m, _ = run(Mission(replace(AUTO, takeoff_timeout_s=20.0)),
               [on_pad, on_pad, replace(on_pad, armed=True), taking_off])
    hold = climbing(replace(STREAMING, flight_mode=FlightMode.HOLD), 5.5)  # a pilot's, at 5.5 m
    m, ticks = run(m, [hold] * 40, 4.0)
    assert m.state is State.READY  # "takeoff failed: pilot's turn"
    assert not {k for t in ticks for k in kinds(t)} & set(NEVER_AGAIN)


def test_a_refused_arm_is_asked_again_until_a_mode_change_or_the_timeout() -> None:
    on_pad = replace(ON_GROUND, flight_mode=FlightMode.HOLD)
    m, ticks = run(Mission(AUTO), [on_pad] * 6)  # refused (PX4: "velocity unstable")
    assert [kinds(t) for t in ticks] == [[], [K.ARM], [], [K.ARM], [], [K.ARM]]
    m, ticks = run(m, [replace(on_pad, armed=True)], 6.0)
    assert kinds(ticks[0]) == [K.TAKEOFF]
    m, ticks = run(Mission(AUTO), [on_pad, on_pad, on_pad, replace(on_pad,
                                   flight_mode=FlightMode.POSCTL)] + [on_pad] * 30)
    flat = [k for t in ticks for k in kinds(t)]
    assert flat == [K.ARM]  # the pilot's mode: no retry (and on the ground nothing to hold)
    assert m.state is State.PILOT_HAS_CONTROL


def ready_to_ask(**config: object) -> Mission:
    """Airborne after our own take-off, streaming: the tick that asks for OFFBOARD is next."""
    cfg = replace(AUTO, **config)  # type: ignore[arg-type]
    hold = replace(STREAMING, flight_mode=FlightMode.HOLD, alt_rel_m=8.0)
    m, _ = run(Mission(cfg), [ON_GROUND, ON_GROUND, replace(ON_GROUND, armed=True),
                              replace(hold, flight_mode=FlightMode.TAKEOFF), hold])
    assert m.state is State.READY and m.stream is Stream.HOLD_HERE
    return m


HOLD_UP = replace(STREAMING, flight_mode=FlightMode.HOLD, alt_rel_m=8.0)


def test_an_unanswered_offboard_request_is_asked_again_every_2_s_until_the_timeout() -> None:
    m, ticks = run(ready_to_ask(offboard_retry_s=7.0), [HOLD_UP] * 12, 5.0)  # lost, or refused
    assert [kinds(t) for t in ticks] == [[K.START_OFFBOARD], [], [K.START_OFFBOARD], [],
                                         [K.START_OFFBOARD], [], [K.START_OFFBOARD], [], [],
                                         [], [], []]
    assert texts(ticks[7]) == ["offboard refused: pilot's turn"]
    assert ticks[7][0].severity is Severity.WARNING and m.state is State.READY
    m, ticks = run(m, [HOLD_UP] * 10 + [OFFBOARD], 17.0)  # the pilot's OFFBOARD still works
    assert all(kinds(t) == [] for t in ticks[:-1]) and ticks[-1][0] == PLANNER


def test_an_offboard_granted_on_a_retry_starts_the_search() -> None:
    m, ticks = run(ready_to_ask(), [HOLD_UP] * 3 + [OFFBOARD], 5.0)
    assert [kinds(t) for t in ticks] == [[K.START_OFFBOARD], [], [K.START_OFFBOARD],
                                         [K.START_SETPOINTS]]
    assert m.state is State.SEARCHING


@pytest.mark.parametrize("mode", [FlightMode.POSCTL, FlightMode.ALTCTL, FlightMode.RTL])
def test_a_mode_change_while_offboard_is_awaited_ends_the_retries(mode: FlightMode) -> None:
    other = replace(HOLD_UP, flight_mode=mode)
    _, ticks = run(ready_to_ask(), [HOLD_UP, other] + [other] * 10 + [HOLD_UP] * 10, 5.0)
    assert [k for t in ticks for k in kinds(t)] == [K.START_OFFBOARD]


def test_no_offboard_retry_after_leaving_ready() -> None:
    m, ticks = run(ready_to_ask(), [HOLD_UP, replace(HOLD_UP, position_ok=False), HOLD_UP,
                                    HOLD_UP, replace(HOLD_UP, setpoints_streaming=False)]
                   + [HOLD_UP] * 10, 5.0)
    assert m.state is State.READY
    assert [k for t in ticks for k in kinds(t)].count(K.START_OFFBOARD) == 1


def test_mode_changes_before_the_first_decision_are_only_the_baseline() -> None:
    booting = replace(ON_GROUND, health_ok=False, flight_mode=FlightMode.MANUAL)
    m, ticks = run(Mission(AUTO), [booting, replace(booting, flight_mode=FlightMode.HOLD),
                                   replace(ON_GROUND, flight_mode=FlightMode.HOLD)])
    assert kinds(ticks[-1]) == [K.ARM] and m.state is State.ARMING


@pytest.mark.parametrize(
    ("config", "key"),
    [
        ({"takeoff_alt_m": 0.0}, "mission.takeoff_alt_m"),
        ({"takeoff_alt_m": float("nan")}, "mission.takeoff_alt_m"),
        ({"time_limit_s": -1.0}, "mission.time_limit_s"),
        ({"arm_retry_s": True}, "mission.arm_retry_s"),
        ({"offboard_retry_s": 0}, "mission.offboard_retry_s"),
        ({"takeoff_timeout_s": float("inf")}, "mission.takeoff_timeout_s"),
        ({"sweeps": 0}, "search.sweeps"),
        ({"sweeps": 1.5}, "search.sweeps"),
        ({"end": "forever"}, "mission.end"),
        ({"end_action": "crash"}, "mission.end_action"),
    ],
)
def test_bad_config_names_the_key(config: dict[str, object], key: str) -> None:
    with pytest.raises(ConfigError) as err:
        MissionConfig(**config)  # type: ignore[arg-type]
    assert err.value.key == key


# ---------------------------------------------------------------------------------------------
# Over any input sequence
# ---------------------------------------------------------------------------------------------


def mostly(p_true: float) -> st.SearchStrategy[bool]:
    return st.integers(0, 99).map(lambda n: n < 100 * p_true)


INPUTS = st.builds(
    MissionInputs,
    connected=mostly(0.95), health_ok=mostly(0.95), armed=mostly(0.9), in_air=mostly(0.9),
    flight_mode=st.sampled_from([FlightMode.OFFBOARD] * 6 + list(FlightMode)),
    battery_low=mostly(0.03), position_ok=mostly(0.95), coverage_passes=st.integers(0, 2),
    confirmed_targets=st.integers(0, 3), expected_targets=st.none() | st.integers(0, 3),
    setpoints_streaming=st.booleans(),
)


@settings(deadline=None, max_examples=300, derandomize=True)
@given(st.booleans(), st.booleans(), st.booleans(), st.sampled_from(["covered", "targets", "time"]),
       st.lists(INPUTS, max_size=60))
def test_rules_hold_over_random_sequences(
    auto_arm: bool, auto_offboard: bool, resume: bool, end: str, steps: list[MissionInputs]
) -> None:
    cfg = MissionConfig(auto_arm_takeoff=auto_arm, auto_offboard=auto_offboard,
                        resume_on_pilot_offboard=resume, end=end, sweeps=2,  # type: ignore[arg-type]
                        time_limit_s=40.0)
    m, prefix = run(Mission(cfg), [OK, OK, STREAMING, OFFBOARD])
    assert m.state is State.SEARCHING
    all_kinds = [k for t in prefix for k in kinds(t)]
    assert all_kinds.count(K.START_OFFBOARD) == int(auto_offboard)
    lost_control = False
    for n, inputs in enumerate(steps):
        new, commands = advance(m, inputs, 4.0 + n)
        ks = kinds(commands)
        all_kinds += ks
        assert all(len(c.text) <= 50 for c in commands)
        if new.state is not m.state:  # every transition says so, last
            assert texts(commands) != [] and commands[-1].kind is K.STATUSTEXT
        if m.state is State.SEARCHING and new.state is not State.SEARCHING:
            # let go in the same tick: at once, or right after the end's or failsafe's request
            assert K.STOP_SETPOINTS in ks[:2] and ks.index(K.STOP_SETPOINTS) == (
                ks[0] in (K.HOLD, K.LAND, K.RTL))
            lost_control = True
        if lost_control:
            assert K.START_OFFBOARD not in ks and K.ARM not in ks and K.TAKEOFF not in ks
        if PLANNER in commands:
            assert inputs.flight_mode is FlightMode.OFFBOARD and new.state is State.SEARCHING
        if K.RTL in ks and new.state is State.FAILSAFE:
            assert inputs.battery_low
        m = new
    assert all_kinds.count(K.START_OFFBOARD) == int(auto_offboard)
    assert all_kinds.count(K.HOLD) + all_kinds.count(K.LAND) + all_kinds.count(K.RTL) <= 1
    assert K.ARM not in all_kinds  # in the air from the start
