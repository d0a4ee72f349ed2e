"""Pruning and merging of components (Vo & Ma 2006, Table 2), with a cap on their number."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from companion.sat.linalg import inv_stack
from companion.sat.mixture import NO_LABEL, Mixture, symmetrize

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


def prune(mix: Mixture, weight_threshold: float) -> tuple[Mixture, NDArray[np.bool_]]:
    """Keep the components with w > T (Vo & Ma Table 2); also returns the kept mask."""
    keep = mix.weights > weight_threshold
    return mix.take(keep), keep


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
    observed: NDArray[np.bool_] | None = None,
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
    detections (`observed`): then they are one target seen twice. Otherwise they are two targets,
    however close their uncertainties have grown while out of view.
    """
    n = mix.size
    if n == 0:
        return MergeResult(mix, np.zeros(0, dtype=np.int64))
    order = np.argsort(-mix.weights, kind="stable")
    diff = mix.means[None, :, :] - mix.means[:, None, :]  # diff[j, i] = m_i - m_j
    inv = inv_stack(mix.covs)
    close = np.einsum("jid,idk,jik->ji", diff, inv, diff) <= distance_sq_threshold
    if symmetric:
        close &= close.T  # d^2 under P_j: the same quadratic form with the roles swapped
    labelled = mix.labels != NO_LABEL
    if np.count_nonzero(labelled) > 1:
        lab = mix.labels
        apart = labelled[:, None] & labelled[None, :] & (lab[:, None] != lab[None, :])
        close &= ~apart
        if observed is not None and np.any(apart & observed[:, None] & observed[None, :]):
            # Two tracks' components both just updated by detections are one target seen twice
            # when their means agree within both their uncertainties: U under P_i + P_j.
            joint = inv_stack(mix.covs[None, :, :, :] + mix.covs[:, None, :, :])
            same = np.einsum("jid,jidk,jik->ji", diff, joint, diff) <= distance_sq_threshold
            close |= apart & observed[:, None] & observed[None, :] & same
    leader_of = np.arange(n)
    linked = close.sum(axis=0) + close.sum(axis=1) > 2  # has a neighbour besides itself
    if np.any(linked):
        remaining = linked.copy()
        for j in order:
            if remaining[j]:
                members = remaining & close[j]
                leader_of[members] = j
                remaining &= ~members
    leaders = order[leader_of[order] == order]  # groups in the greedy (heaviest-first) order
    leaders = leaders[:max_components]
    group_index = np.full(n, -1, dtype=np.int64)
    group_index[leaders] = np.arange(leaders.size)
    group_of = group_index[leader_of]
    if leaders.size == n:  # nothing merged or dropped: the mixture stands as it is
        return MergeResult(mix.take(leaders), group_of)
    return MergeResult(_moment_match(mix, group_of, leaders.size), group_of)


def _moment_match(mix: Mixture, group_of: IntArray, n_groups: int) -> Mixture:
    """Sum of weights, weighted mean and spread-of-means covariance of each group."""
    kept = group_of >= 0
    g = group_of[kept]
    w = mix.weights[kept]
    means = mix.means[kept]
    covs = mix.covs[kept]
    d = mix.dim
    onehot = np.zeros((n_groups, g.size))
    onehot[g, np.arange(g.size)] = w
    w_out = onehot.sum(axis=1)
    m_out = (onehot @ means) / w_out[:, None]
    spread = means - m_out[g]
    scatter = covs + spread[:, :, None] * spread[:, None, :]
    p_out = (onehot @ scatter.reshape(g.size, d * d)).reshape(n_groups, d, d) / w_out[:, None, None]
    labels = np.full(n_groups, np.iinfo(np.int64).max, dtype=np.int64)
    member_labels = mix.labels[kept]
    labelled = member_labels != NO_LABEL
    np.minimum.at(labels, g[labelled], member_labels[labelled])
    labels[labels == np.iinfo(np.int64).max] = NO_LABEL
    return Mixture(w_out, m_out, symmetrize(p_out), labels)
