"""Fault injection for the SITL: what can go wrong, when, and how `--faults` spells it.

A plan is a comma-separated list of items. Steady faults hold for the whole run:

    loss=5          MAVLink packets lost, percent, each direction (loss=2/10: to/from autopilot)
    latency=0.05    added one-way MAVLink delay, seconds
    drop=10         camera frames dropped, percent

Timed faults start at simulation second T (since the SITL started), some for D seconds:

    cut@T+D         MAVLink link cut: nothing passes either way
    freeze@T+D      the camera repeats its last frame (new time stamps)
    black@T+D       black frames
    corrupt@T+D     frames whose JPEG data is garbled
    drop@T+D        no frames at all
    gps@T+D:N/E     the reported position jumps by N metres north and E east
    battery@T:P     the battery falls to P percent (below the low level: the autopilot returns)
    pilot@T:MODE    the pilot flips the mode switch (posctl, altctl, manual, hold, land, rtl)
                    or the arm switch (arm, disarm)
    reboot@T+D      the autopilot reboots, silent for D seconds
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from enum import StrEnum

from companion.errors import ConfigError

__all__ = ["CAMERA_FAULTS", "PILOT_ACTIONS", "FaultEvent", "FaultKind", "FaultPlan", "parse_faults"]

KEY = "--faults"


class FaultKind(StrEnum):
    """A timed fault; the value is how `--faults` spells it."""

    CUT = "cut"
    FREEZE = "freeze"
    BLACK = "black"
    CORRUPT = "corrupt"
    DROP = "drop"
    GPS = "gps"
    BATTERY = "battery"
    PILOT = "pilot"
    REBOOT = "reboot"


CAMERA_FAULTS = (FaultKind.FREEZE, FaultKind.BLACK, FaultKind.CORRUPT, FaultKind.DROP)
PILOT_ACTIONS = ("posctl", "altctl", "manual", "hold", "land", "rtl", "arm", "disarm")
_TIMED = {  # kind -> (needs a duration, argument syntax or "")
    FaultKind.CUT: (True, ""), FaultKind.FREEZE: (True, ""), FaultKind.BLACK: (True, ""),
    FaultKind.CORRUPT: (True, ""), FaultKind.DROP: (True, ""), FaultKind.GPS: (True, "N/E"),
    FaultKind.BATTERY: (False, "P"), FaultKind.PILOT: (False, "MODE"),
    FaultKind.REBOOT: (True, ""),
}
_ITEM = re.compile(r"^(?P<kind>[a-z]+)@(?P<at>[^+:]+)(\+(?P<dur>[^:]+))?(:(?P<arg>.+))?$")


@dataclass(frozen=True, slots=True)
class FaultEvent:
    """A timed fault: `kind` at simulation second `at_s`, lasting `duration_s`, with `arg`."""

    kind: FaultKind
    at_s: float
    duration_s: float = 0.0
    arg: str = ""

    def __post_init__(self) -> None:
        """The kind as a FaultKind, also when given as its word (ValueError for no kind)."""
        object.__setattr__(self, "kind", FaultKind(self.kind))

    def active(self, t_s: float) -> bool:
        """Whether a fault with a duration is in effect at t_s."""
        return self.at_s <= t_s < self.at_s + self.duration_s

    def gps_offset_ne_m(self) -> tuple[float, float]:
        """The (north, east) jump of a gps fault."""
        north, east = self.arg.split("/")
        return float(north), float(east)


@dataclass(frozen=True, slots=True)
class FaultPlan:
    """Steady faults and timed events, as `--faults` gives them (empty: nothing goes wrong)."""

    loss_to_autopilot: float = 0.0  # probability
    loss_from_autopilot: float = 0.0
    latency_s: float = 0.0
    frame_drop: float = 0.0  # probability
    events: tuple[FaultEvent, ...] = field(default_factory=tuple)

    def camera_fault(self, t_s: float) -> FaultKind | None:
        """The camera fault in effect at t_s (the first listed wins), or None."""
        for e in self.events:
            if e.kind in CAMERA_FAULTS and e.active(t_s):
                return e.kind
        return None


def _number(item: str, text: str, what: str, lo: float, hi: float = math.inf) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and lo <= value <= hi):
        bounds = f"in [{lo:g}, {hi:g}]" if math.isfinite(hi) else f">= {lo:g}"
        raise ConfigError(KEY, f"{item!r}: {what} must be a number {bounds}, got {text!r}")
    return value


def _steady(item: str, name: str, value: str, plan: dict[str, float]) -> None:
    if name == "loss":
        parts = value.split("/")
        if len(parts) not in (1, 2):
            raise ConfigError(KEY, f"{item!r}: loss is PERCENT or TO/FROM percent")
        pct = [_number(item, p, "loss", 0.0, 100.0) / 100.0 for p in parts]
        plan["loss_to_autopilot"], plan["loss_from_autopilot"] = pct[0], pct[-1]
    elif name == "latency":
        plan["latency_s"] = _number(item, value, "latency (seconds)", 0.0, 10.0)
    elif name == "drop":
        plan["frame_drop"] = _number(item, value, "drop (percent)", 0.0, 100.0) / 100.0
    else:
        raise ConfigError(KEY, f"{item!r}: unknown steady fault {name!r} "
                               "(known: loss, latency, drop)")


def _timed(item: str) -> FaultEvent:
    m = _ITEM.match(item)
    if m is None or m["kind"] not in _TIMED:
        known = ", ".join(_TIMED)
        raise ConfigError(KEY, f"{item!r}: not a fault; timed faults are KIND@T[+D][:ARG] with "
                               f"KIND one of {known}")
    kind = FaultKind(m["kind"])
    needs_duration, arg_syntax = _TIMED[kind]
    at_s = _number(item, m["at"], "the start time T (seconds)", 0.0)
    if needs_duration != (m["dur"] is not None):
        form = f"{kind}@T+D" if needs_duration else f"{kind}@T"
        raise ConfigError(KEY, f"{item!r}: write {form}" + (f":{arg_syntax}" if arg_syntax
                                                              else ""))
    duration_s = _number(item, m["dur"], "the duration D (seconds)", 0.0) if m["dur"] else 0.0
    arg = m["arg"] or ""
    if bool(arg) != bool(arg_syntax):
        raise ConfigError(KEY, f"{item!r}: {kind} takes " + (f"the argument :{arg_syntax}"
                                                             if arg_syntax else "no argument"))
    if kind is FaultKind.GPS:
        parts = arg.split("/")
        if len(parts) != 2:
            raise ConfigError(KEY, f"{item!r}: the jump is N/E metres, got {arg!r}")
        for p in parts:
            _number(item, p, "the jump (metres)", -10_000.0, 10_000.0)
    elif kind is FaultKind.BATTERY:
        _number(item, arg, "the battery level (percent)", 0.0, 100.0)
    elif kind is FaultKind.PILOT and arg not in PILOT_ACTIONS:
        raise ConfigError(KEY, f"{item!r}: the pilot action must be one of "
                               f"{', '.join(PILOT_ACTIONS)}, got {arg!r}")
    return FaultEvent(kind, at_s, duration_s, arg)


def parse_faults(spec: str) -> FaultPlan:
    """The plan `spec` describes (see the module's docstring); ConfigError naming the bad item."""
    steady: dict[str, float] = {}
    events: list[FaultEvent] = []
    for raw in spec.split(","):
        item = raw.strip()
        if not item:
            continue
        if "@" in item:
            events.append(_timed(item))
        elif "=" in item:
            name, value = item.split("=", 1)
            _steady(item, name.strip(), value.strip(), steady)
        else:
            raise ConfigError(KEY, f"{item!r}: not a fault; write NAME=VALUE or "
                                   "KIND@T[+D][:ARG]")
    return FaultPlan(**steady, events=tuple(sorted(events, key=lambda e: e.at_s)))
