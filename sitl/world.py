"""The SITL's ground truth in continuous time: the scenario's targets as AprilTags on the ground.

Targets move as in the filter-only simulation (`companion.sim.truth`, one state per scenario
step `dt`), and between two steps along the straight line joining them. Target i wears tag id i
(initial targets first, then appearing ones), lying at a seeded random orientation. The world's
local frame is NED about its (0, 0) corner: north = y, east = x.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from companion.errors import ConfigError
from companion.plan.world import World as Area
from companion.sim.scenario import Scenario
from companion.sim.truth import Truth, advance_truth, initial_truth
from companion.vision.camera import BodyPose, CameraModel, pixels_to_ground
from sitl.camera import TAG36H11_COUNT, Tag

FloatArray = NDArray[np.float64]

__all__ = ["TargetWorld", "clutter_tags"]


class TargetWorld:
    """Where the scenario's targets are at any simulation time t_s >= 0 (memoised by step)."""

    def __init__(self, scenario: Scenario, rng: np.random.Generator) -> None:
        t = scenario.targets
        self.scenario = scenario
        self._area = Area(*scenario.world.size_m)
        self._rng = rng
        self._states: list[Truth] = [
            initial_truth(t.positions_xy, t.count, t.appear, self._area, rng)
        ]
        n = int(self._states[0].xy.shape[0])
        if n > TAG36H11_COUNT:
            raise ConfigError("targets.count", f"{n} targets, but tag36h11 has only "
                                               f"{TAG36H11_COUNT} ids")
        self._yaw_rad = rng.uniform(-math.pi, math.pi, size=(n,))

    @property
    def target_count(self) -> int:
        """Targets that ever exist (their tag ids are 0 .. target_count - 1)."""
        return int(self._states[0].xy.shape[0])

    def _state(self, step: int) -> Truth:
        t = self.scenario.targets
        while len(self._states) <= step:
            k = len(self._states)
            self._states.append(advance_truth(
                self._states[-1], k, self.scenario.dt_s, t.speed_m_s, t.turn_every_steps,
                t.appear, t.disappear, t.count, self._area, self._rng,
            ))
        return self._states[step]

    def positions_xy(self, t_s: float) -> tuple[NDArray[np.int64], FloatArray]:
        """(ids, (n, 2) x east, y north metres) of the targets present at t_s."""
        u = max(t_s, 0.0) / self.scenario.dt_s
        k = math.floor(u)
        a, b = self._state(k), self._state(k + 1)
        frac = u - k
        ids = np.flatnonzero(a.alive)
        return ids, (1.0 - frac) * a.xy[ids] + frac * b.xy[ids]

    def tags(self, t_s: float) -> list[Tag]:
        """The targets' tags at t_s, in the world's NED frame."""
        ids, xy = self.positions_xy(t_s)
        size = self.scenario.targets.tag_size_m
        return [Tag(int(i), float(y), float(x), size, float(self._yaw_rad[i]))
                for i, (x, y) in zip(ids, xy, strict=True)]


def clutter_tags(camera: CameraModel, pose: BodyPose, first_id: int, size_m: float,
                 clutter_prob: float, clutter_rate: float, rng: np.random.Generator) -> list[Tag]:
    """False detections for one frame: one tag with clutter_prob, Poisson(clutter_rate) more.

    Each lies where a uniformly drawn pixel's ray meets the ground (uniform over the footprint of
    a level camera), with an id drawn from [first_id, 587) and a random orientation.
    """
    n = int(rng.random() < clutter_prob) + int(rng.poisson(clutter_rate))
    if n == 0 or first_id >= TAG36H11_COUNT:
        return []
    pixels = rng.uniform([0.0, 0.0], [camera.width_px - 1.0, camera.height_px - 1.0], (n, 2))
    ground = pixels_to_ground(camera, pose, pixels)
    ids = rng.integers(first_id, TAG36H11_COUNT, n)
    yaws = rng.uniform(-math.pi, math.pi, n)
    return [Tag(int(i), float(ne[0]), float(ne[1]), size_m, float(yaw))
            for i, ne, yaw in zip(ids, ground, yaws, strict=True) if np.isfinite(ne).all()]
