"""Update with a limited field of view (Algorithm 1, steps 3-4, and Eq. prob_of_detection, push)."""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

import numpy as np
from numpy.typing import NDArray

from companion.sat.fov import Region, prob_in_region, truncation_moments
from companion.sat.linalg import inv_det_2x2
from companion.sat.mixture import Mixture, symmetrize

FloatArray = NDArray[np.float64]

_TWO_PI = 2.0 * np.pi


class PushMode(Enum):
    """How the limited-FOV update rule moves the no-detection component."""

    PAPER = "paper"  # Eq. push, for p_D inside the band
    MOMENT = "moment"  # the moments of the exact no-detection posterior, any p_D


@dataclass(frozen=True, slots=True)
class PushRule:
    """The limited-FOV update rule: in the no-detection event, means move away from the FOV.

    PAPER applies Eq. push, mu <- p_D (mu - y) + mu, to components with p_D in [lower, upper].
    MOMENT replaces every component by the Gaussian with the mean and covariance of its exact
    no-detection posterior (1 - p(D|F) 1_F(x)) N(x; m, P):
        mu <- m - c S1 / (1 - p_D),   P <- (P - c S2) / (1 - p_D) - (mu - m)(mu - m)^T,
    with c = p(D|F), S1 = E[(x - m) 1_F], S2 = E[(x - m)(x - m)^T 1_F]. Its mean moves by
    p_D / (1 - p_D) (m - E[x | x in F]): the same repulsion, which Eq. push approximates to first
    order in p_D for a component wide compared to the FOV (there E[x | x in F] is the FOV centre
    y), but sized by the component's own spread; and the covariance shrinks across the FOV edge,
    so the next step does not erode the same mass again.
    """

    lower: float = 0.4
    upper: float = 0.6
    mode: PushMode = PushMode.PAPER


@dataclass(frozen=True, slots=True)
class Visibility:
    """Per component: p_D = p(D|F) p(F), and the raw moments of its mass in F when needed."""

    p_d: FloatArray  # (n,)
    p_detect_in_fov: float  # c = p(D|F)
    first: FloatArray | None = None  # (n, 2) E[(x - m) 1_F]
    second: FloatArray | None = None  # (n, 2, 2) E[(x - m)(x - m)^T 1_F]


def visibility(
    pred: Mixture, region: Region, p_detect_in_fov: float, with_moments: bool = False
) -> Visibility:
    """p_D = p(D|F) p(F) per component (Eq. prob_of_detection, Eq. prob_of_detection_given_f)."""
    pos_means, pos_covs = pred.means[:, :2], pred.covs[:, :2, :2]
    if with_moments:
        p_in_fov, first, second = truncation_moments(pos_means, pos_covs, region)
        return Visibility(p_detect_in_fov * p_in_fov, p_detect_in_fov, first, second)
    p_in_fov = prob_in_region(pos_means, pos_covs, region)
    return Visibility(p_detect_in_fov * p_in_fov, p_detect_in_fov)


_MOMENT_MIN_MISS = 1e-9
"""Below this 1 - p_D a missed component keeps its prior moments: its weight is negligible and the
moment formulas would divide by it."""


def no_detection(
    pred: Mixture,
    vis: Visibility,
    sensor_xy: FloatArray,
    push: PushRule | None,
    detected: NDArray[np.bool_] | None = None,
) -> Mixture:
    """The no-detection event (Algorithm 1, lines 4-9): w = (1 - p_D) w, P unchanged.

    With the push rule, means move away from the FOV (see PushRule), except for the components
    that a measurement of this scan claims (`detected`): the measurement says the target is in
    view, so its missed-detection hypothesis is not pushed out of it.
    """
    p_d = vis.p_d
    weights = (1.0 - p_d) * pred.weights
    if push is None:
        return Mixture(weights, pred.means, pred.covs, pred.labels)
    means = pred.means.copy()
    if push.mode is PushMode.PAPER:
        in_band = (p_d >= push.lower) & (p_d <= push.upper)
        if detected is not None:
            in_band &= ~detected
        offset = means[in_band, :2] - sensor_xy
        means[in_band, :2] += p_d[in_band, None] * offset  # Eq. push
        return Mixture(weights, means, pred.covs, pred.labels)
    if vis.first is None or vis.second is None:
        raise ValueError("the moment push rule needs visibility(..., with_moments=True)")
    movable = (p_d > 0.0) & (1.0 - p_d > _MOMENT_MIN_MISS)
    if detected is not None:
        movable &= ~detected
    moved = np.flatnonzero(movable)
    if moved.size == 0:
        return Mixture(weights, means, pred.covs, pred.labels)
    miss = (1.0 - p_d[moved])[:, None]
    shift = -vis.p_detect_in_fov * vis.first[moved] / miss  # E[x - m | no detection]
    c = vis.p_detect_in_fov
    pos_cov = (pred.covs[moved, :2, :2] - c * vis.second[moved]) / miss[:, :, None]
    pos_cov -= shift[:, :, None] * shift[:, None, :]
    pos_cov = symmetrize(pos_cov)
    det = pos_cov[:, 0, 0] * pos_cov[:, 1, 1] - pos_cov[:, 0, 1] ** 2
    valid = (pos_cov[:, 0, 0] > 0.0) & (det > 0.0)  # round-off can break it when p_D ~ 1
    moved, shift, pos_cov = moved[valid], shift[valid], pos_cov[valid]
    means[moved, :2] += shift
    covs = pred.covs.copy()
    covs[moved, :2, :2] = pos_cov
    return Mixture(weights, means, covs, pred.labels)


@dataclass(frozen=True, slots=True)
class DetectionUpdate:
    """The detection-event components and the per-measurement normalisers of one update."""

    children: Mixture  # n_measurements * n_components rows, measurement-major
    explained: FloatArray  # (m,) sum_l p_D,l w_l q_l(z): how well the prior explains each z


def detection(
    pred: Mixture,
    p_d: FloatArray,
    measurements_xy: FloatArray,
    r_cov: FloatArray,
    clutter_intensity: float,
    birth_intensity: float,
) -> DetectionUpdate:
    """The detection event of the GM-PHD update (Vo & Ma Table 1, steps 3-4).

    For every measurement z and component j:
      w_j(z) = p_D,j w_j q_j(z) / (kappa(z) + b(z) + sum_l p_D,l w_l q_l(z)),
      q_j(z) = N(z; H m_j, H P_j H^T + R), m_j(z) = m_j + K_j (z - H m_j), P_j(z) = (I - K_j H) P_j,
    where kappa is the clutter intensity and b the intensity of measurements from newborn targets
    (Ristic et al. 2012; zero when births do not compete for measurements).
    """
    n, m = pred.size, measurements_xy.shape[0]
    d = pred.dim
    if n == 0 or m == 0:
        return DetectionUpdate(Mixture.empty(d), np.zeros(m))
    s_cov = pred.covs[:, :2, :2] + r_cov  # S = H P H^T + R
    s_inv, s_det = inv_det_2x2(s_cov)
    gain = pred.covs[:, :, :2] @ s_inv  # K = P H^T S^-1
    covs_upd = symmetrize(pred.covs - gain @ pred.covs[:, :2, :])  # P = (I - K H) P
    innov = measurements_xy[None, :, :] - pred.means[:, None, :2]  # (n, m, 2)
    maha_sq = np.einsum("nmi,nij,nmj->nm", innov, s_inv, innov)
    q = np.exp(-0.5 * maha_sq) / (_TWO_PI * np.sqrt(s_det))[:, None]  # N(z; H m, S)
    numer = (p_d * pred.weights)[:, None] * q
    explained = numer.sum(axis=0)
    denom = np.maximum(clutter_intensity + birth_intensity + explained, np.finfo(float).tiny)
    weights = (numer / denom).T.reshape(-1)
    means = (pred.means[:, None, :] + np.einsum("nij,nmj->nmi", gain, innov)).transpose(1, 0, 2)
    children = Mixture(
        weights,
        means.reshape(m * n, d),
        np.broadcast_to(covs_upd, (m, n, d, d)).reshape(m * n, d, d),
        np.tile(pred.labels, m),
    )
    return DetectionUpdate(children, explained)
