"""The vehicle over MAVSDK 4: telemetry with the autopilot's own timestamps in, commands out.

`MavsdkLink.connect(url)` finds the first autopilot and identifies us as an onboard computer
(component 195). It asks for the telemetry it needs, because an ArduPilot sends nothing until
asked. `run_telemetry(sink, record)` then feeds a `TelemetrySink` until cancelled. Poses come
from the raw GLOBAL_POSITION_INT, LOCAL_POSITION_NED and ATTITUDE_QUATERNION messages
(MavlinkDirect, one subscription to every message), so each carries the autopilot's
`time_boot_ms`, the time base of the camera's capture times. Flight mode, armed state, health,
in-air and battery come from the Telemetry plugin.

Stopping: `release()` ends the setpoint stream without asking for any mode. MAVSDK's own
Offboard.stop() asks for Hold even after a pilot switched to Position, taking the vehicle back
from the pilot, so the service never calls it.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import json
import math
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass
from typing import Any, Protocol

from mavsdk.asyncio import ComponentType, Configuration, Mavsdk
from mavsdk.asyncio.plugins.action import ActionAsync
from mavsdk.asyncio.plugins.mavlink_direct import MavlinkDirectAsync
from mavsdk.asyncio.plugins.offboard import OffboardAsync, PositionNedYaw
from mavsdk.asyncio.plugins.telemetry import FlightMode, TelemetryAsync
from mavsdk.logging import LogLevel, log_subscribe
from mavsdk.plugins.mavlink_direct.mavlink_direct import MavlinkMessage

from companion.errors import CompanionError
from companion.vehicle.events import describe_event

__all__ = ["ONBOARD_COMPONENT_ID", "FlightMode", "MavsdkLink", "Status", "TelemetrySink",
           "VehicleError", "route_mavsdk_log"]

ONBOARD_COMPONENT_ID = 195  # MAV_COMP_ID_ONBOARD_COMPUTER: what MAVSDK uses for a companion
STATUSTEXT_MAX_CHARS = 50
# MAV_SEVERITY
SEVERITY = {"emergency": 0, "alert": 1, "critical": 2, "error": 3, "warning": 4, "notice": 5,
            "info": 6, "debug": 7}


class VehicleError(CompanionError):
    """The vehicle is unreachable or refused a command; the message says which."""


@dataclass(frozen=True, slots=True)
class Status:
    """The vehicle's state flags as MAVSDK last reported them."""

    flight_mode: FlightMode
    armed: bool
    in_air: bool
    position_ok: bool  # global and local position estimates good, home set
    armable: bool
    battery_percent: float  # NaN when unknown


class TelemetrySink(Protocol):
    """Where `MavsdkLink.run_telemetry` delivers what it reads (called on the event loop)."""

    def on_position(self, t_s: float, lat_deg: float, lon_deg: float, alt_amsl_m: float,
                    alt_rel_m: float, vel_ne_m_s: tuple[float, float] = (0.0, 0.0)) -> None: ...

    def on_local_position(self, t_s: float, north_m: float, east_m: float,
                          down_m: float) -> None: ...

    def on_attitude(self, t_s: float, q_wxyz: tuple[float, float, float, float]) -> None: ...

    def on_status(self, status: Status) -> None: ...

    def on_heartbeat(self, autopilot: int) -> None: ...

    def on_accuracy(self, source: str, horizontal_std_m: float, vertical_std_m: float,
                    attitude_std_deg: float = math.nan,
                    heading_std_deg: float = math.nan) -> None: ...

    def on_distance(self, t_s: float, distance_m: float, min_m: float, max_m: float) -> None: ...

    def on_terrain_height(self, t_s: float, height_m: float) -> None: ...

    def on_autopilot_text(self, text: str) -> None: ...


def route_mavsdk_log(sink: Callable[[str], None]) -> None:
    """Send MAVSDK's warnings and errors to sink as plain lines; drop its debug and info."""
    def forward(level: LogLevel, message: str, file: str | None, line: int) -> bool:
        if level >= LogLevel.WARN:
            sink(f"mavsdk {level.name.lower()}: {message}")
        return True  # not MAVSDK's own coloured output

    log_subscribe(forward)


MAV_SENSOR_ROTATION_PITCH_270 = 25  # a DISTANCE_SENSOR that looks down
HEIGHT_RATE_HZ = 10.0  # rangefinder and terrain heights: a frame takes one within 0.3 s
MM = 1e-3
CM = 1e-2
TERRAIN_UNKNOWN_M = -1000.0  # ALTITUDE.altitude_terrain below this: unknown
ODOMETRY_VARIANCES = (0, 6, 11, 15, 18, 20)  # x, y, z, roll, pitch, yaw in the 6x6 triangle


def _odometry(f: dict[str, Any]) -> tuple[float, float, float, float] | None:
    """ODOMETRY's pose covariance as 1-sigma horizontal, vertical (m), tilt and heading (deg);
    None when unknown (a NaN first entry)."""
    cov = [float(f["pose_covariance"][k]) for k in ODOMETRY_VARIANCES]
    if not math.isfinite(cov[0]) or min(cov) < 0.0:
        return None
    return (math.sqrt(max(cov[0], cov[1])), math.sqrt(cov[2]),
            math.degrees(math.sqrt(max(cov[3], cov[4]))), math.degrees(math.sqrt(cov[5])))


def _fields(message: Any) -> dict[str, Any]:
    parsed: dict[str, Any] = json.loads(message.fields_json)
    return parsed


class MavsdkLink:
    """One MAVSDK connection to one autopilot; every method is a coroutine on one event loop."""

    def __init__(self, mavsdk: Mavsdk, system: Any) -> None:
        self._mavsdk = mavsdk
        self._system = system
        self.telemetry = TelemetryAsync(system)
        self.action = ActionAsync(system)
        self.offboard = OffboardAsync(system)
        self.direct = MavlinkDirectAsync(system)
        self._status = Status(FlightMode.UNKNOWN, False, False, False, False, math.nan)
        self.malformed = 0  # telemetry messages whose fields could not be read

    @classmethod
    @contextlib.asynccontextmanager
    async def connect(cls, url: str, timeout_s: float = 30.0,
                      telemetry_rate_hz: float = 20.0) -> AsyncIterator[MavsdkLink]:
        """Connect to the first autopilot at url (udpin://, tcpout://, serial://...)."""
        config = Configuration.create_with_component_type(ComponentType.COMPANION_COMPUTER)
        async with Mavsdk(config) as mavsdk:
            try:
                await mavsdk.add_any_connection(url)
            except Exception as exc:  # MAVSDK raises its own types for a bad URL or port
                raise VehicleError(f"cannot open the MAVLink connection {url!r}: {exc}") from exc
            system = await mavsdk.first_autopilot(timeout_s=timeout_s)
            if system is None:
                raise VehicleError(f"no autopilot heartbeat on {url} within {timeout_s:g} s")
            link = cls(mavsdk, system)
            await link.request_rates(telemetry_rate_hz)
            yield link

    async def request_rates(self, rate_hz: float) -> None:
        """Ask for the streams the service needs (an ArduPilot sends nothing until asked)."""
        t = self.telemetry
        for set_rate, hz in ((t.set_rate_position, rate_hz),
                             (t.set_rate_position_velocity_ned, rate_hz),
                             (t.set_rate_attitude_quaternion, rate_hz),
                             (t.set_rate_health, 2.0), (t.set_rate_in_air, 2.0),
                             (t.set_rate_battery, 1.0), (t.set_rate_gps_info, 2.0),
                             (t.set_rate_odometry, 2.0),  # for its covariance (PX4: 30 Hz)
                             (t.set_rate_distance_sensor, HEIGHT_RATE_HZ),
                             (t.set_rate_altitude, HEIGHT_RATE_HZ)):
            with contextlib.suppress(Exception):  # an autopilot may refuse a rate: keep its own
                await set_rate(hz)

    @property
    def status(self) -> Status:
        """The latest flags."""
        return self._status

    # -- telemetry ---------------------------------------------------------------------------

    async def run_telemetry(self, sink: TelemetrySink,
                            record: Callable[[int, int, str, str], None] | None = None) -> None:
        """Deliver telemetry to sink until cancelled, and every message received to record, as
        (system, component, name, fields as JSON); record must be quick (it runs on the loop)."""
        def gps(f: dict[str, Any]) -> None:
            if f.get("h_acc") and f.get("v_acc"):  # 0: the receiver does not say
                sink.on_accuracy("gps", f["h_acc"] * MM, f["v_acc"] * MM)

        def odometry(f: dict[str, Any]) -> None:
            sigma = _odometry(f)
            if sigma is not None:
                sink.on_accuracy("odometry", *sigma)

        def distance(f: dict[str, Any]) -> None:
            if f["orientation"] == MAV_SENSOR_ROTATION_PITCH_270:
                sink.on_distance(f["time_boot_ms"] / 1e3, f["current_distance"] * CM,
                                 f["min_distance"] * CM, f["max_distance"] * CM)

        def altitude(f: dict[str, Any]) -> None:
            if f["altitude_terrain"] > TERRAIN_UNKNOWN_M:
                sink.on_terrain_height(f["time_usec"] / 1e6, f["altitude_terrain"])

        handlers: dict[str, Callable[[dict[str, Any]], None]] = {
            "GLOBAL_POSITION_INT": lambda f: sink.on_position(
                f["time_boot_ms"] / 1e3, f["lat"] / 1e7, f["lon"] / 1e7, f["alt"] / 1e3,
                f["relative_alt"] / 1e3, (f["vx"] / 100.0, f["vy"] / 100.0)),
            "LOCAL_POSITION_NED": lambda f: sink.on_local_position(
                f["time_boot_ms"] / 1e3, f["x"], f["y"], f["z"]),
            "ATTITUDE_QUATERNION": lambda f: sink.on_attitude(
                f["time_boot_ms"] / 1e3, (f["q1"], f["q2"], f["q3"], f["q4"])),
            "HEARTBEAT": lambda f: sink.on_heartbeat(int(f["autopilot"])),
            "GPS_RAW_INT": gps,
            "ESTIMATOR_STATUS": lambda f: sink.on_accuracy(
                "estimator", f["pos_horiz_accuracy"], f["pos_vert_accuracy"]),
            "ODOMETRY": odometry,
            "DISTANCE_SENSOR": distance,
            "ALTITUDE": altitude,
            "STATUSTEXT": lambda f: sink.on_autopilot_text(str(f["text"]).rstrip("\x00")),
            "EVENT": lambda f: sink.on_autopilot_text(
                describe_event(int(f["id"]))),
        }
        async with asyncio.TaskGroup() as group:
            group.create_task(self._messages(handlers, record))
            group.create_task(self._status_updates(sink))

    async def _messages(self, handlers: dict[str, Callable[[dict[str, Any]], None]],
                        record: Callable[[int, int, str, str], None] | None) -> None:
        """One subscription to every message (each further one costs the event loop): each to
        record, and the autopilot's own (component 1) to its handler."""
        async with contextlib.aclosing(self.direct.subscribe_message("")) as messages:
            async for message in messages:
                if record is not None:
                    record(message.system_id, message.component_id, message.message_name,
                           message.fields_json)
                handler = handlers.get(message.message_name)
                if handler is None or message.component_id != 1:
                    continue  # only the autopilot's own estimate
                try:
                    handler(_fields(message))
                except (KeyError, TypeError, ValueError, ArithmeticError):  # malformed fields
                    self.malformed += 1

    async def _status_updates(self, sink: TelemetrySink) -> None:
        def update(**changes: Any) -> None:
            self._status = dataclasses.replace(self._status, **changes)
            sink.on_status(self._status)

        async def follow(stream: AsyncIterator[Any], apply: Callable[[Any], None]) -> None:
            async with contextlib.aclosing(stream) as values:  # type: ignore[type-var]
                async for value in values:
                    apply(value)

        t = self.telemetry
        async with asyncio.TaskGroup() as group:
            group.create_task(follow(t.subscribe_flight_mode(),
                                     lambda m: update(flight_mode=FlightMode(m))))
            group.create_task(follow(t.subscribe_armed(), lambda a: update(armed=bool(a))))
            group.create_task(follow(t.subscribe_in_air(), lambda a: update(in_air=bool(a))))
            group.create_task(follow(t.subscribe_health(), lambda h: update(
                position_ok=bool(h.is_global_position_ok and h.is_local_position_ok
                                 and h.is_home_position_ok),
                armable=bool(h.is_armable))))
            group.create_task(follow(t.subscribe_battery(), lambda b: update(
                battery_percent=float(b.remaining_percent))))

    # -- commands ----------------------------------------------------------------------------

    async def _command(self, what: str, call: Callable[[], Awaitable[Any]]) -> None:
        try:
            await call()
        except Exception as exc:  # MAVSDK's ActionError / OffboardError carry .result
            result = getattr(getattr(exc, "result", None), "name", None) or str(exc)
            raise VehicleError(f"{what} refused: {result}") from exc

    async def arm(self) -> None:
        """Arm the motors."""
        await self._command("arm", self.action.arm)

    async def take_off(self, alt_rel_m: float) -> None:
        """Take off to alt_rel_m above home."""
        await self._command("set takeoff altitude",
                            lambda: self.action.set_takeoff_altitude(alt_rel_m))
        await self._command("takeoff", self.action.takeoff)

    async def set_setpoint(self, north_m: float, east_m: float, down_m: float,
                           yaw_deg: float) -> None:
        """The position setpoint MAVSDK streams (local NED about the autopilot's origin)."""
        await self._command("setpoint", lambda: self.offboard.set_position_ned(
            PositionNedYaw(north_m, east_m, down_m, yaw_deg)))

    async def start_offboard(self) -> None:
        """Request OFFBOARD (PX4) / GUIDED (ArduPilot); a setpoint must have been set."""
        await self._command("offboard start", self.offboard.start)

    def release(self) -> None:
        """Stop sending setpoints now, asking for no mode: the pilot may have taken control.

        MAVSDK's Offboard.stop() asks for Hold whatever the mode is, which would take the
        vehicle from a pilot who switched to Position; dropping the plugin stops its 20 Hz
        resend without a word to the autopilot.
        """
        self.offboard.destroy()
        self.offboard = OffboardAsync(self._system)

    async def hold(self) -> None:
        """Request Hold (PX4 AUTO.LOITER, ArduPilot LOITER/BRAKE)."""
        await self._command("hold", self.action.hold)

    async def land(self) -> None:
        """Request a landing here."""
        await self._command("land", self.action.land)

    async def return_to_launch(self) -> None:
        """Request RTL."""
        await self._command("return to launch", self.action.return_to_launch)

    async def status_text(self, text: str, severity: str = "info") -> None:
        """Send STATUSTEXT to the ground station (cut to MAVLink's 50 characters)."""
        fields = {"severity": SEVERITY[severity], "text": text[:STATUSTEXT_MAX_CHARS],
                  "id": 0, "chunk_seq": 0}
        message = MavlinkMessage("STATUSTEXT", 0, 0, 0, 0, json.dumps(fields))
        await self._command("statustext", lambda: self.direct.send_message(message))
