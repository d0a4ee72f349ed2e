"""Update with a limited field of view (Algorithm 1, steps 3-4, and Eq. prob_of_detection, push)."""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

import numpy as np
from numpy.typing import NDArray

from companion.sat.fov import Region, prob_in_region, region_moments
from companion.sat.linalg import inv_det_2x2
from companion.sat.mixture import Mixture, symmetrize

FloatArray = NDArray[np.float64]

_TWO_PI = 2.0 * np.pi


class PushMode(Enum):
    """How the limited-FOV update rule moves the no-detection component."""

    PAPER = "paper"  # Eq. push, for p_D inside the band
    MOMENT = "moment"  # the mean of the truncated posterior (1 - p_D(x)) N(x; m, P), any p_D


@dataclass(frozen=True, slots=True)
class PushRule:
    """The limited-FOV update rule: in the no-detection event, means move away from the FOV.

    PAPER applies Eq. push, mu <- p_D (mu - y) + mu, to components with p_D in [lower, upper].
    MOMENT moves every component to the mean of its exact no-detection posterior,
    mu <- (mu - p(D|F) p(F) E[x | x in F]) / (1 - p_D): the same repulsion, which Eq. push
    approximates to first order in p_D for a component wide compared to the FOV (there
    E[x | x in F] is the FOV centre y), but sized by the component's own spread, so a well-localised
    target at the edge of the view moves by centimetres, not by p_D times the FOV radius.
    """

    lower: float = 0.4
    upper: float = 0.6
    mode: PushMode = PushMode.PAPER


@dataclass(frozen=True, slots=True)
class Visibility:
    """Per component: p_D = p(D|F) p(F), and E[x | x in F] when the push rule needs it."""

    p_d: FloatArray  # (n,)
    mean_in_fov_xy: FloatArray | None  # (n, 2)


def visibility(
    pred: Mixture, region: Region, p_detect_in_fov: float, with_mean: bool = False
) -> Visibility:
    """p_D = p(D|F) p(F) per component (Eq. prob_of_detection, Eq. prob_of_detection_given_f)."""
    pos_means, pos_covs = pred.means[:, :2], pred.covs[:, :2, :2]
    if with_mean:
        p_in_fov, mean_in = region_moments(pos_means, pos_covs, region)
        return Visibility(p_detect_in_fov * p_in_fov, mean_in)
    return Visibility(p_detect_in_fov * prob_in_region(pos_means, pos_covs, region), None)


def no_detection(
    pred: Mixture, vis: Visibility, sensor_xy: FloatArray, push: PushRule | None
) -> Mixture:
    """The no-detection event (Algorithm 1, lines 4-9): w = (1 - p_D) w, P unchanged.

    With the push rule, means move away from the FOV (see PushRule).
    """
    p_d = vis.p_d
    weights = (1.0 - p_d) * pred.weights
    if push is None:
        return Mixture(weights, pred.means, pred.covs, pred.labels)
    means = pred.means.copy()
    if push.mode is PushMode.PAPER:
        in_band = (p_d >= push.lower) & (p_d <= push.upper)
        offset = means[in_band, :2] - sensor_xy
        means[in_band, :2] += p_d[in_band, None] * offset  # Eq. push
    else:
        if vis.mean_in_fov_xy is None:
            raise ValueError("the moment push rule needs visibility(..., with_mean=True)")
        moved = (p_d > 0.0) & (p_d < 1.0)
        pd = p_d[moved, None]
        # E[x | no detection] = (m - p_D E[x | x in F]) / (1 - p_D)
        means[moved, :2] = (means[moved, :2] - pd * vis.mean_in_fov_xy[moved]) / (1.0 - pd)
    return Mixture(weights, means, pred.covs, pred.labels)


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
