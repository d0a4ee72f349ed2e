"""The vehicle's recent poses, interpolated at a frame's capture time.

Positions (GLOBAL_POSITION_INT) and attitudes (ATTITUDE_QUATERNION) arrive as separate streams,
each stamped with the autopilot's boot time in seconds (`time_boot_ms / 1000`). `PoseBuffer`
keeps each series sorted, interpolates each on its own (position linearly, attitude by slerp)
and refuses to invent a pose it did not see: no answer across a gap longer than max_gap_s, nor
further than max_extrapolation_s beyond the samples. Pure: no clock, no threads, no locks.
"""

from __future__ import annotations

import math
import numbers
from bisect import bisect_left
from dataclasses import dataclass

from companion.errors import ConfigError, InputError

__all__ = ["GeoPoseSample", "PoseBuffer", "slerp"]

Quaternion = tuple[float, float, float, float]
_UNIT_TOLERANCE = 1e-3  # |q| may differ from 1 by this much (float32 telemetry); it is normalized


@dataclass(frozen=True, slots=True)
class GeoPoseSample:
    """The vehicle's pose at t_s (boot time, s): WGS84 position, altitudes, body(FRD)->NED q."""

    t_s: float
    lat_deg: float
    lon_deg: float
    alt_amsl_m: float
    alt_rel_m: float  # above the home (take-off) altitude
    q_wxyz: Quaternion


def _finite(name: str, value: object) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real) \
            or not math.isfinite(float(value)):
        raise InputError(f"{name} must be a finite number, got {value!r}")
    return float(value)


def _positive(key: str, value: object) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real) \
            or not 0.0 < float(value) < math.inf:
        raise ConfigError(key, f"must be a number > 0, got {value!r}")
    return float(value)


def slerp(q0: Quaternion, q1: Quaternion, u: float) -> Quaternion:
    """The rotation u of the way from q0 to q1 along the shorter arc (u outside [0, 1]
    extrapolates); q and -q are the same rotation."""
    dot = sum(a * b for a, b in zip(q0, q1, strict=True))
    sign = -1.0 if dot < 0.0 else 1.0
    dot = min(abs(dot), 1.0)
    if dot > 0.9995:  # nearly equal: lerp is exact to ~1e-9 and avoids dividing by sin(~0)
        w0, w1 = 1.0 - u, u
    else:
        theta = math.acos(dot)
        w0 = math.sin((1.0 - u) * theta) / math.sin(theta)
        w1 = math.sin(u * theta) / math.sin(theta)
    q = [w0 * a + sign * w1 * b for a, b in zip(q0, q1, strict=True)]
    norm = math.sqrt(sum(c * c for c in q))
    return (q[0] / norm, q[1] / norm, q[2] / norm, q[3] / norm)


class _Series:
    """One stream's samples, sorted by time, one per time (a repeat replaces)."""

    def __init__(self) -> None:
        self.t_s: list[float] = []
        self.values: list[tuple[float, ...]] = []

    def insert(self, t_s: float, value: tuple[float, ...], max_age_s: float) -> None:
        i = bisect_left(self.t_s, t_s)
        if i < len(self.t_s) and self.t_s[i] == t_s:
            self.values[i] = value
        else:
            self.t_s.insert(i, t_s)
            self.values.insert(i, value)
        old = bisect_left(self.t_s, self.t_s[-1] - max_age_s)
        del self.t_s[:old], self.values[:old]

    def bracket(self, t_s: float, max_gap_s: float,
                max_extrapolation_s: float) -> tuple[int, int, float] | None:
        """(i, j, u): the value at t_s is u of the way from sample i to j; None if unseen."""
        times, n = self.t_s, len(self.t_s)
        i = bisect_left(times, t_s)
        if i < n and times[i] == t_s:
            return i, i, 0.0
        if n == 0 or (i == 0 and times[0] - t_s > max_extrapolation_s) \
                or (i == n and t_s - times[-1] > max_extrapolation_s):
            return None
        if 0 < i < n:
            lo, hi = i - 1, i
            if times[hi] - times[lo] > max_gap_s:
                return None
        else:  # just beyond an end: extrapolate along the end segment, or hold a lone sample
            lo, hi = (0, 1) if i == 0 else (n - 2, n - 1)
            if n == 1 or times[hi] - times[lo] > max_gap_s:
                return (0, 0, 0.0) if i == 0 else (n - 1, n - 1, 0.0)
        return lo, hi, (t_s - times[lo]) / (times[hi] - times[lo])


class PoseBuffer:
    """Recent positions and attitudes on the autopilot's boot time base; at(t_s) interpolates.

    Samples may arrive out of order or repeated (a repeat replaces). A sample more than
    reboot_jump_s older than its stream's newest means the autopilot rebooted: everything is
    cleared. Samples older than max_age_s before their stream's newest are dropped.
    """

    def __init__(self, max_age_s: float = 10.0, max_gap_s: float = 0.5,
                 max_extrapolation_s: float = 0.1, reboot_jump_s: float = 1.0) -> None:
        self.max_age_s = _positive("pose_buffer.max_age_s", max_age_s)
        self.max_gap_s = _positive("pose_buffer.max_gap_s", max_gap_s)
        self.max_extrapolation_s = _positive("pose_buffer.max_extrapolation_s",
                                             max_extrapolation_s)
        self.reboot_jump_s = _positive("pose_buffer.reboot_jump_s", reboot_jump_s)
        self._positions = _Series()
        self._attitudes = _Series()
        self.reboots = 0  # backward time jumps seen (each cleared the buffer)

    @property
    def position_count(self) -> int:
        """Position samples held."""
        return len(self._positions.t_s)

    @property
    def attitude_count(self) -> int:
        """Attitude samples held."""
        return len(self._attitudes.t_s)

    def clear(self) -> None:
        """Forget every sample."""
        for series in (self._positions, self._attitudes):
            series.t_s.clear()
            series.values.clear()

    def add_position(self, t_s: float, lat_deg: float, lon_deg: float, alt_amsl_m: float,
                     alt_rel_m: float) -> None:
        """Add a position sample (degrees WGS84, metres); InputError if a value is unusable."""
        lat, lon = _finite("position.lat_deg", lat_deg), _finite("position.lon_deg", lon_deg)
        if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
            raise InputError(f"position.lat_deg/lon_deg out of range: ({lat_deg!r}, {lon_deg!r})")
        self._add(self._positions, _finite("position.t_s", t_s),
                  (lat, lon, _finite("position.alt_amsl_m", alt_amsl_m),
                   _finite("position.alt_rel_m", alt_rel_m)))

    def add_attitude(self, t_s: float, q_wxyz: tuple[float, float, float, float]) -> None:
        """Add an attitude sample (unit quaternion, body FRD -> NED, scalar first)."""
        if not isinstance(q_wxyz, tuple | list) or len(q_wxyz) != 4:
            raise InputError(f"attitude.q_wxyz must be 4 numbers, got {q_wxyz!r}")
        q = tuple(_finite("attitude.q_wxyz", c) for c in q_wxyz)
        norm = math.sqrt(sum(c * c for c in q))
        if abs(norm - 1.0) > _UNIT_TOLERANCE:
            raise InputError(f"attitude.q_wxyz must be a unit quaternion, norm is {norm:.6f}")
        self._add(self._attitudes, _finite("attitude.t_s", t_s), tuple(c / norm for c in q))

    def newest(self) -> GeoPoseSample | None:
        """The pose at the newest position's time, or None when there is none or when it is more
        than max_gap_s older than the newest attitude (the position stream stopped).

        at(the newest time of either stream) is None whenever a lossy link has delivered an
        attitude more than max_extrapolation_s after the last position; the vehicle is then
        still where that position put it, a moment ago."""
        positions, attitudes = self._positions.t_s, self._attitudes.t_s
        if not positions or (attitudes and attitudes[-1] - positions[-1] > self.max_gap_s):
            return None
        return self.at(positions[-1])

    def _add(self, series: _Series, t_s: float, value: tuple[float, ...]) -> None:
        if series.t_s and t_s < series.t_s[-1] - self.reboot_jump_s:
            self.clear()
            self.reboots += 1
        series.insert(t_s, value, self.max_age_s)

    def at(self, t_s: float) -> GeoPoseSample | None:
        """The pose at t_s, or None where either stream has no samples close enough."""
        t_s = _finite("t_s", t_s)
        pos = self._positions.bracket(t_s, self.max_gap_s, self.max_extrapolation_s)
        att = self._attitudes.bracket(t_s, self.max_gap_s, self.max_extrapolation_s)
        if pos is None or att is None:
            return None
        (i, j, u), (k, m, v) = pos, att
        (lat0, lon0, amsl0, rel0), (lat1, lon1, amsl1, rel1) = (self._positions.values[i],
                                                                self._positions.values[j])
        lon1 += -360.0 if lon1 - lon0 > 180.0 else 360.0 if lon1 - lon0 < -180.0 else 0.0
        lon = lon0 + u * (lon1 - lon0)  # the short way, also across the antimeridian
        lon += -360.0 if lon > 180.0 else 360.0 if lon < -180.0 else 0.0
        q0, q1 = self._attitudes.values[k], self._attitudes.values[m]
        q = slerp((q0[0], q0[1], q0[2], q0[3]), (q1[0], q1[1], q1[2], q1[3]), v)
        return GeoPoseSample(t_s, lat0 + u * (lat1 - lat0), lon, amsl0 + u * (amsl1 - amsl0),
                             rel0 + u * (rel1 - rel0), q)
