"""Update with a limited field of view (Algorithm 1, steps 3-4, and Eq. prob_of_detection, push)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import Enum

import numpy as np
from numpy.typing import NDArray

from companion.kernel_cache import kernel
from companion.sat.fov import Region, prob_in_region, truncation_moments
from companion.sat.mixture import Mixture

FloatArray = NDArray[np.float64]

_TWO_PI = 2.0 * math.pi
_TINY = float(np.finfo(np.float64).tiny)


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
        p_in_fov, first, second = truncation_moments(pos_means, pos_covs, region, check=False)
        return Visibility(p_detect_in_fov * p_in_fov, p_detect_in_fov, first, second)
    p_in_fov = prob_in_region(pos_means, pos_covs, region, check=False)
    return Visibility(p_detect_in_fov * p_in_fov, p_detect_in_fov)  # Eq. prob_of_detection


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
    mode = push_code(push)
    if mode == MOMENT_PUSH and (vis.first is None or vis.second is None) and p_d.any():
        raise ValueError("the moment push rule needs visibility(..., with_moments=True)")
    n, d = pred.size, pred.dim
    missed = Mixture(np.empty(n), np.empty((n, d)), np.empty((n, d, d)), pred.labels)
    missed_kernel(
        pred.weights, pred.means, pred.covs, p_d, vis.p_detect_in_fov,
        NO_FIRST if vis.first is None else vis.first,
        NO_SECOND if vis.second is None else vis.second,
        np.zeros(n, dtype=np.bool_) if detected is None else detected, sensor_xy, mode,
        0.0 if push is None else push.lower, 0.0 if push is None else push.upper,
        missed.weights, missed.means, missed.covs,
    )
    return missed


NO_PUSH, PAPER_PUSH, MOMENT_PUSH = 0, 1, 2
"""The push rule as a kernel argument (push_code)."""

NO_FIRST, NO_SECOND = np.zeros((0, 2)), np.zeros((0, 2, 2))
"""Placeholder moments for missed_kernel when the push rule reads none."""


def push_code(push: PushRule | None) -> int:
    """The push rule for missed_kernel: NO_PUSH, PAPER_PUSH or MOMENT_PUSH."""
    if push is None:
        return NO_PUSH
    return PAPER_PUSH if push.mode is PushMode.PAPER else MOMENT_PUSH


@kernel
def missed_kernel(  # pragma: no cover - compiled; tested through no_detection
    weights: FloatArray,
    means: FloatArray,
    covs: FloatArray,
    p_d: FloatArray,
    c: float,
    first: FloatArray,
    second: FloatArray,
    claimed: NDArray[np.bool_],
    sensor_xy: FloatArray,
    push: int,
    lower: float,
    upper: float,
    w_out: FloatArray,
    m_out: FloatArray,
    p_out: FloatArray,
) -> None:
    """Fill the no-detection components (see no_detection): w = (1 - p_D) w, and the push rule
    (NO_PUSH, PAPER_PUSH in [lower, upper] or MOMENT_PUSH) on the unclaimed ones."""
    w_out[:] = weights
    m_out[:] = means
    p_out[:] = covs
    in_view = False
    for j in range(p_d.shape[0]):
        in_view = in_view or p_d[j] != 0.0
    if not in_view:  # nothing in view: (1 - 0) w = w, and no rule moves a component
        return
    for j in range(p_d.shape[0]):
        w_out[j] = (1.0 - p_d[j]) * weights[j]
    if push == PAPER_PUSH:
        paper_push_kernel(p_d, lower, upper, claimed, sensor_xy, m_out)
    elif push == MOMENT_PUSH:
        _moment_kernel(p_d, c, first, second, claimed, m_out, p_out)


@kernel
def paper_push_kernel(  # pragma: no cover - compiled; tested through no_detection
    p_d: FloatArray,
    lower: float,
    upper: float,
    claimed: NDArray[np.bool_],
    sensor_xy: FloatArray,
    means: FloatArray,
) -> None:
    """Move each unclaimed component with p_D in [lower, upper] away from the sensor: mu <- mu +
    p_D (mu - y) (Eq. push); in place."""
    for j in range(p_d.shape[0]):
        if lower <= p_d[j] <= upper and not claimed[j]:
            for a in range(2):
                means[j, a] += p_d[j] * (means[j, a] - sensor_xy[a])  # Eq. push


@kernel
def _moment_kernel(  # pragma: no cover - compiled; tested through no_detection
    p_d: FloatArray,
    c: float,
    first: FloatArray,
    second: FloatArray,
    claimed: NDArray[np.bool_],
    means: FloatArray,
    covs: FloatArray,
) -> None:
    """Replace each unclaimed component's position moments by those of its no-detection
    posterior (see PushRule); keep them where 1 - p_D is tiny or round-off breaks P."""
    for j in range(p_d.shape[0]):
        miss = 1.0 - p_d[j]
        if claimed[j] or p_d[j] <= 0.0 or miss <= _MOMENT_MIN_MISS:
            continue
        s0 = -c * first[j, 0] / miss  # E[x - m | no detection]
        s1 = -c * first[j, 1] / miss
        p00 = (covs[j, 0, 0] - c * second[j, 0, 0]) / miss - s0 * s0
        p11 = (covs[j, 1, 1] - c * second[j, 1, 1]) / miss - s1 * s1
        p01 = 0.5 * (covs[j, 0, 1] + covs[j, 1, 0] - c * (second[j, 0, 1] + second[j, 1, 0]))
        p01 = p01 / miss - s0 * s1
        if p00 <= 0.0 or p00 * p11 - p01 * p01 <= 0.0:  # round-off when p_D ~ 1
            continue
        if means.shape[1] == 4:
            # A (x, y, vx, vy) state keeps its velocity: carried through the position-velocity
            # correlation, the outward shift would become an outward velocity and the component
            # would fly off scan after scan. Dropping the correlation keeps P positive definite.
            covs[j, :2, 2:] = 0.0
            covs[j, 2:, :2] = 0.0
        means[j, 0] += s0
        means[j, 1] += s1
        covs[j, 0, 0], covs[j, 1, 1] = p00, p11
        covs[j, 0, 1] = covs[j, 1, 0] = p01


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
    weights = np.empty(m * n)
    means = np.empty((m * n, d))
    covs = np.empty((m * n, d, d))
    labels = np.empty(m * n, dtype=np.int64)
    explained = np.zeros(m)
    detection_kernel(
        pred.weights, pred.means, pred.covs, pred.labels, p_d, measurements_xy, r_cov,
        clutter_intensity + birth_intensity, weights, means, covs, labels, explained,
    )
    return DetectionUpdate(Mixture(weights, means, covs, labels), explained)


@kernel
def detection_kernel(  # pragma: no cover - compiled; tested through detection
    w: FloatArray,
    mean: FloatArray,
    cov: FloatArray,
    labels: NDArray[np.int64],
    p_d: FloatArray,
    z: FloatArray,
    r: FloatArray,
    background: float,
    w_out: FloatArray,
    m_out: FloatArray,
    cov_out: FloatArray,
    labels_out: NDArray[np.int64],
    explained: FloatArray,
) -> None:
    """Fill the detection children (measurement-major rows k n + j: weight, mean, covariance and
    label of component j updated by measurement k) and each measurement's sum_l p_D w q."""
    n, d = mean.shape
    p_out = np.empty((n, d, d))  # the updated covariance, one per component
    gain = np.empty((n, d, 2))
    s_inv = np.empty((n, 2, 2))
    norm = np.empty(n)
    for j in range(n):
        s00, s01 = cov[j, 0, 0] + r[0, 0], cov[j, 0, 1] + r[0, 1]  # S = H P H^T + R
        s10, s11 = cov[j, 1, 0] + r[1, 0], cov[j, 1, 1] + r[1, 1]
        det = s00 * s11 - s01 * s10
        s_inv[j, 0, 0], s_inv[j, 0, 1] = s11 / det, -s01 / det
        s_inv[j, 1, 0], s_inv[j, 1, 1] = -s10 / det, s00 / det
        norm[j] = 1.0 / (_TWO_PI * math.sqrt(det))
        for a in range(d):  # K = P H^T S^-1
            gain[j, a, 0] = cov[j, a, 0] * s_inv[j, 0, 0] + cov[j, a, 1] * s_inv[j, 1, 0]
            gain[j, a, 1] = cov[j, a, 0] * s_inv[j, 0, 1] + cov[j, a, 1] * s_inv[j, 1, 1]
        # P = (I - K H) P. Its position rows use I - P_pos S^-1 = R S^-1 (S = P_pos + R): the
        # subtraction P - K H P cancels catastrophically where R << P_pos (a nearly singular R,
        # or a component that grew wide over a long gap), leaving round-off that breaks
        # positive definiteness; the product R S^-1 P keeps every digit.
        m00 = r[0, 0] * s_inv[j, 0, 0] + r[0, 1] * s_inv[j, 1, 0]  # M = R S^-1
        m01 = r[0, 0] * s_inv[j, 0, 1] + r[0, 1] * s_inv[j, 1, 1]
        m10 = r[1, 0] * s_inv[j, 0, 0] + r[1, 1] * s_inv[j, 1, 0]
        m11 = r[1, 0] * s_inv[j, 0, 1] + r[1, 1] * s_inv[j, 1, 1]
        for b in range(d):  # position rows: M P
            p_out[j, 0, b] = m00 * cov[j, 0, b] + m01 * cov[j, 1, b]
            p_out[j, 1, b] = m10 * cov[j, 0, b] + m11 * cov[j, 1, b]
        p01 = 0.5 * (p_out[j, 0, 1] + p_out[j, 1, 0])  # symmetrised
        p_out[j, 0, 1] = p_out[j, 1, 0] = p01
        for a in range(2, d):  # velocity rows: the position-velocity block by symmetry
            p_out[j, a, 0], p_out[j, a, 1] = p_out[j, 0, a], p_out[j, 1, a]
            for b in range(a, d):
                pab = cov[j, a, b] - gain[j, a, 0] * cov[j, 0, b] - gain[j, a, 1] * cov[j, 1, b]
                pba = cov[j, b, a] - gain[j, b, 0] * cov[j, 0, a] - gain[j, b, 1] * cov[j, 1, a]
                p_out[j, a, b] = p_out[j, b, a] = 0.5 * (pab + pba)
    for k in range(z.shape[0]):
        for j in range(n):
            row = k * n + j
            v0, v1 = z[k, 0] - mean[j, 0], z[k, 1] - mean[j, 1]  # innovation z - H m
            maha = v0 * (s_inv[j, 0, 0] * v0 + s_inv[j, 0, 1] * v1) + v1 * (
                s_inv[j, 1, 0] * v0 + s_inv[j, 1, 1] * v1
            )
            numer = p_d[j] * w[j] * norm[j] * math.exp(-0.5 * maha)  # p_D w N(z; H m, S)
            w_out[row] = numer
            explained[k] += numer
            for a in range(d):  # m = m + K (z - H m)
                m_out[row, a] = mean[j, a] + gain[j, a, 0] * v0 + gain[j, a, 1] * v1
            cov_out[row] = p_out[j]
            labels_out[row] = labels[j]
        denom = max(background + explained[k], _TINY)
        for j in range(n):
            w_out[k * n + j] /= denom  # Vo & Ma Table 1, step 4: normalised by kappa + b + sum
