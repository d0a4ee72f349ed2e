"""Prediction (Algorithm 1, steps 1-2): a linear motion model, or GP regression for tracks."""

from __future__ import annotations

from enum import Enum
from functools import lru_cache

import numpy as np
from numba import njit
from numpy.typing import NDArray

from companion.sat.gp import GpFit, GpParams, gp_predict_rows
from companion.sat.mixture import Mixture

FloatArray = NDArray[np.float64]

_VAR_FLOOR_REL = 1e-12
"""Relative increase of every variance in a constant-velocity prediction (see predict_linear)."""


class LinearModel(Enum):
    """The linear motion model of components that belong to no confirmed track."""

    CONSTANT_POSITION = "cp"
    CONSTANT_VELOCITY = "cv"

    @property
    def state_dim(self) -> int:
        """2 for (x, y); 4 for (x, y, vx, vy)."""
        return 2 if self is LinearModel.CONSTANT_POSITION else 4


@lru_cache(maxsize=64)
def transition(model: LinearModel, dt_s: float, q_m2_per_s: float) -> tuple[FloatArray, FloatArray]:
    """F and Q of the linear model over dt_s (Vo & Ma Table 1, step 2); read-only, memoised.

    Constant position is a random walk, Q = q dt I. Constant velocity is the white-noise
    acceleration model with spectral density q: Q = q [[dt^3/3, dt^2/2], [dt^2/2, dt]] per axis.
    """
    f, q = _transition(model, dt_s, q_m2_per_s)
    f.setflags(write=False)
    q.setflags(write=False)
    return f, q


def _transition(
    model: LinearModel, dt_s: float, q_m2_per_s: float
) -> tuple[FloatArray, FloatArray]:
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
    if f.shape == (2, 2):  # constant position: F = I, the mean does not move
        means = mix.means
        covs = mix.covs + q
    else:
        means = mix.means @ f.T
        covs = np.einsum("ij,njk,lk->nil", f, mix.covs, f) + q
        # F P F^T moves position variance into the position-velocity correlation: with little
        # process noise, a long step (or a nearly singular P) leaves a matrix whose correlation
        # is within round-off of 1, singular to working precision (Cholesky and inversion in
        # merging fail). Raising every variance by _VAR_FLOOR_REL of itself keeps the smallest
        # eigenvalue of the correlation matrix above ~1e-12 and changes nothing measurable.
        diag = np.arange(f.shape[0])
        covs[:, diag, diag] *= 1.0 + _VAR_FLOOR_REL
    weights = mix.weights if p_survive == 1.0 else p_survive * mix.weights  # 1 w = w exactly
    return Mixture(weights, means, covs, mix.labels)


def apply_gp(
    predicted: Mixture,
    prior: Mixture,
    track_ids: NDArray[np.int64],
    confirmed: NDArray[np.bool_],
    fit: GpFit,
    params: GpParams,
    t_before_s: float,
    t_now_s: float,
    incremental: bool = False,
) -> Mixture:
    """Predict the components of confirmed tracks by their GP regression, not the linear model.

    A component labelled with a confirmed track whose window holds at least two detections
    takes the GP mean at t_now_s (Eq. gp_prediction), and its prior position covariance grows
    by the increase of the GP's predictive variance from t_before_s to t_now_s, in place of the
    linear model's Q. In a constant-velocity state the derivative of the GP mean becomes the
    velocity mean and the velocity block keeps its linear prediction. `track_ids` are sorted.
    """
    if predicted.size == 0 or track_ids.size == 0:
        return predicted
    means = predicted.means.copy()
    covs = predicted.covs.copy()
    _apply_gp_kernel(
        prior.labels, prior.means, prior.covs, track_ids, confirmed, fit.t_s, fit.count, fit.mu,
        fit.beta, fit.ky_inv, params.sigma_f_m**2, params.lengthscale_s, t_before_s, t_now_s,
        incremental, means, covs,
    )
    return Mixture(predicted.weights, means, covs, predicted.labels)


@njit(cache=True, nogil=True)
def _apply_gp_kernel(  # pragma: no cover - compiled; tested through apply_gp
    labels: NDArray[np.int64],
    prior_means: FloatArray,
    prior_covs: FloatArray,
    track_ids: NDArray[np.int64],
    confirmed: NDArray[np.bool_],
    t_s: FloatArray,
    count: NDArray[np.int64],
    mu: FloatArray,
    beta: FloatArray,
    ky_inv: FloatArray,
    sf2: float,
    lam: float,
    t_before: float,
    t_now: float,
    incremental: bool,
    means: FloatArray,
    covs: FloatArray,
) -> None:
    """Overwrite the predicted means and covariances of the components of confirmed tracks."""
    times = np.array([t_now, t_before])
    mean = np.empty((2, 1, 2))
    var = np.empty((2, 1))
    velocity = np.empty((2, 1, 2))
    row = np.empty(1, dtype=np.int64)
    dim = means.shape[1]
    for j in range(labels.shape[0]):
        if labels[j] < 0:
            continue
        r = np.searchsorted(track_ids, labels[j])
        if r >= track_ids.shape[0] or track_ids[r] != labels[j]:
            continue
        if not confirmed[r] or count[r] < 2:
            continue
        row[0] = r
        gp_predict_rows(
            t_s, count, mu, beta, ky_inv, row, times, sf2, lam, mean, var, velocity
        )
        growth = max(var[0, 0] - var[1, 0], 0.0)
        if incremental:
            means[j, 0] = prior_means[j, 0] + mean[0, 0, 0] - mean[1, 0, 0]
            means[j, 1] = prior_means[j, 1] + mean[0, 0, 1] - mean[1, 0, 1]
        else:
            means[j, 0], means[j, 1] = mean[0, 0, 0], mean[0, 0, 1]
        covs[j, 0, 0] = prior_covs[j, 0, 0] + growth
        covs[j, 1, 1] = prior_covs[j, 1, 1] + growth
        covs[j, 0, 1], covs[j, 1, 0] = prior_covs[j, 0, 1], prior_covs[j, 1, 0]
        if dim == 4:
            means[j, 2], means[j, 3] = velocity[0, 0, 0], velocity[0, 0, 1]
            for a in range(2):
                for b in range(2, 4):
                    covs[j, a, b] = covs[j, b, a] = 0.0
