"""One step of GM-PHD search and tracking (the paper's flowchart), as a pure function of its inputs.

predict (linear / GP) -> update with the limited FOV (no detection, push rule, detections) ->
measurement-driven birth -> prune and merge -> state extraction -> track maintenance.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from companion.errors import InputError
from companion.sat.birth import BirthWeight, birth, birth_weights
from companion.sat.extract import extract
from companion.sat.fov import Region
from companion.sat.gp import GpParams, GpPredictor
from companion.sat.mixture import Mixture
from companion.sat.predict import LinearModel, apply_gp, predict_linear, transition
from companion.sat.reduce import merge, prune
from companion.sat.tracks import TrackParams, Tracks, maintain
from companion.sat.update import PushMode, PushRule, detection, no_detection, visibility

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class SatParams:
    """Every parameter of the filter; defaults are the paper's simulation values."""

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


@dataclass(frozen=True, slots=True)
class SatState:
    """The estimator's whole state: time, mixture (Layers 1-2) and tracks (Layer 3)."""

    t_s: float
    mixture: Mixture
    tracks: Tracks


@dataclass(frozen=True, slots=True)
class StepReport:
    """What one step did, for logs and counters."""

    estimates: int
    dropped_measurements: int
    blind: bool


def initial_state(mixture: Mixture, t_s: float, params: SatParams) -> SatState:
    """The state before the first step: the initial belief and no tracks."""
    return SatState(t_s, mixture, Tracks.empty(mixture.dim, params.gp.window))


def _checked_measurements(scan: Scan) -> tuple[FloatArray, int]:
    """The finite rows of the scan's measurements and how many rows were dropped."""
    z = np.asarray(scan.measurements_xy, dtype=np.float64)
    if z.size == 0:
        return np.zeros((0, 2)), 0
    if z.ndim != 2 or z.shape[1] != 2:
        raise InputError(f"scan measurements: expected shape (m, 2), got {z.shape}")
    finite = np.all(np.isfinite(z), axis=1)
    return z[finite], int(z.shape[0] - finite.sum())


def _checked_r(r: object) -> FloatArray:
    """The scan's measurement covariance as a symmetric positive definite 2x2, or InputError."""
    r_cov = np.asarray(r, dtype=np.float64)
    if r_cov.shape != (2, 2):
        raise InputError(f"scan measurement covariance: expected shape (2, 2), got {r_cov.shape}")
    (a, b), (c, d) = r_cov.tolist()
    if not all(map(np.isfinite, (a, b, c, d))):
        raise InputError("scan measurement covariance: must be finite")
    if abs(b - c) > 1e-9 * max(abs(a), abs(d)):
        raise InputError("scan measurement covariance: must be symmetric")
    if not (a > 0.0 and a * d - b * c > 0.0):
        raise InputError("scan measurement covariance: must be positive definite")
    return r_cov


def _predict(state: SatState, dt_s: float, params: SatParams) -> Mixture:
    """Linear prediction for every component, GP prediction for those of confirmed tracks.

    A confirmed track's component takes the GP mean at the new time (Eq. gp_prediction) over the
    track's recent detections, and its position covariance grows by the increase of the GP's
    predictive variance over the step: growth that saturates at sigma_f^2 however long the target
    stays out of view, where a random walk would grow without bound.
    """
    prior = state.mixture
    f, q = transition(params.linear_model, dt_s, params.q_m2_per_s)
    predicted = predict_linear(prior, f, q, params.p_survive)
    tracks = state.tracks
    if not params.use_gp or tracks.size == 0 or prior.size == 0:
        return predicted
    return apply_gp(
        predicted, prior, tracks.ids, tracks.confirmed, tracks.gp_fit(), params.gp,
        state.t_s, state.t_s + dt_s,
    )


def step(
    state: SatState, scan: Scan, params: SatParams, gp: GpPredictor
) -> tuple[SatState, StepReport]:
    """Advance the estimator to scan.t_s with the scan's measurements (one pass of the flowchart).

    `gp` fits the GP windows that changed and memoises their solves; the result does not depend
    on its cache.
    """
    if not np.isfinite(scan.t_s) or scan.t_s < state.t_s:
        raise InputError(f"scan time {scan.t_s!r} s: must be finite and >= {state.t_s} s")
    z, dropped = _checked_measurements(scan)
    sensor_xy = np.asarray(scan.sensor_xy, dtype=np.float64)
    region = scan.region
    if region is not None and not np.all(np.isfinite(sensor_xy)):
        region = None  # no usable pose: this frame tells nothing about where we looked
    if region is None:
        dropped += z.shape[0]
        z = np.zeros((0, 2))
    r_cov = _checked_r(scan.r_cov)

    predicted = _predict(state, scan.t_s - state.t_s, params)
    dim = predicted.dim
    if region is None:
        posterior = predicted
        detected = np.zeros(predicted.size, dtype=bool)
        explained = np.zeros(0)
        clutter = newborn = 0.0
    else:
        area = region.area_m2
        clutter = params.clutter_per_scan / area  # kappa(z): false positives uniform in the FOV
        newborn = params.birth_weight / area if params.birth is BirthWeight.ADAPTIVE else 0.0
        moments = params.push is not None and params.push.mode is PushMode.MOMENT
        vis = visibility(predicted, region, params.p_detect, moments)
        found = detection(predicted, vis.p_d, z, r_cov, clutter, newborn)
        # A component that a measurement claims is in view: its missed part is not pushed out.
        from_detections = found.children.weights.reshape(z.shape[0], predicted.size).sum(axis=0)
        claimed = from_detections > 0.5 * predicted.weights
        missed = no_detection(predicted, vis, sensor_xy, params.push, claimed)
        posterior = Mixture.concat([missed, found.children])
        detected = np.arange(posterior.size) >= missed.size
        explained = found.explained

    if z.shape[0]:
        # Measurement-driven birth joins the update's components before reduction, so that a
        # newborn component on top of a known target merges into it and keeps its track's label.
        w_new = birth_weights(params.birth, params.birth_weight, explained, clutter, newborn)
        born = birth(z, w_new, r_cov, params.velocity_var_m2_s2, dim)
        posterior = Mixture.concat([posterior, born])
        detected = np.concatenate([detected, np.ones(born.size, dtype=bool)])

    pruned, kept = prune(posterior, params.prune_weight)
    merged = merge(
        pruned, params.merge_distance_sq, params.max_components, observed=detected[kept],
        resolution=r_cov,
    )
    reduced = merged.mixture
    # A merged component owes its weight to a detection when most of it came from detections.
    in_group = merged.group_of >= 0
    from_detection = np.bincount(
        merged.group_of[in_group],
        weights=(pruned.weights * detected[kept])[in_group],
        minlength=reduced.size,
    )
    detected_reduced = from_detection > 0.5 * reduced.weights

    est_index = extract(reduced, params.extract_weight)
    est_rows = np.flatnonzero(reduced.weights > params.extract_weight)
    tracks, labelled = maintain(
        state.tracks, reduced, est_rows, detected_reduced, scan.t_s, params.tracks
    )
    # Only confirmed tracks are predicted by their GP: refit the windows that just changed.
    fresh = np.flatnonzero(
        tracks.confirmed & (tracks.win_count > 0) & (tracks.win_t_s[:, -1] == scan.t_s)
    )
    tracks = tracks.refit_gp(fresh, gp)
    report = StepReport(int(est_index.size), dropped, region is None)
    return SatState(scan.t_s, labelled, tracks), report
