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
from dataclasses import astuple, dataclass

import numpy as np

from companion.errors import InputError
from companion.geo import LocalNed
from companion.vehicle.mavsdk_link import Status
from companion.vehicle.plausibility import PositionGate
from companion.vehicle.pose_buffer import PoseBuffer

__all__ = ["Accuracy", "VehicleView", "height_agl_m"]

ORIGIN_SAMPLES = 25  # median over the first this many global/local pairs
CLOCK_SAMPLES = 200
PAIR_TOLERANCE_S = 0.02
HEIGHT_SAMPLES = 100  # rangefinder / terrain heights kept (10 s at 10 Hz)
HEIGHT_WITHIN_S = 0.3  # a height this close in time to a frame's capture is used for it
ACCURACY_FRESH_S = 5.0  # an accuracy report older than this (receive clock) is not used
MAV_AUTOPILOT_ARDUPILOTMEGA = 3
ACCURACY_SOURCES = ("odometry", "estimator", "gps")  # the better first


@dataclass(frozen=True, slots=True)
class Accuracy:
    """The autopilot's own 1-sigma figures for its estimate; NaN where it says nothing."""

    horizontal_std_m: float = math.nan
    vertical_std_m: float = math.nan
    attitude_std_deg: float = math.nan
    heading_std_deg: float = math.nan


def height_agl_m(alt_rel_m: float, rest_height_m: float) -> float:
    """Height above ground from the relative altitude (zero is the resting vehicle) and the
    camera's height above ground at rest; never below the ground."""
    return max(alt_rel_m + rest_height_m, 0.0)


class VehicleView:
    """Telemetry in, the vehicle's pose, local origin, clock and status out."""

    def __init__(self, receive_clock: Callable[[], float], max_gap_s: float = 0.5,
                 gate: PositionGate | None = None) -> None:
        self._clock = receive_clock
        self.poses = PoseBuffer(max_gap_s=max_gap_s)
        self.gate = gate or PositionGate()
        self.rejected = {"position": 0, "local_position": 0, "attitude": 0, "implausible": 0}
        self.status: Status | None = None
        self.has_flown = False  # the landed state has said "in the air" since the link came up
        self.on_mode_change: Callable[[], None] = lambda: None  # flight mode or arming changed
        self.local_ned_m: tuple[float, float, float] | None = None
        self.latest_boot_s: float | None = None
        self.home_amsl_m: float | None = None  # from alt_amsl - alt_rel
        self._locals: deque[tuple[float, float, float, float]] = deque(maxlen=50)
        self._origins: deque[tuple[float, float, float]] = deque(maxlen=ORIGIN_SAMPLES)
        self._offsets: deque[float] = deque(maxlen=CLOCK_SAMPLES)
        self.ardupilot = False  # from the heartbeat: ArduPilot (else PX4 rules)
        self._accuracy: dict[str, tuple[float, Accuracy]] = {}  # source: (received, figures)
        self._ranges: deque[tuple[float, float]] = deque(maxlen=HEIGHT_SAMPLES)
        self._terrain: deque[tuple[float, float]] = deque(maxlen=HEIGHT_SAMPLES)
        self.on_text: Callable[[str], None] = lambda _: None

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
        self.has_flown = self.has_flown or status.in_air
        if before is None or (before.flight_mode, before.armed) != (status.flight_mode,
                                                                    status.armed):
            self.on_mode_change()

    def on_heartbeat(self, autopilot: int) -> None:
        """The autopilot's HEARTBEAT: which firmware family it is."""
        self.ardupilot = autopilot == MAV_AUTOPILOT_ARDUPILOTMEGA

    def on_accuracy(self, source: str, horizontal_std_m: float, vertical_std_m: float,
                    attitude_std_deg: float = math.nan, heading_std_deg: float = math.nan) -> None:
        """The autopilot's own uncertainty figures from one source (odometry, estimator, gps)."""
        values = (horizontal_std_m, vertical_std_m, attitude_std_deg, heading_std_deg)
        if source in ACCURACY_SOURCES and all(math.isnan(v) or 0.0 <= v < math.inf
                                              for v in values):
            self._accuracy[source] = (self._clock(), Accuracy(*values))

    def on_distance(self, t_s: float, distance_m: float, min_m: float, max_m: float) -> None:
        """A downward rangefinder's reading; out of its range it says nothing."""
        if all(map(math.isfinite, (t_s, distance_m))) and min_m <= distance_m <= max_m:
            self._ranges.append((t_s, distance_m))

    def on_terrain_height(self, t_s: float, height_m: float) -> None:
        """The autopilot's height above the terrain under it."""
        if math.isfinite(t_s) and math.isfinite(height_m) and height_m >= 0.0:
            self._terrain.append((t_s, height_m))

    def on_autopilot_text(self, text: str) -> None:
        """A STATUSTEXT or event of the autopilot's (a refusal's reason, say)."""
        self.on_text(text)

    # -- what it knows -----------------------------------------------------------------------

    def landed(self) -> bool:
        """Whether the landed state says the vehicle is down again after it flew (a firmware
        that never reports a landed state is never taken to have landed)."""
        return self.has_flown and self.status is not None and not self.status.in_air

    def accuracy(self) -> Accuracy:
        """The autopilot's latest figures, each from the best source that gave it recently."""
        now = self._clock()
        best = [math.nan] * 4
        for source in reversed(ACCURACY_SOURCES):  # the better overwrite
            received_s, figures = self._accuracy.get(source, (-math.inf, Accuracy()))
            if now - received_s <= ACCURACY_FRESH_S:
                best = [b if math.isnan(v) else v for b, v in zip(best, astuple(figures),
                                                                  strict=True)]
        return Accuracy(*best)

    def height_at(self, t_s: float, alt_rel_m: float, tilt_cos: float,
                  rest_height_m: float) -> tuple[float, str]:
        """The camera's height above ground at t_s and where it came from: a downward
        rangefinder (its slant range times the cosine of the tilt), else the autopilot's
        terrain height, else the relative altitude plus the camera's resting height."""
        for samples, source, scale in ((self._ranges, "rangefinder", tilt_cos),
                                       (self._terrain, "terrain", 1.0)):
            near = min(samples, key=lambda s: abs(s[0] - t_s), default=None)
            if near is not None and abs(near[0] - t_s) <= HEIGHT_WITHIN_S:
                return near[1] * scale, source
        return height_agl_m(alt_rel_m, rest_height_m), "altitude"

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
