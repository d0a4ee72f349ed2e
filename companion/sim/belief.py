"""The initial GM-PHD from a belief: exact / under / over / empty / explicit components."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from companion.plan.world import World
from companion.sat.mixture import Mixture, lift_positions, make_mixture

FloatArray = NDArray[np.float64]


def initial_belief(
    kind: str,
    count: int,
    offset_m: float,
    variance_m2: float,
    explicit: list[tuple[float, FloatArray, FloatArray]],
    truth_xy: FloatArray,
    world: World,
    rng: np.random.Generator,
    state_dim: int = 2,
    velocity_var_m2_s2: float = 1.0,
) -> Mixture:
    """Components of weight 1 and covariance variance*I, each `offset_m` from a true target.

    exact/under/over take `count` components: one near each of min(count, targets) targets chosen
    at random, and the rest (over-estimate) uniform in the world. empty has none; explicit has the
    given (weight, mean, cov) components.
    """
    if kind == "empty":
        return Mixture.empty(state_dim)
    if kind == "explicit":
        weights = [w for w, _, _ in explicit]
        means = np.array([m for _, m, _ in explicit], dtype=np.float64).reshape(-1, 2)
        covs = np.array([c for _, _, c in explicit], dtype=np.float64).reshape(-1, 2, 2)
    else:
        near = rng.permutation(truth_xy.shape[0])[: min(count, truth_xy.shape[0])]
        angle = rng.uniform(0.0, 2.0 * np.pi, size=near.size)
        around = truth_xy[near] + offset_m * np.column_stack([np.cos(angle), np.sin(angle)])
        extra = rng.uniform(0.0, 1.0, size=(count - near.size, 2)) * [world.width_m, world.height_m]
        means = world.clip(np.concatenate([around, extra]))
        weights = [1.0] * count
        covs = np.broadcast_to(variance_m2 * np.eye(2), (count, 2, 2))
    return make_mixture(weights, *lift_positions(means, covs, state_dim, velocity_var_m2_s2))
