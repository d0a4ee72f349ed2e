"""Ground truth of the filter-only simulation: target placement and motion, seeded."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from companion.plan.world import World

FloatArray = NDArray[np.float64]

_HEADING_TRIES = 64


@dataclass(frozen=True, slots=True)
class Truth:
    """Every target that ever exists: position, heading and whether it is in the world now."""

    xy: FloatArray  # (N, 2)
    heading_rad: FloatArray  # (N,)
    alive: NDArray[np.bool_]  # (N,)

    @property
    def alive_xy(self) -> FloatArray:
        """Positions of the targets present now."""
        return self.xy[self.alive]


def initial_truth(
    positions_xy: FloatArray,
    count: int,
    appear: tuple[tuple[int, float, float], ...],
    world: World,
    rng: np.random.Generator,
) -> Truth:
    """Initial targets (explicit, or `count` uniform in the world) and later ones, not alive."""
    if positions_xy.shape[0]:
        start = np.asarray(positions_xy, dtype=np.float64)
    else:
        start = rng.uniform(0.0, 1.0, size=(count, 2)) * [world.width_m, world.height_m]
    later = np.array([[x, y] for _, x, y in appear], dtype=np.float64).reshape(-1, 2)
    xy = np.concatenate([start, later])
    alive = np.arange(xy.shape[0]) < start.shape[0]
    heading = np.asarray(rng.uniform(0.0, 2.0 * np.pi, size=xy.shape[0]), dtype=np.float64)
    return Truth(xy, heading, alive)


def advance_truth(
    truth: Truth,
    step: int,
    dt_s: float,
    speed_m_s: float,
    turn_every_steps: int,
    appear: tuple[tuple[int, float, float], ...],
    disappear: tuple[tuple[int, int], ...],
    n_initial: int,
    world: World,
    rng: np.random.Generator,
) -> Truth:
    """Truth at `step` from truth at step - 1: births, deaths, straight-line motion with turns.

    Moving targets go straight at `speed_m_s`, take a new random heading every
    `turn_every_steps` steps, and at the boundary pick a random heading that keeps them inside.
    """
    alive = truth.alive.copy()
    for k, (at, _, _) in enumerate(appear):
        if at == step:
            alive[n_initial + k] = True
    for at, index in disappear:
        if at == step:
            alive[index] = False
    xy, heading = truth.xy, truth.heading_rad
    if speed_m_s > 0.0:
        heading = heading.copy()
        if turn_every_steps > 0 and step % turn_every_steps == 0:
            heading = rng.uniform(0.0, 2.0 * np.pi, size=heading.shape)
        stride = speed_m_s * dt_s
        xy = xy.copy()
        for i in np.flatnonzero(alive):
            for _ in range(_HEADING_TRIES):
                nxt = xy[i] + stride * np.array([np.cos(heading[i]), np.sin(heading[i])])
                if world.contains(nxt):
                    break
                heading[i] = rng.uniform(0.0, 2.0 * np.pi)
            else:
                centre = np.array([world.width_m, world.height_m]) / 2.0
                heading[i] = np.arctan2(*(centre - xy[i])[::-1])
                nxt = xy[i] + stride * np.array([np.cos(heading[i]), np.sin(heading[i])])
            xy[i] = nxt
    return Truth(xy, heading, alive)
