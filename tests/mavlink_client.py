"""A minimal MAVLink 2 ground station over loopback UDP, for the protocol tests."""

from __future__ import annotations

import math
import socket
import time
from collections.abc import Callable

from pymavlink.dialects.v20 import ardupilotmega as mavlink

Predicate = Callable[[mavlink.MAVLink_message], bool]
POSITION_ONLY = 0xDF8  # type mask: use x, y, z and yaw, ignore velocity and acceleration


class Client:
    """Sends to the autopilot's address and reads what it sends back."""

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.05)
        self.mav = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
        self.mav.robust_parsing = True
        self.autopilot: tuple[str, int] | None = None

    @property
    def port(self) -> int:
        """Where the client listens (the autopilot's remote)."""
        return int(self.sock.getsockname()[1])

    def send(self, msg: mavlink.MAVLink_message) -> None:
        """Send to the autopilot (once it has been heard from)."""
        assert self.autopilot is not None, "no packet from the autopilot yet"
        self.sock.sendto(msg.pack(self.mav), self.autopilot)

    def messages(self, timeout_s: float) -> list[mavlink.MAVLink_message]:
        """Everything received within timeout_s of wall time."""
        out: list[mavlink.MAVLink_message] = []
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            out.extend(self._receive())
        return out

    def messages_until(self, kind: str, count: int,
                       timeout_s: float) -> list[mavlink.MAVLink_message]:
        """Everything received until `count` messages of a type have come (a loaded autopilot
        sends fewer a second), or AssertionError after timeout_s of wall time."""
        out: list[mavlink.MAVLink_message] = []
        seen = 0
        deadline = time.monotonic() + timeout_s
        while seen < count:
            if time.monotonic() >= deadline:
                raise AssertionError(f"{seen} of {count} {kind} messages within {timeout_s} s")
            new = self._receive()
            out.extend(new)
            seen += sum(m.get_type() == kind for m in new)
        return out

    def _receive(self) -> list[mavlink.MAVLink_message]:
        """The messages of one datagram (none when the socket times out)."""
        try:
            data, addr = self.sock.recvfrom(65535)
        except TimeoutError:
            return []
        self.autopilot = (addr[0], addr[1])
        return self.mav.parse_buffer(data) or []

    def wait_for(self, predicate: Predicate, timeout_s: float = 5.0) -> mavlink.MAVLink_message:
        """The first message received that satisfies predicate, or AssertionError on timeout."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for msg in self._receive():
                if predicate(msg):
                    return msg
        raise AssertionError("no such message within the timeout")

    def wait_type(self, kind: str, timeout_s: float = 5.0) -> mavlink.MAVLink_message:
        """The next message of a type."""
        return self.wait_for(lambda m: m.get_type() == kind, timeout_s)

    def command(
        self, command: int, *params: float, timeout_s: float = 5.0
    ) -> mavlink.MAVLink_message:
        """Send COMMAND_LONG to system 1, component 1, and return its COMMAND_ACK."""
        p = [*params, *[0.0] * (7 - len(params))]
        self.send(self.mav.command_long_encode(1, 1, command, 0, *p))
        return self.wait_for(
            lambda m: m.get_type() == "COMMAND_ACK" and m.command == command, timeout_s
        )

    def set_px4_mode(self, custom_mode: int) -> int:
        """DO_SET_MODE with a PX4 custom mode ((main << 16) | (sub << 24)); the ack's result."""
        ack = self.command(mavlink.MAV_CMD_DO_SET_MODE,
                           mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
                           (custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF)
        return int(ack.result)

    def stream_setpoints(self, ned: tuple[float, float, float], seconds_wall: float,
                         mask: int = POSITION_ONLY) -> list[mavlink.MAVLink_message]:
        """Send a local NED setpoint at 50 Hz for seconds_wall; what was received meanwhile."""
        received: list[mavlink.MAVLink_message] = []
        end = time.monotonic() + seconds_wall
        while time.monotonic() < end:
            self.send(self.mav.set_position_target_local_ned_encode(
                0, 1, 1, mavlink.MAV_FRAME_LOCAL_NED, mask, *ned, 0, 0, 0, 0, 0, 0, 0.0, 0.0))
            received += self.messages(0.02)
        return received

    def fly_to(self, ned: tuple[float, float, float], tolerance_m: float,
               timeout_wall_s: float) -> mavlink.MAVLink_message:
        """Stream a setpoint until LOCAL_POSITION_NED is within tolerance and nearly still."""
        end = time.monotonic() + timeout_wall_s
        while time.monotonic() < end:
            for m in self.stream_setpoints(ned, 0.1):
                if m.get_type() == "LOCAL_POSITION_NED" and math.dist(
                        (m.x, m.y, m.z), ned) < tolerance_m and math.hypot(m.vx, m.vy) < 0.1:
                    return m
        raise AssertionError(f"did not reach {ned} within {timeout_wall_s} s")

    def close(self) -> None:
        """Close the socket."""
        self.sock.close()
