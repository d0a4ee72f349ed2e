"""Compiled loops of track maintenance (companion.sat.tracks): association, hold, support,
scoring, GP windows and survival.

Each step's track maintenance works on a few rows; as numpy calls its time went to call
overhead, so the per-row logic of a step's common path is written out here once, in a few
kernels (support_of, support with survivors, append_tracks). Every kernel states the rule it
computes; companion.sat.tracks documents what the rules mean.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from companion.kernel_cache import kernel
from companion.sat.fov import disk_kernel
from companion.sat.mixture import NO_LABEL

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]


@kernel
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


@kernel
def _density(d_sq: float, pt: FloatArray, pe: FloatArray) -> float:
    """N(m_e; m_t, P_t + P_e) over the position block, from its squared distance d_sq."""
    det = (pt[0, 0] + pe[0, 0]) * (pt[1, 1] + pe[1, 1]) - (pt[0, 1] + pe[0, 1]) * (
        pt[1, 0] + pe[1, 0])
    return math.exp(-0.5 * d_sq) / (2.0 * math.pi * math.sqrt(det))


@kernel
def associate(
    track_ids: IntArray,
    track_means: FloatArray,
    track_covs: FloatArray,
    est_labels: IntArray,
    est_means: FloatArray,
    est_covs: FloatArray,
    gate_sq: float,
    alone: BoolArray,
    clutter_per_m2: float,
    held: BoolArray,
    est_detected: BoolArray,
) -> IntArray:
    """For each estimate, the row of the track it continues, or -1 (track ids sorted).

    1. An estimate continues the track its label names; of two with one label, the closer
       (gate distance, ties by estimate order). 2. The rest take the unclaimed tracks they
    gate with (distance <= gate_sq), nearest pairs first (ties by track row, then estimate); a
    track coasting alone (`alone`, on its grown covariance) gates only with an estimate it
    explains better than clutter does, N(m_e; m_t, P_t + P_e) > clutter_per_m2 (Eq.
    coast_gate); a track of a standing target that a component of its own lineage still holds
    (`held`) gates only with an estimate that a detection made (`est_detected`): an estimate no
    detection made says nothing new of where a still target is (Eq. held_gate).
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
            if held[r] and not est_detected[e]:
                continue  # Eq. held_gate
            d = _gate_sq(track_means[r], track_covs[r], est_means[e], est_covs[e])
            if d <= gate_sq and (not alone[r] or _density(  # Eq. coast_gate
                    d, track_covs[r], est_covs[e]) > clutter_per_m2):
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


@kernel
def _hold(
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


@kernel
def support_of(
    track_ids: IntArray, track_means: FloatArray, track_covs: FloatArray, confirmed: BoolArray,
    moving: bool, est_rows: IntArray, labels: IntArray, means: FloatArray, covs: FloatArray,
    weights: FloatArray, detected: BoolArray, gate_sq: float, alone: BoolArray,
    clutter_per_m2: float, standing: BoolArray,
) -> tuple[IntArray, BoolArray, IntArray, IntArray, BoolArray, IntArray]:
    """Which component supports each track this step, from the estimates (mixture rows est_rows)
    and the mixture's labels: (supported_by (T,) mixture row or -1, hit (T,) supported by a
    detection, the supported rows, those of them missed, coasting (T,), the estimates that
    continue no track).

    An estimate continues the track `associate` gives it; a confirmed track with no estimate is
    held by the heaviest component labelled with its id (`_hold`); a track is hit when the
    estimate that continues it owes its weight to a detection; a confirmed track of moving
    targets that nothing supports coasts. `standing` (T,): the tracks whose windows stand
    (Eq. held_gate).
    """
    n_tracks = track_ids.shape[0]
    held = np.zeros(n_tracks, dtype=np.bool_)
    if n_tracks:
        for i in range(labels.shape[0]):
            r = min(np.searchsorted(track_ids, labels[i]), n_tracks - 1)
            held[r] |= track_ids[r] == labels[i] and standing[r]
    assigned = associate(  # Eq. gate, Panta et al.'s association
        track_ids, track_means, track_covs, labels[est_rows], means[est_rows], covs[est_rows],
        gate_sq, alone, clutter_per_m2, held, detected[est_rows],
    )
    supported_by = np.full(n_tracks, -1, dtype=np.int64)
    hit = np.zeros(n_tracks, dtype=np.bool_)
    for e in range(est_rows.shape[0]):
        if assigned[e] >= 0:
            supported_by[assigned[e]] = est_rows[e]
            hit[assigned[e]] = detected[est_rows[e]]
    idle = np.flatnonzero((supported_by < 0) & confirmed)
    if idle.size:
        _hold(supported_by, idle, track_ids, labels, weights)
    supported = supported_by >= 0
    coasting = ~supported & confirmed & moving
    return (supported_by, hit, np.flatnonzero(supported), np.flatnonzero(supported & ~hit),
            coasting, est_rows[assigned < 0])


@kernel
def _score_delta(
    cov: FloatArray, p_in: float, hit: bool, r_cov: FloatArray, p_detect: float,
    clutter_per_m2: float, gate_sq: float,
) -> float:
    """A supported track's log-likelihood ratio increment: log(p_D / p_FA) for a detection, p_FA =
    min(1/2, kappa pi U sqrt|P + R|) (Eq. track_score_hit), else log(1 - p_D p(F)) (Eq.
    track_score_miss); P is the supporting component's covariance."""
    if hit:
        a00 = cov[0, 0] + r_cov[0, 0]
        a01 = cov[0, 1] + r_cov[0, 1]
        a10 = cov[1, 0] + r_cov[1, 0]
        a11 = cov[1, 1] + r_cov[1, 1]
        gate_area_m2 = math.pi * gate_sq * math.sqrt(a00 * a11 - a01 * a10)
        p_fa = min(0.5, clutter_per_m2 * gate_area_m2)
        return math.log(max(p_detect, 1e-300) / max(p_fa, 1e-300))
    return math.log1p(-min(p_detect * p_in, 1.0 - 1e-12))


@kernel
def push_window(
    win_t_s: FloatArray, win_xy: FloatArray, win_count: IntArray, row: int, t_s: float,
    xy: FloatArray, window: int,
) -> None:
    """Shift row's GP window left by one and put a detection at t_s, position xy, at its right
    end; its count grows by one up to `window`. In place."""
    width = win_t_s.shape[1]
    for w in range(width - 1):
        win_t_s[row, w] = win_t_s[row, w + 1]
        win_xy[row, w, 0] = win_xy[row, w + 1, 0]
        win_xy[row, w, 1] = win_xy[row, w + 1, 1]
    win_t_s[row, width - 1] = t_s
    win_xy[row, width - 1, 0] = xy[0]
    win_xy[row, width - 1, 1] = xy[1]
    win_count[row] = min(win_count[row] + 1, window)


@kernel
def push_windows(
    win_t_s: FloatArray, win_xy: FloatArray, win_count: IntArray, rows: IntArray, t_s: float,
    xy: FloatArray, window: int,
) -> None:
    """push_window for each of rows, with positions xy (k, 2); in place."""
    for k in range(rows.shape[0]):
        push_window(win_t_s, win_xy, win_count, rows[k], t_s, xy[k], window)


@kernel
def support(
    means: FloatArray, covs: FloatArray, hits: IntArray, life: IntArray, last_t_s: FloatArray,
    seen_t_s: FloatArray, alone: BoolArray, score: FloatArray, confirmed: BoolArray,
    win_t_s: FloatArray, win_xy: FloatArray, win_count: IntArray, track_ids: IntArray,
    supported_by: IntArray, hit: BoolArray, coasting: BoolArray, p_in: FloatArray,
    center_xy: FloatArray, radius_m: float, mix_means: FloatArray, mix_covs: FloatArray,
    t_s: float, scored: bool, r_cov: FloatArray, p_detect: float, clutter_per_m2: float,
    gate_sq: float, max_existence: float, window: int, confirm_length: int,
    confirm_existence: float, log_ids: IntArray, log_t_s: FloatArray, log_means: FloatArray,
    log_covs: FloatArray, log_start: int, timeout_s: float, drop_existence: float,
) -> tuple[FloatArray, FloatArray, IntArray, IntArray, FloatArray, FloatArray, BoolArray,
           FloatArray, BoolArray, FloatArray, FloatArray, IntArray, BoolArray, IntArray, int,
           int, bool]:
    """New (means, covs, hits, life, last_t_s, seen_t_s, alone, score, confirmed, win_t_s,
    win_xy, win_count) after this step's support, then, unless a row is coasting (its state
    changes first), `survivors` on them: (alive, labels, number alive, number newly confirmed,
    True); else (-, -, 0, 0, False).

    Each row with supported_by[row] >= 0 takes that component's moments and time t_s, and
    writes them to the log's buffers from row log_start on (in row order); a row with hit also
    counts a detection and pushes the component's position onto its GP window. When `scored`
    (a frame was processed), a supported row's score gains _score_delta, capped at the logit of
    max_existence; a miss reads its component's p(F): computed here in a disk (radius_m > 0,
    centre center_xy), else given in p_in (T,). A row with confirm_length hits and an existence
    of at least confirm_existence becomes confirmed.
    """
    new_means, new_covs, new_hits, new_life = means.copy(), covs.copy(), hits.copy(), life.copy()
    new_last_t, new_seen_t, new_alone = last_t_s.copy(), seen_t_s.copy(), alone.copy()
    new_score, new_confirmed = score.copy(), confirmed.copy()
    max_score, confirm_score = logit(max_existence), logit(confirm_existence)
    new_win_t, new_win_xy, new_win_count = win_t_s.copy(), win_xy.copy(), win_count.copy()
    mass, moment, second = np.empty(1), np.zeros((1, 2)), np.zeros((1, 2, 2))
    n_logged = 0
    for row in range(supported_by.shape[0]):
        comp = supported_by[row]
        if hit[row]:
            new_hits[row] += 1
            new_seen_t[row] = t_s
        if comp >= 0:
            new_means[row] = mix_means[comp]
            new_covs[row] = mix_covs[comp]
            new_life[row] += 1
            new_last_t[row] = t_s
            new_alone[row] = False
            if scored:  # Eqs. track_score_hit, track_score_miss
                p_f = 0.0
                if hit[row]:
                    pass
                elif radius_m > 0.0:
                    disk_kernel(mix_means[comp:comp + 1], mix_covs[comp:comp + 1, 0, 0],
                                mix_covs[comp:comp + 1, 0, 1], mix_covs[comp:comp + 1, 1, 1],
                                center_xy, radius_m, 0, mass, moment, second)
                    p_f = mass[0]
                else:
                    p_f = p_in[row]
                total = new_score[row] + _score_delta(
                    mix_covs[comp], p_f, hit[row], r_cov, p_detect, clutter_per_m2, gate_sq
                )
                new_score[row] = max_score if total > max_score else total
            if hit[row]:  # the GP window holds detected positions only
                push_window(new_win_t, new_win_xy, new_win_count, row, t_s, mix_means[comp],
                            window)
            at = log_start + n_logged
            log_ids[at], log_t_s[at] = track_ids[row], t_s
            log_means[at], log_covs[at] = new_means[row], new_covs[row]
            n_logged += 1
        if new_hits[row] >= confirm_length and new_score[row] >= confirm_score:
            new_confirmed[row] = True
    decided = not coasting.any()
    if decided:
        alive, labels, n_alive, n_new = survivors(
            supported_by, coasting, confirmed, last_t_s, new_score, _NO_AREA, new_confirmed,
            track_ids, mix_means.shape[0], t_s, timeout_s, drop_existence,
        )
    else:
        alive, labels = np.zeros(0, dtype=np.bool_), np.zeros(0, dtype=np.int64)
        n_alive = n_new = 0
    return (new_means, new_covs, new_hits, new_life, new_last_t, new_seen_t, new_alone,
            new_score, new_confirmed, new_win_t, new_win_xy, new_win_count, alive, labels,
            n_alive, n_new, decided)


_NO_AREA = np.zeros(0)
"""in_area for survivors when no row is coasting."""


@kernel
def logit(p: float) -> float:  # pragma: no cover - compiled
    """log(p / (1 - p)): the score of existence p."""
    return math.log(p / (1.0 - p))


@kernel
def existence(score: float) -> float:  # pragma: no cover - compiled
    """The probability that a track's target exists, from its log-likelihood ratio."""
    return 1.0 / (1.0 + math.exp(-score))


@kernel
def existences(score: FloatArray) -> FloatArray:  # pragma: no cover - compiled
    """existence of each score."""
    out = np.empty(score.shape[0])
    for row in range(score.shape[0]):
        out[row] = existence(score[row])
    return out


@kernel
def survivors(
    supported_by: IntArray, coasting: BoolArray, confirmed: BoolArray, last_t_s: FloatArray,
    score: FloatArray, in_area: FloatArray, confirmed_now: BoolArray, track_ids: IntArray,
    n_components: int, t_s: float, timeout_s: float, drop_existence: float,
) -> tuple[BoolArray, IntArray, int, int]:
    """(alive (T,), labels (n_components,), number alive, number of the alive confirmed this
    step). A track lives on when it is supported, coasting, or confirmed and supported within
    timeout_s (confirmed, last_t_s: before this step), and its existence (existence(score),
    times in_area for a coasting row when in_area (T,) is given) is at least drop_existence;
    each component supporting a live track is labelled with its id, the others with
    NO_LABEL."""
    alive = np.empty(supported_by.shape[0], dtype=np.bool_)
    labels = np.full(n_components, NO_LABEL, dtype=np.int64)
    n_alive = n_new = 0
    for row in range(supported_by.shape[0]):
        kept = supported_by[row] >= 0 or coasting[row] or (
            confirmed[row] and t_s - last_t_s[row] <= timeout_s)
        exists = existence(score[row])
        if in_area.shape[0] and coasting[row]:
            exists *= in_area[row]
        alive[row] = kept and exists >= drop_existence
        if not alive[row]:
            continue
        n_alive += 1
        n_new += confirmed_now[row] and not confirmed[row]
        if supported_by[row] >= 0:
            labels[supported_by[row]] = track_ids[row]
    return alive, labels, n_alive, n_new


@kernel
def append_tracks(
    ids: IntArray, hits: IntArray, life: IntArray, confirmed: BoolArray, born_t_s: FloatArray,
    last_t_s: FloatArray, seen_t_s: FloatArray, score: FloatArray, alone: BoolArray,
    means: FloatArray, covs: FloatArray, win_t_s: FloatArray, win_xy: FloatArray,
    win_count: IntArray, gp_mu: FloatArray, gp_beta: FloatArray, gp_ky_inv: FloatArray,
    comp: IntArray, hit: BoolArray, mix_means: FloatArray, mix_covs: FloatArray,
    new_score: FloatArray, t_s: float, next_id: int, confirm_length: int,
    confirm_existence: float, log_ids: IntArray, log_t_s: FloatArray, log_means: FloatArray,
    log_covs: FloatArray, log_start: int,
) -> tuple[IntArray, IntArray, IntArray, BoolArray, FloatArray, FloatArray, FloatArray,
           FloatArray, BoolArray, FloatArray, FloatArray, FloatArray, FloatArray, IntArray,
           FloatArray, FloatArray, FloatArray]:
    """The track rows (in Tracks' field order) followed by one new track per component row
    comp[k]: id next_id + k, born, supported and seen at t_s, that component's moments, score
    new_score[k], one hit and one detection in its GP window if hit[k], confirmed with
    confirm_length hits and an existence of at least confirm_existence, no GP fit yet. Their
    first rows go to the log's buffers from row log_start on."""
    n = ids.shape[0] + comp.shape[0]
    ids, hits, life = _extended(ids, n), _extended(hits, n), _extended(life, n)
    confirmed, born_t_s = _extended(confirmed, n), _extended(born_t_s, n)
    last_t_s, seen_t_s = _extended(last_t_s, n), _extended(seen_t_s, n)
    score, alone = _extended(score, n), _extended(alone, n)
    means, covs = _extended(means, n), _extended(covs, n)
    win_t_s, win_xy = _extended(win_t_s, n), _extended(win_xy, n)
    win_count, gp_mu = _extended(win_count, n), _extended(gp_mu, n)
    gp_beta, gp_ky_inv = _extended(gp_beta, n), _extended(gp_ky_inv, n)
    last, confirm_score = win_t_s.shape[1] - 1, logit(confirm_existence)
    for k in range(comp.shape[0]):
        row, c = n - comp.shape[0] + k, comp[k]
        ids[row] = next_id + k
        hits[row] = win_count[row] = 1 if hit[k] else 0
        life[row] = 1
        born_t_s[row] = last_t_s[row] = seen_t_s[row] = t_s
        score[row] = new_score[k]
        confirmed[row] = hits[row] >= confirm_length and new_score[k] >= confirm_score
        means[row], covs[row] = mix_means[c], mix_covs[c]
        win_t_s[row, last] = t_s  # only counted (win_count) when it is a detection
        win_xy[row, last, 0], win_xy[row, last, 1] = mix_means[c, 0], mix_means[c, 1]
        log_ids[log_start + k], log_t_s[log_start + k] = ids[row], t_s
        log_means[log_start + k], log_covs[log_start + k] = means[row], covs[row]
    return (ids, hits, life, confirmed, born_t_s, last_t_s, seen_t_s, score, alone, means, covs,
            win_t_s, win_xy, win_count, gp_mu, gp_beta, gp_ky_inv)


@kernel
def _extended(a: NDArray[Any], n: int) -> NDArray[Any]:  # pragma: no cover - compiled
    """a's rows followed by zeros, n rows in all."""
    out = np.zeros((n, *a.shape[1:]), dtype=a.dtype)
    out[: a.shape[0]] = a
    return out


@kernel
def write_rows(
    buf_ids: IntArray, buf_t_s: FloatArray, buf_means: FloatArray, buf_covs: FloatArray,
    start: int, ids: IntArray, t_s: float, means: FloatArray, covs: FloatArray, rows: IntArray,
) -> None:
    """Write the given rows of (ids, means, covs), at time t_s, into the log's buffers from row
    start on, in order."""
    for k in range(rows.shape[0]):
        buf_ids[start + k] = ids[rows[k]]
        buf_t_s[start + k] = t_s
        buf_means[start + k] = means[rows[k]]
        buf_covs[start + k] = covs[rows[k]]
