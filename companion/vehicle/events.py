"""PX4's events (MAVLink EVENT) as text: PX4 reports why it refused a command this way, not
with STATUSTEXT, on the link an onboard computer uses.

An event is a 32-bit id (component in the top 8 bits, a hash of the event's name below) with
packed arguments; its text lives in metadata the autopilot serves. The service knows the texts
of the refusals it meets when it arms and takes off, and names any other event by its id.
"""

from __future__ import annotations

__all__ = ["EVENT_TEXTS", "UNKNOWN_PREFIX", "describe_event"]

# PX4 v1.15's ids (its build's events/all_events.json) of the refusals met at arming and
# take-off, and of the failsafes; texts are ours.
EVENT_TEXTS: dict[int, str] = {
    0x0187D640: "preflight: horizontal velocity unstable (arming refused for now)",
    0x018BF108: "preflight: vertical velocity unstable (arming refused for now)",
    0x019303EE: "preflight: height estimate not stable",
    0x0189C3F5: "preflight: height estimate error",
    0x01FDF2ED: "preflight: heading estimate not stable",
    0x019231E9: "preflight: yaw estimate error",
    0x01929C22: "preflight: the estimator does not use GPS yet",
    0x01BCBE91: "preflight: GPS fix too low",
    0x01C7CE3A: "preflight: not enough GPS satellites",
    0x0102089D: "arming refused: health failures to resolve first",
    0x01A04397: "mode switch refused: that mode is not available now",
    0x01DEDBD0: "failsafe: autopilot disengaged",
    0x0144B3E0: "failsafe: switching mode shortly",
    0x01D11DF6: "failsafe: switching to hold shortly",
    0x0194CA8A: "failsafe: switching mode",
    0x0198C273: "no valid global position estimate",
    0x01D31BB9: "no valid local position estimate",
    0x019F748F: "no valid attitude estimate",
    0x01A4B458: "connection to the ground station lost",
    0x01414569: "take-off detected",
}


UNKNOWN_PREFIX = "autopilot event 0x"


def describe_event(event_id: int) -> str:
    """One line for an autopilot event: its known text, else its id (`UNKNOWN_PREFIX`...)."""
    text = EVENT_TEXTS.get(event_id)
    return f"autopilot: {text}" if text else f"{UNKNOWN_PREFIX}{event_id:08x}"
