"""Track maintenance (Layer 3): track-to-estimate association after Panta et al. 2009.

Every live track has a stable id, and the component that supports it carries that id as its
label through prediction, update and merging. Each step, an estimate continues the track its
component is labelled with (the GM-PHD's own association); an unlabelled estimate continues an
unclaimed track it gates with (squared Mahalanobis distance <= the merge threshold U); a second
estimate of one lineage (a split) and an estimate that gates with no track start new tracks. A
track is confirmed once `confirm_length` steps have supported it with a detection and its
existence (below) is high; out of view is not gone: a confirmed track whose labelled component
still survives in the mixture is held by it, and a confirmed track ends when nothing has supported
it for `timeout_s` or when what the sensor saw makes it unlikely to exist. A tentative track ends
at its first unsupported step. Each track keeps its history (time, mean, covariance) in an
append-only log.

Evidence (a sequential likelihood-ratio test per track, Blackman & Popoli 1999, Sec. 6.2): each
step with a frame adds to the track's log-likelihood ratio of existence

    detected:  log(p_D / p_FA),   p_FA = min(1/2, kappa A_gate)           # Eq. track_score_hit
    missed:    log(1 - p_D p(F))                                           # Eq. track_score_miss

where kappa is the clutter density, A_gate the area of the track's gate and p(F) the mass of
the track's Gaussian in the frame's footprint: a miss in view counts against the track, one out
of view (p(F) = 0) does not. A track's covariance is that of the component supporting it plus
the displacement variance of the targets' motion class since its last detection
(companion.sat.motion), so that a track coasting unseen says honestly how far its target may
have gone, and a re-detected mover gates with its own grown track instead of starting another.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from companion.sat import track_kernels as kernels
from companion.sat.fov import Disk, Region, prob_in_region, truncation_moments
from companion.sat.gp import STANDING_P_MOVING, GpFit, GpPredictor
from companion.sat.linalg import inv_det_2x2
from companion.sat.mixture import Mixture
from companion.sat.motion import TargetMotion, iou_variance_m2

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]


@dataclass(frozen=True, slots=True)
class TrackParams:
    """Association gate, confirmation, ending, GP window length and the targets' motion class."""

    gate_sq: float = 10.0
    confirm_length: int = 3
    timeout_s: float = 30.0
    window: int = 30
    motion: TargetMotion = field(default_factory=TargetMotion)
    confirm_existence: float = 0.99  # existence a track needs to be confirmed
    drop_existence: float = 0.1  # existence below which a track ends
    max_existence: float = 0.9999  # cap, so that misses in view can end a long-seen track
    area: Region | None = None  # the search area, where the targets are (None: anywhere)
    coast_after_s: float = 10.0  # a track not detected for longer is coasting on prediction


class Evidence(NamedTuple):
    """What the sensor could say this step: its footprint, p(D|F), clutter density, R and the
    density of targets not yet seen (the birth intensity)."""

    region: Region
    p_detect: float
    clutter_per_m2: float
    r_cov: FloatArray
    birth_per_m2: float


class _LogBuffer:
    """Growable storage shared by TrackLog views; only ever written past every view's end."""

    __slots__ = ("covs", "ids", "means", "t_s", "used")

    def __init__(self, dim: int, capacity: int) -> None:
        self.ids = np.zeros(capacity, dtype=np.int64)
        self.t_s = np.zeros(capacity)
        self.means = np.zeros((capacity, dim))
        self.covs = np.zeros((capacity, dim, dim))
        self.used = 0


class TrackLog(NamedTuple):
    """Append-only history rows (track id, t_s, mean, cov); appending returns a new view.

    Views share one buffer and copy it only when an older view is appended to again, so that
    every TrackLog value is immutable from the outside while appending costs O(rows added).
    """

    buffer: _LogBuffer
    length: int

    @staticmethod
    def empty(dim: int) -> TrackLog:
        """A log with no rows."""
        return TrackLog(_LogBuffer(dim, 1024), 0)

    def append(
        self, ids: IntArray, t_s: float, means: FloatArray, covs: FloatArray,
        rows: IntArray | None = None,
    ) -> TrackLog:
        """A view with the rows of this one followed by the given rows (only `rows` of the given
        arrays, in that order, when given)."""
        picked = np.arange(ids.shape[0]) if rows is None else rows
        k = picked.shape[0]
        if k == 0:
            return self
        buf = self.writable(k)
        kernels.write_rows(buf.ids, buf.t_s, buf.means, buf.covs, self.length, ids, t_s, means,
                           covs, picked)
        return self.extended(buf, k)

    def writable(self, k: int) -> _LogBuffer:
        """A buffer holding this view's rows whose next k rows no view reads: this view's own,
        or a grown copy of its rows."""
        buf = self.buffer
        end = self.length + k
        if k and (buf.used != self.length or end > buf.ids.shape[0]):
            grown = _LogBuffer(buf.means.shape[1], max(2 * buf.ids.shape[0], end))
            for name in ("ids", "t_s", "means", "covs"):
                getattr(grown, name)[: self.length] = getattr(buf, name)[: self.length]
            buf = grown
        return buf

    def extended(self, buf: _LogBuffer, k: int) -> TrackLog:
        """The view of this one's rows and the k written after them into buf (from writable)."""
        if k == 0:
            return self
        buf.used = self.length + k
        return TrackLog(buf, buf.used)

    def history(self, track_id: int) -> tuple[FloatArray, FloatArray, FloatArray]:
        """(t_s (k,), means (k, d), covs (k, d, d)) of one track, oldest first."""
        rows = np.flatnonzero(self.buffer.ids[: self.length] == track_id)
        buf = self.buffer
        return buf.t_s[rows].copy(), buf.means[rows].copy(), buf.covs[rows].copy()


class Tracks(NamedTuple):
    """The live tracks, one row each, with their recent positions for GP prediction."""

    ids: IntArray  # (T,)
    hits: IntArray  # (T,) steps supported by a detection (confirmation counts these)
    life: IntArray  # (T,) steps supported at all: the track's length l
    confirmed: BoolArray  # (T,)
    born_t_s: FloatArray  # (T,)
    last_t_s: FloatArray  # (T,) time of the last support
    seen_t_s: FloatArray  # (T,) time of the last detection (its birth, if never detected)
    score: FloatArray  # (T,) log-likelihood ratio of existence (Eq. track_score_*)
    alone: BoolArray  # (T,) means/covs are the track's own belief, grown to last_t_s: a GM-PHD
    # track coasting with no component, or every LMB track (a Bernoulli's own moments)
    means: FloatArray  # (T, d) state at the last support
    covs: FloatArray  # (T, d, d) of the supporting component at last_t_s (see grown_covs)
    win_t_s: FloatArray  # (T, W) times of the most recent detections, right-aligned
    win_xy: FloatArray  # (T, W, 2) positions at those detections, right-aligned
    win_count: IntArray  # (T,) valid entries at the right of the window
    gp_mu: FloatArray  # (T, 5) GP fit of each window (see GpFit), refitted when it changes
    gp_beta: FloatArray  # (T, W, 2)
    gp_ky_inv: FloatArray  # (T, W, W)
    log: TrackLog
    next_id: int = 0

    @property
    def size(self) -> int:
        """Number of live tracks."""
        return int(self.ids.shape[0])

    @staticmethod
    def empty(dim: int, window: int) -> Tracks:
        """No tracks yet."""
        return Tracks(
            ids=np.zeros(0, dtype=np.int64),
            hits=np.zeros(0, dtype=np.int64),
            life=np.zeros(0, dtype=np.int64),
            confirmed=np.zeros(0, dtype=bool),
            born_t_s=np.zeros(0),
            last_t_s=np.zeros(0),
            seen_t_s=np.zeros(0),
            score=np.zeros(0),
            alone=np.zeros(0, dtype=bool),
            means=np.zeros((0, dim)),
            covs=np.zeros((0, dim, dim)),
            win_t_s=np.zeros((0, window)),
            win_xy=np.zeros((0, window, 2)),
            win_count=np.zeros(0, dtype=np.int64),
            gp_mu=np.zeros((0, 5)),
            gp_beta=np.zeros((0, window, 2)),
            gp_ky_inv=np.zeros((0, window, window)),
            log=TrackLog.empty(dim),
        )

    @property
    def existence(self) -> FloatArray:
        """(T,) probability that each track's target exists, from its score."""
        result: FloatArray = kernels.existences(self.score)
        return result

    def coasting(self, t_s: float, after_s: float) -> BoolArray:
        """(T,) tracks not detected for more than after_s seconds at t_s: on prediction alone."""
        result: BoolArray = t_s - self.seen_t_s > after_s
        return result

    def gp_fit(self) -> GpFit:
        """The GP fit of every track's window (a view, no copy)."""
        return GpFit(self.win_t_s, self.win_count, self.gp_mu, self.gp_beta, self.gp_ky_inv)

    def refit_fresh(self, t_s: float, gp: GpPredictor) -> Tracks:
        """The tracks with the GP fits of the confirmed tracks' windows that gained a detection
        at t_s recomputed (only confirmed tracks are predicted by their GP)."""
        fit = gp.refit(self.win_t_s, self.win_xy, self.win_count, self.confirmed, t_s,
                       self.gp_fit())
        if fit.mu is self.gp_mu:
            return self
        return Tracks(self.ids, self.hits, self.life, self.confirmed, self.born_t_s,
                      self.last_t_s, self.seen_t_s, self.score, self.alone, self.means,
                      self.covs, self.win_t_s, self.win_xy, self.win_count, fit.mu, fit.beta,
                      fit.ky_inv, self.log, self.next_id)

    def take(self, keep: BoolArray | IntArray) -> Tracks:
        """The tracks selected by a mask or an index, sharing the log."""
        return self._replace(**{name: getattr(self, name)[keep] for name in _ROW_FIELDS})


_ROW_FIELDS = tuple(name for name in Tracks._fields if name not in ("log", "next_id"))
"""The fields of Tracks that hold one row per track."""


def same_layout(a: Tracks, b: Tracks) -> bool:
    """Whether a and b hold their rows in arrays of the same dtypes and widths (tracks saved by
    another version of the estimator may not)."""
    return all(
        getattr(a, name).dtype == getattr(b, name).dtype
        and getattr(a, name).shape[1:] == getattr(b, name).shape[1:]
        for name in _ROW_FIELDS
    )


def grown_covs(tracks: Tracks, t_s: float, motion: TargetMotion) -> FloatArray:
    """(T, d, d) each track's honest covariance at t_s (Eq. iou_variance on the position block).

    A track supported by a component: that component's covariance plus the motion class's
    displacement variance since the last detection. A track coasting alone: its own belief at
    last_t_s, grown by the increase of that variance since.
    """
    if tracks.size == 0 or motion.speed_m_s == 0.0:
        return tracks.covs
    sv2, tau_c = motion.velocity_var_m2_s2, motion.correlation_s
    growth = iou_variance_m2(sv2, tau_c, t_s - tracks.seen_t_s) - np.where(
        tracks.alone, iou_variance_m2(sv2, tau_c, tracks.last_t_s - tracks.seen_t_s), 0.0
    )
    covs = tracks.covs.copy()
    covs[:, 0, 0] += growth
    covs[:, 1, 1] += growth
    return covs


def _gating_view(tracks: Tracks, t_s: float, motion: TargetMotion) -> Tracks:
    """The tracks with the honest covariance for those coasting alone, for association."""
    if not np.count_nonzero(tracks.alone):  # (faster than any() on a few rows)
        return tracks
    covs = np.where(tracks.alone[:, None, None], grown_covs(tracks, t_s, motion), tracks.covs)
    return tracks._replace(covs=covs)


def _coast(
    tracks: Tracks, rows: IntArray, t_s: float, params: TrackParams, evidence: Evidence | None
) -> Tracks:
    """Confirmed tracks with no component coast alone on their honest Gaussian.

    A frame that does not see the target updates that Gaussian as the no-detection update does
    a component: the moments of (1 - p_D 1_F(x)) N(x; m, P), and scores the miss.
    """
    if rows.size == 0:
        return tracks
    means = tracks.means.copy()
    covs = tracks.covs.copy()
    score = tracks.score.copy()
    honest = grown_covs(tracks, t_s, params.motion)[rows]
    if evidence is not None:
        p_d = evidence.p_detect
        mass, moment, second = truncation_moments(
            means[rows, :2], honest[:, :2, :2], evidence.region, check=False
        )
        kept = 1.0 - p_d * np.minimum(mass, 1.0 - 1e-12)  # Eq. track_score_miss
        shift = -p_d * moment / kept[:, None]
        pos = (honest[:, :2, :2] - p_d * second) / kept[:, None, None]
        honest[:, :2, :2] = pos - shift[:, :, None] * shift[:, None, :]
        means[rows, :2] += shift
        score[rows] += np.log(kept)
    covs[rows] = honest
    last_t = tracks.last_t_s.copy()
    last_t[rows] = t_s
    alone = tracks.alone.copy()
    alone[rows] = True
    return tracks._replace(means=means, covs=covs, score=score, last_t_s=last_t, alone=alone)


def maintain(
    tracks: Tracks,
    mix: Mixture,
    est_rows: IntArray,
    detected: BoolArray,
    t_s: float,
    params: TrackParams,
    evidence: Evidence | None = None,
) -> tuple[Tracks, Mixture]:
    """Associate this step's estimates with the tracks; returns the tracks and relabelled mixture.

    `est_rows` are the mixture rows extracted as targets, each once: a component of weight w is
    round(w) targets in Layer 2, but in Layer 3 it supports one track, since copies of one
    estimate cannot be told apart; when its targets separate, the mixture holds two components
    and the second starts a new track: the split. `detected[i]` says whether component i owes
    its weight to a detection this step. `evidence` is what the frame could see (None: a blind
    step, which scores nothing).
    """
    gating = _gating_view(tracks, t_s, params.motion)
    supported_by, hit, rows, missed, coasting, new_rows = kernels.support_of(
        gating.ids, gating.means, gating.covs, tracks.confirmed, params.motion.speed_m_s > 0.0,
        est_rows, mix.labels, mix.means, mix.covs, mix.weights, detected, params.gate_sq,
        tracks.alone, 0.0 if evidence is None else evidence.clutter_per_m2,
        tracks.gp_mu[:, -1] <= STANDING_P_MOVING,
    )
    updated, alive, labels, n_alive, n_new, decided = _support(
        tracks, rows, missed, supported_by, hit, coasting, mix, t_s, params, evidence
    )
    if not decided:
        # A moving target's confirmed track that nothing supports coasts on its growing
        # uncertainty until the frames refute it; a stationary one's ends after the timeout.
        updated = _coast(updated, coasting.nonzero()[0], t_s, params, evidence)
        in_area = _NO_P_IN
        if params.area is not None:
            # a track coasting alone exists only as far as its Gaussian lies in the search area
            honest = grown_covs(updated, t_s, params.motion)[coasting, :2, :2]
            in_area = np.ones(tracks.size)
            in_area[coasting] = prob_in_region(
                updated.means[coasting, :2], honest, params.area, check=False
            )
        alive, labels, n_alive, n_new = kernels.survivors(
            supported_by, coasting, tracks.confirmed, tracks.last_t_s, updated.score, in_area,
            updated.confirmed, tracks.ids, mix.size, t_s, params.timeout_s,
            params.drop_existence,
        )
    survivors = updated if n_alive == tracks.size else updated.take(alive)
    if n_new and evidence is not None and params.motion.speed_m_s > 0.0:
        survivors, labels = _absorb(
            survivors, labels, tracks.confirmed[alive], t_s, params, evidence.birth_per_m2
        )
    if new_rows.size == 0:
        return survivors, Mixture(mix.weights, mix.means, mix.covs, labels)
    with_new = _with_new_tracks(survivors, new_rows, detected[new_rows], mix, t_s, params)
    labels[new_rows] = with_new.ids[survivors.size:]
    return with_new, Mixture(mix.weights, mix.means, mix.covs, labels)


def _absorb(
    tracks: Tracks,
    labels: IntArray,
    was_confirmed: BoolArray,
    t_s: float,
    params: TrackParams,
    birth_per_m2: float,
) -> tuple[Tracks, IntArray]:
    """A track confirmed this step is the target of a confirmed track not detected since the
    new one was born, found again, when that explains it better than a target not yet seen:
    N(m_new; m_old, P_old + P_new) > the birth intensity (Eq. refound), with P_old the old
    track's honest covariance; the old track then takes the new one's state and its component's
    label, and the new one ends. Most likely pairs first.
    """
    new = (tracks.confirmed & ~was_confirmed).nonzero()[0]
    old = was_confirmed.nonzero()[0]
    if new.size == 0 or old.size == 0:
        return tracks, labels
    honest = grown_covs(tracks, t_s, params.motion)
    diff = tracks.means[new, None, :2] - tracks.means[None, old, :2]
    inv, det = inv_det_2x2(honest[None, old, :2, :2] + tracks.covs[new, None, :2, :2])
    dist = np.einsum("noi,noij,noj->no", diff, inv, diff)
    density = np.exp(-0.5 * dist) / (2.0 * math.pi * np.sqrt(det))
    unseen = tracks.seen_t_s[old][None, :] < tracks.born_t_s[new][:, None]
    pairs = np.argwhere((density > birth_per_m2) & unseen)  # Eq. refound
    if pairs.size == 0:
        return tracks, labels
    taken = np.zeros(tracks.size, dtype=bool)
    ended = np.zeros(tracks.size, dtype=bool)
    rows = {name: getattr(tracks, name).copy() for name in _ROW_FIELDS}
    for i, j in pairs[np.argsort(-density[pairs[:, 0], pairs[:, 1]], kind="stable")]:
        n, o = new[i], old[j]
        if taken[n] or taken[o]:
            continue
        taken[n] = taken[o] = ended[n] = True
        for name in _ROW_FIELDS:
            if name not in ("ids", "born_t_s", "hits", "life"):
                rows[name][o] = rows[name][n]
        rows["hits"][o] += rows["hits"][n]
        rows["life"][o] += rows["life"][n]
        labels[labels == tracks.ids[n]] = tracks.ids[o]
    found = taken & ~ended
    log = tracks.log.append(rows["ids"][found], t_s, rows["means"][found], rows["covs"][found])
    return tracks._replace(**rows, log=log).take(~ended), labels


def _support(
    tracks: Tracks,
    rows: IntArray,
    missed: IntArray,
    supported_by: IntArray,
    hit: BoolArray,
    coasting: BoolArray,
    mix: Mixture,
    t_s: float,
    params: TrackParams,
    evidence: Evidence | None,
) -> tuple[Tracks, BoolArray, IntArray, int, int, bool]:
    """The tracks with this step's support and evidence applied to the supported rows (`rows`;
    `missed`: those not hit), and which survive unless a row is coasting: see kernels.support.

    Rows supported by a component are scored with that component's Gaussian (Eqs.
    track_score_hit, track_score_miss); unsupported rows and blind steps score nothing. The GP
    window holds detected positions only: a coasting track's own predictions would feed back
    into its next prediction.
    """
    p_in, center_xy, radius_m = _NO_P_IN, _NO_R[0], 0.0
    if evidence is not None and isinstance(evidence.region, Disk):  # p(F) in kernels.support
        center_xy, radius_m = evidence.region.center_xy, evidence.region.radius_m
    elif evidence is not None and missed.size:  # a polygon's needs scipy's Owen's T
        comp = supported_by[missed]
        p_in = np.zeros(tracks.size)
        p_in[missed] = prob_in_region(
            mix.means[comp, :2], mix.covs[comp, :2, :2], evidence.region, check=False
        )
    r_cov = _NO_R if evidence is None else evidence.r_cov
    buf = tracks.log.writable(rows.shape[0])
    (means, covs, hits, life, last_t, seen_t, alone, score, confirmed, win_t, win_xy, win_count,
     alive, labels, n_alive, n_new, decided) = kernels.support(
        tracks.means, tracks.covs, tracks.hits, tracks.life, tracks.last_t_s, tracks.seen_t_s,
        tracks.alone, tracks.score, tracks.confirmed, tracks.win_t_s, tracks.win_xy,
        tracks.win_count, tracks.ids, supported_by, hit, coasting, p_in, center_xy, radius_m,
        mix.means, mix.covs, t_s, evidence is not None, r_cov,
        0.0 if evidence is None else evidence.p_detect,
        0.0 if evidence is None else evidence.clutter_per_m2, params.gate_sq,
        params.max_existence, params.window, params.confirm_length,
        params.confirm_existence, buf.ids, buf.t_s, buf.means, buf.covs,
        tracks.log.length, params.timeout_s, params.drop_existence,
    )
    updated = Tracks(
        ids=tracks.ids,
        hits=hits,
        life=life,
        confirmed=confirmed,
        born_t_s=tracks.born_t_s,
        last_t_s=last_t,
        seen_t_s=seen_t,
        score=score,
        alone=alone,
        means=means,
        covs=covs,
        win_t_s=win_t,
        win_xy=win_xy,
        win_count=win_count,
        gp_mu=tracks.gp_mu,
        gp_beta=tracks.gp_beta,
        gp_ky_inv=tracks.gp_ky_inv,
        log=tracks.log.extended(buf, rows.shape[0]),
        next_id=tracks.next_id,
    )
    return updated, alive, labels, n_alive, n_new, decided


_NO_R = np.zeros((2, 2))
"""Placeholder R for kernels.support on a blind step, which scores nothing."""

_NO_P_IN = np.zeros(0)
"""Placeholder p(F) for kernels.support (a disk's it computes itself, a blind step reads none)
and in_area for kernels.survivors (no track coasting in a search area)."""


def pushed_windows(
    tracks: Tracks, rows: IntArray, xy: FloatArray, t_s: float, window: int
) -> tuple[FloatArray, FloatArray, IntArray]:
    """The GP windows (times, positions, counts) with a detection at t_s, positions xy (k, 2),
    pushed onto the given rows (distinct); the other rows' windows are shared, not copied."""
    if rows.size == 0:
        return tracks.win_t_s, tracks.win_xy, tracks.win_count
    win_t, win_xy, win_count = tracks.win_t_s.copy(), tracks.win_xy.copy(), tracks.win_count.copy()
    kernels.push_windows(win_t, win_xy, win_count, rows, t_s, xy, window)
    return win_t, win_xy, win_count


def _with_new_tracks(
    tracks: Tracks,
    comp: IntArray,
    hit: BoolArray,
    mix: Mixture,
    t_s: float,
    params: TrackParams,
    existence: FloatArray | None = None,
) -> Tracks:
    """The tracks followed by one new tentative track per unassigned estimate (component rows
    `comp`, `hit`: born of a detection), with fresh ids; the new ones' first rows go to the log
    (kernels.append_tracks).

    Its score starts at the logit of `existence`, by default of its component's weight (the
    PHD's own belief in it, within [0.01, 0.99]).
    """
    k = comp.shape[0]
    w = np.clip(mix.weights[comp], 0.01, 0.99) if existence is None else existence
    score = np.log(w / (1.0 - w))
    buf = tracks.log.writable(k)
    rows = kernels.append_tracks(
        tracks.ids, tracks.hits, tracks.life, tracks.confirmed, tracks.born_t_s,
        tracks.last_t_s, tracks.seen_t_s, tracks.score, tracks.alone, tracks.means, tracks.covs,
        tracks.win_t_s, tracks.win_xy, tracks.win_count, tracks.gp_mu, tracks.gp_beta,
        tracks.gp_ky_inv, comp, hit, mix.means, mix.covs, score, t_s, tracks.next_id,
        params.confirm_length, params.confirm_existence, buf.ids, buf.t_s, buf.means,
        buf.covs, tracks.log.length,
    )
    return Tracks(*rows, log=tracks.log.extended(buf, k), next_id=tracks.next_id + k)
