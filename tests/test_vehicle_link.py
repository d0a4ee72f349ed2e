"""The service's MAVSDK link against the SITL autopilot, both flavours: times, status, commands."""

from __future__ import annotations

import asyncio
import math
from collections.abc import Iterator

import numpy as np
import pytest

from companion.geo import LocalNed
from companion.vehicle.mavsdk_link import (
    ONBOARD_COMPONENT_ID,
    FlightMode,
    MavsdkLink,
    Status,
    VehicleError,
)
from sitl.autopilot import AutopilotConfig, MockAutopilot
from sitl.clock import SimClock
from sitl.link import UdpLink, free_udp_port
from sitl.modes import Behaviour, Flavour

pytestmark = pytest.mark.sitl

SPEEDUP = 3.0
GEO = LocalNed(47.397742, 8.545594, 488.0)


@pytest.fixture(params=[Flavour.PX4, Flavour.ARDUPILOT], ids=lambda f: f.value)
def autopilot(request: pytest.FixtureRequest) -> Iterator[tuple[MockAutopilot, int]]:
    port = free_udp_port()
    link = UdpLink([("127.0.0.1", port)], np.random.default_rng(0))
    config = AutopilotConfig(flavour=request.param, armable_after_s=1.0,
                             ekf_origin_offset_ned=(3.0, -2.0))
    ap = MockAutopilot(config, link, SimClock(SPEEDUP), GEO)
    ap.start()
    yield ap, port
    ap.stop()


class Recorder:
    """A TelemetrySink that keeps everything and wakes waiters."""

    def __init__(self) -> None:
        self.positions: list[tuple[float, ...]] = []
        self.locals: list[tuple[float, ...]] = []
        self.attitudes: list[tuple[float, tuple[float, float, float, float]]] = []
        self.statuses: list[Status] = []
        self.autopilots: list[int] = []
        self.accuracies: list[tuple[str, float, float, float, float]] = []
        self.distances: list[tuple[float, float]] = []
        self.texts: list[str] = []
        self.changed = asyncio.Event()

    def on_position(self, t_s: float, lat_deg: float, lon_deg: float, alt_amsl_m: float,
                    alt_rel_m: float, vel_ne_m_s: tuple[float, float] = (0.0, 0.0)) -> None:
        self.positions.append((t_s, lat_deg, lon_deg, alt_amsl_m, alt_rel_m, *vel_ne_m_s))
        self.changed.set()

    def on_local_position(self, t_s: float, north_m: float, east_m: float,
                          down_m: float) -> None:
        self.locals.append((t_s, north_m, east_m, down_m))
        self.changed.set()

    def on_attitude(self, t_s: float, q_wxyz: tuple[float, float, float, float]) -> None:
        self.attitudes.append((t_s, q_wxyz))
        self.changed.set()

    def on_status(self, status: Status) -> None:
        self.statuses.append(status)
        self.changed.set()

    def on_heartbeat(self, autopilot: int) -> None:
        self.autopilots.append(autopilot)

    def on_accuracy(self, source: str, horizontal_std_m: float, vertical_std_m: float,
                    attitude_std_deg: float = math.nan, heading_std_deg: float = math.nan) -> None:
        self.accuracies.append((source, horizontal_std_m, vertical_std_m, attitude_std_deg,
                                heading_std_deg))
        self.changed.set()

    def on_distance(self, t_s: float, distance_m: float, min_m: float, max_m: float) -> None:
        self.distances.append((t_s, distance_m))

    def on_terrain_height(self, t_s: float, height_m: float) -> None:
        self.distances.append((t_s, height_m))

    def on_autopilot_text(self, text: str) -> None:
        self.texts.append(text)
        self.changed.set()

    async def until(self, condition: object, timeout_s: float) -> None:
        async def wait() -> None:
            while not condition():  # type: ignore[operator]
                self.changed.clear()
                await self.changed.wait()

        await asyncio.wait_for(wait(), timeout_s)


def test_telemetry_carries_boot_times_and_commands_fly(
        autopilot: tuple[MockAutopilot, int]) -> None:
    ap, port = autopilot

    async def session() -> None:
        sink = Recorder()
        async with MavsdkLink.connect(f"udpin://127.0.0.1:{port}", timeout_s=10.0) as link:
            telemetry = asyncio.create_task(link.run_telemetry(sink))
            try:
                await sink.until(lambda: len(sink.positions) >= 5 and len(sink.attitudes) >= 5
                                 and len(sink.locals) >= 5, 10.0)
                now_s = ap.snapshot().t_s
                for series in (sink.positions, sink.attitudes, sink.locals):
                    times = [sample[0] for sample in series]
                    assert times == sorted(times)
                    assert now_s - 1.0 < times[-1] <= now_s + 1e-9  # the autopilot's boot time
                lat, lon = sink.positions[-1][1:3]
                assert (lat, lon) == pytest.approx((GEO.lat_deg, GEO.lon_deg), abs=1e-6)
                _, north_m, east_m, _ = sink.locals[-1]
                if ap.config.flavour is Flavour.ARDUPILOT:  # about the EKF origin, not home
                    assert (north_m, east_m) == pytest.approx((-3.0, 2.0), abs=0.3)
                else:
                    assert (north_m, east_m) == pytest.approx((0.0, 0.0), abs=0.3)

                await sink.until(lambda: link.status.position_ok and link.status.armable, 10.0)
                await link.arm()
                await link.take_off(5.0)
                await sink.until(lambda: sink.positions[-1][4] > 4.7, 20.0)
                assert link.status.armed and link.status.in_air
                north0, east0 = sink.locals[-1][1:3]
                await link.set_setpoint(north0 + 6.0, east0, -5.0, 0.0)
                while not ap.snapshot().setpoints_streaming:  # MAVSDK resends it at 20 Hz
                    await asyncio.sleep(0.02)
                await link.start_offboard()
                await sink.until(lambda: link.status.flight_mode is FlightMode.OFFBOARD, 5.0)
                await sink.until(lambda: abs(sink.locals[-1][1] - north0 - 6.0) < 0.5, 20.0)
                await link.status_text("companion: 5 targets confirmed", "notice")
                # The pilot takes over; releasing stops the setpoints and leaves the mode alone.
                ap.pilot_set_mode(Behaviour.POSITION)
                await sink.until(lambda: link.status.flight_mode is FlightMode.POSCTL
                                 or link.status.flight_mode is FlightMode.HOLD, 5.0)
                released_s = ap.clock.now_s()
                link.release()
                await sink.until(lambda: sink.attitudes[-1][0] > ap.snapshot().t_s - 0.1
                                 and ap.clock.now_s() > released_s + 1.0, 10.0)
                snap = ap.snapshot()
                assert snap.behaviour is Behaviour.POSITION
                assert snap.last_setpoint_clock_s < released_s + 0.1
                await link.land()
                await sink.until(lambda: not link.status.armed, 40.0)
            finally:
                telemetry.cancel()
                with pytest.raises(asyncio.CancelledError):
                    await telemetry

    asyncio.run(session())
    assert (ONBOARD_COMPONENT_ID, 5, "companion: 5 targets confirmed") in ap.texts_received


def test_a_refused_command_names_itself(autopilot: tuple[MockAutopilot, int]) -> None:
    _, port = autopilot

    async def session() -> None:
        async with MavsdkLink.connect(f"udpin://127.0.0.1:{port}", timeout_s=10.0) as link:
            with pytest.raises(VehicleError, match="offboard start refused"):
                await link.start_offboard()  # no setpoint set

    asyncio.run(session())


def test_no_autopilot_is_a_clear_error() -> None:
    async def session() -> None:
        async with MavsdkLink.connect(f"udpin://127.0.0.1:{free_udp_port()}", timeout_s=1.0):
            pass

    with pytest.raises(VehicleError, match=r"no autopilot heartbeat on udpin://127\.0\.0\.1:"):
        asyncio.run(session())
