"""The labeled multi-Bernoulli (LMB) filter with a limited field of view, as pure functions.

After Reuter, Vo, Vo & Dietmayer 2014. The LMB lives in the same SatState as the GM-PHD: every
mixture component is labelled, the components of label l form Bernoulli l, and their weights are
r_l times its spatial mixture, so that the mixture is the LMB's PHD (what planners and reports
read) and r_l = sum of the weights with label l. Each Bernoulli has one row in Tracks, whose id is
its label; the row's score is logit(r_l) (Tracks.existence is r) and its mean and covariance are
the Bernoulli's moments (`alone`: already its own honest belief, grown while unseen).

One update, for the Bernoullis l and measurements z_i of a frame with footprint F:
    p_D,j = p(D|F) p(F)_j per component j                        # Eq. prob_of_detection
    phi_l(undetected) = 1 - sum_j w_j p_D,j                       # absent, or present and missed
    phi_l(i) = sum_j w_j p_D,j N(z_i; H m_j, S_j) / (kappa + b)   # z_i is l's, not clutter or new
and the joint association hypotheses of each cluster of Bernoullis that share gated measurements
(each measurement used at most once) weigh prod_l phi_l(theta_l). Their marginals give
    r_l' = P_l(undetected) (r_l - sum_j w_j p_D,j) / phi_l(undetected) + sum_i P_l(i)   # Eq. lmb_r
and a spatial mixture of the missed-detection components (the exact no-detection moments of the
"moment" push rule) and the Kalman-updated ones. Clusters of one Bernoulli are solved in closed
form; larger ones by enumerating their hypotheses, or past EXACT_LIMIT of them by a seeded Gibbs
sampler with a fixed number of sweeps (companion.sat.hypotheses), so each step's cost is bounded.
Adaptive birth: a measurement that the existing Bernoullis explain with probability r_U(z) gives
a new Bernoulli with r_B(z) = (1 - r_U(z)) b / (b + kappa) (Eq. lmb_birth): kappa the clutter
intensity and b that of measurements from targets not yet seen, birth_weight over the search area
(over the frame when no area is known).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from companion.kernel_cache import kernel
from companion.sat.birth import birth
from companion.sat.fov import Disk, Region, prob_in_region, truncation_moments
from companion.sat.hypotheses import (
    EXACT_LIMIT,
    GIBBS_SWEEPS,
    exact_marginals,
    gibbs_marginals,
    hypothesis_bound,
)
from companion.sat.linalg import inv_det_2x2
from companion.sat.mixture import Mixture
from companion.sat.motion import TargetMotion, iou_variance_m2
from companion.sat.reduce import _moment_match, merge, prune
from companion.sat.tracks import TrackParams, Tracks, _with_new_tracks, pushed_windows
from companion.sat.update import PushMode, detection, no_detection, visibility

if TYPE_CHECKING:
    from companion.sat.filter import SatParams

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

GATE_SQ = 25.0
"""Squared Mahalanobis gate of an association (under P + R): a target's own measurement falls
outside it with probability exp(-12.5) ~ 4e-6, so gating changes no marginal measurably."""

_TINY = 1e-300


@dataclass(frozen=True, slots=True)
class Association:
    """Marginal association probabilities of one frame, per track row (Bernoulli)."""

    undetected: FloatArray  # (L,) P_l(undetected): absent, or present and missed
    detected: FloatArray  # (m, L) P_l(i): measurement i is Bernoulli l's


def bernoullis(mixture: Mixture, t_s: float, params: SatParams) -> tuple[Mixture, Tracks]:
    """The initial belief as Bernoullis: a component of weight w becomes ceil(w) Bernoullis of
    existence w / ceil(w) (at most max_existence), each with a tentative track row."""
    mixture = mixture.take(mixture.weights > 0.0)  # (no Bernoulli for a target that is not)
    copies = np.maximum(np.ceil(mixture.weights - 1e-9), 1).astype(np.int64)
    prior = mixture.take(np.repeat(np.arange(mixture.size), copies))
    r = np.minimum(prior.weights / np.repeat(copies, copies), params.tracks.max_existence)
    prior = Mixture(r, prior.means, prior.covs, prior.labels)
    tracks = Tracks.empty(mixture.dim, params.gp.window)
    if prior.size == 0:
        return prior, tracks
    rows = np.arange(prior.size)
    born = _with_new_tracks(tracks, rows, np.zeros(prior.size, dtype=bool), prior, t_s,
                            params.tracks, existence=r)
    labelled = Mixture(r, prior.means, prior.covs, born.ids)
    return labelled, born


def grow_unseen(
    predicted: Mixture, tracks: Tracks, t_before_s: float, t_now_s: float, params: TrackParams
) -> Mixture:
    """The components of confirmed tracks seen moving with the motion class's displacement
    variance added for the step (Eq. iou_variance): a Bernoulli's own covariance says how far
    its target may have gone since its last detection. Inside a known search area, a moving
    Bernoulli survives only inside it (p_S(x) = 1_A(x): its weight loses the mass outside) and
    every component that reaches past it is moment-matched to its part inside."""
    motion = params.motion
    moving = np.zeros(predicted.size, dtype=bool)
    covs = predicted.covs
    if motion.speed_m_s > 0.0 and predicted.size and tracks.confirmed.any():
        seen = tracks.seen_t_s
        sv2, tau_c = motion.velocity_var_m2_s2, motion.correlation_s
        growth = iou_variance_m2(sv2, tau_c, t_now_s - seen) - iou_variance_m2(
            sv2, tau_c, t_before_s - seen
        )
        row = _rows(tracks, predicted.labels)
        moving = (tracks.confirmed & seen_moving(tracks, motion))[row]
        add = np.where(moving, growth[row], 0.0)
        covs = covs.copy()
        covs[:, 0, 0] += add
        covs[:, 1, 1] += add
    if params.area is None or predicted.size == 0:
        return Mixture(predicted.weights, predicted.means, covs, predicted.labels)
    mass = np.ones(predicted.size)
    near = np.flatnonzero(~_deep_inside(predicted.means[:, :2], covs[:, :2, :2], params.area))
    mass[near] = prob_in_region(predicted.means[near, :2], covs[near, :2, :2], params.area,
                                check=False)
    weights = np.where(moving, mass, 1.0) * predicted.weights
    edge = np.flatnonzero((mass < 1.0 - 1e-9) & (mass > 1e-6))
    if edge.size == 0:
        return Mixture(weights, predicted.means, covs, predicted.labels)
    means, covs = predicted.means.copy(), covs.copy()
    inside, first, second = truncation_moments(
        means[edge, :2], covs[edge, :2, :2], params.area, check=False
    )
    shift = first / inside[:, None]
    means[edge, :2] += shift
    covs[edge, :2, :2] = second / inside[:, None, None] - shift[:, :, None] * shift[:, None, :]
    if predicted.dim == 4:
        covs[edge, :2, 2:] = 0.0
        covs[edge, 2:, :2] = 0.0
    return Mixture(weights, means, covs, predicted.labels)


def _deep_inside(means_xy: FloatArray, covs_xy: FloatArray, area: Region) -> BoolArray:
    """(n,) Gaussians whose mean lies over 8 standard deviations (of the trace) inside the area:
    their mass outside it is below 1e-15, so the area changes nothing for them."""
    sd = np.sqrt(covs_xy[:, 0, 0] + covs_xy[:, 1, 1])
    if isinstance(area, Disk):
        depth = area.radius_m - np.hypot(*(means_xy - area.center_xy).T)
    else:
        v = area.vertices_xy  # counter-clockwise: the inside is left of every edge
        edge = np.roll(v, -1, axis=0) - v
        normal = np.column_stack([-edge[:, 1], edge[:, 0]]) / np.hypot(*edge.T)[:, None]
        depth = ((means_xy[:, None, :] - v[None]) * normal[None]).sum(axis=2).min(axis=1)
    result: BoolArray = depth > 8.0 * sd
    return result


def seen_moving(tracks: Tracks, motion: TargetMotion) -> BoolArray:
    """(T,) tracks whose detected positions moved over their GP window: the least-squares
    displacement over the window's span exceeds half the class's typical displacement in that
    time (Eq. iou_variance). A target seen standing still is not grown while unseen; with a
    stationary motion class (speed 0) no target is moving."""
    if motion.speed_m_s == 0.0:
        return np.zeros(tracks.size, dtype=bool)
    count = tracks.win_count
    w = tracks.win_t_s.shape[1]
    valid = np.arange(w)[None, :] >= (w - count)[:, None]
    n = np.maximum(count, 1)[:, None]
    t = np.where(valid, tracks.win_t_s, 0.0)
    t_mean = t.sum(axis=1, keepdims=True) / n
    dt = np.where(valid, tracks.win_t_s - t_mean, 0.0)
    xy_mean = np.where(valid[..., None], tracks.win_xy, 0.0).sum(axis=1) / n
    dxy = np.where(valid[..., None], tracks.win_xy - xy_mean[:, None, :], 0.0)
    sxx = (dt * dt).sum(axis=1)
    velocity = (dt[..., None] * dxy).sum(axis=1) / np.maximum(sxx, _TINY)[:, None]
    span = np.where(count > 0, tracks.win_t_s[:, -1] - np.where(
        valid, tracks.win_t_s, np.inf).min(axis=1), 0.0)
    moved_sq = (velocity**2).sum(axis=1) * span**2
    typical_sq = 2.0 * iou_variance_m2(motion.velocity_var_m2_s2, motion.correlation_s, span)
    result: BoolArray = (count >= 3) & (moved_sq > 0.25 * typical_sq)
    return result


def _rows(tracks: Tracks, labels: IntArray) -> IntArray:
    """The track row of each label (every LMB component is labelled with a live track)."""
    rows: IntArray = np.searchsorted(tracks.ids, labels)
    return rows


def _per_row(row: IntArray, values: FloatArray, n_rows: int) -> FloatArray:
    """(n_rows,) the sum of values over the components of each row (float even when empty)."""
    sums: FloatArray = np.bincount(row, values, n_rows).astype(np.float64, copy=False)
    return sums


@kernel
def _components(  # pragma: no cover - compiled; tested through associate
    a: IntArray, b: IntArray, nodes: int
) -> IntArray:
    """The connected component (its smallest node) of each node of a graph with edges a-b."""
    parent = np.arange(nodes)
    for k in range(a.shape[0]):
        x, y = a[k], b[k]
        while parent[x] != x:
            x = parent[x]
        while parent[y] != y:
            y = parent[y]
        if x != y:
            parent[max(x, y)] = min(x, y)
    for v in range(nodes):
        root = v
        while parent[root] != root:
            root = parent[root]
        parent[v] = root
    return parent


def associate(phi_undetected: FloatArray, phi: FloatArray) -> Association:
    """Marginal association probabilities from the hypothesis factors (see the module).

    `phi_undetected` (L,) > 0; `phi` (m, L) >= 0, zero where a measurement is outside a
    Bernoulli's gate. Clusters of Bernoullis linked by shared measurements are independent.
    """
    m, n = phi.shape
    undetected = np.ones(n)
    detected = np.zeros((m, n))
    gated_i, gated_l = np.nonzero(phi > 0.0)
    if gated_i.size == 0:
        return Association(undetected, detected)
    component = _components(gated_l, n + gated_i, n + m)  # Bernoullis 0..n-1, measurements after
    involved = np.unique(gated_l)
    for c in np.unique(component[involved]):
        bern = involved[component[involved] == c]
        meas = np.unique(gated_i[np.isin(gated_l, bern)])
        sub = phi[np.ix_(meas, bern)]
        if bern.size == 1:  # one Bernoulli: undetected or one of its measurements
            total = phi_undetected[bern[0]] + sub[:, 0].sum()
            undetected[bern[0]] = phi_undetected[bern[0]] / total
            detected[meas, bern[0]] = sub[:, 0] / total
            continue
        if hypothesis_bound(sub) <= EXACT_LIMIT:
            p_undet, p_det = exact_marginals(phi_undetected[bern], sub)
        else:  # seeded by the cluster's first row: the same inputs give the same marginals
            draws = np.random.default_rng(int(bern[0])).random((GIBBS_SWEEPS, bern.size))
            p_undet, p_det = gibbs_marginals(phi_undetected[bern], sub, draws)
        undetected[bern] = p_undet
        detected[np.ix_(meas, bern)] = p_det
    return Association(undetected, detected)


def update(
    predicted: Mixture,
    tracks: Tracks,
    region: Region,
    z: FloatArray,
    r_cov: FloatArray,
    sensor_xy: FloatArray,
    params: SatParams,
) -> tuple[Mixture, Association, FloatArray]:
    """The LMB update of one frame (Eq. lmb_r) and the birth existences of its measurements.

    Returns the updated mixture (missed-detection then detection components, unreduced), the
    association marginals and r_B (m,) (Eq. lmb_birth).
    """
    area = region.area_m2
    area_a = params.tracks.area.area_m2 if params.tracks.area is not None else area
    b = params.birth_weight / area_a  # intensity of measurements from targets not yet seen
    kappa = max(params.clutter_per_scan / area, _TINY) + b  # clutter and newborn intensity
    n_rows, m = tracks.size, z.shape[0]
    moments = params.push is not None and params.push.mode is PushMode.MOMENT
    vis = visibility(predicted, region, params.p_detect, moments)
    row = _rows(tracks, predicted.labels)
    seen_mass = _per_row(row, predicted.weights * vis.p_d, n_rows)
    phi_undetected = np.maximum(1.0 - seen_mass, _TINY)
    found = detection(predicted, vis.p_d, z, r_cov, kappa, 0.0)
    n = predicted.size
    raw = found.children.weights.reshape(m, n) * np.maximum(kappa + found.explained, _TINY)[:, None]
    raw *= _in_gate(predicted, z, r_cov, GATE_SQ)
    phi = np.zeros((m, n_rows))
    for i in range(m):
        phi[i] = _per_row(row, raw[i], n_rows) / kappa
    assoc = associate(phi_undetected, phi)
    missed = no_detection(predicted, vis, sensor_xy, params.push)
    missed_scale = assoc.undetected / phi_undetected
    with np.errstate(divide="ignore", invalid="ignore"):
        det_scale = np.where(phi > 0.0, assoc.detected / (kappa * phi), 0.0)
    children = found.children
    posterior = Mixture.concat([
        Mixture(missed.weights * missed_scale[row], missed.means, missed.covs, missed.labels),
        Mixture((raw * det_scale[:, row]).reshape(-1), children.means, children.covs,
                children.labels),
    ])
    r_unexplained = np.clip(1.0 - assoc.detected.sum(axis=1), 0.0, 1.0)
    r_birth = np.minimum(r_unexplained * b / kappa, params.tracks.max_existence)
    return posterior, assoc, r_birth


def _in_gate(pred: Mixture, z: FloatArray, r_cov: FloatArray, gate_sq: float) -> FloatArray:
    """(m, n) 1 where measurement i lies within component j's gate (d^2 <= gate_sq under
    P + R), else 0."""
    diff = z[:, None, :] - pred.means[None, :, :2]
    inv, _ = inv_det_2x2(pred.covs[:, :2, :2] + r_cov)
    d2 = np.einsum("mni,nij,mnj->mn", diff, inv, diff)
    gated: FloatArray = (d2 <= gate_sq).astype(np.float64)
    return gated


def step(
    tracks: Tracks,
    predicted: Mixture,
    region: Region | None,
    z: FloatArray,
    r_cov: FloatArray,
    sensor_xy: FloatArray,
    t_s: float,
    params: SatParams,
) -> tuple[Mixture, Tracks, int]:
    """One LMB step after prediction: update, birth, pruning and merging within each Bernoulli,
    and the track rows; returns the mixture, the tracks and the number of Bernoullis with
    r > extract_weight. A blind step (region None) updates nothing."""
    detected_p = np.zeros(tracks.size)
    posterior = predicted
    if region is not None:
        posterior, assoc, r_birth = update(predicted, tracks, region, z, r_cov, sensor_xy, params)
        detected_p = assoc.detected.sum(axis=0)
        born = birth(z, r_birth, r_cov, params.velocity_var_m2_s2, predicted.dim)
        # Newborn Bernoullis take provisional labels past every track id: they never merge
        # with another Bernoulli, and the cap on components counts them.
        labels = tracks.next_id + np.arange(born.size, dtype=np.int64)
        posterior = Mixture.concat([posterior, born._replace(labels=labels)])
    pruned, _ = prune(posterior, params.prune_weight)
    reduced = merge(pruned, params.merge_distance_sq, params.max_components).mixture
    return _maintain(tracks, reduced, detected_p, t_s, params)


def _maintain(
    tracks: Tracks,
    reduced: Mixture,
    detected_p: FloatArray,
    t_s: float,
    params: SatParams,
) -> tuple[Mixture, Tracks, int]:
    """The track rows of the Bernoullis after this step: existence, moments, detections, GP
    windows and confirmation; a Bernoulli ends when its components are pruned away, or when it
    is a confirmed track whose existence fell below drop_existence. Components labelled past
    the last track id are newborn Bernoullis (one component each): they get new rows."""
    tp = params.tracks
    newborn = reduced.labels >= tracks.next_id
    born = reduced.take(newborn)
    mix = reduced.take(~newborn)
    row = _rows(tracks, mix.labels)
    r = _per_row(row, mix.weights, tracks.size)
    capped = np.minimum(r, tp.max_existence)
    scale = np.divide(capped, r, out=np.ones_like(r), where=r > 0.0)
    weights = mix.weights * scale[row]
    hit = detected_p > 0.5
    hits = tracks.hits + hit
    score = np.log(np.maximum(capped, _TINY)) - np.log(np.maximum(1.0 - capped, _TINY))
    # Confirmed: confirm_length detections and r >= confirm_existence; it stays confirmed while
    # r >= extract_weight (a target whose r stays high out of view keeps its track).
    proven = hits >= tp.confirm_length
    confirmed = (tracks.confirmed & (capped >= params.extract_weight)) | (
        proven & (capped >= tp.confirm_existence)
    )
    alive = (r > 0.0) & ~(proven & (capped < tp.drop_existence))
    summary = _moment_match(Mixture(weights, mix.means, mix.covs, mix.labels), row, tracks.size)
    seen = np.flatnonzero(hit & alive)
    win_t, win_xy, win_count = pushed_windows(tracks, seen, summary.means[seen, :2], t_s,
                                              tp.window)
    updated = tracks._replace(
        hits=hits,
        life=tracks.life + 1,
        confirmed=confirmed,
        last_t_s=np.full(tracks.size, t_s),
        seen_t_s=np.where(hit, t_s, tracks.seen_t_s),
        score=score,
        means=np.where(r[:, None] > 0.0, summary.means, tracks.means),
        covs=np.where(r[:, None, None] > 0.0, summary.covs, tracks.covs),
        win_t_s=win_t,
        win_xy=win_xy,
        win_count=win_count,
    )
    keep = alive[row]
    mix = Mixture(weights[keep], mix.means[keep], mix.covs[keep], mix.labels[keep])
    survivors = updated.take(alive)
    survivors = survivors._replace(log=survivors.log.append(
        survivors.ids, t_s, survivors.means, survivors.covs))
    if born.size:
        rows = np.arange(born.size)
        n_old = survivors.size
        survivors = _with_new_tracks(survivors, rows, np.ones(born.size, dtype=bool), born,
                                     t_s, tp, existence=born.weights)
        mix = Mixture.concat([mix, born._replace(labels=survivors.ids[n_old:])])
    survivors = survivors._replace(alone=np.ones(survivors.size, dtype=bool))
    extracted = int(np.count_nonzero(survivors.existence > params.extract_weight))
    return mix, survivors, extracted

