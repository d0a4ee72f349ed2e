"""What the service knows of the vehicle: poses over time, its local origin, its clock, its status.

`VehicleView` is the telemetry sink of `MavsdkLink.run_telemetry`. It is pure bookkeeping (the
receive clock is passed in), so replay can drive it from a log.
- Poses go into a `PoseBuffer` keyed by the autopilot's boot time.
- The autopilot's local NED origin, which local setpoints are relative to and which is not
  necessarily home, is estimated from pairs of global and local positions at the same boot time.
- The boot clock: boot time = receive time + offset, where the offset is the largest seen in the
  last samples. That makes it the least delayed sample, so a frame from a camera that knows no
  boot time can be stamped.
- Bad samples never get in: non-finite or out-of-range values (latitude 200, a quaternion that
  is not a rotation) are refused and counted in `rejected`, and so are positions that a
  `PositionGate` finds implausible (a GPS glitch). Frames taken then have no pose.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable

import numpy as np

from companion.errors import InputError
from companion.geo import LocalNed
from companion.vehicle.mavsdk_link import Status
from companion.vehicle.plausibility import PositionGate
from companion.vehicle.pose_buffer import PoseBuffer

__all__ = ["VehicleView"]

ORIGIN_SAMPLES = 25  # median over the first this many global/local pairs
CLOCK_SAMPLES = 200
PAIR_TOLERANCE_S = 0.02


class VehicleView:
    """Telemetry in, the vehicle's pose, local origin, clock and status out."""

    def __init__(self, receive_clock: Callable[[], float], max_gap_s: float = 0.5,
                 gate: PositionGate | None = None) -> None:
        self._clock = receive_clock
        self.poses = PoseBuffer(max_gap_s=max_gap_s)
        self.gate = gate or PositionGate()
        self.rejected = {"position": 0, "local_position": 0, "attitude": 0, "implausible": 0}
        self.status: Status | None = None
        self.on_mode_change: Callable[[], None] = lambda: None  # flight mode or arming changed
        self.local_ned_m: tuple[float, float, float] | None = None
        self.latest_boot_s: float | None = None
        self.home_amsl_m: float | None = None  # from alt_amsl - alt_rel
        self._locals: deque[tuple[float, float, float, float]] = deque(maxlen=50)
        self._origins: deque[tuple[float, float, float]] = deque(maxlen=ORIGIN_SAMPLES)
        self._offsets: deque[float] = deque(maxlen=CLOCK_SAMPLES)

    # -- the sink ----------------------------------------------------------------------------

    def _stamp(self, t_s: float) -> None:
        if self.latest_boot_s is not None and t_s < self.latest_boot_s - 1.0:
            # a reboot: the local origin may move too, estimate it again
            self._origins.clear()
            self._offsets.clear()
            self._locals.clear()
            self.gate.reset()
            self.latest_boot_s = None
        self.latest_boot_s = t_s if self.latest_boot_s is None else max(self.latest_boot_s, t_s)
        self._offsets.append(t_s - self._clock())

    def on_position(self, t_s: float, lat_deg: float, lon_deg: float, alt_amsl_m: float,
                    alt_rel_m: float, vel_ne_m_s: tuple[float, float] = (0.0, 0.0)) -> None:
        """A GLOBAL_POSITION_INT (vel_ne_m_s: its north and east velocity)."""
        if not (all(map(math.isfinite, (t_s, lat_deg, lon_deg, alt_amsl_m, alt_rel_m,
                                         *vel_ne_m_s)))
                and abs(lat_deg) <= 90.0 and abs(lon_deg) <= 180.0
                and (lat_deg, lon_deg) != (0.0, 0.0) and t_s >= 0.0):
            self.rejected["position"] += 1
            return
        self._stamp(t_s)
        if not self.gate.check(t_s, lat_deg, lon_deg, vel_ne_m_s):
            self.rejected["implausible"] += 1
            return
        self.poses.add_position(t_s, lat_deg, lon_deg, alt_amsl_m, alt_rel_m)
        self.home_amsl_m = alt_amsl_m - alt_rel_m
        for local in self._locals:
            if abs(local[0] - t_s) <= PAIR_TOLERANCE_S:
                self._pair(lat_deg, lon_deg, alt_amsl_m, local[1:])
                break

    def on_local_position(self, t_s: float, north_m: float, east_m: float,
                          down_m: float) -> None:
        """A LOCAL_POSITION_NED (about the autopilot's local origin)."""
        if not all(map(math.isfinite, (t_s, north_m, east_m, down_m))) or t_s < 0.0:
            self.rejected["local_position"] += 1
            return
        self._stamp(t_s)
        self.local_ned_m = (north_m, east_m, down_m)
        self._locals.append((t_s, north_m, east_m, down_m))
        sample = self.poses.at(t_s)
        if sample is not None:
            self._pair(sample.lat_deg, sample.lon_deg, sample.alt_amsl_m,
                       (north_m, east_m, down_m))

    def on_attitude(self, t_s: float, q_wxyz: tuple[float, float, float, float]) -> None:
        """An ATTITUDE_QUATERNION."""
        if not all(map(math.isfinite, (t_s, *q_wxyz))) or t_s < 0.0:
            self.rejected["attitude"] += 1
            return
        try:
            self.poses.add_attitude(t_s, q_wxyz)
        except InputError:  # not a unit quaternion
            self.rejected["attitude"] += 1
            return
        self._stamp(t_s)

    def on_status(self, status: Status) -> None:
        """Mode, armed, health, battery; a change of mode or arming calls `on_mode_change`."""
        before, self.status = self.status, status
        if before is None or (before.flight_mode, before.armed) != (status.flight_mode,
                                                                    status.armed):
            self.on_mode_change()

    # -- what it knows -----------------------------------------------------------------------

    def _pair(self, lat_deg: float, lon_deg: float, alt_amsl_m: float,
              ned_m: tuple[float, float, float]) -> None:
        if len(self._origins) == ORIGIN_SAMPLES:
            return  # the origin stays put until a reboot
        here = LocalNed(lat_deg, lon_deg, alt_amsl_m)
        lat, lon, alt = here.ned_to_geodetic(-ned_m[0], -ned_m[1], -ned_m[2])
        self._origins.append((float(lat), float(lon), float(alt)))

    def local_origin(self) -> LocalNed | None:
        """The autopilot's local NED origin (median of recent estimates), once known."""
        if len(self._origins) < 3:
            return None
        lat, lon, alt = np.median(np.array(self._origins), axis=0)
        return LocalNed(float(lat), float(lon), float(alt))

    def boot_time_now(self) -> float | None:
        """The autopilot's boot time now, from the receive clock."""
        if not self._offsets:
            return None
        return self._clock() + max(self._offsets)
