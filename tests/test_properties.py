"""Property and fuzz tests: the estimator, the metrics and the projection never break on bad input.

Hypothesis drives the GM-PHD core (`companion.sat.filter.step`) with random sequences of scans:
random measurement sets (none to 30 points, inside and far outside the world, duplicates, points
exactly on the region's boundary), random sensor poses (also unknown), SPD measurement
covariances from nearly singular to very large, random fields of view (tiny and huge disks,
convex polygons, thin slivers, tiny triangles, no region = blind) and random time steps (zero,
tiny, ordinary and long gaps), with random filter parameters built the way the simulation
builds them (a FilterSpec through `sat_params`). After every step the state must be sound:
finite non-negative weights, finite means, symmetric positive definite covariances, at most
`max_components` components, and track arrays consistent with each other and with the
mixture's labels. Invalid scans must raise InputError and nothing else.

`companion.metrics` (OSPA, Mahalanobis distance to tracks) and
`companion.vision.projection.project_detections` (random attitudes, heights, pixels inside,
outside and NaN) must return finite results or flag them invalid, or raise InputError.

Every test is derandomized (the project's rule: randomness is seeded).
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any, Literal

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from numpy.typing import NDArray

from companion.errors import CompanionError, InputError
from companion.geo import Utm
from companion.metrics import mahalanobis_to_tracks, ospa, ospa_components
from companion.sat.filter import (
    FilterKind,
    SatParams,
    SatState,
    Scan,
    StepReport,
    initial_state,
    step,
)
from companion.sat.fov import ConvexPolygon, Disk, Region
from companion.sat.gp import GpPredictor
from companion.sat.mixture import NO_LABEL, Mixture, make_mixture
from companion.sat.params import FilterSpec, MotionModel, sat_params
from companion.sat.update import detection
from companion.vision.camera import CameraModel
from companion.vision.projection import GeoPose, PoseUncertainty, project_detections, vehicle_utm

FloatArray = NDArray[np.float64]

WORLD_M = 150.0
"""Side of the square world the scans are centred on (the paper's)."""

FAST = settings(max_examples=60, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


# ---------------------------------------------------------------------------------------------
# Strategies: parameters, mixtures, regions, measurements, covariances, times
# ---------------------------------------------------------------------------------------------


def _log_uniform(lo: float, hi: float) -> st.SearchStrategy[float]:
    """Floats spread evenly over the decades between lo and hi (both > 0)."""
    return st.floats(math.log10(lo), math.log10(hi)).map(lambda e: float(10.0**e))


@st.composite
def filter_specs(draw: st.DrawFn) -> FilterSpec:
    """A valid [filter] table: every key within its declared range."""
    lo = draw(st.floats(0.0, 1.0))
    hi = draw(st.floats(lo, 1.0))
    return FilterSpec(
        kind=draw(st.sampled_from(list(FilterKind))),
        p_survive=draw(st.sampled_from([1.0, 0.99]) | st.floats(0.0, 1.0)),
        push_rule=draw(st.booleans()),
        push_band=(lo, hi),
        push_mode=draw(st.sampled_from(["moment", "paper"])),
        extract_weight=draw(st.sampled_from([0.5]) | st.floats(0.05, 2.0)),
        confirm_length=draw(st.integers(1, 4)),
        prune_weight=draw(st.sampled_from([1e-3, 0.0]) | st.floats(0.0, 0.2)),
        merge_distance=draw(st.sampled_from([10.0, 0.0]) | st.floats(0.0, 100.0)),
        max_components=draw(st.integers(1, 40)),
        motion=draw(st.sampled_from(list(MotionModel))),
        process_noise=draw(st.sampled_from([0.01, 0.0]) | _log_uniform(1e-6, 100.0)),
        birth_weight=draw(st.sampled_from([1.0]) | _log_uniform(1e-3, 10.0)),
        birth=draw(st.sampled_from(["adaptive", "constant"])),
        linear_model=draw(st.sampled_from(["cp", "cv"])),
        velocity_variance=draw(_log_uniform(1e-3, 100.0)),
        gp_sigma_f=draw(_log_uniform(0.1, 10.0)),
        gp_lengthscale=draw(_log_uniform(1.0, 200.0)),
        gp_sigma_n=draw(_log_uniform(0.05, 3.0)),
        gp_window=draw(st.integers(2, 12)),
        track_timeout=draw(_log_uniform(0.5, 100.0)),
        target_speed=draw(st.sampled_from([0.0, 0.3]) | _log_uniform(1e-3, 5.0)),
        manoeuvre_time=draw(_log_uniform(1.0, 1000.0)),
        confirm_existence=draw(st.sampled_from([0.99, 1e-6]) | st.floats(1e-6, 0.9999)),
        drop_existence=draw(st.sampled_from([0.1, 1e-6]) | st.floats(1e-6, 0.9)),
        coast_after=draw(_log_uniform(0.1, 100.0)),
    )


@st.composite
def sat_params_st(draw: st.DrawFn) -> SatParams:
    """Filter parameters as the simulation builds them from a scenario."""
    return sat_params(
        draw(filter_specs()),
        p_detect=draw(st.sampled_from([0.98, 1.0, 0.0]) | st.floats(0.0, 1.0)),
        clutter_per_scan=draw(st.sampled_from([0.1, 0.0]) | st.floats(0.0, 5.0)),
        dt_s=draw(st.sampled_from([1.0, 0.5]) | _log_uniform(0.01, 10.0)),
    )


@st.composite
def spd_2x2(draw: st.DrawFn, lo: float = 1e-4, hi: float = 1e12,
            min_ratio: float = 1e-10) -> FloatArray:
    """A symmetric positive definite 2x2 matrix, eigenvalues in [min_ratio lo, hi], any axes;
    the smaller eigenvalue down to min_ratio times the larger (nearly singular)."""
    big = draw(_log_uniform(lo, hi))
    ratio = draw(st.sampled_from([1.0, min_ratio]) | _log_uniform(min_ratio, 1.0))
    angle = draw(st.floats(0.0, math.pi))
    c, s = math.cos(angle), math.sin(angle)
    rot = np.array([[c, -s], [s, c]])
    m: FloatArray = rot @ np.diag([big, big * ratio]) @ rot.T
    m[1, 0] = m[0, 1]  # exactly symmetric
    return m


@st.composite
def mixtures(draw: st.DrawFn, dim: int) -> Mixture:
    """A valid initial belief: 0-8 components in, around and far from the world, from sharp
    (1e-6 m^2) to vague (1e10 m^2), round or nearly degenerate."""
    n = draw(st.integers(0, 8))
    weights = [draw(st.floats(0.0, 3.0)) for _ in range(n)]
    means = np.zeros((n, dim))
    covs = np.zeros((n, dim, dim))
    for i in range(n):
        coord = st.floats(-20.0, WORLD_M + 20.0) | st.floats(-1e7, 1e7)
        means[i, :2] = [draw(coord) for _ in range(2)]
        if dim == 4:
            means[i, 2:] = [draw(st.floats(-2.0, 2.0)) for _ in range(2)]
        covs[i, :2, :2] = draw(spd_2x2(lo=1e-6, hi=1e10, min_ratio=1e-8))
        if dim == 4:
            covs[i, 2, 2] = covs[i, 3, 3] = draw(_log_uniform(1e-3, 10.0))
    return make_mixture(weights, means, covs)


def _convex_polygon(draw: st.DrawFn, centre: FloatArray) -> Region | None:
    """A convex polygon about centre: a regular-ish one, a thin sliver or a tiny triangle, at any
    orientation; None when the constructor refuses it (it must then say InputError)."""
    kind = draw(st.sampled_from(["round", "sliver", "tiny", "camera"]))
    angle = draw(st.floats(0.0, 2.0 * math.pi))
    c, s = math.cos(angle), math.sin(angle)
    rot = np.array([[c, -s], [s, c]])
    if kind == "round":
        k = draw(st.integers(3, 8))
        steps = sorted(draw(st.lists(st.floats(0.0, 2.0 * math.pi), min_size=k, max_size=k,
                                     unique=True)))
        radius = draw(_log_uniform(0.5, 1e5))
        local = radius * np.column_stack([np.cos(steps), np.sin(steps)])
    elif kind == "sliver":
        length = draw(_log_uniform(1.0, 1e4))
        width = length * draw(_log_uniform(1e-9, 1e-2))
        local = np.array([[0.0, 0.0], [length, 0.0], [length, width], [0.0, width]])
    elif kind == "tiny":
        size = draw(_log_uniform(1e-6, 1e-2))
        local = size * np.array([[0.0, 0.0], [1.0, 0.0], [draw(st.floats(0.0, 1.0)), 1.0]])
    else:  # a camera's trapezoid footprint
        half_near = draw(st.floats(1.0, 30.0))
        half_far = half_near * draw(st.floats(1.0, 3.0))
        depth = draw(st.floats(1.0, 60.0))
        local = np.array([[-half_near, 0.0], [half_near, 0.0], [half_far, depth],
                          [-half_far, depth]])
    if draw(st.booleans()):
        local = local[::-1]  # clockwise given
    try:
        return ConvexPolygon(centre + local @ rot.T)
    except InputError:
        return None


@st.composite
def regions(draw: st.DrawFn, centre: FloatArray) -> Region | None:
    """None (blind), a disk of any radius from 1 um to 1000 km, or a convex polygon."""
    kind = draw(st.sampled_from(["none", "disk", "disk", "polygon", "polygon"]))
    if kind == "none":
        return None
    offset = np.array([draw(st.floats(-5.0, 5.0)), draw(st.floats(-5.0, 5.0))])
    if kind == "disk":
        radius = draw(st.sampled_from([25.0, 1e-6, 1e6]) | _log_uniform(1e-6, 1e6))
        return Disk(centre + offset, radius)
    return _convex_polygon(draw, centre + offset)


def _boundary_points(region: Region | None, count: int, draw: st.DrawFn) -> list[FloatArray]:
    """Points exactly on the region's boundary: vertices, edge points, the disk's rim."""
    if region is None:
        return []
    out: list[FloatArray] = []
    for _ in range(count):
        if isinstance(region, Disk):
            a = draw(st.sampled_from([0.0, math.pi / 2]) | st.floats(0.0, 2.0 * math.pi))
            out.append(region.center_xy + region.radius_m * np.array([math.cos(a), math.sin(a)]))
        else:
            v = region.vertices_xy
            i = draw(st.integers(0, v.shape[0] - 1))
            t = draw(st.sampled_from([0.0, 0.5]) | st.floats(0.0, 1.0))
            out.append(v[i] + t * (v[(i + 1) % v.shape[0]] - v[i]))
    return out


@st.composite
def measurement_sets(draw: st.DrawFn, region: Region | None, sensor_xy: FloatArray) -> FloatArray:
    """0-30 measurements: in the world, far outside it, on the region's edge, near the sensor,
    and repeats of earlier ones."""
    n = draw(st.integers(0, 30))
    points: list[FloatArray] = []
    for _ in range(n):
        kind = draw(st.sampled_from(["world", "world", "far", "edge", "sensor", "duplicate"]))
        if kind == "world":
            points.append(np.array([draw(st.floats(0.0, WORLD_M)) for _ in range(2)]))
        elif kind == "far":
            points.append(np.array([draw(st.floats(-1e9, 1e9)) for _ in range(2)]))
        elif kind == "edge" and region is not None:
            points += _boundary_points(region, 1, draw)
        elif kind == "sensor" and np.all(np.isfinite(sensor_xy)):
            points.append(sensor_xy + np.array([draw(st.floats(-3.0, 3.0)) for _ in range(2)]))
        elif kind == "duplicate" and points:
            points.append(points[draw(st.integers(0, len(points) - 1))].copy())
    return np.array(points, dtype=np.float64).reshape(-1, 2)


def _dt(draw: st.DrawFn) -> float:
    """A time step: zero, tiny, ordinary, or a long gap (up to a day)."""
    return float(draw(st.sampled_from([0.0, 1.0, 1e-9, 3600.0]) | st.floats(0.0, 5.0)
                      | _log_uniform(10.0, 86400.0)))


@st.composite
def scans(draw: st.DrawFn, t_s: float) -> Scan:
    """One valid scan at t_s."""
    if draw(st.integers(0, 9)) == 0:
        sensor = np.array([math.nan, math.nan])  # no pose for this frame
    else:
        sensor = np.array([draw(st.floats(-50.0, WORLD_M + 50.0)) for _ in range(2)])
    centre = np.where(np.isfinite(sensor), sensor, WORLD_M / 2.0)
    region = draw(regions(centre))
    z = draw(measurement_sets(region, sensor))
    r_cov = draw(st.sampled_from([np.eye(2)]) | spd_2x2())
    return Scan(t_s, region, z, r_cov, sensor)


@st.composite
def scenarios(draw: st.DrawFn) -> tuple[SatParams, SatState, list[Scan]]:
    """Parameters, an initial state and 1-6 scans at non-decreasing times."""
    params = draw(sat_params_st())
    mix = draw(mixtures(params.linear_model.state_dim))
    t = draw(st.sampled_from([0.0, 1.7e9]))  # from zero, or a Unix-epoch-like clock
    state = initial_state(mix, t, params)
    sequence: list[Scan] = []
    for _ in range(draw(st.integers(1, 6))):
        t += _dt(draw)
        sequence.append(draw(scans(t)))
    return params, state, sequence


# ---------------------------------------------------------------------------------------------
# Invariants
# ---------------------------------------------------------------------------------------------


def _assert_spd(covs: FloatArray, what: str) -> None:
    """Every matrix finite, symmetric to round-off and positive definite: Cholesky succeeds,
    the correlation matrix D^-1/2 P D^-1/2 has eigenvalues > 0 (scale-free: a position variance
    of 1e7 m^2 next to a velocity variance of 1 m^2/s^2 is fine), and the position block has
    a positive determinant (the closed-form 2x2 formulas of the update divide by it)."""
    assert np.all(np.isfinite(covs)), f"{what}: non-finite covariance"
    if covs.shape[0] == 0:
        return
    scale = np.abs(covs).max(axis=(1, 2))
    asym = np.abs(covs - np.swapaxes(covs, 1, 2)).max(axis=(1, 2))
    assert np.all(asym <= 1e-9 * scale), f"{what}: asymmetric covariance"
    diag = np.diagonal(covs, axis1=1, axis2=2)
    assert np.all(diag > 0.0), f"{what}: variance <= 0"
    np.linalg.cholesky(covs)  # LinAlgError (a test failure) unless positive definite
    inv_sd = 1.0 / np.sqrt(diag)
    corr = covs * inv_sd[:, :, None] * inv_sd[:, None, :]
    assert np.all(np.linalg.eigvalsh(corr)[:, 0] > 0.0), f"{what}: eigenvalue <= 0"
    det = covs[:, 0, 0] * covs[:, 1, 1] - covs[:, 0, 1] * covs[:, 1, 0]
    assert np.all(det > 0.0), f"{what}: position block not positive definite"


def _check_state(state: SatState, params: SatParams, report: StepReport, scan: Scan) -> None:
    """The invariants every step must keep."""
    mix = state.mixture
    n, d = mix.size, params.linear_model.state_dim
    assert state.t_s == scan.t_s
    assert mix.weights.shape == (n,) and mix.means.shape == (n, d)
    assert mix.covs.shape == (n, d, d) and mix.labels.shape == (n,)
    assert np.all(np.isfinite(mix.weights)) and np.all(mix.weights >= 0.0)
    assert np.all(np.isfinite(mix.means))
    _assert_spd(mix.covs, "mixture")
    assert n <= params.max_components
    lmb = params.kind is FilterKind.LMB
    if lmb:  # a Bernoulli is one target: estimates are the Bernoullis with r > extract_weight
        assert report.estimates == int(np.count_nonzero(
            state.tracks.existence > params.extract_weight))
    else:
        assert report.estimates == int(
            np.maximum(np.floor(mix.weights[mix.weights > params.extract_weight] + 0.5), 1).sum()
        )
    assert report.blind == (scan.region is None or not np.all(np.isfinite(scan.sensor_xy)))

    tracks = state.tracks
    t = tracks.size
    w = params.tracks.window
    shapes = {
        "ids": (t,), "hits": (t,), "life": (t,), "confirmed": (t,), "born_t_s": (t,),
        "last_t_s": (t,), "seen_t_s": (t,), "score": (t,), "alone": (t,), "means": (t, d),
        "covs": (t, d, d), "win_t_s": (t, w),
        "win_xy": (t, w, 2), "win_count": (t,), "gp_mu": (t, 5), "gp_beta": (t, w, 2),
        "gp_ky_inv": (t, w, w),
    }
    for name, shape in shapes.items():
        assert getattr(tracks, name).shape == shape, name
    assert np.all(np.diff(tracks.ids) > 0), "track ids sorted and unique"
    assert np.all((tracks.ids >= 0) & (tracks.ids < tracks.next_id))
    assert np.all((tracks.win_count >= 0) & (tracks.win_count <= w))
    assert np.all((tracks.hits >= 0) & (tracks.hits <= tracks.life))
    assert np.all(~tracks.confirmed | (tracks.hits >= params.tracks.confirm_length)), (
        "a confirmed track has confirm_length detections"
    )
    if params.kind is FilterKind.GMPHD:
        assert np.all(~tracks.alone | tracks.confirmed), "only confirmed tracks coast alone"
    assert np.all(np.isfinite(tracks.score)), "track scores finite"
    assert np.all((tracks.existence >= 0.0) & (tracks.existence <= 1.0))
    assert np.all(tracks.born_t_s <= tracks.seen_t_s) and np.all(tracks.seen_t_s <= state.t_s)
    assert np.all(tracks.born_t_s <= tracks.last_t_s) and np.all(tracks.last_t_s <= state.t_s)
    for name in ("means", "win_xy", "gp_mu", "gp_beta", "gp_ky_inv"):
        assert np.all(np.isfinite(getattr(tracks, name))), name
    _assert_spd(tracks.covs, "tracks")
    labelled = mix.labels[mix.labels != NO_LABEL]
    assert np.all(np.isin(labelled, tracks.ids)), "every label is a live track"
    if not lmb:
        assert np.unique(labelled).size == labelled.size, "one component per track"
        return
    # The LMB: every component belongs to a Bernoulli, whose existence is its weight sum, and
    # the total existence is the expected number of targets.
    assert labelled.size == n, "every LMB component is labelled"
    r = np.array([mix.weights[mix.labels == i].sum() for i in tracks.ids])
    np.testing.assert_allclose(r, tracks.existence, rtol=1e-9, atol=1e-12)
    assert np.all(r <= params.tracks.max_existence * (1 + 1e-12))
    assert math.isclose(r.sum(), mix.total_weight, rel_tol=1e-9, abs_tol=1e-12)


# ---------------------------------------------------------------------------------------------
# The estimator
# ---------------------------------------------------------------------------------------------


@settings(FAST, max_examples=300)
@given(scenarios())
def test_step_keeps_the_state_sound_on_random_scans(
    case: tuple[SatParams, SatState, list[Scan]],
) -> None:
    params, state, sequence = case
    gp = GpPredictor(params.gp)
    for scan in sequence:
        state, report = step(state, scan, params, gp)
        _check_state(state, params, report, scan)


@settings(FAST, max_examples=50)
@given(sat_params_st(), st.data())
def test_a_long_run_keeps_the_state_sound_and_bounded(
    params: SatParams, data: st.DataObject
) -> None:
    """Twenty steps of one sensor sweeping the world over the same few targets."""
    state = initial_state(data.draw(mixtures(params.linear_model.state_dim)), 0.0, params)
    gp = GpPredictor(params.gp)
    targets = np.array([[20.0, 30.0], [75.0, 75.0], [120.0, 40.0]])
    t = 0.0
    for k in range(20):
        t += data.draw(st.sampled_from([1.0, 0.0, 0.5, 30.0]))
        sensor = np.array([7.5 * k, 75.0 + data.draw(st.floats(-40.0, 40.0))])
        region = Disk(sensor, data.draw(st.sampled_from([25.0, 5.0, 60.0])))
        seen = targets[region.contains(targets)]
        noise = np.array([[data.draw(st.floats(-1.0, 1.0)) for _ in range(2)] for _ in seen])
        clutter = data.draw(measurement_sets(region, sensor))[:3]
        z = np.vstack([seen + noise.reshape(-1, 2), clutter])
        scan = Scan(t, region, z, np.eye(2), sensor)
        state, report = step(state, scan, params, gp)
        _check_state(state, params, report, scan)


@settings(FAST, max_examples=100)
@given(st.sampled_from([2, 4]), st.data())
def test_detection_covariance_is_the_kalman_update_and_stays_positive_definite(
    dim: int, data: st.DataObject
) -> None:
    """The update's covariance, computed as R S^-1 P on the position rows, equals the textbook
    (I - K H) P where that is well conditioned, and stays positive definite where it is not
    (R a million times below P, or nearly singular)."""
    mix = data.draw(mixtures(dim))
    r_cov = data.draw(spd_2x2(lo=1e-6, hi=1e6, min_ratio=1e-8))
    found = detection(mix, np.full(mix.size, 0.9), np.array([[1.0, 2.0]]), r_cov, 1e-3, 0.0)
    _assert_spd(found.children.covs, "updated")
    h = np.eye(2, dim)
    for p, p_upd in zip(mix.covs, found.children.covs, strict=True):
        gain = p @ h.T @ np.linalg.inv(h @ p @ h.T + r_cov)
        textbook = (np.eye(dim) - gain @ h) @ p
        if np.linalg.cond(p) < 1e6 and np.linalg.cond(r_cov) < 1e6:
            scale = float(np.abs(p).max())
            np.testing.assert_allclose(p_upd, 0.5 * (textbook + textbook.T), rtol=1e-7,
                                       atol=1e-9 * scale)


# ----------------------------------------------------------------------- invalid scans: InputError


def _one_component_state(params: SatParams) -> SatState:
    d = params.linear_model.state_dim
    means = np.zeros((1, d))
    means[0, :2] = 10.0
    return initial_state(make_mixture([1.0], means, [np.eye(d)]), 5.0, params)


_GOOD = Scan(6.0, Disk(np.array([10.0, 10.0]), 20.0), np.array([[10.0, 11.0]]), np.eye(2),
             np.array([10.0, 10.0]))

_BAD_SCANS: dict[str, dict[str, Any]] = {
    "time before the state": {"t_s": 4.0},
    "NaN time": {"t_s": math.nan},
    "infinite time": {"t_s": math.inf},
    "time not a number": {"t_s": "6"},
    "time gap beyond 1e9 s": {"t_s": 5.0 + 2e9},
    "R negative definite": {"r_cov": -np.eye(2)},
    "R indefinite": {"r_cov": np.array([[1.0, 2.0], [2.0, 1.0]])},
    "R singular": {"r_cov": np.array([[1.0, 1.0], [1.0, 1.0]])},
    "R zero": {"r_cov": np.zeros((2, 2))},
    "R singular to working precision": {"r_cov": np.array([[1.0, 1.0 - 1e-14],
                                                           [1.0 - 1e-14, 1.0]])},
    "R underflowing": {"r_cov": 1e-200 * np.eye(2)},
    "R asymmetric": {"r_cov": np.array([[1.0, 0.5], [0.1, 1.0]])},
    "R NaN": {"r_cov": np.array([[1.0, math.nan], [math.nan, 1.0]])},
    "R infinite": {"r_cov": np.array([[math.inf, 0.0], [0.0, 1.0]])},
    "R overflowing": {"r_cov": 1e200 * np.eye(2)},
    "R 3x3": {"r_cov": np.eye(3)},
    "R scalar": {"r_cov": 1.0},
    "R not numbers": {"r_cov": [["a", "b"], ["c", "d"]]},
    "measurements (m, 3)": {"measurements_xy": np.zeros((2, 3))},
    "measurements flat": {"measurements_xy": np.zeros(4)},
    "measurements not numbers": {"measurements_xy": [["a", 1.0]]},
    "sensor of 3 numbers": {"sensor_xy": np.zeros(3)},
    "sensor scalar": {"sensor_xy": np.float64(1.0)},
    "sensor not numbers": {"sensor_xy": ["a", "b"]},
    "region not a region": {"region": "disk"},
}


@pytest.mark.parametrize("kind", list(FilterKind))
@pytest.mark.parametrize("push", ["paper", "moment"])
@pytest.mark.parametrize("bad", sorted(_BAD_SCANS))
def test_invalid_scans_raise_input_error(
    bad: str, push: Literal["paper", "moment"], kind: FilterKind
) -> None:
    spec = replace(_valid_spec(), push_mode=push, kind=kind)
    params = sat_params(spec, 0.9, 0.1, 1.0)
    state = _one_component_state(params)
    scan = replace(_GOOD, **_BAD_SCANS[bad])
    with pytest.raises(InputError):
        step(state, scan, params, GpPredictor(params.gp))
    step(state, _GOOD, params, GpPredictor(params.gp))  # the good scan itself is fine


def _valid_spec() -> FilterSpec:
    return FilterSpec(
        kind=FilterKind.GMPHD, p_survive=1.0, push_rule=True, push_band=(0.4, 0.6),
        push_mode="moment",
        extract_weight=0.5, confirm_length=3, prune_weight=1e-3, merge_distance=10.0,
        max_components=100, motion=MotionModel.GP, process_noise=0.01, birth_weight=1.0,
        birth="adaptive", linear_model="cp", velocity_variance=1.0, gp_sigma_f=2.0,
        gp_lengthscale=40.0, gp_sigma_n=0.3, gp_window=30, track_timeout=30.0,
        target_speed=0.3, manoeuvre_time=200.0, confirm_existence=0.99, drop_existence=0.1,
        coast_after=10.0,
    )


@settings(FAST)
@given(
    st.lists(st.tuples(st.sampled_from([math.nan, math.inf, -math.inf, 3.0]),
                       st.sampled_from([math.nan, 4.0, -math.inf])), min_size=1, max_size=10),
    st.integers(0, 5),
)
def test_non_finite_measurements_are_dropped_and_counted(
    bad: list[tuple[float, float]], good: int
) -> None:
    """NaN or infinite rows are not refused: they are dropped, and the report counts them."""
    params = sat_params(_valid_spec(), 0.9, 0.1, 1.0)
    state = _one_component_state(params)
    rows = [r for r in bad if not all(map(math.isfinite, r))]
    z = np.array(rows + [(10.0 + k, 10.0) for k in range(good)]).reshape(-1, 2)
    scan = replace(_GOOD, measurements_xy=z)
    after, report = step(state, scan, params, GpPredictor(params.gp))
    assert report.dropped_measurements == len(rows)
    _check_state(after, params, report, scan)


@pytest.mark.parametrize("radius", [1e-200, 1e-170, 1e-101, 1e101, 1e160, 1e300])
def test_disks_whose_area_is_out_of_range_are_refused(radius: float) -> None:
    with pytest.raises(InputError):
        Disk(np.zeros(2), radius)


@pytest.mark.parametrize("scale", [1e-200, 1e-101, 1e160, 1e300])
def test_polygons_whose_area_or_coordinates_are_out_of_range_are_refused(scale: float) -> None:
    with pytest.raises(InputError):
        ConvexPolygon(scale * np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]))


def test_a_mixture_of_the_wrong_dimension_is_refused() -> None:
    cv = sat_params(replace(_valid_spec(), linear_model="cv"), 0.9, 0.1, 1.0)
    flat = make_mixture([1.0], [[1.0, 1.0]], [np.eye(2)])
    with pytest.raises(InputError):
        initial_state(flat, 0.0, cv)
    cp = sat_params(_valid_spec(), 0.9, 0.1, 1.0)
    state = initial_state(flat, 0.0, cp)
    with pytest.raises(InputError):
        step(state, _GOOD, cv, GpPredictor(cv.gp))


@settings(FAST, max_examples=200)
@given(st.data())
def test_only_companion_errors_escape_a_step(data: st.DataObject) -> None:
    """Scans with any mix of wrong shapes, types and values: a step either succeeds (and keeps
    the state sound) or raises a CompanionError."""
    params = data.draw(sat_params_st())
    state = _one_component_state(params)
    junk = (st.none() | st.floats() | st.integers(-3, 3) | st.text(max_size=2)
            | st.lists(st.floats(), max_size=5)
            | st.lists(st.lists(st.floats(), max_size=3), max_size=4))
    fields = {
        "t_s": st.floats() | st.just(6.0),
        "region": st.none() | regions(np.array([10.0, 10.0])) | junk,
        "measurements_xy": junk | measurement_sets(None, np.array([10.0, 10.0])),
        "r_cov": junk | spd_2x2(),
        "sensor_xy": junk | st.just(np.array([10.0, 10.0])),
    }
    changed = data.draw(st.lists(st.sampled_from(sorted(fields)), min_size=1, unique=True))
    values: dict[str, Any] = {name: data.draw(fields[name]) for name in changed}
    scan = replace(_GOOD, **values)
    try:
        after, report = step(state, scan, params, GpPredictor(params.gp))
    except CompanionError:
        return
    _check_state(after, params, report, scan)


# ---------------------------------------------------------------------------------------------
# Metrics
# ---------------------------------------------------------------------------------------------

_coord = st.floats(-1e6, 1e6) | st.sampled_from([0.0, math.nan, math.inf])


def _points(n_max: int) -> st.SearchStrategy[FloatArray]:
    return st.lists(st.tuples(_coord, _coord), max_size=n_max).map(
        lambda rows: np.array(rows, dtype=np.float64).reshape(-1, 2)
    )


@settings(FAST, max_examples=300)
@given(_points(8), _points(8), st.floats(0.5, 20.0) | st.sampled_from([1.0, math.inf, math.nan]),
       st.floats(-1.0, 1e4) | st.sampled_from([math.nan, 100.0]))
def test_ospa_is_finite_in_zero_to_c_or_refuses(
    est: FloatArray, truth: FloatArray, p: float, c: float
) -> None:
    valid_input = (np.all(np.isfinite(est)) and np.all(np.isfinite(truth)) and math.isfinite(p)
                   and p >= 1.0 and math.isfinite(c) and c > 0.0)
    try:
        total, loc, card = ospa_components(est, truth, p, c)
    except InputError:
        assert not valid_input
        return
    assert valid_input
    for value in (total, loc, card):
        assert math.isfinite(value) and 0.0 <= value <= c * (1.0 + 1e-12)
    assert ospa(est, truth, p, c) == total


def _is_spd(c: FloatArray) -> bool:
    """Symmetric (to 1e-8 relative) and positive definite by Sylvester's criterion."""
    a, b, d = float(c[0, 0]), 0.5 * float(c[0, 1] + c[1, 0]), float(c[1, 1])
    symmetric = abs(float(c[0, 1] - c[1, 0])) <= 1e-8 * max(abs(a), abs(d))
    return symmetric and a > 0.0 and d - b * b / a > 0.0


@st.composite
def _track_covs(draw: st.DrawFn, n: int) -> FloatArray:
    covs = np.zeros((n, 2, 2))
    for i in range(n):
        kind = draw(st.sampled_from(["spd", "spd", "spd", "junk"]))
        if kind == "spd":
            covs[i] = draw(spd_2x2(lo=1e-6, hi=1e12, min_ratio=1e-12))
        else:
            covs[i] = np.array([[draw(_coord) for _ in range(2)] for _ in range(2)])
    return covs


@settings(FAST, max_examples=300)
@given(_points(6), st.data())
def test_mahalanobis_to_tracks_is_non_negative_or_refuses(
    truth: FloatArray, data: st.DataObject
) -> None:
    means = data.draw(_points(6))
    covs = data.draw(_track_covs(means.shape[0]))
    try:
        closest, second = mahalanobis_to_tracks(truth, means, covs)
    except InputError:
        finite = bool(np.all(np.isfinite(truth)) and np.all(np.isfinite(means))
                      and np.all(np.isfinite(covs)))
        # Refused although finite: then some covariance is not symmetric positive definite.
        assert not finite or not all(_is_spd(c) for c in covs)
        return
    m = truth.shape[0]
    assert closest.shape == (m,) and second.shape == (m,)
    for out in (closest, second):
        assert not np.any(np.isnan(out)) and np.all(out >= 0.0)
    assert np.all(closest <= second)
    # Finite where the tracks exist (coordinates <= 1e6 m, variances >= 1e-18 m^2: no overflow).
    assert np.all(np.isfinite(closest)) == (means.shape[0] >= 1 or m == 0)
    assert np.all(np.isfinite(second)) == (means.shape[0] >= 2 or m == 0)


# ---------------------------------------------------------------------------------------------
# Projection
# ---------------------------------------------------------------------------------------------

_UTM_CACHE: dict[int, Utm] = {}


def _utm_at(lat: float, lon: float) -> Utm:
    utm = Utm.at(lat, lon)
    return _UTM_CACHE.setdefault(utm.epsg, utm)


@st.composite
def unit_quaternions(draw: st.DrawFn) -> tuple[float, float, float, float]:
    """A uniformly random rotation, or level / upside-down / nearly so."""
    special = draw(st.sampled_from([None, None, None, (1.0, 0.0, 0.0, 0.0),
                                    (0.0, 1.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)]))
    if special is not None:
        return special
    g = np.array([draw(st.floats(-1.0, 1.0)) for _ in range(4)])
    norm = float(np.linalg.norm(g))
    if norm < 1e-3:
        return (1.0, 0.0, 0.0, 0.0)
    w, x, y, z = (float(c) for c in g / norm)
    return (w, x, y, z)


@st.composite
def cameras(draw: st.DrawFn) -> CameraModel:
    width = draw(st.sampled_from([640, 1280, 16]))
    height = draw(st.sampled_from([480, 720, 16]))
    dist = draw(st.sampled_from([(0.0,) * 5, (-0.12, 0.03, 0.001, -0.0015, 0.0)]))
    mount = (draw(st.floats(-30.0, 30.0)), draw(st.floats(-45.0, 45.0)),
             draw(st.floats(-180.0, 180.0)))
    return CameraModel.from_hfov(draw(st.floats(1.0, 170.0)), width, height, dist=dist,
                                 mount_rpy_deg=mount)


@settings(FAST, max_examples=200)
@given(cameras(), unit_quaternions(), st.floats(0.5, 200.0), st.floats(-70.0, 70.0),
       st.floats(-179.0, 179.0), st.data())
def test_projection_is_finite_or_flagged_invalid(
    camera: CameraModel, q: tuple[float, float, float, float], height_m: float, lat: float,
    lon: float, data: st.DataObject,
) -> None:
    pose = GeoPose(100.0, lat, lon, 400.0 + height_m, height_m, q)
    utm = _utm_at(lat, lon)
    w, h = camera.width_px, camera.height_px
    inside = st.tuples(st.floats(-0.5, w - 0.5), st.floats(-0.5, h - 0.5))
    outside = st.tuples(st.floats(-1e4, 1e4), st.floats(-1e4, 1e4))
    pixels = np.array(data.draw(st.lists(inside | outside, max_size=8)),
                      dtype=np.float64).reshape(-1, 2)
    max_range = data.draw(st.sampled_from([100.0, 1e4]) | st.floats(1.0, 1e3))
    sigma = data.draw(st.sampled_from([PoseUncertainty(), PoseUncertainty(0.0, 0.0, 0.0, 0.0)]))
    out = project_detections(camera, pose, pixels, utm, pixel_std_px=1.0, pose_sigma=sigma,
                             max_range_m=max_range)
    n = pixels.shape[0]
    assert out.xy_utm_m.shape == (n, 2) and out.cov_utm_m2.shape == (n, 2, 2)
    assert out.valid.shape == (n,) and out.valid.dtype == np.bool_
    ok = out.valid
    assert np.all(np.isfinite(out.xy_utm_m[ok])) and np.all(np.isfinite(out.cov_utm_m2[ok]))
    assert np.all(np.isnan(out.xy_utm_m[~ok])) and np.all(np.isnan(out.cov_utm_m2[~ok]))
    cov = out.cov_utm_m2[ok]
    assert np.allclose(cov, np.swapaxes(cov, 1, 2), rtol=0.0,
                       atol=1e-9 * max(1.0, float(np.abs(cov).max(initial=0.0))))
    if sigma.horizontal_m > 0.0 and ok.any():
        assert np.all(np.linalg.eigvalsh(cov)[:, 0] > 0.0)
    # A valid point lies within max_range of the camera (UTM scale ~1.001, mount offset 0).
    if ok.any():
        reach = np.hypot(*(out.xy_utm_m[ok] - vehicle_utm(pose, utm)).T)
        assert np.all(reach <= 1.002 * max_range + 1e-6)


@settings(FAST, max_examples=40)
@given(unit_quaternions(), st.floats(0.5, 200.0),
       st.lists(st.tuples(st.sampled_from([math.nan, math.inf, 10.0]),
                          st.sampled_from([math.nan, 20.0])), min_size=1, max_size=4))
def test_projection_refuses_non_finite_pixels(
    q: tuple[float, float, float, float], height_m: float, rows: list[tuple[float, float]]
) -> None:
    bad = [r for r in rows if not all(map(math.isfinite, r))] or [(math.nan, 0.0)]
    pose = GeoPose(0.0, 47.4, 8.55, 500.0, height_m, q)
    with pytest.raises(InputError):
        project_detections(CameraModel.from_hfov(90.0), pose, np.array(bad), _utm_at(47.4, 8.55))
