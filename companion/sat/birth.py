"""Measurement-driven birth (Ristic et al. 2012): one new component per measurement."""

from __future__ import annotations

from enum import Enum

import numpy as np
from numpy.typing import NDArray

from companion.kernel_cache import kernel
from companion.sat.mixture import NO_LABEL, Mixture

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
    return born_weights_kernel(
        mode is BirthWeight.ADAPTIVE, birth_weight, explained, clutter_intensity, birth_intensity
    )


@kernel
def born_weights_kernel(  # pragma: no cover - compiled; tested through birth_weights
    adaptive: bool,
    birth_weight: float,
    explained: FloatArray,
    clutter_intensity: float,
    birth_intensity: float,
) -> FloatArray:
    """birth_weights with the mode as a flag (True: adaptive, False: constant)."""
    if not adaptive:
        return np.full(explained.shape[0], birth_weight)
    return birth_intensity / (clutter_intensity + birth_intensity + explained)


def birth(
    measurements_xy: FloatArray, weights: FloatArray, r_cov: FloatArray, velocity_var_m2_s2: float,
    state_dim: int,
) -> Mixture:
    """Components with mean z, covariance R (and a zero-mean velocity prior in a 4-D state)."""
    m = measurements_xy.shape[0]
    born = Mixture(
        np.empty(m), np.empty((m, state_dim)), np.empty((m, state_dim, state_dim)),
        np.empty(m, dtype=np.int64),
    )
    born_kernel(measurements_xy, weights, r_cov, velocity_var_m2_s2,
                born.weights, born.means, born.covs, born.labels)
    return born


@kernel
def born_kernel(  # pragma: no cover - compiled; tested through birth
    z: FloatArray,
    weights: FloatArray,
    r_cov: FloatArray,
    velocity_var_m2_s2: float,
    w_out: FloatArray,
    m_out: FloatArray,
    p_out: FloatArray,
    labels_out: NDArray[np.int64],
) -> None:
    """Fill one new component per measurement: weight, mean z (zero velocity), covariance R (and
    velocity_var_m2_s2 on the velocity diagonal in a 4-D state), no label."""
    d = m_out.shape[1]
    for k in range(z.shape[0]):
        w_out[k] = weights[k]
        m_out[k] = 0.0
        m_out[k, 0], m_out[k, 1] = z[k, 0], z[k, 1]
        p_out[k] = 0.0
        p_out[k, 0, 0], p_out[k, 0, 1] = r_cov[0, 0], r_cov[0, 1]
        p_out[k, 1, 0], p_out[k, 1, 1] = r_cov[1, 0], r_cov[1, 1]
        for a in range(2, d):
            p_out[k, a, a] = velocity_var_m2_s2
        labels_out[k] = NO_LABEL
