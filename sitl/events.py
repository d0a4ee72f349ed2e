"""The mock PX4's EVENT messages (MAVLink 410): their ids, their texts and the message itself.

PX4 sends no STATUSTEXT on its API link: it reports why it refused a command as an EVENT, a
32-bit id with arguments that a client looks up in the component's event metadata. The mock's
ids are PX4 v1.15's where PX4 has that event (the estimator checks), else its own in PX4's
namespace (1, the top byte), and `PX4_EVENT_TEXTS` is their metadata: the human text of each.
The installed pymavlink dialects lack EVENT, so `MAVLink_event_message` defines it here (the
wire format of common.xml: 53 bytes, CRC extra 160) and importing this module registers it
with pymavlink's ardupilotmega dialect, unless that dialect has its own.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from typing import ClassVar

from pymavlink.dialects.v20 import ardupilotmega as mavlink

MAVLINK_MSG_ID_EVENT = 410
EVENT_ARGUMENTS_BYTES = 40
PX4_NAMESPACE = 1  # the top byte of a PX4 event id: the component's event namespace

# The mock's event ids (the first four: PX4 v1.15's own).
EVENT_ESTIMATOR_NOT_READY = 0x0192_9C22
EVENT_NO_GPS_FIX = 0x01BC_BE91
EVENT_HORIZONTAL_VELOCITY_UNSTABLE = 0x0187_D640
EVENT_VERTICAL_VELOCITY_UNSTABLE = 0x018B_F108
EVENT_MODE_NOT_ARMABLE = 0x01C0_0005
EVENT_BATTERY_LOW = 0x01C0_0006
EVENT_POSITION_NOT_AVAILABLE = 0x01C0_0007
EVENT_ALTITUDE_NOT_AVAILABLE = 0x01C0_0008
EVENT_OFFBOARD_NOT_AVAILABLE = 0x01C0_0009

# What each id means, as a ground station shows it (PX4's wording where it was measured).
PX4_EVENT_TEXTS: dict[int, str] = {
    EVENT_ESTIMATOR_NOT_READY: "Preflight Fail: estimator not ready",
    EVENT_NO_GPS_FIX: "Preflight Fail: GPS fix too low",
    EVENT_HORIZONTAL_VELOCITY_UNSTABLE: "Preflight Fail: horizontal velocity unstable",
    EVENT_VERTICAL_VELOCITY_UNSTABLE: "Preflight Fail: vertical velocity unstable",
    EVENT_MODE_NOT_ARMABLE: "Arming denied: not possible in this mode",
    EVENT_BATTERY_LOW: "Preflight Fail: low battery",
    EVENT_POSITION_NOT_AVAILABLE: "Switching to Position is currently not available",
    EVENT_ALTITUDE_NOT_AVAILABLE: "Switching to Altitude is currently not available",
    EVENT_OFFBOARD_NOT_AVAILABLE: "Switching to Offboard is currently not available",
}

LOG_ERROR = 3  # libevents' log level: Emergency 0 ... Error 3, Warning 4, ..., Debug 7
LOG_LEVELS_ERROR = (LOG_ERROR << 4) | LOG_ERROR  # internal (high nibble) and external


class MAVLink_event_message(mavlink.MAVLink_message):  # type: ignore[misc]  # noqa: N801
    """EVENT (410): one event of a component, numbered by its sequence (common.xml)."""

    id = MAVLINK_MSG_ID_EVENT
    msgname = "EVENT"
    fieldnames: ClassVar[list[str]] = [
        "destination_component", "destination_system", "id", "event_time_boot_ms", "sequence",
        "log_levels", "arguments"]
    ordered_fieldnames: ClassVar[list[str]] = [
        "id", "event_time_boot_ms", "sequence", "destination_component", "destination_system",
        "log_levels", "arguments"]
    fieldtypes: ClassVar[list[str]] = [
        "uint8_t", "uint8_t", "uint32_t", "uint32_t", "uint16_t", "uint8_t", "uint8_t"]
    fielddisplays_by_name: ClassVar[dict[str, str]] = {}
    fieldenums_by_name: ClassVar[dict[str, str]] = {}
    fieldunits_by_name: ClassVar[dict[str, str]] = {"event_time_boot_ms": "ms"}
    native_format = bytearray(b"<IIHBBBB")
    orders: ClassVar[list[int]] = [3, 4, 0, 1, 2, 5, 6]
    lengths: ClassVar[list[int]] = [1, 1, 1, 1, 1, 1, EVENT_ARGUMENTS_BYTES]
    array_lengths: ClassVar[list[int]] = [0, 0, 0, 0, 0, 0, EVENT_ARGUMENTS_BYTES]
    crc_extra = 160
    unpacker = struct.Struct(f"<IIHBBB{EVENT_ARGUMENTS_BYTES}B")
    instance_field = None
    instance_offset = -1

    def __init__(self, destination_component: int, destination_system: int, id: int,
                 event_time_boot_ms: int, sequence: int, log_levels: int,
                 arguments: Sequence[int]) -> None:
        mavlink.MAVLink_message.__init__(self, MAVLINK_MSG_ID_EVENT, "EVENT")
        self._fieldnames = MAVLink_event_message.fieldnames
        self._instance_field = None
        self._instance_offset = -1
        self.destination_component = destination_component
        self.destination_system = destination_system
        self.id = id
        self.event_time_boot_ms = event_time_boot_ms
        self.sequence = sequence
        self.log_levels = log_levels
        self.arguments = list(arguments)

    def pack(self, mav: mavlink.MAVLink, force_mavlink1: bool = False) -> bytes:
        """The framed message (MAVLink 2 only: its id needs 24 bits)."""
        args = [*self.arguments, *[0] * EVENT_ARGUMENTS_BYTES][:EVENT_ARGUMENTS_BYTES]
        payload = self.unpacker.pack(self.id, self.event_time_boot_ms, self.sequence,
                                     self.destination_component, self.destination_system,
                                     self.log_levels, *args)
        return bytes(self._pack(mav, self.crc_extra, payload, force_mavlink1=force_mavlink1))


def event_message(event_id: int, time_boot_ms: int, sequence: int,
                  log_levels: int = LOG_LEVELS_ERROR) -> MAVLink_event_message:
    """A broadcast EVENT without arguments."""
    return MAVLink_event_message(0, 0, event_id, time_boot_ms & 0xFFFFFFFF, sequence & 0xFFFF,
                                 log_levels, [0] * EVENT_ARGUMENTS_BYTES)


mavlink.mavlink_map.setdefault(MAVLINK_MSG_ID_EVENT, MAVLink_event_message)
