"""Simulated time: wall time times a speed-up factor, since the simulation started."""

from __future__ import annotations

import time
from collections.abc import Callable


class SimClock:
    """Simulation seconds since start, running `speedup` times as fast as the wall clock."""

    def __init__(self, speedup: float = 1.0, wall: Callable[[], float] = time.monotonic) -> None:
        if not speedup > 0.0:
            raise ValueError(f"speedup must be > 0, got {speedup!r}")
        self.speedup = float(speedup)
        self._wall = wall
        self._start = wall()

    def now_s(self) -> float:
        """Simulation time now."""
        return (self._wall() - self._start) * self.speedup

    def wall_s(self, sim_s: float) -> float:
        """Wall-clock duration of a simulated one."""
        return sim_s / self.speedup
