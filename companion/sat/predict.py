"""Prediction (Algorithm 1, steps 1-2): a linear motion model, or GP regression for tracks."""

from __future__ import annotations

from enum import Enum

import numpy as np
from numpy.typing import NDArray

from companion.sat.mixture import Mixture

FloatArray = NDArray[np.float64]


class LinearModel(Enum):
    """The linear motion model of components that belong to no confirmed track."""

    CONSTANT_POSITION = "cp"
    CONSTANT_VELOCITY = "cv"

    @property
    def state_dim(self) -> int:
        """2 for (x, y); 4 for (x, y, vx, vy)."""
        return 2 if self is LinearModel.CONSTANT_POSITION else 4


def transition(model: LinearModel, dt_s: float, q_m2_per_s: float) -> tuple[FloatArray, FloatArray]:
    """F and Q of the linear model over dt_s (Vo & Ma Table 1, step 2).

    Constant position is a random walk, Q = q dt I. Constant velocity is the white-noise
    acceleration model with spectral density q: Q = q [[dt^3/3, dt^2/2], [dt^2/2, dt]] per axis.
    """
    if model is LinearModel.CONSTANT_POSITION:
        return np.eye(2), q_m2_per_s * dt_s * np.eye(2)
    eye = np.eye(2)
    f = np.block([[eye, dt_s * eye], [np.zeros((2, 2)), eye]])
    q = q_m2_per_s * np.block(
        [[dt_s**3 / 3.0 * eye, dt_s**2 / 2.0 * eye], [dt_s**2 / 2.0 * eye, dt_s * eye]]
    )
    return f, q


def predict_linear(mix: Mixture, f: FloatArray, q: FloatArray, p_survive: float) -> Mixture:
    """w = p_S w, m = F m, P = F P F^T + Q for every component (Vo & Ma Table 1, step 2)."""
    if mix.size == 0:
        return mix
    if mix.dim == 2 and np.array_equal(f, np.eye(2)):
        means = mix.means  # constant position: F = I, the mean does not move
        covs = mix.covs + q
    else:
        means = mix.means @ f.T
        covs = np.einsum("ij,njk,lk->nil", f, mix.covs, f) + q
    return Mixture(p_survive * mix.weights, means, covs, mix.labels)


def apply_gp(
    predicted: Mixture,
    prior: Mixture,
    index: NDArray[np.int64],
    gp_mean_xy: FloatArray,
    gp_var_m2: FloatArray,
    gp_velocity_xy: FloatArray,
) -> Mixture:
    """Predict components `index` by their tracks' GP regression instead of the linear model.

    The GP gives the new position means and the growth of the prior position covariance over
    the step (in place of the linear model's Q). In a constant-velocity state the derivative of
    the GP mean becomes the velocity mean and the velocity block keeps its linear prediction.
    """
    if index.size == 0:
        return predicted
    means = predicted.means.copy()
    covs = predicted.covs.copy()
    means[index, :2] = gp_mean_xy
    covs[index, :2, :2] = prior.covs[index, :2, :2]
    covs[index, 0, 0] += gp_var_m2
    covs[index, 1, 1] += gp_var_m2
    if predicted.dim == 4:
        means[index, 2:] = gp_velocity_xy
        covs[index, :2, 2:] = 0.0
        covs[index, 2:, :2] = 0.0
    return Mixture(predicted.weights, means, covs, predicted.labels)
