"""Tests for companion.metrics: OSPA (hand cases, Stone Soup oracle, metric axioms) and
Mahalanobis distance to tracks (hand cases, per-pair loop oracle)."""

from __future__ import annotations

import datetime
import itertools
import math
from collections.abc import Iterator
from typing import Any

import numpy as np
import numpy.typing as npt
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.errors import InputError
from companion.metrics import (
    mahalanobis_to_tracks,
    ospa,
    ospa_components,
    summarize_mahalanobis,
)

FloatArray = npt.NDArray[np.float64]


def _pts(*xy: tuple[float, float]) -> FloatArray:
    return np.array(xy, dtype=np.float64).reshape(-1, 2)


# --------------------------------------------------------------------------- OSPA, hand cases


def test_ospa_identical_sets_is_zero() -> None:
    x = _pts((0.0, 0.0), (5.0, 1.0), (-3.0, 7.5))
    assert ospa(x, x[::-1], p=2, c=100) == 0.0
    assert ospa(x, x, p=1, c=10) == 0.0


@pytest.mark.parametrize("p", [1.0, 2.0, 3.0])
def test_ospa_one_to_one_shift_below_cutoff(p: float) -> None:
    truth = _pts((0.0, 0.0), (50.0, 0.0), (0.0, 50.0))
    est = truth + np.array([3.0, 0.0])  # every estimate 3 m east of its target, c = 100
    assert ospa(est, truth, p=p, c=100) == pytest.approx(3.0, abs=1e-12)


def test_ospa_shift_beyond_cutoff_saturates_at_c() -> None:
    truth = _pts((0.0, 0.0), (500.0, 0.0))
    assert ospa(truth + 30.0, truth, p=2, c=10) == pytest.approx(10.0, abs=1e-12)


def test_ospa_one_missing_of_ten_is_pure_cardinality_error() -> None:
    rng = np.random.default_rng(7)
    truth = rng.uniform(0.0, 150.0, size=(10, 2))
    est = truth[1:]  # one of ten missing, the other nine exact
    expected = math.sqrt(100.0**2 * 1 / 10)  # (c^p (n - m) / n)^(1/p)
    assert ospa(est, truth, p=2, c=100) == pytest.approx(expected, abs=1e-12)
    total, loc, card = ospa_components(est, truth, p=2, c=100)
    assert total == pytest.approx(expected, abs=1e-12)
    assert loc == 0.0
    assert card == pytest.approx(expected, abs=1e-12)


def test_ospa_both_empty_is_zero() -> None:
    empty = np.empty((0, 2))
    assert ospa(empty, empty, p=2, c=100) == 0.0
    assert ospa_components(empty, empty, p=2, c=100) == (0.0, 0.0, 0.0)


def test_ospa_exactly_one_empty_is_c() -> None:
    empty = np.empty((0, 2))
    pts = _pts((1.0, 2.0), (3.0, 4.0))
    assert ospa(empty, pts, p=2, c=100) == 100.0
    assert ospa(pts, empty, p=1, c=10) == 10.0
    assert ospa_components(pts, empty, p=2, c=100) == (100.0, 0.0, 100.0)


def test_ospa_assigns_on_d_power_p_not_on_d() -> None:
    # Pairing (A-C, B-D) has distances (0, 10): sum 10, sum of squares 100.
    # Pairing (A-D, B-C) has distances (6, 6):  sum 12, sum of squares 72.
    # So p = 1 picks the first (OSPA 10/2) and p = 2 the second (OSPA sqrt(72/2) = 6).
    est = _pts((0.0, 0.0), (6.0, 0.0))  # A, B
    truth = _pts((0.0, 0.0), (-7.0 / 3.0, math.sqrt(275.0) / 3.0))  # C = A, D
    assert ospa(est, truth, p=1, c=100) == pytest.approx(5.0, abs=1e-12)
    assert ospa(est, truth, p=2, c=100) == pytest.approx(6.0, abs=1e-12)


def test_ospa_components_total_matches_ospa_and_adds_in_pth_power() -> None:
    rng = np.random.default_rng(3)
    for _ in range(50):
        est = rng.uniform(0.0, 80.0, size=(int(rng.integers(0, 8)), 2))
        truth = rng.uniform(0.0, 80.0, size=(int(rng.integers(0, 8)), 2))
        for p, c in [(1.0, 10.0), (2.0, 100.0), (2.5, 30.0)]:
            total, loc, card = ospa_components(est, truth, p, c)
            assert total == ospa(est, truth, p, c)
            assert total**p == pytest.approx(loc**p + card**p, rel=1e-12, abs=1e-12)


def test_ospa_does_not_mutate_inputs() -> None:
    est = _pts((1.0, 2.0), (30.0, 4.0))
    truth = _pts((1.5, 2.0))
    est0, truth0 = est.copy(), truth.copy()
    ospa_components(est, truth, p=2, c=100)
    np.testing.assert_array_equal(est, est0)
    np.testing.assert_array_equal(truth, truth0)


@pytest.mark.parametrize(
    ("p", "c"),
    [
        (0.5, 100.0),
        (0.0, 100.0),
        (math.nan, 100.0),
        (math.inf, 100.0),
        (2.0, 0.0),
        (2.0, -1.0),
        (2.0, math.nan),
        (2.0, math.inf),
    ],
)
def test_ospa_rejects_bad_order_or_cutoff(p: float, c: float) -> None:
    with pytest.raises(InputError, match=r"OSPA (order p|cut-off c)"):
        ospa(_pts((0.0, 0.0)), _pts((1.0, 1.0)), p=p, c=c)


@pytest.mark.parametrize(
    "bad",
    [
        np.array([[0.0, math.nan]]),
        np.array([[math.inf, 0.0]]),
        np.zeros((2, 3)),
        np.zeros(3),
        np.zeros((1, 2, 2)),
        [["a", "b"]],
    ],
)
def test_ospa_rejects_bad_points(bad: Any) -> None:
    with pytest.raises(InputError, match="estimates_xy"):
        ospa(bad, _pts((1.0, 1.0)), p=2, c=100)
    with pytest.raises(InputError, match="truth_xy"):
        ospa(_pts((1.0, 1.0)), bad, p=2, c=100)


# ------------------------------------------------------------ OSPA against Stone Soup 1.9.1

_T0 = datetime.datetime(2024, 1, 1)


def _stonesoup_states(est: FloatArray, truth: FloatArray) -> tuple[list[Any], list[Any]]:
    state_mod = pytest.importorskip("stonesoup.types.state")
    gt_mod = pytest.importorskip("stonesoup.types.groundtruth")
    tracks = [state_mod.State(x.reshape(2, 1), timestamp=_T0) for x in est]
    truths = [gt_mod.GroundTruthState(y.reshape(2, 1), timestamp=_T0) for y in truth]
    return tracks, truths


def _random_sets(seed: int) -> list[tuple[FloatArray, FloatArray]]:
    """Seeded random pairs of sets with sizes 0..12 (never both empty: Stone Soup needs a
    timestamp from at least one state), spread so that some distances exceed c = 10."""
    rng = np.random.default_rng(seed)
    cases: list[tuple[FloatArray, FloatArray]] = []
    while len(cases) < 150:
        n, m = (int(k) for k in rng.integers(0, 13, size=2))
        if n == m == 0:
            continue
        cases.append((rng.uniform(0.0, 60.0, (n, 2)), rng.uniform(0.0, 60.0, (m, 2))))
    return cases


_Case = tuple[Any, FloatArray, FloatArray, list[Any], list[Any]]


def _reference_cases(p: float, c: float, seed: int) -> Iterator[_Case]:
    """(reference metric, est, truth, its tracks, its truths) for each random pair of sets;
    skips the test when the reference is not installed."""
    ospametric = pytest.importorskip("stonesoup.metricgenerator.ospametric")
    metric = ospametric.OSPAMetric(p=p, c=c)
    for est, truth in _random_sets(seed=seed):
        tracks, truths = _stonesoup_states(est, truth)
        yield metric, est, truth, tracks, truths


@pytest.mark.parametrize("c", [10.0, 100.0])
def test_ospa_matches_stonesoup_ospa_metric_p1(c: float) -> None:
    for metric, est, truth, tracks, truths in _reference_cases(1, c, seed=11):
        expected = metric.compute_OSPA_distance(tracks, truths).value
        assert ospa(est, truth, p=1, c=c) == pytest.approx(expected, abs=1e-9)


@pytest.mark.parametrize("p", [1.0, 2.0])
@pytest.mark.parametrize("c", [10.0, 100.0])
def test_ospa_matches_stonesoup_gospa_alpha2(p: float, c: float) -> None:
    # Stone Soup's GOSPA (alpha = 2) solves the assignment on min(d, c)^p, and
    # GOSPA^p = min_pi sum min(d, c)^p + (c^p / 2)(n - m), so
    # OSPA = ((GOSPA^p + (c^p / 2)(n - m)) / n)^(1/p) with n >= m the set sizes.
    for metric, est, truth, tracks, truths in _reference_cases(p, c, seed=12):
        gospa = metric.compute_gospa_metric(tracks, truths)[0].value["distance"]
        n, m = max(len(est), len(truth)), min(len(est), len(truth))
        expected = ((gospa**p + c**p / 2.0 * (n - m)) / n) ** (1.0 / p)
        assert ospa(est, truth, p=p, c=c) == pytest.approx(expected, abs=1e-9)


@pytest.mark.parametrize("c", [10.0, 100.0])
def test_ospa_never_exceeds_stonesoup_ospa_distance_p2(c: float) -> None:
    # Stone Soup 1.9.1's compute_OSPA_distance assigns on min(d, c) rather than min(d, c)^p,
    # so for p > 1 it can return more than the optimum; ours is the optimum, never above it.
    for metric, est, truth, tracks, truths in _reference_cases(2, c, seed=13):
        upper = metric.compute_OSPA_distance(tracks, truths).value
        assert ospa(est, truth, p=2, c=c) <= upper + 1e-9


# ----------------------------------------------------------------- OSPA, metric properties

_coord = st.floats(min_value=-60.0, max_value=60.0, allow_nan=False, allow_subnormal=False)
_point_set = st.lists(st.tuples(_coord, _coord), min_size=0, max_size=5).map(
    lambda pts: np.array(pts, dtype=np.float64).reshape(-1, 2)
)
_order = st.sampled_from([1.0, 2.0, 3.5])
_cutoff = st.floats(min_value=1.0, max_value=200.0)


def _equal_within(x: FloatArray, y: FloatArray, tol_m: float) -> bool:
    """Brute force: same size and some pairing puts every point within tol_m of its mate."""
    if len(x) != len(y):
        return False
    return any(
        bool(np.all(np.hypot(*(x - y[list(perm)]).T) <= tol_m))
        for perm in itertools.permutations(range(len(y)))
    )


@settings(deadline=None, max_examples=150)
@given(x=_point_set, y=_point_set, p=_order, c=_cutoff)
def test_ospa_symmetric_nonnegative_bounded(
    x: FloatArray, y: FloatArray, p: float, c: float
) -> None:
    d_xy = ospa(x, y, p, c)
    assert d_xy == pytest.approx(ospa(y, x, p, c), abs=1e-12)
    assert 0.0 <= d_xy <= c * (1.0 + 1e-12)


@settings(deadline=None, max_examples=150)
@given(x=_point_set, y=_point_set, p=_order, c=_cutoff)
def test_ospa_zero_iff_sets_equal(x: FloatArray, y: FloatArray, p: float, c: float) -> None:
    if ospa(x, y, p, c) <= 1e-12:
        assert _equal_within(x, y, tol_m=1e-9)
    if _equal_within(x, y, tol_m=0.0):
        assert ospa(x, y, p, c) == 0.0


@settings(deadline=None, max_examples=100)
@given(x=_point_set, data=st.data(), p=_order, c=_cutoff)
def test_ospa_zero_on_permutation_positive_after_move(
    x: FloatArray, data: st.DataObject, p: float, c: float
) -> None:
    perm = data.draw(st.permutations(list(range(len(x)))))
    y = x[perm]
    assert ospa(x, y, p, c) == 0.0
    if len(x):
        y_moved = y.copy()
        y_moved[0, 0] += data.draw(st.floats(min_value=1e-3, max_value=100.0))
        assert ospa(x, y_moved, p, c) > 0.0


@settings(deadline=None, max_examples=200)
@given(x=_point_set, y=_point_set, z=_point_set, p=_order, c=_cutoff)
def test_ospa_triangle_inequality(
    x: FloatArray, y: FloatArray, z: FloatArray, p: float, c: float
) -> None:
    assert ospa(x, z, p, c) <= ospa(x, y, p, c) + ospa(y, z, p, c) + 1e-9


# ------------------------------------------------------------------------- Mahalanobis


def test_mahalanobis_diagonal_and_correlated_by_hand() -> None:
    truth = _pts((2.0, 3.0), (11.0, 11.0), (9.0, 11.0))
    means = _pts((0.0, 0.0), (10.0, 10.0))
    covs = np.array(
        [
            [[4.0, 0.0], [0.0, 9.0]],  # diagonal: P^-1 = diag(1/4, 1/9)
            [[2.0, 1.0], [1.0, 2.0]],  # correlated: P^-1 = [[2, -1], [-1, 2]] / 3
        ]
    )
    closest, second = mahalanobis_to_tracks(truth, means, covs)
    # target 0: to track 0, d = (2, 3): 4/4 + 9/9 = 2; to track 1, d = (-8, -7):
    #   (2*64 - 2*56 + 2*49) / 3 = 38.
    # target 1: to track 1, d = (1, 1): (2 - 2 + 2) / 3 = 2/3; to track 0, d = (11, 11):
    #   121/4 + 121/9.
    # target 2: to track 1, d = (-1, 1): (2 + 2 + 2) / 3 = 2; to track 0, d = (9, 11):
    #   81/4 + 121/9.
    np.testing.assert_allclose(closest, np.sqrt([2.0, 2.0 / 3.0, 2.0]), rtol=1e-14)
    np.testing.assert_allclose(
        second, np.sqrt([38.0, 121 / 4 + 121 / 9, 81 / 4 + 121 / 9]), rtol=1e-14
    )


def test_mahalanobis_uses_the_track_covariance() -> None:
    # The same 3 m offset is 3 sigma for a 1 m^2 track and 1 sigma for a 9 m^2 track.
    truth = _pts((0.0, 0.0))
    means = _pts((3.0, 0.0), (0.0, -3.0))
    covs = np.array([np.eye(2), 9.0 * np.eye(2)])
    closest, second = mahalanobis_to_tracks(truth, means, covs)
    np.testing.assert_allclose(closest, [1.0], rtol=1e-15)
    np.testing.assert_allclose(second, [3.0], rtol=1e-15)


def test_mahalanobis_missing_tracks_give_inf() -> None:
    truth = _pts((0.0, 0.0), (1.0, 1.0))
    closest, second = mahalanobis_to_tracks(truth, np.empty((0, 2)), np.empty((0, 2, 2)))
    assert closest.shape == second.shape == (2,)
    assert np.all(np.isinf(closest)) and np.all(np.isinf(second))

    closest, second = mahalanobis_to_tracks(truth, _pts((0.0, 0.0)), 4.0 * np.eye(2)[None])
    np.testing.assert_allclose(closest, [0.0, math.sqrt(2.0) / 2.0], rtol=1e-15)
    assert np.all(np.isposinf(second))


def test_mahalanobis_no_targets_gives_empty() -> None:
    closest, second = mahalanobis_to_tracks(np.empty((0, 2)), _pts((0.0, 0.0)), np.eye(2)[None])
    assert closest.shape == second.shape == (0,)


def test_mahalanobis_matches_per_pair_inverse_loop() -> None:
    rng = np.random.default_rng(42)
    for n_targets, n_tracks in [(1, 1), (10, 2), (7, 9), (25, 40)]:
        truth = rng.uniform(0.0, 150.0, size=(n_targets, 2))
        means = rng.uniform(0.0, 150.0, size=(n_tracks, 2))
        a = rng.normal(size=(n_tracks, 2, 2)) * rng.uniform(0.5, 8.0, size=(n_tracks, 1, 1))
        covs = a @ a.transpose(0, 2, 1) + 0.1 * np.eye(2)
        truth0, means0, covs0 = truth.copy(), means.copy(), covs.copy()
        closest, second = mahalanobis_to_tracks(truth, means, covs)

        dist = np.empty((n_targets, n_tracks))
        for i in range(n_targets):
            for j in range(n_tracks):
                d = truth[i] - means[j]
                dist[i, j] = math.sqrt(d @ np.linalg.inv(covs[j]) @ d)
        ordered = np.sort(dist, axis=1)
        np.testing.assert_allclose(closest, ordered[:, 0], rtol=1e-10)
        if n_tracks >= 2:
            np.testing.assert_allclose(second, ordered[:, 1], rtol=1e-10)
        else:
            assert np.all(np.isposinf(second))
        assert np.all(closest <= second)
        np.testing.assert_array_equal(truth, truth0)
        np.testing.assert_array_equal(means, means0)
        np.testing.assert_array_equal(covs, covs0)


@pytest.mark.parametrize(
    ("cov", "match"),
    [
        ([[1.0, 2.0], [2.0, 1.0]], "not positive definite"),  # indefinite, det = -3
        ([[1.0, 1.0], [1.0, 1.0]], "not positive definite"),  # singular
        ([[0.0, 0.0], [0.0, 1.0]], "not positive definite"),
        ([[-1.0, 0.0], [0.0, -1.0]], "not positive definite"),
        ([[1.0, 0.5], [0.0, 1.0]], "not symmetric"),
        ([[1.0, math.nan], [math.nan, 1.0]], "NaN or infinite"),
    ],
)
def test_mahalanobis_rejects_bad_covariance(cov: list[list[float]], match: str) -> None:
    covs = np.array([np.eye(2), cov])
    with pytest.raises(InputError, match=match):
        mahalanobis_to_tracks(_pts((0.0, 0.0)), _pts((1.0, 1.0), (2.0, 2.0)), covs)


def test_mahalanobis_rejects_mismatched_shapes() -> None:
    with pytest.raises(InputError, match="track_covs_xy"):
        mahalanobis_to_tracks(_pts((0.0, 0.0)), _pts((1.0, 1.0), (2.0, 2.0)), np.eye(2)[None])
    with pytest.raises(InputError, match="truth_xy"):
        mahalanobis_to_tracks(np.zeros((2, 3)), _pts((1.0, 1.0)), np.eye(2)[None])


# ------------------------------------------------------------------- summary over targets


def test_summarize_mahalanobis_by_hand() -> None:
    summary = summarize_mahalanobis(np.array([1.0, 3.0]), np.array([4.0, 8.0]))
    assert summary == {
        "mahal_closest_mean": 2.0,
        "mahal_closest_std": 1.0,  # population std (ddof = 0); ddof = 1 would give sqrt(2)
        "mahal_second_mean": 6.0,
    }


def test_summarize_mahalanobis_inf_propagates_per_value() -> None:
    summary = summarize_mahalanobis(np.array([1.0, 3.0]), np.array([4.0, math.inf]))
    assert summary["mahal_closest_mean"] == 2.0
    assert summary["mahal_closest_std"] == 1.0
    assert summary["mahal_second_mean"] == math.inf

    summary = summarize_mahalanobis(np.array([math.inf, 3.0]), np.array([math.inf, 5.0]))
    assert summary == {
        "mahal_closest_mean": math.inf,
        "mahal_closest_std": math.inf,
        "mahal_second_mean": math.inf,
    }


def test_summarize_mahalanobis_no_targets_is_nan() -> None:
    summary = summarize_mahalanobis(np.empty(0), np.empty(0))
    assert set(summary) == {"mahal_closest_mean", "mahal_closest_std", "mahal_second_mean"}
    assert all(math.isnan(v) for v in summary.values())


def test_summarize_mahalanobis_end_to_end_with_missing_track() -> None:
    truth = _pts((0.0, 0.0), (3.0, 4.0))
    closest, second = mahalanobis_to_tracks(truth, _pts((0.0, 0.0)), np.eye(2)[None])
    summary = summarize_mahalanobis(closest, second)
    assert summary["mahal_closest_mean"] == pytest.approx(2.5)
    assert summary["mahal_closest_std"] == pytest.approx(2.5)
    assert summary["mahal_second_mean"] == math.inf


@pytest.mark.parametrize(
    ("closest", "second", "match"),
    [
        ([1.0, math.nan], [2.0, 3.0], "closest"),
        ([1.0, 2.0], [-1.0, 3.0], "second"),
        ([1.0, 2.0], [2.0], "differ in length"),
        ([[1.0]], [[2.0]], "1-D"),
    ],
)
def test_summarize_mahalanobis_rejects_bad_input(
    closest: list[Any], second: list[Any], match: str
) -> None:
    with pytest.raises(InputError, match=match):
        summarize_mahalanobis(np.array(closest), np.array(second))
