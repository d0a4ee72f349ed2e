"""The mission state machine: a pure step from what the service observed to what it must do.

`advance(mission, inputs, t_s)` returns the next `Mission` and the `Command`s the shell carries
out in order. Rules that hold on every path:

* START_OFFBOARD is emitted at most once per mission, only with `auto_offboard`, only from READY,
  only while our setpoints stream and the vehicle is armed and in the air; never after a pilot
  takeover or a link loss (the pilot selects OFFBOARD then). ARM/TAKEOFF likewise at most once.
* Whenever we stop commanding (mode changed by someone else, failsafe, end, link lost) the same
  tick carries STOP_SETPOINTS, before any mode request (MAVSDK's offboard stop asks for Hold).
* After a takeover, with `resume_on_pilot_offboard` the shell streams HOLD_HERE setpoints (the
  vehicle's current position, ignored by the autopilot outside OFFBOARD) once it reports the
  planner stream stopped, so that PX4 accepts OFFBOARD if the pilot selects it; the search then
  resumes. Without it nothing is streamed and the service never flies again in this mission.
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


class State(Enum):
    """Where the mission is."""

    WAITING_FOR_VEHICLE = "waiting_for_vehicle"
    WAITING_FOR_HEALTH = "waiting_for_health"
    ARMING = "arming"
    TAKING_OFF = "taking_off"
    READY = "ready"
    SEARCHING = "searching"
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
    arm_timeout_s: float = 10.0
    takeoff_timeout_s: float = 60.0

    def __post_init__(self) -> None:
        """Check every value once."""
        for key in ("takeoff_alt_m", "time_limit_s", "arm_timeout_s", "takeoff_timeout_s"):
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


def _may_hold_stream(m: Mission, i: MissionInputs) -> bool:
    """Stream HOLD_HERE in READY: never into a stale OFFBOARD, nor after a no-resume takeover."""
    return i.flight_mode is not FlightMode.OFFBOARD and not (
        m.pilot_took_over and not m.config.resume_on_pilot_offboard
    )


def _enter_ready(
    m: Mission, i: MissionInputs, t_s: float, text: str, severity: Severity = Severity.INFO
) -> tuple[Mission, list[Command]]:
    stream = _may_hold_stream(m, i) and m.stream is None
    return _go(m, State.READY, t_s, text, severity, [_start(Stream.HOLD_HERE)] if stream else [],
               stream=Stream.HOLD_HERE if stream else m.stream)


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
        return _go(m, State.PILOT_HAS_CONTROL, t_s, f"mode {i.flight_mode.name}: pilot has control",
                   Severity.WARNING, [_STOP], stream=None, pilot_took_over=True)
    if i.battery_low:
        return _go(m, State.FAILSAFE, t_s, "battery low: stopped, requesting RTL",
                   Severity.CRITICAL, [_STOP, Command(CommandKind.RTL)], stream=None)
    if not (i.health_ok and i.position_ok):
        return _go(m, State.FAILSAFE, t_s, "position lost: stopped, autopilot failsafe",
                   Severity.CRITICAL, [_STOP], stream=None)
    started_s = t_s if m.search_started_s is None else m.search_started_s
    reason = _end_reason(cfg, i, t_s - started_s)
    if reason is not None:
        return _go(m, State.DONE, t_s, f"{reason}: {cfg.end_action}", Severity.NOTICE,
                   [_STOP, Command(_END_COMMAND[cfg.end_action])], stream=None)
    return m, []


def _pilot_has_control(m: Mission, i: MissionInputs, t_s: float) -> tuple[Mission, list[Command]]:
    healthy = i.health_ok and i.position_ok and not i.battery_low
    if not (healthy and m.config.resume_on_pilot_offboard):
        return (dataclasses.replace(m, stream=None), [_STOP]) if m.stream else (m, [])
    if i.flight_mode is FlightMode.OFFBOARD and m.stream is Stream.HOLD_HERE:
        return _go(m, State.SEARCHING, t_s, "pilot chose offboard: searching", Severity.INFO,
                   [_start(Stream.PLANNER)], stream=Stream.PLANNER)
    if m.stream is None and i.flight_mode is not FlightMode.OFFBOARD and not i.setpoints_streaming:
        return dataclasses.replace(m, stream=Stream.HOLD_HERE), [_start(Stream.HOLD_HERE)]
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
    healthy = i.health_ok and i.position_ok and not i.battery_low
    if m.state is State.WAITING_FOR_VEHICLE:
        return _go(m, State.WAITING_FOR_HEALTH, t_s, "vehicle connected: checking health",
                   Severity.INFO, [])
    if m.state is State.SEARCHING:
        return _searching(m, i, t_s)
    if m.state is State.PILOT_HAS_CONTROL:
        return _pilot_has_control(m, i, t_s)
    if m.state is State.WAITING_FOR_HEALTH:
        if not healthy:
            return m, []
        if cfg.auto_arm_takeoff and not m.auto_arm_spent and not i.in_air:
            if i.armed:
                return _go(m, State.TAKING_OFF, t_s, f"taking off to {cfg.takeoff_alt_m:g} m",
                           Severity.INFO, [Command(CommandKind.TAKEOFF,
                                                   takeoff_alt_m=cfg.takeoff_alt_m)],
                           auto_arm_spent=True)
            return _go(m, State.ARMING, t_s, "healthy: arming", Severity.INFO,
                       [Command(CommandKind.ARM)], auto_arm_spent=True)
        return _enter_ready(m, i, t_s, "healthy: ready, waiting for offboard")
    # ARMING, TAKING_OFF, READY: we do not fly the vehicle; on bad health wait for it again.
    if not healthy:
        why = "battery low" if i.battery_low else "position lost"
        return _go(m, State.WAITING_FOR_HEALTH, t_s, f"{why}: waiting for health",
                   Severity.WARNING, _stop(m), stream=None)
    waited_s = t_s - m.since_s
    if m.state is State.ARMING:
        if i.armed:
            return _go(m, State.TAKING_OFF, t_s, f"armed: taking off to {cfg.takeoff_alt_m:g} m",
                       Severity.INFO, [Command(CommandKind.TAKEOFF,
                                               takeoff_alt_m=cfg.takeoff_alt_m)])
        if waited_s >= cfg.arm_timeout_s:
            return _enter_ready(m, i, t_s, "arming failed: pilot's turn", Severity.WARNING)
        return m, []
    if m.state is State.TAKING_OFF:
        if i.in_air and i.flight_mode not in (FlightMode.TAKEOFF, FlightMode.UNKNOWN):
            return _enter_ready(m, i, t_s, "airborne: ready, waiting for offboard")
        if not i.armed or waited_s >= cfg.takeoff_timeout_s:
            return _enter_ready(m, i, t_s, "takeoff failed: pilot's turn", Severity.WARNING)
        return m, []
    # READY
    if i.flight_mode is FlightMode.OFFBOARD and m.stream is not None:
        return _go(m, State.SEARCHING, t_s, "offboard: searching", Severity.INFO,
                   [_start(Stream.PLANNER)], stream=Stream.PLANNER, auto_offboard_spent=True,
                   search_started_s=t_s if m.search_started_s is None else m.search_started_s)
    if m.stream is None and _may_hold_stream(m, i):
        return dataclasses.replace(m, stream=Stream.HOLD_HERE), [_start(Stream.HOLD_HERE)]
    if (cfg.auto_offboard and not m.auto_offboard_spent and m.stream is not None
            and i.setpoints_streaming and i.armed and i.in_air
            and i.flight_mode is not FlightMode.OFFBOARD):
        return dataclasses.replace(m, auto_offboard_spent=True), [
            Command(CommandKind.START_OFFBOARD), statustext("requesting offboard")]
    return m, []
