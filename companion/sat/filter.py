"""One step of GM-PHD search and tracking (the paper's flowchart), as a pure function of its inputs.

predict (linear / GP) -> update with the limited FOV (no detection, push rule, detections) ->
measurement-driven birth -> prune and merge -> state extraction -> track maintenance.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, field
from enum import StrEnum
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from companion.errors import InputError
from companion.kernel_cache import kernel
from companion.sat import lmb
from companion.sat.birth import BirthWeight, born_kernel, born_weights_kernel
from companion.sat.extract import count_estimates
from companion.sat.fov import (
    ConvexPolygon,
    Disk,
    Region,
    disk_kernel,
    prob_in_region,
    truncation_moments,
)
from companion.sat.gp import GpParams, GpPredictor
from companion.sat.linalg import inv_det_2x2, spd_2x2_faults_of
from companion.sat.mixture import Mixture
from companion.sat.predict import LinearModel, predict, transition
from companion.sat.reduce import merge_kernel, prune_kernel
from companion.sat.tracks import Evidence, TrackParams, Tracks, maintain
from companion.sat.update import (
    NO_FIRST,
    NO_SECOND,
    PushMode,
    PushRule,
    detection_kernel,
    missed_kernel,
    push_code,
)

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

EDGE_TOUCH = 1e-3
"""A frame touches a track's edge when its Gaussian widened EDGE_REACH times has p(F) above this
and its own Gaussian below 1 - EDGE_TOUCH (Eq. edge_shift)."""

EDGE_REACH = 3.0
"""How many standard deviations a track's misses may have moved it off its GP mean and the frame
still count as touching it (Eq. edge_shift)."""


class FilterKind(StrEnum):
    """The estimator, by its TOML name: the paper's GM-PHD or the labeled multi-Bernoulli."""

    GMPHD = "gmphd"
    LMB = "lmb"


@dataclass(frozen=True, slots=True)
class SatParams:
    """Every parameter of the filter; defaults are the paper's simulation values."""

    kind: FilterKind = FilterKind.GMPHD
    p_survive: float = 1.0
    p_detect: float = 0.98  # p(D|F): detection probability of a target inside the FOV
    clutter_per_scan: float = 0.1  # expected false positives per scan, uniform in the FOV
    push: PushRule | None = field(default_factory=PushRule)  # limited-FOV rule; None: off
    extract_weight: float = 0.5
    prune_weight: float = 1e-3
    merge_distance_sq: float = 10.0  # Vo & Ma's U, on the squared Mahalanobis distance
    max_components: int = 100
    use_gp: bool = True  # GP regression for components of confirmed tracks
    linear_model: LinearModel = LinearModel.CONSTANT_POSITION
    q_m2_per_s: float = 0.01  # process noise of the linear model
    birth: BirthWeight = BirthWeight.ADAPTIVE
    birth_weight: float = 1.0
    velocity_var_m2_s2: float = 1.0  # velocity prior of a new component in a 4-D state
    gp: GpParams = field(default_factory=GpParams)
    tracks: TrackParams = field(default_factory=TrackParams)


@dataclass(frozen=True, slots=True)
class Scan:
    """What the sensor reported for one step, in the filter's ground frame (metres).

    `region` is the ground area that this frame really covered, or None when no frame was
    processed (blind: predict only, no no-detection update that would erase unseen targets).
    `sensor_xy` is the centre the push rule pushes away from (the robot's ground position).
    """

    t_s: float
    region: Region | None
    measurements_xy: FloatArray
    r_cov: FloatArray
    sensor_xy: FloatArray


class SatState(NamedTuple):
    """The estimator's whole state: time, mixture (Layers 1-2) and tracks (Layer 3)."""

    t_s: float
    mixture: Mixture
    tracks: Tracks


class StepReport(NamedTuple):
    """What one step did, for logs and counters."""

    estimates: int
    dropped_measurements: int
    blind: bool


_MAX_GAP_S = 1e9
"""Longest step accepted (~31 years, the GP's bound on time offsets): a longer gap can overflow
the predicted covariances (the constant-velocity Q grows as dt^3)."""


_REGIONS = (Disk, ConvexPolygon)
"""The kinds of region a scan may cover."""


def _check_dim(mixture: Mixture, params: SatParams) -> None:
    """InputError unless the mixture's state dimension is the linear model's (2 or 4)."""
    if mixture.dim != params.linear_model.state_dim:
        raise InputError(
            f"mixture state dimension {mixture.dim} does not match the "
            f"{params.linear_model.value!r} linear model's {params.linear_model.state_dim}"
        )


def initial_state(mixture: Mixture, t_s: float, params: SatParams) -> SatState:
    """The state before the first step: the initial belief and no tracks (for the LMB, one
    Bernoulli with a tentative track per unit of the belief's weight, lmb.bernoullis)."""
    _check_dim(mixture, params)
    if params.kind is FilterKind.LMB:
        return SatState(t_s, *lmb.bernoullis(mixture, t_s, params))
    return SatState(t_s, mixture, Tracks.empty(mixture.dim, params.gp.window))


def _float_array(value: object, what: str) -> FloatArray:
    """value as a float64 array, or InputError (strings, None and other non-numbers)."""
    try:
        return np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{what}: must be numbers, got {value!r}") from exc


def _checked_scan(
    scan: Scan, state: SatState, params: SatParams
) -> tuple[FloatArray, int, FloatArray, Region | None, FloatArray]:
    """(the measurements to use (m, 2), how many rows were dropped, the sensor's ground position
    (2,), the region seen, R) of a scan, or InputError: see step.

    Non-finite measurement rows are dropped; a blind step (no region, or no finite sensor
    position: nothing is known of where the frame looked) drops them all.
    """
    raw: object = scan.t_s  # typed float, but callers may hand in anything
    if type(raw) is float:  # the common case, without the slower abstract-class test
        t = raw
    else:
        t = math.nan if isinstance(raw, bool) or not isinstance(raw, numbers.Real) else float(raw)
    if not (math.isfinite(t) and state.t_s <= t <= state.t_s + _MAX_GAP_S):
        raise InputError(
            f"scan time {raw!r} s: must be finite, >= {state.t_s} s and at most "
            f"{_MAX_GAP_S:.0e} s later"
        )
    if state.mixture.means.shape[1] != params.linear_model.state_dim:
        _check_dim(state.mixture, params)
    z = _float_array(scan.measurements_xy, "scan measurements")
    if z.size and (z.ndim != 2 or z.shape[1] != 2):
        raise InputError(f"scan measurements: expected shape (m, 2), got {z.shape}")
    if z.size == 0:
        z = _NO_MEASUREMENTS
    sensor_xy = _float_array(scan.sensor_xy, "scan sensor_xy")
    if sensor_xy.shape != (2,):
        raise InputError(f"scan sensor_xy: expected shape (2,), got {sensor_xy.shape}")
    region = scan.region
    if region is not None and not isinstance(region, _REGIONS):
        raise InputError(f"scan region: must be a Disk, a ConvexPolygon or None, got {region!r}")
    r_cov = _float_array(scan.r_cov, "scan measurement covariance")
    if r_cov.shape != (2, 2):
        raise InputError(f"scan measurement covariance: expected shape (2, 2), got {r_cov.shape}")
    finite_rows, pose_known, r_fault = _scan_kernel(z, sensor_xy, r_cov)
    if r_fault:
        raise InputError(f"scan measurement covariance: {_R_FAULTS[r_fault]}")
    if region is None or not pose_known:
        return _NO_MEASUREMENTS, z.shape[0], sensor_xy, None, r_cov
    dropped = z.shape[0] - finite_rows
    if dropped:
        z = z[np.isfinite(z).all(axis=1)]
    return z, dropped, sensor_xy, region, r_cov


_NO_MEASUREMENTS = np.zeros((0, 2))
"""No measurements (size 0: nothing in it to change)."""

_R_FAULTS = ("", "must be finite", "must be symmetric", "must be positive definite",
             "too large (its determinant overflows)")
"""The messages of _scan_kernel's codes for R; positive definite as fov accepts the components'
covariances; a determinant beyond ~1e308 (R beyond ~1e154 m^2) would overflow R's inverse."""


@kernel
def _scan_kernel(  # pragma: no cover - compiled; tested through step
    z: FloatArray, sensor_xy: FloatArray, r_cov: FloatArray
) -> tuple[int, bool, int]:
    """(rows of z (m, 2) with both entries finite, whether sensor_xy is finite, the fault of R:
    an index into _R_FAULTS, 0 for none)."""
    finite_rows = 0
    for i in range(z.shape[0]):
        finite_rows += math.isfinite(z[i, 0]) and math.isfinite(z[i, 1])
    pose_known = math.isfinite(sensor_xy[0]) and math.isfinite(sensor_xy[1])
    a, b, c, d = r_cov[0, 0], r_cov[0, 1], r_cov[1, 0], r_cov[1, 1]
    if not (math.isfinite(a) and math.isfinite(b) and math.isfinite(c) and math.isfinite(d)):
        return finite_rows, pose_known, 1
    asymmetric, indefinite = spd_2x2_faults_of(a, b, c, d)
    if asymmetric or indefinite:
        return finite_rows, pose_known, 2 if asymmetric else 3
    return finite_rows, pose_known, 0 if math.isfinite(a * d - b * c) else 4


def _predict(
    state: SatState, dt_s: float, params: SatParams, region: Region | None, z: FloatArray,
    r_cov: FloatArray,
) -> Mixture:
    """Linear prediction for every component, GP prediction for those of confirmed tracks.

    A confirmed track's component takes the GP mean at the new time (Eq. gp_prediction) over the
    track's recent detections, and its position covariance grows by the increase of the GP's
    predictive variance over the step: growth that saturates at sigma_f^2 however long the target
    stays out of view, where a random walk would grow without bound.
    """
    f, q = transition(params.linear_model, dt_s, params.q_m2_per_s)
    tracks = state.tracks
    lmb_kind = params.kind is FilterKind.LMB
    # Targets said to stand still (filter.target_speed = 0): the LMB's Bernoullis stay where
    # their own updates put them, under the linear model's noise; a GP's trend over still
    # targets is the pose's drift, not motion.
    if not params.use_gp or (lmb_kind and params.tracks.motion.speed_m_s == 0.0):
        return predict(state.mixture, f, q, params.p_survive, params.gp)
    return predict(
        state.mixture, f, q, params.p_survive, params.gp, tracks.gp_fit(), tracks.ids,
        tracks.confirmed, state.t_s, state.t_s + dt_s, incremental=lmb_kind,
        keep_shift=None if lmb_kind else _edge_shifts(
            tracks, state.t_s, region, z, r_cov, params.tracks.gate_sq),
    )


def _edge_shifts(
    tracks: Tracks, t_s: float, region: Region | None, z: FloatArray, r_cov: FloatArray,
    gate_sq: float,
) -> BoolArray | None:
    """The confirmed tracks not detected at t_s whose Gaussian the new frame touches and whose
    gate (d^2 <= gate_sq under P + R) holds none of its measurements z: each may keep the shift
    its misses gave its component (Eq. edge_shift, capped and only for a standing window in
    `predict`), or None if there is none.

    A miss at the frame's edge cuts the part of a component inside the frame and moves its mean
    out (the moment rule); the GP prediction would put the mean back on the window of
    detections, so that every further look at the same edge cut the same part again and wore
    down the track of a target standing just outside. The shift is kept only while the frame
    still touches the track: once it has moved on, the GP mean holds again. Nor is it kept when
    the frame holds a detection in the track's gate: that detection says where the target is,
    and a component kept off it would split into the part the detection updates and the part
    it misses, two estimates of one target.
    """
    if region is None or not tracks.size:
        return None
    centre = region.centroid_xy
    if isinstance(region, Disk):
        outer_m = inner_m = region.radius_m
    else:
        outer_m = float(np.hypot(*(region.vertices_xy - centre).T).max())
        inner_m = 0.0
    rows = _edge_rows_kernel(tracks.confirmed, tracks.seen_t_s, t_s, tracks.means, tracks.covs,
                             centre, outer_m, inner_m, EDGE_REACH)
    if not rows.size:
        return None
    keep = np.zeros(tracks.size, dtype=np.bool_)
    covs = tracks.covs[rows, :2, :2]
    p_in = prob_in_region(np.concatenate([tracks.means[rows, :2]] * 2),
                          np.concatenate([covs, EDGE_REACH**2 * covs]), region, check=False)
    own, widened = p_in[: rows.size], p_in[rows.size :]
    keep[rows] = (widened > EDGE_TOUCH) & (own < 1.0 - EDGE_TOUCH)  # Eq. edge_shift
    if z.shape[0]:
        diff = z[None, :, :] - tracks.means[rows, None, :2]
        inv, _ = inv_det_2x2(covs + r_cov)
        near = np.einsum("rmi,rij,rmj->rm", diff, inv, diff) <= gate_sq
        keep[rows] &= ~near.any(axis=1)
    return keep


@kernel
def _edge_rows_kernel(  # pragma: no cover - compiled; tested through step
    confirmed: BoolArray, seen_t_s: FloatArray, t_s: float, means: FloatArray,
    covs: FloatArray, centre_xy: FloatArray, outer_m: float, inner_m: float, reach: float,
) -> IntArray:
    """The confirmed tracks not detected at t_s that a frame's edge may cross (Eq. edge_shift):
    the others are decided without p(F), by bounds exact for EDGE_TOUCH = 1e-3. A Gaussian whose
    largest standard deviation sd fits 3.72 sd inside the disk of radius inner_m round
    centre_xy (inside the frame) has p(F) > 0.999; one farther than 3.1 widened sd (reach sd)
    outside the disk of radius outer_m (round the frame) has p(F) < 1e-3."""
    out = np.empty(confirmed.shape[0], dtype=np.int64)
    n = 0
    for r in range(confirmed.shape[0]):
        if not confirmed[r] or seen_t_s[r] >= t_s:
            continue
        a, b, c = covs[r, 0, 0], covs[r, 0, 1], covs[r, 1, 1]
        sd = math.sqrt(0.5 * (a + c) + math.hypot(0.5 * (a - c), b))
        gap = math.hypot(means[r, 0] - centre_xy[0], means[r, 1] - centre_xy[1])
        if gap - outer_m < 3.1 * reach * sd and inner_m - gap < 3.72 * sd:
            out[n] = r
            n += 1
    return out[:n]


def step(
    state: SatState, scan: Scan, params: SatParams, gp: GpPredictor
) -> tuple[SatState, StepReport]:
    """Advance the estimator to scan.t_s with the scan's measurements (one pass of the flowchart).

    `gp` fits the GP windows that changed and memoises their solves; the result does not depend
    on its cache. A bad scan raises InputError: a time before the state's or more than 1e9 s
    after it, a region that is neither a Disk nor a ConvexPolygon nor None, a sensor_xy not of
    shape (2,), measurements not of shape (m, 2), or an R that is not a symmetric positive
    definite 2x2 (linalg.spd_2x2_faults, determinant finite). Non-finite measurement rows are
    dropped and counted, not refused; a non-finite sensor_xy makes the step blind.
    """
    # Every input is checked here, so that a bad scan raises InputError and nothing else.
    z, dropped, sensor_xy, region, r_cov = _checked_scan(scan, state, params)

    predicted = _predict(state, scan.t_s - state.t_s, params, region, z, r_cov)
    if params.kind is FilterKind.LMB:
        predicted = lmb.grow_unseen(predicted, state.tracks, state.t_s, scan.t_s, params.tracks)
        mixture, tracks, estimates = lmb.step(
            state.tracks, predicted, region, z, r_cov, sensor_xy, scan.t_s, params
        )
        tracks = tracks.refit_fresh(scan.t_s, gp)
        return SatState(scan.t_s, mixture, tracks), StepReport(estimates, dropped, region is None)
    n = predicted.size
    if region is None:
        reduced, detected, est_rows, n_estimates = _reduced(*_reduce_kernel(
            predicted.weights, predicted.means, predicted.covs, predicted.labels,
            np.full(n, -1, dtype=np.int64), np.zeros(n, dtype=bool), params.prune_weight,
            params.merge_distance_sq, params.max_components, r_cov, params.extract_weight,
        ))
    else:
        area = region.area_m2
        clutter = params.clutter_per_scan / area  # kappa(z): false positives uniform in the FOV
        newborn = params.birth_weight / area if params.birth is BirthWeight.ADAPTIVE else 0.0
        moments = params.push is not None and params.push.mode is PushMode.MOMENT
        if isinstance(region, Disk):  # p(F) and its moments by the update kernel
            p_in, first, second = _NO_P_IN, NO_FIRST, NO_SECOND
            center_xy, radius_m = region.center_xy, region.radius_m
        else:  # a polygon's need scipy's Owen's T: computed here
            center_xy, radius_m = sensor_xy, 0.0
            first, second = NO_FIRST, NO_SECOND
            pos_means, pos_covs = predicted.means[:, :2], predicted.covs[:, :2, :2]
            if moments:
                p_in, first, second = truncation_moments(pos_means, pos_covs, region, check=False)
            else:
                p_in = prob_in_region(pos_means, pos_covs, region, check=False)
        push = params.push
        reduced, detected, est_rows, n_estimates = _reduced(*_update_kernel(
            predicted.weights, predicted.means, predicted.covs, predicted.labels, p_in, first,
            second, center_xy, radius_m, moments, params.p_detect, z, r_cov, clutter, newborn,
            params.birth is BirthWeight.ADAPTIVE, params.birth_weight, sensor_xy,
            push_code(push), 0.0 if push is None else push.lower,
            0.0 if push is None else push.upper, params.velocity_var_m2_s2,
            params.prune_weight, params.merge_distance_sq, params.max_components,
            params.extract_weight,
        ))
    evidence = None if region is None else Evidence(
        region, params.p_detect, clutter, r_cov, params.birth_weight / area
    )
    tracks, labelled = maintain(
        state.tracks, reduced, est_rows, detected, scan.t_s, params.tracks, evidence
    )
    tracks = tracks.refit_fresh(scan.t_s, gp)
    report = StepReport(n_estimates, dropped, region is None)
    return SatState(scan.t_s, labelled, tracks), report


def _reduced(
    weights: FloatArray, means: FloatArray, covs: FloatArray, labels: IntArray,
    detected: BoolArray, est_rows: IntArray, n_estimates: int,
) -> tuple[Mixture, BoolArray, IntArray, int]:
    """_reduce_kernel's result as (mixture, detected, est_rows, number of estimates)."""
    return Mixture(weights, means, covs, labels), detected, est_rows, n_estimates


_NO_P_IN = np.zeros(0)
"""Placeholder p(F) for _update_kernel when it computes p(F) itself (a disk)."""


@kernel
def _update_kernel(  # pragma: no cover - compiled; tested through step
    weights: FloatArray,
    means: FloatArray,
    covs: FloatArray,
    labels: IntArray,
    p_in: FloatArray,
    first: FloatArray,
    second: FloatArray,
    center_xy: FloatArray,
    radius_m: float,
    moments: bool,
    p_detect: float,
    z: FloatArray,
    r_cov: FloatArray,
    clutter: float,
    newborn: float,
    adaptive: bool,
    birth_weight: float,
    sensor_xy: FloatArray,
    push: int,
    lower: float,
    upper: float,
    velocity_var_m2_s2: float,
    prune_weight: float,
    merge_distance_sq: float,
    max_components: int,
    extract_weight: float,
) -> tuple[FloatArray, FloatArray, FloatArray, IntArray, BoolArray, IntArray, int]:
    """The update of a step with a frame, then _reduce_kernel.

    p(F) of each predicted component and, with `moments`, the raw moments of its mass in F
    (fov.truncation_moments) are computed here for a disk (radius_m > 0, centre center_xy) and
    given in (p_in, first, second) for a polygon. Then p_D = p(D|F) p(F) (Eq.
    prob_of_detection), the detection children (update.detection, with the newborn intensity
    competing), the claim of each component by the measurements (their children's weights sum
    to more than half its own), the birth weights (birth.birth_weights, adaptive or constant).
    The posterior is, in order: the no-detection components (update.missed_kernel, the push rule
    sparing the claimed ones), the detection children and one newborn component per
    measurement (birth.born_kernel); the children and the newborn come from detections."""
    n, d = means.shape
    m = z.shape[0]
    if radius_m > 0.0:
        p_in = np.empty(n)
        first, second = np.zeros((n, 2)), np.zeros((n, 2, 2))
        disk_kernel(means, covs[:, 0, 0], covs[:, 0, 1], covs[:, 1, 1], center_xy, radius_m,
                    2 if moments else 0, p_in, first, second)
    p_d = p_detect * p_in  # Eq. prob_of_detection
    n_children = m * n
    rows = n + n_children + m
    w_out, m_out = np.empty(rows), np.empty((rows, d))
    p_out, labels_out = np.empty((rows, d, d)), np.empty(rows, dtype=np.int64)
    explained = np.zeros(m)
    end = n + n_children
    if n_children:
        detection_kernel(weights, means, covs, labels, p_d, z, r_cov, clutter + newborn,
                         w_out[n:end], m_out[n:end], p_out[n:end], labels_out[n:end], explained)
    # A component that a measurement claims is in view: its missed part is not pushed out.
    claimed = np.zeros(n, dtype=np.bool_)
    for j in range(n if m else 0):
        from_detections = 0.0
        for k in range(m):
            from_detections += w_out[n + k * n + j]
        claimed[j] = from_detections > 0.5 * weights[j]
    missed_kernel(weights, means, covs, p_d, p_detect, first, second, claimed, sensor_xy, push,
                  lower, upper, w_out[:n], m_out[:n], p_out[:n])
    labels_out[:n] = labels
    # Measurement-driven birth joins the update's components before reduction, so that a
    # newborn component on top of a known target merges into it and keeps its track's label.
    w_new = born_weights_kernel(adaptive, birth_weight, explained, clutter, newborn)
    born_kernel(z, w_new, r_cov, velocity_var_m2_s2, w_out[end:], m_out[end:], p_out[end:],
                labels_out[end:])
    detection, counts_two = posterior_detections(weights, m)
    return _reduce_kernel(w_out, m_out, p_out, labels_out, detection, counts_two, prune_weight,
                          merge_distance_sq, max_components, r_cov, extract_weight)


TWO_TARGETS_WEIGHT = 1.5
"""A component's weight from which extraction counts it as two targets (round(w) >= 2)."""


@kernel
def posterior_detections(weights: FloatArray, m: int) -> tuple[IntArray, BoolArray]:
    """For the posterior of n predicted components (weights) and m detections, laid out as the
    update lays it out (n missed, the m n detection children measurement-major, m newborn): the
    detection that made each row (-1: none) and whether the row's parent already counts two
    targets (Eq. one_detection, reduce.merge)."""
    n = weights.shape[0]
    detection = np.full(n + m * n + m, -1, dtype=np.int64)
    counts_two = np.zeros(n + m * n + m, dtype=np.bool_)
    for k in range(m):
        for j in range(n):
            detection[n + k * n + j] = k
            counts_two[n + k * n + j] = weights[j] >= TWO_TARGETS_WEIGHT
        detection[n + m * n + k] = k
    return detection, counts_two


@kernel
def _reduce_kernel(  # pragma: no cover - compiled; tested through step
    weights: FloatArray,
    means: FloatArray,
    covs: FloatArray,
    labels: IntArray,
    detection: IntArray,
    counts_two: BoolArray,
    prune_weight: float,
    merge_distance_sq: float,
    max_components: int,
    r_cov: FloatArray,
    extract_weight: float,
) -> tuple[FloatArray, FloatArray, FloatArray, IntArray, BoolArray, IntArray, int]:
    """Prune and merge a posterior (reduce.prune, reduce.merge with R as the resolution), then
    extract: the reduced (weights, means, covs, labels), whether each reduced component owes
    most of its weight to detections, the rows above extract_weight and the number of
    estimates (extract.extract)."""
    weights, means, covs, labels, keep, _ = prune_kernel(
        weights, means, covs, labels, prune_weight
    )
    kept_detection = detection[keep]
    observed = kept_detection >= 0
    w_out, m_out, p_out, labels_out, group_of = merge_kernel(
        weights, means, covs, labels, kept_detection, counts_two[keep], merge_distance_sq, True,
        r_cov, True, max_components,
    )
    from_detection = np.zeros(w_out.shape[0])
    for i in range(group_of.shape[0]):
        if group_of[i] >= 0:
            from_detection[group_of[i]] += weights[i] * observed[i]
    return (w_out, m_out, p_out, labels_out, from_detection > 0.5 * w_out,
            np.flatnonzero(w_out > extract_weight), count_estimates(w_out, extract_weight))
