"""Training data for the GP hyperparameters: noisy observations of a scenario's target motion.

The paper learns sigma_f, lambda and sigma_n offline "using a training set consisting of noisy
observations of the target's motion"; here that set is the scenario's own motion model (speed,
turns, world) run on training seeds, observed every step with the sensor's noise.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from companion.plan.world import World
from companion.sat.gp import GpParams, learn_gp_params
from companion.sat.motion import TargetMotion, learn_motion
from companion.sim.scenario import Scenario
from companion.sim.truth import advance_truth, initial_truth

FloatArray = NDArray[np.float64]


def training_trajectories(
    s: Scenario, n_targets: int, steps: int, rng: np.random.Generator
) -> list[tuple[FloatArray, FloatArray]]:
    """`n_targets` trajectories of `steps` + 1 noisy positions (t_s (k,), xy (k, 2))."""
    world = World(*s.world.size_m)
    tg = s.targets
    truth = initial_truth(np.zeros((0, 2)), n_targets, (), world, rng)
    path = [truth.xy.copy()]
    for k in range(1, steps + 1):
        truth = advance_truth(
            truth, k, s.dt_s, tg.speed_m_s, tg.turn_every_steps, (), (), n_targets, world, rng
        )
        path.append(truth.xy.copy())
    xy = np.stack(path, axis=1)  # (targets, steps + 1, 2)
    noisy = np.asarray(xy + rng.normal(0.0, s.sensor.noise_std_m, size=xy.shape), np.float64)
    t_s = np.arange(steps + 1, dtype=np.float64) * s.dt_s
    return [(t_s, noisy[i]) for i in range(n_targets)]


def learn_for_scenario(s: Scenario, n_targets: int, steps: int, seed: int) -> GpParams:
    """GP hyperparameters learned from the scenario's motion model (window: its gp_window)."""
    rng = np.random.default_rng(seed)
    return learn_gp_params(training_trajectories(s, n_targets, steps, rng), s.filter.gp_window)


def learn_motion_for_scenario(s: Scenario, n_targets: int, steps: int, seed: int) -> TargetMotion:
    """The motion class learned from the scenario's motion model (the same training set)."""
    rng = np.random.default_rng(seed)
    return learn_motion(training_trajectories(s, n_targets, steps, rng))
