"""The real MAVSDK library (version 4, native) flying the mock autopilot, both flavours."""

from __future__ import annotations

import asyncio
import contextlib
import math
import time
from collections.abc import AsyncIterator, Iterator
from dataclasses import dataclass

import numpy as np
import pytest
from mavsdk.asyncio import ComponentType, Configuration, Mavsdk
from mavsdk.asyncio.plugins.action import ActionAsync
from mavsdk.asyncio.plugins.offboard import OffboardAsync, PositionNedYaw
from mavsdk.asyncio.plugins.telemetry import FlightMode, TelemetryAsync

from companion.geo import LocalNed
from sitl.autopilot import AutopilotConfig, MockAutopilot
from sitl.clock import SimClock
from sitl.link import UdpLink, free_udp_port
from sitl.modes import Behaviour, Flavour

pytestmark = pytest.mark.sitl

SPEEDUP = 3.0
ALT_M = 8.0
GEO = LocalNed(37.2, -80.4, 600.0)


@pytest.fixture(params=[Flavour.PX4, Flavour.ARDUPILOT], ids=lambda f: f.value)
def sitl(request: pytest.FixtureRequest) -> Iterator[tuple[MockAutopilot, int]]:
    port = free_udp_port()
    flavour: Flavour = request.param
    link = UdpLink([("127.0.0.1", port)], np.random.default_rng(0))
    autopilot = MockAutopilot(AutopilotConfig(flavour=flavour, armable_after_s=1.0), link,
                              SimClock(SPEEDUP), GEO)
    autopilot.start()
    yield autopilot, port
    autopilot.stop()


@dataclass
class Drone:
    tel: TelemetryAsync
    act: ActionAsync
    off: OffboardAsync


@contextlib.asynccontextmanager
async def _connect(port: int, flavour: Flavour) -> AsyncIterator[Drone]:
    config = Configuration.create_with_component_type(ComponentType.COMPANION_COMPUTER)
    async with Mavsdk(config) as mavsdk:
        await mavsdk.add_any_connection(f"udpin://127.0.0.1:{port}")
        system = await mavsdk.first_autopilot(timeout_s=10.0)
        assert system is not None
        drone = Drone(TelemetryAsync(system), ActionAsync(system), OffboardAsync(system))
        if flavour is Flavour.ARDUPILOT:  # an ArduPilot streams nothing until asked
            for set_rate in (drone.tel.set_rate_health, drone.tel.set_rate_position,
                             drone.tel.set_rate_position_velocity_ned,
                             drone.tel.set_rate_attitude_quaternion, drone.tel.set_rate_in_air):
                await set_rate(5.0)
        yield drone


async def _until(stream: AsyncIterator[object], done: object, timeout_s: float) -> object:
    async def first() -> object:
        async for value in stream:
            if done(value):  # type: ignore[operator]
                return value
        raise AssertionError("stream ended")

    return await asyncio.wait_for(first(), timeout_s)


async def _start_offboard(drone: Drone, autopilot: MockAutopilot) -> None:
    """Start offboard once the autopilot sees the setpoint stream (MAVSDK resends at 20 Hz)."""
    while not autopilot.snapshot().setpoints_streaming:
        await asyncio.sleep(0.02)
    await drone.off.start()


async def _hover_in_offboard(drone: Drone, autopilot: MockAutopilot) -> None:
    """Take off, then hold the take-off point at ALT_M in OFFBOARD."""
    await _take_off(drone)
    await drone.off.set_position_ned(PositionNedYaw(0.0, 0.0, -ALT_M, 0.0))
    await _start_offboard(drone, autopilot)


async def _take_off(drone: Drone) -> None:
    await _until(drone.tel.subscribe_health(),
                 lambda h: h.is_global_position_ok and h.is_home_position_ok and h.is_armable, 20)
    await drone.act.set_takeoff_altitude(ALT_M)
    await drone.act.arm()
    await drone.act.takeoff()
    await _until(drone.tel.subscribe_position(), lambda p: p.relative_altitude_m > ALT_M - 0.3,
                 20)


async def _fly_to(drone: Drone, north_m: float, east_m: float) -> None:
    await drone.off.set_position_ned(PositionNedYaw(north_m, east_m, -ALT_M, 0.0))
    await _until(
        drone.tel.subscribe_position_velocity_ned(),
        lambda pv: math.hypot(pv.position.north_m - north_m, pv.position.east_m - east_m) < 0.5
        and abs(pv.velocity.north_m_s) + abs(pv.velocity.east_m_s) < 0.3,
        20,
    )


def test_mission_flight(sitl: tuple[MockAutopilot, int]) -> None:
    autopilot, port = sitl

    async def flight() -> None:
        async with _connect(port, autopilot.config.flavour) as drone:
            await _hover_in_offboard(drone, autopilot)
            await _until(drone.tel.subscribe_flight_mode(), lambda m: m == FlightMode.OFFBOARD, 5)
            for north in (10.0, -10.0):  # two setpoints 20 m apart
                await _fly_to(drone, north, 0.0)
            await drone.off.stop()
            await drone.act.land()
            await _until(drone.tel.subscribe_armed(), lambda armed: not armed, 40)

    asyncio.run(flight())
    snap = autopilot.snapshot()
    assert not snap.armed and snap.vehicle.on_ground


def test_pilot_override_and_link_cut(sitl: tuple[MockAutopilot, int]) -> None:
    autopilot, port = sitl

    async def flight() -> None:
        async with _connect(port, autopilot.config.flavour) as drone:
            await _hover_in_offboard(drone, autopilot)
            await _fly_to(drone, 5.0, 0.0)
            # The pilot takes over: the mode changes under MAVSDK, which keeps sending setpoints
            # for a while; the autopilot ignores them and never goes back to OFFBOARD by itself.
            held_ned = autopilot.snapshot().vehicle.position_ned.copy()
            autopilot.pilot_set_mode(Behaviour.POSITION)
            await _until(drone.tel.subscribe_flight_mode(), lambda m: m == FlightMode.POSCTL, 5)
            await drone.off.set_position_ned(PositionNedYaw(15.0, 0.0, -ALT_M, 0.0))
            await asyncio.sleep(1.0)  # MAVSDK streams the new setpoint meanwhile
            assert autopilot.snapshot().behaviour is Behaviour.POSITION
            assert np.linalg.norm(autopilot.snapshot().vehicle.position_ned - held_ned) < 1.0
            if autopilot.config.flavour is not Flavour.PX4:
                return  # an ArduPilot in GUIDED has no offboard-loss failsafe to show
            # Back in OFFBOARD, the link is cut: setpoints stop arriving, PX4 falls back to
            # Position mode within COM_OF_LOSS_T. OFFBOARD is still the mode asked for, so when
            # the link comes back with MAVSDK's setpoints PX4 returns to it by itself.
            await _start_offboard(drone, autopilot)
            await _until(drone.tel.subscribe_flight_mode(), lambda m: m == FlightMode.OFFBOARD, 5)
            cut_at = autopilot.clock.now_s()
            autopilot.link.faults.cut_until_s = cut_at + 5.0
            while autopilot.snapshot().behaviour is Behaviour.OFFBOARD:
                await asyncio.sleep(0.05)
            assert autopilot.clock.now_s() - cut_at < 1.0 + 0.5
            assert autopilot.snapshot().behaviour is Behaviour.POSITION
            while (autopilot.snapshot().behaviour is Behaviour.POSITION
                   and autopilot.clock.now_s() < cut_at + 10.0):
                await asyncio.sleep(0.05)
            assert autopilot.snapshot().behaviour is Behaviour.OFFBOARD
            assert autopilot.clock.now_s() > cut_at + 5.0  # not before the link came back
            assert "failsafe: offboard setpoints back, offboard" in autopilot.statustexts

    started = time.monotonic()
    asyncio.run(flight())
    assert time.monotonic() - started < 60.0
