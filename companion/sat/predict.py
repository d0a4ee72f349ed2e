"""Prediction (Algorithm 1, steps 1-2): a linear motion model, or GP regression for tracks."""

from __future__ import annotations

import math
from enum import Enum
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from companion.kernel_cache import kernel
from companion.sat.gp import STANDING_P_MOVING, GpFit, GpParams, gp_predict_rows
from companion.sat.mixture import Mixture

FloatArray = NDArray[np.float64]

SHIFT_CAP_SD = 0.5
"""The most a kept edge shift may be, in standard deviations of the component (Eq. edge_shift)."""

_VAR_FLOOR_REL = 1e-12
"""Relative increase of every variance in a constant-velocity prediction (see predict)."""


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


def predict(
    prior: Mixture,
    f: FloatArray,
    q: FloatArray,
    p_survive: float,
    gp: GpParams,
    fit: GpFit | None = None,
    track_ids: NDArray[np.int64] | None = None,
    confirmed: NDArray[np.bool_] | None = None,
    t_before_s: float = 0.0,
    t_now_s: float = 0.0,
    incremental: bool = False,
    keep_shift: NDArray[np.bool_] | None = None,
) -> Mixture:
    """w = p_S w, m = F m, P = F P F^T + Q for every component (Vo & Ma Table 1, step 2); with a
    GP fit of the tracks' windows, the components of confirmed tracks by their GP instead.

    A component labelled with a confirmed track (`track_ids` sorted, `confirmed`) whose window
    holds at least two detections takes the GP mean at t_now_s (Eq. gp_prediction), and its
    prior position covariance grows by the increase of the GP's predictive variance from
    t_before_s to t_now_s, in place of the linear model's Q; `incremental` moves its prior mean
    by the GP mean's change instead. In a constant-velocity state the derivative of the GP mean
    becomes the velocity mean and the velocity block keeps its linear prediction.
    A track whose row of `keep_shift` (aligned with track_ids) is set and whose window stands
    (P(moving) <= STANDING_P_MOVING) keeps the shift of its component's mean off the GP mean at
    t_before_s, up to SHIFT_CAP_SD of the component's standard deviation (Eq. edge_shift).
    """
    if fit is None or track_ids is None or confirmed is None:
        fit, track_ids, confirmed = _NO_FIT, _NO_TRACKS, _NO_CONFIRMED
    if keep_shift is None:
        keep_shift = np.zeros(track_ids.shape[0], dtype=np.bool_)
    weights, means, covs = _predict_kernel(
        prior.weights, prior.means, prior.covs, prior.labels, f, q, p_survive, track_ids,
        confirmed, fit.t_s, fit.counts, fit.mu, fit.beta, fit.ky_inv, gp.sigma_f_m**2,
        gp.lengthscale_s, t_before_s, t_now_s, incremental, keep_shift,
    )
    return Mixture(weights, means, covs, prior.labels)


_NO_FIT = GpFit.empty(1)
_NO_TRACKS, _NO_CONFIRMED = np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.bool_)
"""No GP windows: predict moves every component by the linear model."""


@kernel
def _predict_kernel(  # pragma: no cover - compiled; tested through predict
    weights: FloatArray,
    means: FloatArray,
    covs: FloatArray,
    labels: NDArray[np.int64],
    f: FloatArray,
    q: FloatArray,
    p_survive: float,
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
    keep_shift: NDArray[np.bool_],
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The predicted (weights, means, covs), see predict."""
    n, d = means.shape
    m_out, p_out = np.empty((n, d)), np.empty((n, d, d))
    if d == 2:  # constant position: F = I, the mean does not move
        m_out[:] = means
        for i in range(n):
            for a in range(2):
                for b in range(2):
                    p_out[i, a, b] = covs[i, a, b] + q[a, b]
    else:
        for i in range(n):
            for a in range(d):
                total = 0.0
                for b in range(d):
                    total += f[a, b] * means[i, b]
                m_out[i, a] = total
            for a in range(d):  # F P F^T + Q, summed as numpy's einsum does
                for b in range(d):
                    total = 0.0
                    for j in range(d):
                        for k in range(d):
                            total += f[a, j] * covs[i, j, k] * f[b, k]
                    p_out[i, a, b] = total + q[a, b]
            # F P F^T moves position variance into the position-velocity correlation: with
            # little process noise, a long step (or a nearly singular P) leaves a matrix whose
            # correlation is within round-off of 1, singular to working precision (Cholesky and
            # inversion in merging fail). Raising every variance by _VAR_FLOOR_REL of itself
            # keeps the smallest eigenvalue of the correlation matrix above ~1e-12 and changes
            # nothing measurable.
            for a in range(d):
                p_out[i, a, a] *= 1.0 + _VAR_FLOOR_REL
    if track_ids.shape[0]:
        _apply_gp_kernel(labels, means, covs, track_ids, confirmed, t_s, count, mu, beta,
                         ky_inv, sf2, lam, t_before, t_now, incremental, keep_shift, m_out,
                         p_out)
    w_out = weights if p_survive == 1.0 else p_survive * weights  # 1 w = w exactly
    return w_out, m_out, p_out


@kernel
def _apply_gp_kernel(  # pragma: no cover - compiled; tested through predict
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
    keep_shift: NDArray[np.bool_],
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
            if keep_shift[r] and mu[r, mu.shape[1] - 1] <= STANDING_P_MOVING:
                # Eq. edge_shift: the misses' shift off the GP mean at t_before, capped
                s0 = prior_means[j, 0] - mean[1, 0, 0]
                s1 = prior_means[j, 1] - mean[1, 0, 1]
                a, b, c = prior_covs[j, 0, 0], prior_covs[j, 0, 1], prior_covs[j, 1, 1]
                det = a * c - b * b
                if det > 0.0:
                    d2 = (c * s0 * s0 - 2.0 * b * s0 * s1 + a * s1 * s1) / det
                    scale = 1.0 if d2 <= SHIFT_CAP_SD**2 else SHIFT_CAP_SD / math.sqrt(d2)
                    means[j, 0] += scale * s0
                    means[j, 1] += scale * s1
        covs[j, 0, 0] = prior_covs[j, 0, 0] + growth
        covs[j, 1, 1] = prior_covs[j, 1, 1] + growth
        covs[j, 0, 1], covs[j, 1, 0] = prior_covs[j, 0, 1], prior_covs[j, 1, 0]
        if dim == 4:
            means[j, 2], means[j, 3] = velocity[0, 0, 0], velocity[0, 0, 1]
            for a in range(2):
                for b in range(2, 4):
                    covs[j, a, b] = covs[j, b, a] = 0.0
