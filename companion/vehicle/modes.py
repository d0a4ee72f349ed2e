"""The autopilot's flight modes, as MAVSDK names them, in the mission's terms."""

from __future__ import annotations

from companion import mission as ms
from companion.vehicle.mavsdk_link import FlightMode, Status

__all__ = ["mission_mode"]

_MODES = {
    FlightMode.OFFBOARD: ms.FlightMode.OFFBOARD, FlightMode.HOLD: ms.FlightMode.HOLD,
    FlightMode.POSCTL: ms.FlightMode.POSCTL, FlightMode.ALTCTL: ms.FlightMode.ALTCTL,
    FlightMode.MANUAL: ms.FlightMode.MANUAL, FlightMode.STABILIZED: ms.FlightMode.MANUAL,
    FlightMode.ACRO: ms.FlightMode.MANUAL, FlightMode.RATTITUDE: ms.FlightMode.MANUAL,
    FlightMode.MISSION: ms.FlightMode.MISSION, FlightMode.TAKEOFF: ms.FlightMode.TAKEOFF,
    FlightMode.LAND: ms.FlightMode.LAND, FlightMode.RETURN_TO_LAUNCH: ms.FlightMode.RTL,
    FlightMode.UNKNOWN: ms.FlightMode.UNKNOWN,
}


def mission_mode(status: Status | None) -> ms.FlightMode:
    """The mission's name for the reported mode: UNKNOWN before any status, OTHER if unmapped."""
    if status is None:
        return ms.FlightMode.UNKNOWN
    return _MODES.get(status.flight_mode, ms.FlightMode.OTHER)
