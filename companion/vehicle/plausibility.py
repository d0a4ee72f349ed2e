"""Is a reported position plausible? A GPS glitch moves it further than the vehicle can fly.

`PositionGate.check(t_s, lat_deg, lon_deg, vel_ne_m_s)` dead-reckons from the last plausible
position with the reported velocities (trapezoid between samples: the velocity comes from the
inertial solution, which a GNSS jump does not move) and refuses a sample further than gate_m
from there. While it refuses, it keeps dead-reckoning; a position that comes back within the
gate is plausible again. A position that stays away for accept_after_s is accepted (the vehicle
really is there: the estimate was reset), and the gate starts again from it. It remembers its
recent glitches, so a frame is judged by the position at its capture time, however late it is
processed. Pure: no clock.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

from companion.errors import ConfigError

__all__ = ["PositionGate", "offset_ne_m"]

_M_PER_DEG_LAT = 111_320.0  # metres per degree of latitude; enough for a gate of metres
_GLITCHES_KEPT = 16  # frames wait for seconds at most; these cover far longer


def offset_ne_m(lat0_deg: float, lon0_deg: float, lat1_deg: float,
                lon1_deg: float) -> tuple[float, float]:
    """North and east metres from the first position to the second (a few km at most)."""
    m_per_deg_lon = _M_PER_DEG_LAT * math.cos(math.radians(lat0_deg))
    return (lat1_deg - lat0_deg) * _M_PER_DEG_LAT, (lon1_deg - lon0_deg) * m_per_deg_lon


@dataclass
class _Reckoned:
    t_s: float
    lat_deg: float
    lon_deg: float
    vel_ne_m_s: tuple[float, float]


class PositionGate:
    """Accepts or refuses each position sample; counts refusals."""

    def __init__(self, gate_m: float = 8.0, accept_after_s: float = 10.0) -> None:
        if not gate_m > 0.0 or not accept_after_s > 0.0:
            raise ConfigError("pose.glitch_gate_m", f"gate_m ({gate_m!r}) and accept_after_s "
                                                    f"({accept_after_s!r}) must be > 0")
        self.gate_m = gate_m
        self.accept_after_s = accept_after_s
        self._at: _Reckoned | None = None  # dead-reckoned from the last plausible sample
        self.refusing_since_s: float | None = None  # boot time of the first refused sample
        # (last plausible sample before a glitch, first plausible one after it), oldest first
        self._glitches: deque[tuple[float, float]] = deque(maxlen=_GLITCHES_KEPT)
        self._glitch_from_s = math.nan  # the last plausible sample before the refusing one
        self.refused = 0
        self.accepted_jumps = 0

    def reset(self) -> None:
        """Forget the past (an autopilot reboot)."""
        self._at, self.refusing_since_s = None, None
        self._glitches.clear()

    def refused_around(self, t_s: float) -> bool:
        """Whether t_s lies in a glitch: between the last plausible sample before refused ones
        and the first plausible one after them (or any time after, while it still refuses)."""
        if self.refusing_since_s is not None and t_s > self._glitch_from_s:
            return True
        return any(from_s < t_s < until_s for from_s, until_s in self._glitches)

    def _plausible_again(self, t_s: float) -> None:
        """A plausible sample at t_s: a glitch in progress ends there."""
        if self.refusing_since_s is not None:
            self._glitches.append((self._glitch_from_s, t_s))
            self.refusing_since_s = None

    def check(self, t_s: float, lat_deg: float, lon_deg: float,
              vel_ne_m_s: tuple[float, float]) -> bool:
        """Whether the sample is plausible; the gate's state moves on either way."""
        at = self._at
        if at is None:
            self._at = _Reckoned(t_s, lat_deg, lon_deg, vel_ne_m_s)
            return True
        dt_s = max(t_s - at.t_s, 0.0)  # a repeated or late sample is judged where we are
        north_m = 0.5 * (at.vel_ne_m_s[0] + vel_ne_m_s[0]) * dt_s
        east_m = 0.5 * (at.vel_ne_m_s[1] + vel_ne_m_s[1]) * dt_s
        m_per_deg_lon = _M_PER_DEG_LAT * math.cos(math.radians(at.lat_deg))
        lat_pred = at.lat_deg + north_m / _M_PER_DEG_LAT
        lon_pred = at.lon_deg + east_m / max(m_per_deg_lon, 1.0)
        miss_m = math.hypot((lat_deg - lat_pred) * _M_PER_DEG_LAT,
                            (lon_deg - lon_pred) * m_per_deg_lon)
        if miss_m <= self.gate_m:
            self._at = _Reckoned(max(t_s, at.t_s), lat_deg, lon_deg, vel_ne_m_s)
            self._plausible_again(t_s)
            return True
        if self.refusing_since_s is None:
            self.refusing_since_s, self._glitch_from_s = t_s, at.t_s
        if t_s - self.refusing_since_s >= self.accept_after_s:  # it stayed there: believe it
            self._at = _Reckoned(t_s, lat_deg, lon_deg, vel_ne_m_s)
            self._plausible_again(t_s)
            self.accepted_jumps += 1
            return True
        self._at = _Reckoned(max(t_s, at.t_s), lat_pred, lon_pred, vel_ne_m_s)
        self.refused += 1
        return False
