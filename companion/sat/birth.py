"""Measurement-driven birth (Ristic et al. 2012): one new component per measurement."""

from __future__ import annotations

from enum import Enum

import numpy as np
from numpy.typing import NDArray

from companion.sat.mixture import NO_LABEL, Mixture, lift_positions

FloatArray = NDArray[np.float64]


class BirthWeight(Enum):
    """How a new component's weight is set."""

    CONSTANT = "constant"  # the paper: every measurement gives a component of the birth weight
    ADAPTIVE = "adaptive"  # Ristic et al.: the share of the measurement that nothing else explains


def birth_weights(
    mode: BirthWeight,
    birth_weight: float,
    explained: FloatArray,
    clutter_intensity: float,
    birth_intensity: float,
) -> FloatArray:
    """The weight of the component born from each measurement.

    Adaptive: w_b(z) = b(z) / (kappa(z) + b(z) + sum_l p_D,l w_l q_l(z)) (Ristic et al. 2012), with
    b(z) = birth_weight / |FOV| the intensity of measurements from new targets; a measurement that
    neither clutter nor the prior explains gives birth_weight / (1 + expected clutter count).
    """
    if mode is BirthWeight.CONSTANT:
        return np.full(explained.shape, birth_weight)
    return birth_intensity / (clutter_intensity + birth_intensity + explained)


def birth(
    measurements_xy: FloatArray, weights: FloatArray, r_cov: FloatArray, velocity_var_m2_s2: float,
    state_dim: int,
) -> Mixture:
    """Components with mean z, covariance R (and a zero-mean velocity prior in a 4-D state)."""
    means, covs = lift_positions(measurements_xy, r_cov, state_dim, velocity_var_m2_s2)
    return Mixture(weights.copy(), means, covs, np.full(len(means), NO_LABEL, dtype=np.int64))
