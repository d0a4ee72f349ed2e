"""Compiled loops of track maintenance (companion.sat.tracks): association, hold and scoring.

Each step's track maintenance works on a few rows; as numpy calls its time went to call
overhead, so the per-row logic is written out here once. Every kernel states the numpy rule it
computes; companion.sat.tracks documents what the rules mean.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]


@njit(cache=True, nogil=True)
def _gate_sq(mt: FloatArray, pt: FloatArray, me: FloatArray, pe: FloatArray) -> float:
    """(m_e - m_t)^T (P_t + P_e)^-1 (m_e - m_t) over the position block (Eq. gate)."""
    a00 = pt[0, 0] + pe[0, 0]
    a01 = pt[0, 1] + pe[0, 1]
    a10 = pt[1, 0] + pe[1, 0]
    a11 = pt[1, 1] + pe[1, 1]
    det = a00 * a11 - a01 * a10
    dx = me[0] - mt[0]
    dy = me[1] - mt[1]
    return float((dx * (a11 * dx - a01 * dy) + dy * (a00 * dy - a10 * dx)) / det)


@njit(cache=True, nogil=True)
def associate(
    track_ids: IntArray,
    track_means: FloatArray,
    track_covs: FloatArray,
    est_labels: IntArray,
    est_means: FloatArray,
    est_covs: FloatArray,
    gate_sq: float,
) -> IntArray:
    """For each estimate, the row of the track it continues, or -1 (track ids sorted).

    1. An estimate continues the track its label names; of two with one label, the closer
       (gate distance, ties by estimate order). 2. The rest take the unclaimed tracks they
    gate with (distance <= gate_sq), nearest pairs first (ties by track row, then estimate).
    """
    n_tracks = track_ids.shape[0]
    n_est = est_labels.shape[0]
    assigned = np.full(n_est, -1, dtype=np.int64)
    if n_tracks == 0 or n_est == 0:
        return assigned
    claimed = np.zeros(n_tracks, dtype=np.bool_)
    rows = np.minimum(np.searchsorted(track_ids, est_labels), n_tracks - 1)
    claims = np.flatnonzero(track_ids[rows] == est_labels)
    dist = np.empty(claims.size)
    for k in range(claims.size):
        c, r = claims[k], rows[claims[k]]
        dist[k] = _gate_sq(track_means[r], track_covs[r], est_means[c], est_covs[c])
    for c in claims[np.argsort(dist, kind="mergesort")]:  # of one label's estimates, the closer
        r = rows[c]
        if not claimed[r]:
            claimed[r] = True
            assigned[c] = r
    free = np.flatnonzero(assigned < 0)
    if free.size == 0:
        return assigned
    pair_t = np.empty(n_tracks * free.size, dtype=np.int64)
    pair_e = np.empty(n_tracks * free.size, dtype=np.int64)
    pair_d = np.empty(n_tracks * free.size)
    n_pairs = 0
    for r in range(n_tracks):
        if claimed[r]:
            continue
        for e in free:
            d = _gate_sq(track_means[r], track_covs[r], est_means[e], est_covs[e])
            if d <= gate_sq:
                pair_t[n_pairs] = r
                pair_e[n_pairs] = e
                pair_d[n_pairs] = d
                n_pairs += 1
    for k in np.argsort(pair_d[:n_pairs], kind="mergesort"):
        r, e = pair_t[k], pair_e[k]
        if not claimed[r] and assigned[e] < 0:
            claimed[r] = True
            assigned[e] = r
    return assigned


@njit(cache=True, nogil=True)
def hold(
    supported_by: IntArray, idle: IntArray, track_ids: IntArray, labels: IntArray,
    weights: FloatArray,
) -> None:
    """supported_by[row] = the heaviest component labelled with the track's id (ties: the
    first), for each idle row whose id labels a component; in place (ids are never NO_LABEL)."""
    for row in idle:
        best = -1
        for i in range(labels.shape[0]):
            if labels[i] == track_ids[row] and (best < 0 or weights[i] > weights[best]):
                best = i
        if best >= 0:
            supported_by[row] = best


@njit(cache=True, nogil=True)
def score_deltas(
    covs: FloatArray, p_in: FloatArray, hit: BoolArray, r_cov: FloatArray,
    p_detect: float, clutter_per_m2: float, gate_sq: float,
) -> FloatArray:
    """Each row's log-likelihood ratio increment: log(p_D / p_FA) for a detection, p_FA =
    min(1/2, kappa pi U sqrt|P + R|) (Eq. track_score_hit), else log(1 - p_D p(F)) (Eq.
    track_score_miss)."""
    out = np.empty(hit.shape[0])
    for k in range(hit.shape[0]):
        if hit[k]:
            a00 = covs[k, 0, 0] + r_cov[0, 0]
            a01 = covs[k, 0, 1] + r_cov[0, 1]
            a10 = covs[k, 1, 0] + r_cov[1, 0]
            a11 = covs[k, 1, 1] + r_cov[1, 1]
            gate_area_m2 = math.pi * gate_sq * math.sqrt(a00 * a11 - a01 * a10)
            p_fa = min(0.5, clutter_per_m2 * gate_area_m2)
            out[k] = math.log(max(p_detect, 1e-300) / max(p_fa, 1e-300))
        else:
            out[k] = math.log1p(-min(p_detect * p_in[k], 1.0 - 1e-12))
    return out


@njit(cache=True, nogil=True)
def supported_rows(
    means: FloatArray, covs: FloatArray, hits: IntArray, life: IntArray, last_t_s: FloatArray,
    seen_t_s: FloatArray, alone: BoolArray, supported_by: IntArray, hit: BoolArray,
    mix_means: FloatArray, mix_covs: FloatArray, t_s: float,
) -> tuple[FloatArray, FloatArray, IntArray, IntArray, FloatArray, FloatArray, BoolArray]:
    """New (means, covs, hits, life, last_t_s, seen_t_s, alone): each row with supported_by[row]
    >= 0 takes that component's moments and time t_s, a row with hit also counts a detection."""
    means, covs, hits, life = means.copy(), covs.copy(), hits.copy(), life.copy()
    last_t_s, seen_t_s, alone = last_t_s.copy(), seen_t_s.copy(), alone.copy()
    for row in range(supported_by.shape[0]):
        comp = supported_by[row]
        if hit[row]:
            hits[row] += 1
            seen_t_s[row] = t_s
        if comp < 0:
            continue
        means[row] = mix_means[comp]
        covs[row] = mix_covs[comp]
        life[row] += 1
        last_t_s[row] = t_s
        alone[row] = False
    return means, covs, hits, life, last_t_s, seen_t_s, alone
