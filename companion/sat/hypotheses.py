"""Marginal association probabilities of one cluster of Bernoullis sharing measurements.

A joint hypothesis gives each Bernoulli l "undetected" (factor phi_u[l]) or one measurement i
(factor phi[i, l] > 0), each measurement to at most one Bernoulli; its weight is the product of
the factors. `exact_marginals` enumerates every hypothesis (depth first); `gibbs_marginals`
samples hypotheses with a Gibbs sampler (Vo, Vo & Hoang 2017): each sweep redraws every
Bernoulli's choice given the others', so the chain visits the heavy hypotheses, which are then
weighed exactly.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from companion.kernel_cache import kernel

FloatArray = NDArray[np.float64]

EXACT_LIMIT = 4096
"""Clusters with at most this many hypotheses (an upper bound: prod_l (1 + gated_l)) are
enumerated exactly; larger ones are sampled."""

GIBBS_SWEEPS = 1000
"""Sweeps of the Gibbs sampler per cluster, the first tenth burn-in: the cost of a step is
bounded by sweeps x Bernoullis x measurements."""


def hypothesis_bound(phi: FloatArray) -> float:
    """An upper bound on a cluster's number of hypotheses: prod_l (1 + gated measurements)."""
    gated = np.count_nonzero(phi > 0.0, axis=0).astype(np.float64)
    return float(np.prod(1.0 + gated))


@kernel
def exact_marginals(  # pragma: no cover - compiled; tested through lmb.associate
    phi_u: FloatArray, phi: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """(P_l(undetected) (n,), P_l(i) (m, n)) over every hypothesis of the cluster."""
    m, n = phi.shape
    undetected = np.zeros(n)
    detected = np.zeros((m, n))
    choice = np.full(n, -2, dtype=np.int64)
    used = np.zeros(m, dtype=np.bool_)
    weight = np.ones(n + 1)
    total = 0.0
    level = 0
    while level >= 0:
        if level == n:  # a whole hypothesis: add its weight to every choice it makes
            hyp_w = float(weight[n])
            total += hyp_w
            for b in range(n):
                if choice[b] < 0:
                    undetected[b] += hyp_w
                else:
                    detected[choice[b], b] += hyp_w
            level -= 1
            continue
        # the next choice of Bernoulli `level` after its current one (-2: none tried yet)
        c = choice[level]
        if c >= 0:
            used[c] = False
        c += 1
        while c < m and (c >= 0 and (used[c] or phi[c, level] <= 0.0)):
            c += 1
        if c >= m:
            choice[level] = -2
            level -= 1
            continue
        choice[level] = c
        if c < 0:
            weight[level + 1] = weight[level] * phi_u[level]
        else:
            used[c] = True
            weight[level + 1] = weight[level] * phi[c, level]
        level += 1
    return undetected / total, detected / total


def gibbs_marginals(
    phi_u: FloatArray, phi: FloatArray, uniforms: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """(P_l(undetected), P_l(i)) over the distinct hypotheses a Gibbs sampler visits, each
    weighed exactly (prod of its factors), normalised over them: the heavy hypotheses the
    chain finds, with the light ones it never visits truncated. `uniforms` (sweeps, n) in
    [0, 1) drive the draws, so the same ones give the same marginals."""
    m, n = phi.shape
    visited = np.unique(_gibbs_sweeps(phi_u, phi, uniforms), axis=0)  # (H, n) choices
    with np.errstate(divide="ignore"):
        log_u, log_phi = np.log(phi_u), np.log(phi)
    cols = np.arange(n)
    log_w = np.where(visited < 0, log_u[cols], log_phi[np.maximum(visited, 0), cols]).sum(axis=1)
    w = np.exp(log_w - log_w.max())
    w /= w.sum()
    undetected = ((visited < 0) * w[:, None]).sum(axis=0)
    detected = np.zeros((m, n))
    rows, bern = np.nonzero(visited >= 0)
    np.add.at(detected, (visited[rows, bern], bern), w[rows])
    return undetected, detected


@kernel
def _gibbs_sweeps(  # pragma: no cover - compiled; tested through gibbs_marginals
    phi_u: FloatArray, phi: FloatArray, uniforms: FloatArray
) -> NDArray[np.int64]:
    """The choice of every Bernoulli (-1: undetected) after each sweep past the first tenth,
    from "every Bernoulli undetected": each sweep redraws each choice given the others'."""
    m, n = phi.shape
    owner = np.full(m, -1, dtype=np.int64)  # the Bernoulli each measurement is assigned to
    choice = np.full(n, -1, dtype=np.int64)
    probs = np.empty(m + 1)
    total_sweeps = uniforms.shape[0]
    burn = total_sweeps // 10
    out = np.empty((total_sweeps - burn, n), dtype=np.int64)
    for sweep in range(total_sweeps):
        for b in range(n):
            if choice[b] >= 0:
                owner[choice[b]] = -1
            probs[0] = phi_u[b]
            total = probs[0]
            for i in range(m):
                p = phi[i, b] if owner[i] < 0 else 0.0
                probs[i + 1] = p
                total += p
            u = uniforms[sweep, b] * total
            k = 0
            acc = probs[0]
            while acc < u and k < m:
                k += 1
                acc += probs[k]
            choice[b] = k - 1
            if k > 0:
                owner[k - 1] = b
        if sweep >= burn:
            out[sweep - burn] = choice
    return out
