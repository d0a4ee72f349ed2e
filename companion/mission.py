"""The mission state machine: a pure step from what the service observed to what it must do.

`advance(mission, inputs, t_s)` returns the next `Mission` and the `Command`s the shell carries
out in order. Rules that hold on every path:

* START_OFFBOARD is one request per mission, only with `auto_offboard`, only from READY, only
  while our setpoints stream and the vehicle is armed and in the air; never after a pilot
  takeover or a link loss (the pilot selects OFFBOARD then). A request the autopilot refuses or
  never answers (a lossy link) is asked again every 2 s for `offboard_retry_s`, as long as no
  mode change was seen since the first ask. ARM likewise (`arm_retry_s`); TAKEOFF at most once.
* Whenever we stop commanding (mode changed by someone else, failsafe, end, link lost) the same
  tick carries STOP_SETPOINTS (which asks for no mode). From our own OFFBOARD, the end action's
  or the low battery's mode request comes first: the stream goes on while a lossy link retries
  it, so that PX4 does not meet a lapsed stream (its offboard-loss failsafe) on the way.
* After a takeover, with `resume_on_pilot_offboard` the shell streams HOLD_HERE setpoints (the
  vehicle's current position, ignored by the autopilot outside OFFBOARD) once it reports the
  planner stream stopped, so that PX4 accepts OFFBOARD if the pilot selects it; the search then
  resumes. Without it nothing is streamed and the service never flies again in this mission.
* The service never requests a mode, arms or takes off after anyone else changed the mode.
  Every mode change it sees once it has started deciding is either one its own last command
  leads to (`Mission.expected_modes`: its take-off's AUTO.TAKEOFF then Hold on PX4, GUIDED on
  ArduPilot; its OFFBOARD request) or someone else's: the pilot's, a ground station's or the
  autopilot's own failsafe. Someone else's spends every automatic step for good.
* "Airborne" is the vehicle in the air *and* at the take-off altitude, whichever of the landed
  state and the heartbeat comes first; nothing streams during a take-off the autopilot flies.
  After its own take-off on ArduPilot (GUIDED, which MAVSDK reports as OFFBOARD) the search
  starts by itself once airborne, with `auto_offboard`.
* A lost position or health flag while searching is a pause (PAUSED: nothing is commanded);
  the search resumes when it is usable again if the vehicle is still in OFFBOARD, and a mode
  left meanwhile is a takeover.
* DONE and FAILSAFE are final: a new mission needs a new `Mission`.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from enum import Enum, IntEnum
from typing import Literal

from companion.errors import ConfigError

STATUSTEXT_MAX = 50  # MAVLink STATUSTEXT payload, characters
RETRY_EVERY_S = 2.0  # a refused arm or OFFBOARD is asked again this often (PX4's refusals)
# Airborne: within 1 m of the take-off altitude (PX4 ends its take-off within NAV_MC_ALT_RAD,
# 0.8 m by default), or at 85 % of a low one.
TAKEOFF_REACHED_FRACTION = 0.85
TAKEOFF_REACHED_M = 1.0
# PX4's switch from AUTO.TAKEOFF to Hold is its own above half the altitude: the heartbeat that
# shows it can come with a position a few tenths of a second old, taken on the climb. A pilot's
# Hold higher up is taken for it, but the take-off then never counts as done unless the vehicle
# is within TAKEOFF_REACHED_M, and a take-off that fails spends the automatic offboard.
PX4_TAKEOFF_END_FRACTION = 0.5


class FlightMode(Enum):
    """The autopilot's flight mode as the service sees it; OFFBOARD is the one we fly in."""

    OFFBOARD = "offboard"
    HOLD = "hold"
    POSCTL = "posctl"
    ALTCTL = "altctl"
    MANUAL = "manual"
    MISSION = "mission"
    TAKEOFF = "takeoff"
    LAND = "land"
    RTL = "rtl"
    OTHER = "other"
    UNKNOWN = "unknown"


class Autopilot(Enum):
    """The firmware family: its own take-off selects different modes."""

    PX4 = "px4"
    ARDUPILOT = "ardupilot"


class State(Enum):
    """Where the mission is."""

    WAITING_FOR_VEHICLE = "waiting_for_vehicle"
    WAITING_FOR_HEALTH = "waiting_for_health"
    ARMING = "arming"
    TAKING_OFF = "taking_off"
    READY = "ready"
    SEARCHING = "searching"
    PAUSED = "paused"  # searching, but the position is unusable: nothing is commanded
    PILOT_HAS_CONTROL = "pilot_has_control"
    FAILSAFE = "failsafe"
    DONE = "done"


class Stream(Enum):
    """What the shell streams as setpoints: the vehicle's current position, or the planner's."""

    HOLD_HERE = "hold_here"
    PLANNER = "planner"


class Severity(IntEnum):
    """MAV_SEVERITY of a STATUSTEXT."""

    EMERGENCY = 0
    ALERT = 1
    CRITICAL = 2
    ERROR = 3
    WARNING = 4
    NOTICE = 5
    INFO = 6
    DEBUG = 7


class CommandKind(Enum):
    """What a Command asks the shell to do."""

    ARM = "arm"
    TAKEOFF = "takeoff"
    START_SETPOINTS = "start_setpoints"
    STOP_SETPOINTS = "stop_setpoints"
    START_OFFBOARD = "start_offboard"
    HOLD = "hold"
    LAND = "land"
    RTL = "rtl"
    STATUSTEXT = "statustext"


@dataclass(frozen=True, slots=True)
class Command:
    """One thing for the shell to do; only the fields of its kind are set."""

    kind: CommandKind
    takeoff_alt_m: float | None = None  # TAKEOFF: above home
    stream: Stream | None = None  # START_SETPOINTS: what to stream until STOP_SETPOINTS
    text: str = ""  # STATUSTEXT, <= 50 characters
    severity: Severity | None = None  # STATUSTEXT


@dataclass(frozen=True, slots=True, kw_only=True)
class MissionConfig:
    """What the service may do by itself, when the mission ends and what it asks then.

    end: "covered" (coverage_passes >= sweeps), "targets" (all expected targets confirmed) or
    "time"; the time limit, counted from the first entry into SEARCHING, always applies.
    """

    auto_arm_takeoff: bool = False
    auto_offboard: bool = False
    takeoff_alt_m: float = 10.0
    resume_on_pilot_offboard: bool = True
    end: Literal["covered", "targets", "time"] = "covered"
    sweeps: int = 1
    time_limit_s: float = 900.0
    end_action: Literal["hold", "land", "rtl"] = "land"
    arm_retry_s: float = 20.0  # a refused arm is asked again every 2 s for this long
    offboard_retry_s: float = 20.0  # an unanswered or refused OFFBOARD request likewise
    takeoff_timeout_s: float = 60.0

    def __post_init__(self) -> None:
        """Check every value once."""
        for key in ("takeoff_alt_m", "time_limit_s", "arm_retry_s", "offboard_retry_s",
                    "takeoff_timeout_s"):
            value: object = getattr(self, key)
            if isinstance(value, bool) or not (
                isinstance(value, int | float) and math.isfinite(value) and value > 0
            ):
                raise ConfigError(f"mission.{key}", f"must be a finite number > 0, got {value!r}")
        sweeps: object = self.sweeps
        if isinstance(sweeps, bool) or not isinstance(sweeps, int) or sweeps < 1:
            raise ConfigError("search.sweeps", f"must be an integer >= 1, got {sweeps!r}")
        if self.end not in ("covered", "targets", "time"):
            raise ConfigError("mission.end", f'must be "covered", "targets" or "time", '
                                             f"got {self.end!r}")
        if self.end_action not in ("hold", "land", "rtl"):
            raise ConfigError("mission.end_action", f'must be "hold", "land" or "rtl", '
                                                    f"got {self.end_action!r}")


@dataclass(frozen=True, slots=True)
class MissionInputs:
    """What the service observed this tick."""

    connected: bool
    health_ok: bool  # the autopilot's position estimate and home are good
    armed: bool
    in_air: bool
    flight_mode: FlightMode
    battery_low: bool
    position_ok: bool  # the position telemetry is fresh
    coverage_passes: int
    confirmed_targets: int
    expected_targets: int | None
    setpoints_streaming: bool  # the shell is actually sending setpoints now
    alt_rel_m: float | None = None  # above home (the autopilot's relative altitude)
    autopilot: Autopilot = Autopilot.PX4


@dataclass(frozen=True, slots=True)
class Mission:
    """The mission's state value; start with Mission(config)."""

    config: MissionConfig
    state: State = State.WAITING_FOR_VEHICLE
    since_s: float = 0.0  # when the state was entered
    stream: Stream | None = None  # what the shell was last told to stream
    auto_arm_spent: bool = False
    auto_offboard_spent: bool = False
    pilot_took_over: bool = False
    search_started_s: float | None = None
    deciding: bool = False  # past WAITING_FOR_HEALTH once: mode changes are judged from then
    mode_seen: FlightMode | None = None  # the mode at the last tick (UNKNOWN never counts)
    mode_ours: bool = False  # the current mode came from our own last command
    mode_fresh: bool = False  # the current mode was entered while we watched
    expected_modes: frozenset[FlightMode] = frozenset()  # what our last command leads to
    arm_asked_s: float = 0.0  # when ARM was last asked
    offboard_first_s: float | None = None  # our OFFBOARD request awaits its mode since then
    offboard_asked_s: float = 0.0  # when OFFBOARD was last asked


_END_COMMAND = {"hold": CommandKind.HOLD, "land": CommandKind.LAND, "rtl": CommandKind.RTL}
_STOP = Command(CommandKind.STOP_SETPOINTS)


def statustext(text: str, severity: Severity = Severity.INFO) -> Command:
    """A STATUSTEXT command, cut to the MAVLink limit of 50 characters."""
    return Command(CommandKind.STATUSTEXT, text=text[:STATUSTEXT_MAX], severity=severity)


def _start(stream: Stream) -> Command:
    return Command(CommandKind.START_SETPOINTS, stream=stream)


def _go(
    m: Mission, state: State, t_s: float, text: str, severity: Severity,
    commands: list[Command], **changes: object,
) -> tuple[Mission, list[Command]]:
    """A transition: the new state with `changes`, the commands and then a STATUSTEXT."""
    new = dataclasses.replace(m, state=state, since_s=t_s, **changes)  # type: ignore[arg-type]
    return new, [*commands, statustext(text, severity)]


def _stop(m: Mission) -> list[Command]:
    return [_STOP] if m.stream is not None else []


def _takeoff_reached(cfg: MissionConfig, i: MissionInputs) -> bool:
    """At the take-off altitude (within 1 m, or 15 % of a low one)."""
    margin_m = min(TAKEOFF_REACHED_M, (1.0 - TAKEOFF_REACHED_FRACTION) * cfg.takeoff_alt_m)
    return i.alt_rel_m is not None and i.alt_rel_m >= cfg.takeoff_alt_m - margin_m


def _takeoff_modes(autopilot: Autopilot) -> frozenset[FlightMode]:
    """The modes our own take-off puts the vehicle in (PX4's Hold only once up: see _observe)."""
    if autopilot is Autopilot.ARDUPILOT:
        return frozenset({FlightMode.OFFBOARD})  # GUIDED: MAVSDK's take-off selects it
    return frozenset({FlightMode.TAKEOFF, FlightMode.HOLD})


def _observe(m: Mission, i: MissionInputs) -> Mission:
    """Follow the flight mode: whose doing is each change? Someone else's spends every
    automatic step. Before the service starts deciding, a change only moves the baseline."""
    mode = i.flight_mode
    if mode is FlightMode.UNKNOWN or mode is m.mode_seen:
        return m
    if not m.deciding or m.mode_seen is None:
        return dataclasses.replace(m, mode_seen=mode, mode_ours=False, mode_fresh=False)
    ours = mode in m.expected_modes
    if (ours and mode is FlightMode.HOLD and m.mode_seen is FlightMode.TAKEOFF
            and (i.alt_rel_m is None or i.alt_rel_m < PX4_TAKEOFF_END_FRACTION
                 * m.config.takeoff_alt_m)):
        ours = False  # PX4 ends its take-off in Hold near the altitude; low down, someone else
    return dataclasses.replace(
        m, mode_seen=mode, mode_ours=ours, mode_fresh=True,
        auto_arm_spent=m.auto_arm_spent or not ours,
        auto_offboard_spent=m.auto_offboard_spent or not ours)


def _may_hold_stream(m: Mission, i: MissionInputs) -> bool:
    """Stream HOLD_HERE in READY: never into an OFFBOARD (stale, or our ArduPilot take-off's
    GUIDED without auto_offboard), nor after a takeover without resume."""
    return i.flight_mode is not FlightMode.OFFBOARD and not (
        m.pilot_took_over and not m.config.resume_on_pilot_offboard
    )


def _enter_ready(
    m: Mission, i: MissionInputs, t_s: float, text: str, severity: Severity = Severity.INFO
) -> tuple[Mission, list[Command]]:
    stream = _may_hold_stream(m, i) and m.stream is None
    return _go(m, State.READY, t_s, text, severity, [_start(Stream.HOLD_HERE)] if stream else [],
               stream=Stream.HOLD_HERE if stream else m.stream)


def _start_search(m: Mission, t_s: float, text: str,
                  **changes: object) -> tuple[Mission, list[Command]]:
    return _go(m, State.SEARCHING, t_s, text, Severity.INFO, [_start(Stream.PLANNER)],
               stream=Stream.PLANNER,
               search_started_s=t_s if m.search_started_s is None else m.search_started_s,
               **changes)


def _takeover(m: Mission, i: MissionInputs, t_s: float) -> tuple[Mission, list[Command]]:
    return _go(m, State.PILOT_HAS_CONTROL, t_s, f"mode {i.flight_mode.name}: pilot has control",
               Severity.WARNING, _stop(m), stream=None, pilot_took_over=True,
               auto_arm_spent=True, auto_offboard_spent=True)


def _end_reason(cfg: MissionConfig, i: MissionInputs, searched_s: float) -> str | None:
    if cfg.end == "covered" and i.coverage_passes >= cfg.sweeps:
        return f"area covered {i.coverage_passes}x"
    if (cfg.end == "targets" and i.expected_targets is not None and i.expected_targets > 0
            and i.confirmed_targets >= i.expected_targets):
        return f"all {i.expected_targets} targets confirmed"
    if searched_s >= cfg.time_limit_s:
        return "time limit reached"
    return None


def _searching(m: Mission, i: MissionInputs, t_s: float) -> tuple[Mission, list[Command]]:
    cfg = m.config
    if i.flight_mode is not FlightMode.OFFBOARD:  # someone else chose a mode: let go at once
        return _takeover(m, i, t_s)
    if i.battery_low:
        return _go(m, State.FAILSAFE, t_s, "battery low: stopped, requesting RTL",
                   Severity.CRITICAL, [Command(CommandKind.RTL), *_stop(m)], stream=None)
    usable = i.health_ok and i.position_ok
    if m.state is State.PAUSED:
        if not usable:
            return m, []
        return _start_search(m, t_s, "position back: searching")
    if not usable:
        return _go(m, State.PAUSED, t_s, "position lost: paused, not commanding",
                   Severity.CRITICAL, [_STOP], stream=None)
    started_s = t_s if m.search_started_s is None else m.search_started_s
    reason = _end_reason(cfg, i, t_s - started_s)
    if reason is not None:
        return _go(m, State.DONE, t_s, f"{reason}: {cfg.end_action}", Severity.NOTICE,
                   [Command(_END_COMMAND[cfg.end_action]), _STOP], stream=None)
    return m, []


def _pilot_has_control(m: Mission, i: MissionInputs, t_s: float) -> tuple[Mission, list[Command]]:
    healthy = i.health_ok and i.position_ok and not i.battery_low
    flying = i.armed and i.in_air
    if not (healthy and flying and m.config.resume_on_pilot_offboard):  # landed: nothing to hold
        return (dataclasses.replace(m, stream=None), [_STOP]) if m.stream else (m, [])
    if i.flight_mode is FlightMode.OFFBOARD and (m.stream is Stream.HOLD_HERE or m.mode_fresh):
        return _start_search(m, t_s, "pilot chose offboard: searching")
    if m.stream is None and i.flight_mode is not FlightMode.OFFBOARD and not i.setpoints_streaming:
        return dataclasses.replace(m, stream=Stream.HOLD_HERE), [_start(Stream.HOLD_HERE)]
    return m, []


def _asked(m: Mission, command: Command, t_s: float, autopilot: Autopilot) -> Mission:
    """The bookkeeping of an automatic command: the modes it leads to, when ARM was asked."""
    if command.kind is CommandKind.TAKEOFF:
        return dataclasses.replace(m, expected_modes=_takeoff_modes(autopilot))
    if command.kind is CommandKind.START_OFFBOARD:
        first_s = t_s if m.offboard_first_s is None else m.offboard_first_s
        return dataclasses.replace(m, expected_modes=frozenset({FlightMode.OFFBOARD}),
                                   offboard_first_s=first_s, offboard_asked_s=t_s)
    if command.kind is CommandKind.ARM:
        return dataclasses.replace(m, arm_asked_s=t_s)
    return m


def _takeoff(m: Mission, i: MissionInputs, t_s: float, text: str,
             **changes: object) -> tuple[Mission, list[Command]]:
    cfg = m.config
    command = Command(CommandKind.TAKEOFF, takeoff_alt_m=cfg.takeoff_alt_m)
    return _go(_asked(m, command, t_s, i.autopilot), State.TAKING_OFF, t_s, text,
               Severity.INFO, [command], **changes)


def _taking_off(m: Mission, i: MissionInputs, t_s: float) -> tuple[Mission, list[Command]]:
    cfg = m.config
    if i.in_air and _takeoff_reached(cfg, i) and i.flight_mode not in (FlightMode.TAKEOFF,
                                                                       FlightMode.UNKNOWN):
        if i.flight_mode is FlightMode.OFFBOARD and m.mode_ours:  # ArduPilot: our GUIDED
            if cfg.auto_offboard and not m.auto_offboard_spent:
                return _start_search(m, t_s, "airborne in guided: searching",
                                     auto_offboard_spent=True)
            return _enter_ready(m, i, t_s, "airborne in guided: pilot's turn")
        return _enter_ready(m, i, t_s, "airborne: ready, waiting for offboard")
    if not i.armed or t_s - m.since_s >= cfg.takeoff_timeout_s:
        return _enter_ready(dataclasses.replace(m, auto_offboard_spent=True), i, t_s,
                            "takeoff failed: pilot's turn", Severity.WARNING)
    return m, []


def advance(mission: Mission, inputs: MissionInputs, t_s: float) -> tuple[Mission, list[Command]]:
    """The mission after this tick's observations and the commands to carry out, in order."""
    m, i, cfg = mission, inputs, mission.config
    if m.state in (State.DONE, State.FAILSAFE):
        return m, []
    if not i.connected:
        if m.state is State.WAITING_FOR_VEHICLE:
            return m, []
        spent = m.state is not State.WAITING_FOR_HEALTH  # we may have commanded: never again
        return _go(m, State.WAITING_FOR_VEHICLE, t_s, "vehicle link lost: stopped",
                   Severity.WARNING, _stop(m), stream=None,
                   auto_arm_spent=m.auto_arm_spent or spent,
                   auto_offboard_spent=m.auto_offboard_spent or spent)
    before = m
    m = _observe(m, i)
    foreign = m.mode_seen is not before.mode_seen and m.mode_fresh and not m.mode_ours
    healthy = i.health_ok and i.position_ok and not i.battery_low
    if m.state is State.WAITING_FOR_VEHICLE:
        return _go(m, State.WAITING_FOR_HEALTH, t_s, "vehicle connected: checking health",
                   Severity.INFO, [])
    if m.state in (State.SEARCHING, State.PAUSED):
        return _searching(m, i, t_s)
    if m.state is State.PILOT_HAS_CONTROL:
        return _pilot_has_control(m, i, t_s)
    if m.state is State.WAITING_FOR_HEALTH:
        if not healthy:
            return m, []
        m = dataclasses.replace(m, deciding=True)
        if cfg.auto_arm_takeoff and not m.auto_arm_spent and not i.in_air:
            if i.armed:
                return _takeoff(m, i, t_s, f"taking off to {cfg.takeoff_alt_m:g} m",
                                auto_arm_spent=True)
            arm = Command(CommandKind.ARM)
            return _go(_asked(m, arm, t_s, i.autopilot), State.ARMING, t_s, "healthy: arming",
                       Severity.INFO, [arm], auto_arm_spent=True)
        return _enter_ready(m, i, t_s, "healthy: ready, waiting for offboard")
    # ARMING, TAKING_OFF, READY: we do not fly the vehicle; on bad health wait for it again.
    if not healthy:
        why = "battery low" if i.battery_low else "position lost"
        return _go(m, State.WAITING_FOR_HEALTH, t_s, f"{why}: waiting for health",
                   Severity.WARNING, _stop(m), stream=None)
    if foreign and m.state is not State.READY:  # (in READY _observe spent the auto steps)
        return _takeover(m, i, t_s)  # someone else chose a mode: no automatic step, ever
    if m.state is State.ARMING:
        if i.armed:
            return _takeoff(m, i, t_s, f"armed: taking off to {cfg.takeoff_alt_m:g} m")
        if t_s - m.since_s >= cfg.arm_retry_s:
            return _enter_ready(m, i, t_s, "arming failed: pilot's turn", Severity.WARNING)
        if t_s - m.arm_asked_s >= RETRY_EVERY_S:  # PX4 refuses for a while after healthy
            arm = Command(CommandKind.ARM)
            return _asked(m, arm, t_s, i.autopilot), [arm]
        return m, []
    if m.state is State.TAKING_OFF:
        return _taking_off(m, i, t_s)
    # READY
    pilot_offboard = m.mode_fresh and not m.mode_ours and i.armed and i.in_air  # ArduPilot GUIDED
    if i.flight_mode is FlightMode.OFFBOARD and (m.stream is not None or pilot_offboard):
        return _start_search(m, t_s, "offboard: searching", auto_offboard_spent=True)
    if m.stream is None and _may_hold_stream(m, i):
        return dataclasses.replace(m, stream=Stream.HOLD_HERE), [_start(Stream.HOLD_HERE)]
    may_ask = (m.stream is not None and i.setpoints_streaming and i.armed and i.in_air
               and i.flight_mode is not FlightMode.OFFBOARD)
    offboard = Command(CommandKind.START_OFFBOARD)
    if cfg.auto_offboard and not m.auto_offboard_spent and may_ask:
        m = _asked(dataclasses.replace(m, auto_offboard_spent=True), offboard, t_s, i.autopilot)
        return m, [offboard, statustext("requesting offboard")]
    if m.offboard_first_s is None or m.offboard_first_s < m.since_s:  # none asked in this READY
        return m, []
    if m.mode_seen is not before.mode_seen:  # a mode change since we asked: never ask again
        return dataclasses.replace(m, offboard_first_s=None), []
    if t_s - m.offboard_first_s >= cfg.offboard_retry_s:
        return (dataclasses.replace(m, offboard_first_s=None),
                [statustext("offboard refused: pilot's turn", Severity.WARNING)])
    if may_ask and t_s - m.offboard_asked_s >= RETRY_EVERY_S:  # refused, or its answer lost
        return _asked(m, offboard, t_s, i.autopilot), [offboard]
    return m, []
