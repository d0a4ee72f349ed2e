"""Flight modes of the two autopilot flavours and their MAVLink encodings.

The mock autopilot simulates a handful of behaviours (`Behaviour`); each flavour names them with
its own numbers in HEARTBEAT.custom_mode: PX4 packs (main << 16) | (sub << 24), ArduPilot
Copter uses its mode number.
"""

from __future__ import annotations

from enum import Enum


class Flavour(Enum):
    """Which autopilot the mock pretends to be."""

    PX4 = "px4"
    ARDUPILOT = "ardupilot"


class Behaviour(Enum):
    """What the vehicle does in a mode."""

    MANUAL = "manual"  # the pilot flies (the simulation holds position: no sticks)
    ALTITUDE = "altitude"
    POSITION = "position"  # the pilot's position-assisted mode: PX4 POSCTL, Copter POSHOLD
    HOLD = "hold"  # PX4 AUTO.LOITER, Copter LOITER
    BRAKE = "brake"  # Copter BRAKE
    TAKEOFF = "takeoff"  # PX4 AUTO.TAKEOFF (a Copter takes off in GUIDED)
    LAND = "land"
    RTL = "rtl"
    MISSION = "mission"
    OFFBOARD = "offboard"  # PX4 OFFBOARD, Copter GUIDED
    READY = "ready"  # PX4 AUTO.READY


# PX4: custom_mode = (main << 16) | (sub << 24)
PX4_MODES: dict[Behaviour, tuple[int, int]] = {
    Behaviour.MANUAL: (1, 0),
    Behaviour.ALTITUDE: (2, 0),
    Behaviour.POSITION: (3, 0),
    Behaviour.READY: (4, 1),
    Behaviour.TAKEOFF: (4, 2),
    Behaviour.HOLD: (4, 3),
    Behaviour.MISSION: (4, 4),
    Behaviour.RTL: (4, 5),
    Behaviour.LAND: (4, 6),
    Behaviour.OFFBOARD: (6, 0),
}
PX4_STABILIZED = (7, 0)  # the pilot's stabilised mode, simulated like MANUAL

# ArduPilot Copter mode numbers.
COPTER_MODES: dict[Behaviour, int] = {
    Behaviour.MANUAL: 0,  # STABILIZE
    Behaviour.ALTITUDE: 2,  # ALT_HOLD
    Behaviour.MISSION: 3,  # AUTO
    Behaviour.OFFBOARD: 4,  # GUIDED
    Behaviour.HOLD: 5,  # LOITER
    Behaviour.RTL: 6,
    Behaviour.LAND: 9,
    Behaviour.POSITION: 16,  # POSHOLD
    Behaviour.BRAKE: 17,
}

# Modes a Copter can be armed in (the others refuse: LAND, RTL, AUTO without a mission, BRAKE).
COPTER_ARMABLE = {
    Behaviour.MANUAL, Behaviour.ALTITUDE, Behaviour.POSITION, Behaviour.HOLD, Behaviour.OFFBOARD,
}
PX4_ARMABLE = {
    Behaviour.MANUAL, Behaviour.ALTITUDE, Behaviour.POSITION, Behaviour.HOLD, Behaviour.READY,
    Behaviour.TAKEOFF, Behaviour.OFFBOARD,
}


def encode(flavour: Flavour, behaviour: Behaviour) -> int:
    """HEARTBEAT.custom_mode of a behaviour."""
    if flavour is Flavour.PX4:
        main, sub = PX4_MODES[behaviour]
        return (main << 16) | (sub << 24)
    return COPTER_MODES[behaviour]


def decode(flavour: Flavour, custom_main: int, custom_sub: int = 0) -> Behaviour | None:
    """The behaviour a DO_SET_MODE request names (PX4: main and sub mode; Copter: its number),
    or None for a mode the simulation does not have."""
    if flavour is Flavour.PX4:
        if (custom_main, custom_sub) == PX4_STABILIZED:
            return Behaviour.MANUAL
        for behaviour, (main, sub) in PX4_MODES.items():
            if main == custom_main and (main != 4 or sub == custom_sub):
                return behaviour
        return None
    for behaviour, number in COPTER_MODES.items():
        if number == custom_main:
            return behaviour
    return None


def decode_custom_mode(flavour: Flavour, custom_mode: int) -> Behaviour | None:
    """The behaviour of a HEARTBEAT.custom_mode value."""
    if flavour is Flavour.PX4:
        return decode(flavour, (custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF)
    return decode(flavour, custom_mode)
