"""Pruning and merging of components (Vo & Ma 2006, Table 2), with a cap on their number."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from companion.kernel_cache import kernel
from companion.sat.mixture import NO_LABEL, Mixture

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


def prune(mix: Mixture, weight_threshold: float) -> tuple[Mixture, NDArray[np.bool_]]:
    """Keep the components with w > T (Vo & Ma Table 2); also returns the kept mask."""
    weights, means, covs, labels, keep, n_kept = prune_kernel(
        mix.weights, mix.means, mix.covs, mix.labels, weight_threshold
    )
    if n_kept == mix.size:  # nothing to prune: the mixture stands as it is
        return mix, keep
    return Mixture(weights, means, covs, labels), keep


@kernel
def prune_kernel(  # pragma: no cover - compiled; tested through prune
    weights: FloatArray, means: FloatArray, covs: FloatArray, labels: IntArray, threshold: float
) -> tuple[FloatArray, FloatArray, FloatArray, IntArray, NDArray[np.bool_], int]:
    """(weights, means, covs, labels) of the components with w > T, the kept mask and how many
    were kept; the arrays given when all are kept."""
    n = weights.shape[0]
    keep = np.empty(n, dtype=np.bool_)
    n_kept = _keep_heavy(weights, threshold, keep)
    if n_kept == n:
        return weights, means, covs, labels, keep, n_kept
    w_out, m_out = np.empty(n_kept), np.empty((n_kept, means.shape[1]))
    p_out = np.empty((n_kept, means.shape[1], means.shape[1]))
    labels_out = np.empty(n_kept, dtype=np.int64)
    _compress(keep, weights, means, covs, labels, w_out, m_out, p_out, labels_out)
    return w_out, m_out, p_out, labels_out, keep, n_kept


@kernel
def _keep_heavy(  # pragma: no cover - compiled; tested through prune
    weights: FloatArray, threshold: float, keep: NDArray[np.bool_]
) -> int:
    """keep = w > T per component (Vo & Ma Table 2); returns how many are kept."""
    n_kept = 0
    for i in range(weights.shape[0]):
        keep[i] = weights[i] > threshold
        n_kept += keep[i]
    return n_kept


@kernel
def _compress(  # pragma: no cover - compiled; tested through prune
    keep: NDArray[np.bool_],
    weights: FloatArray,
    means: FloatArray,
    covs: FloatArray,
    labels: IntArray,
    w_out: FloatArray,
    m_out: FloatArray,
    p_out: FloatArray,
    labels_out: IntArray,
) -> None:
    """Copy the kept components, in order, into the output arrays."""
    at = 0
    for i in range(keep.shape[0]):
        if keep[i]:
            w_out[at] = weights[i]
            m_out[at] = means[i]
            p_out[at] = covs[i]
            labels_out[at] = labels[i]
            at += 1


_NO_RESOLUTION = np.eye(2)
"""Placeholder R when merge is given none (its inverse is then taken as 0)."""


@dataclass(frozen=True, slots=True)
class MergeResult:
    """Merged mixture and, for each input component, the index of its output (-1: capped away)."""

    mixture: Mixture
    group_of: IntArray


def merge(
    mix: Mixture,
    distance_sq_threshold: float,
    max_components: int,
    symmetric: bool = True,
    detection: IntArray | None = None,
    resolution: FloatArray | None = None,
    counts_two: NDArray[np.bool_] | None = None,
) -> MergeResult:
    """Greedy merging (Vo & Ma Table 2) of components within a squared Mahalanobis distance U.

    Repeatedly take the heaviest remaining component j, merge every remaining i with
    (m_i - m_j)^T P_i^-1 (m_i - m_j) <= U into it, and stop after `max_components` groups (the
    components not yet merged are dropped, as the paper does). The merged weight is the sum, the
    mean and covariance are the moment-matched averages. A merged component keeps the smallest
    label among its members: track ids grow with age, so the oldest track it supports lives on.

    Vo & Ma measure the distance with the candidate's covariance P_i only, so a wide component
    (an initial belief, P = 50 I) 20 m from a well-localised target is merged into it and inflates
    its covariance a hundredfold. `symmetric` (the default) also requires the distance under the
    leader's P_j to be within U: the two must each lie within the other's gate.
    Components labelled with different tracks merge only when both were just updated by
    detections (`detection`: the index of the detection that updated each component, -1 for
    none) and agree within U under P_i + P_j, or their positions lie within one standard
    deviation of the measurement noise (`resolution`, R): then they are one target seen twice,
    which the sensor cannot split. Otherwise they are two targets, however close their
    uncertainties have grown while out of view.
    Eq. one_detection: a target gives at most one detection a scan, so components updated by two
    different detections are two targets, and are not merged, when they descend from two tracks
    or when a parent already counted two targets (`counts_two`: its weight rounds to 2 or more).
    Otherwise the second detection may be clutter beside the target, and the two merge.
    """
    n = mix.size
    if n == 0:
        return MergeResult(mix, np.zeros(0, dtype=np.int64))
    weights, means, covs, labels, group_of = merge_kernel(
        mix.weights, mix.means, mix.covs, mix.labels,
        np.full(n, -1, dtype=np.int64) if detection is None else detection,
        np.zeros(n, dtype=np.bool_) if counts_two is None else counts_two, distance_sq_threshold,
        symmetric, _NO_RESOLUTION if resolution is None else resolution, resolution is not None,
        max_components,
    )
    return MergeResult(Mixture(weights, means, covs, labels), group_of)


@kernel
def merge_kernel(  # pragma: no cover - compiled; tested through merge
    weights: FloatArray,
    means: FloatArray,
    covs: FloatArray,
    labels: IntArray,
    detection: IntArray,
    counts_two: NDArray[np.bool_],
    threshold: float,
    symmetric: bool,
    resolution: FloatArray,
    has_resolution: bool,
    max_groups: int,
) -> tuple[FloatArray, FloatArray, FloatArray, IntArray, IntArray]:
    """merge on arrays: the merged (weights, means, covs, labels), heaviest group first, and
    each input component's group (-1: capped away)."""
    n = weights.shape[0]
    order = np.argsort(-weights, kind="mergesort")  # stable: equal weights keep their order
    group_of = np.empty(n, dtype=np.int64)
    leaders = np.empty(n, dtype=np.int64)
    n_groups = _greedy_groups(
        means, covs, labels, detection, counts_two, order, threshold, symmetric, resolution,
        has_resolution, max_groups, group_of, leaders,
    )
    if n_groups == n:  # nothing merged or dropped: the components as they are, in group order
        return weights[leaders], means[leaders], covs[leaders], labels[leaders], group_of
    d = means.shape[1]
    w_out = np.zeros(n_groups)
    m_out = np.zeros((n_groups, d))
    p_out = np.zeros((n_groups, d, d))
    labels_out = np.full(n_groups, NO_LABEL, dtype=np.int64)
    _moment_match_kernel(weights, means, covs, labels, group_of, w_out, m_out, p_out, labels_out)
    return w_out, m_out, p_out, labels_out, group_of


@kernel
def _greedy_groups(  # pragma: no cover - compiled; tested through merge
    means: FloatArray,
    covs: FloatArray,
    labels: IntArray,
    detection: IntArray,
    counts_two: NDArray[np.bool_],
    order: IntArray,
    threshold: float,
    symmetric: bool,
    resolution: FloatArray,
    has_resolution: bool,
    max_groups: int,
    group_of: IntArray,
    leaders: IntArray,
) -> int:
    """Vo & Ma's greedy merging: fill each component's group index (-1: beyond max_groups) and
    the groups' leaders (heaviest members) in greedy order; return the number of groups."""
    resolution_inv = np.zeros((2, 2))
    if has_resolution:  # closed-form 2x2 inverse
        det_r = resolution[0, 0] * resolution[1, 1] - resolution[0, 1] * resolution[1, 0]
        resolution_inv[0, 0], resolution_inv[1, 1] = resolution[1, 1], resolution[0, 0]
        resolution_inv[0, 1], resolution_inv[1, 0] = -resolution[0, 1], -resolution[1, 0]
        for r in range(2):
            for c in range(2):
                resolution_inv[r, c] /= det_r
    n, dim = means.shape
    leader_of = np.full(n, -1, dtype=np.int64)
    diff = np.empty(dim)
    summed = np.empty((dim, dim))
    inv = np.empty_like(covs)
    for i in range(n):
        if dim == 2:
            det = covs[i, 0, 0] * covs[i, 1, 1] - covs[i, 0, 1] * covs[i, 1, 0]
            inv[i, 0, 0], inv[i, 1, 1] = covs[i, 1, 1] / det, covs[i, 0, 0] / det
            inv[i, 0, 1], inv[i, 1, 0] = -covs[i, 0, 1] / det, -covs[i, 1, 0] / det
        else:
            inv[i] = np.linalg.inv(covs[i])
    for j in order:
        if leader_of[j] >= 0:
            continue
        leader_of[j] = j
        for i in range(n):
            if leader_of[i] >= 0:
                continue
            two_tracks = labels[i] != NO_LABEL and labels[j] != NO_LABEL and labels[i] != labels[j]
            detected_both = detection[i] >= 0 and detection[j] >= 0
            if detected_both and detection[i] != detection[j] and (
                    two_tracks or counts_two[i] or counts_two[j]):
                continue  # Eq. one_detection: two detections of one scan are two targets
            if two_tracks:
                # Two tracks' components: one target only when both were just detected and
                # agree within their joint uncertainty.
                if not detected_both:
                    continue
                for k in range(dim):
                    diff[k] = means[i, k] - means[j, k]
                summed[:, :] = covs[i] + covs[j]
                unresolved = _quad(diff[:2], resolution_inv) <= 1.0
                if unresolved or float(diff @ np.linalg.solve(summed, diff)) <= threshold:
                    leader_of[i] = j
                continue
            # Vo & Ma: within U under the candidate's covariance (and the leader's, symmetric).
            if dim == 2:  # the same sums as _quad, on scalars
                d0, d1 = means[i, 0] - means[j, 0], means[i, 1] - means[j, 1]
                far = _quad_2(inv[i], d0, d1) > threshold or (
                    symmetric and _quad_2(inv[j], d0, d1) > threshold)
            else:
                for k in range(dim):
                    diff[k] = means[i, k] - means[j, k]
                far = _quad(diff, inv[i]) > threshold or (
                    symmetric and _quad(diff, inv[j]) > threshold)
            if not far:
                leader_of[i] = j
    group_index = np.full(n, -1, dtype=np.int64)
    n_groups = 0
    for j in order:  # leaders in greedy (heaviest-first) order, up to max_groups
        if leader_of[j] == j and n_groups < max_groups:
            group_index[j] = n_groups
            leaders[n_groups] = j
            n_groups += 1
    for i in range(n):
        group_of[i] = group_index[leader_of[i]]
    return n_groups


@kernel
def _quad(x: FloatArray, a: FloatArray) -> float:  # pragma: no cover - compiled
    """x^T A x for a small vector, without temporaries."""
    total = 0.0
    for r in range(x.shape[0]):
        row = 0.0
        for c in range(x.shape[0]):
            row += a[r, c] * x[c]
        total += x[r] * row
    return total


@kernel
def _quad_2(a: FloatArray, x0: float, x1: float) -> float:  # pragma: no cover - compiled
    """x^T A x for a 2-vector (x0, x1), summed as _quad sums it."""
    return float(x0 * (a[0, 0] * x0 + a[0, 1] * x1) + x1 * (a[1, 0] * x0 + a[1, 1] * x1))


def _moment_match(mix: Mixture, group_of: IntArray, n_groups: int) -> Mixture:
    """Sum of weights, weighted mean and spread-of-means covariance of each group (Vo & Ma
    Table 2); a group of one is passed through exactly."""
    d = mix.dim
    w_out = np.zeros(n_groups)
    m_out = np.zeros((n_groups, d))
    p_out = np.zeros((n_groups, d, d))
    labels = np.full(n_groups, NO_LABEL, dtype=np.int64)
    _moment_match_kernel(
        mix.weights, mix.means, mix.covs, mix.labels, group_of, w_out, m_out, p_out, labels
    )
    return Mixture(w_out, m_out, p_out, labels)


@kernel
def _moment_match_kernel(  # pragma: no cover - compiled; tested through merge
    weights: FloatArray,
    means: FloatArray,
    covs: FloatArray,
    labels: IntArray,
    group_of: IntArray,
    w_out: FloatArray,
    m_out: FloatArray,
    p_out: FloatArray,
    labels_out: IntArray,
) -> None:
    """Fill the merged groups' weights, means, covariances and labels (smallest member label)."""
    n, d = means.shape
    size = np.zeros(w_out.shape[0], dtype=np.int64)
    last = np.zeros(w_out.shape[0], dtype=np.int64)
    for i in range(n):
        g = group_of[i]
        if g < 0:
            continue
        size[g] += 1
        last[g] = i
        w_out[g] += weights[i]  # w = sum w_i
        if labels[i] != NO_LABEL and (labels_out[g] == NO_LABEL or labels[i] < labels_out[g]):
            labels_out[g] = labels[i]
    # The sums below weigh by w_i / w, not w_i then / w: with tiny (subnormal) weights, as when
    # pruning is off, w_i P_i underflows and a merged variance came out 0.
    for i in range(n):
        g = group_of[i]
        if g < 0 or size[g] == 1:
            continue
        share = weights[i] / w_out[g]
        for k in range(d):
            m_out[g, k] += share * means[i, k]  # m = sum w_i m_i / w
    for g in range(w_out.shape[0]):
        if size[g] == 1:
            m_out[g] = means[last[g]]
            p_out[g] = covs[last[g]]
    for i in range(n):
        g = group_of[i]
        if g < 0 or size[g] == 1:
            continue
        share = weights[i] / w_out[g]
        for r in range(d):  # P = sum w_i (P_i + (m - m_i)(m - m_i)^T) / w
            for c in range(d):
                spread = (m_out[g, r] - means[i, r]) * (m_out[g, c] - means[i, c])
                p_out[g, r, c] += share * (covs[i, r, c] + spread)
    for g in range(w_out.shape[0]):
        for r in range(d):
            for c in range(r + 1, d):
                sym = 0.5 * (p_out[g, r, c] + p_out[g, c, r])
                p_out[g, r, c] = p_out[g, c, r] = sym
