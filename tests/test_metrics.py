"""Tests for companion.metrics: OSPA and GOSPA (hand cases, Stone Soup oracle, metric axioms)
and Mahalanobis distance to tracks (hand cases, per-pair loop oracle)."""

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
    gospa_assignment,
    gospa_components,
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


# ------------------------------------------------------------------------ GOSPA, hand cases


@pytest.mark.parametrize("p", [1.0, 2.0])
def test_gospa_both_empty_is_zero(p: float) -> None:
    empty = np.empty((0, 2))
    assert gospa_components(empty, empty, c=10.0, p=p) == (0.0, 0.0, 0, 0)
    g = gospa_assignment(empty, empty, c=10.0, p=p)
    assert g.estimate_idx.size == g.truth_idx.size == 0


@pytest.mark.parametrize("p", [1.0, 2.0])
def test_gospa_one_empty_counts_every_point(p: float) -> None:
    empty = np.empty((0, 2))
    three = _pts((0.0, 0.0), (1.0, 0.0), (50.0, 50.0))
    expected = (10.0**p / 2.0 * 3) ** (1.0 / p)  # (c^p / 2 * 3)^(1/p)
    total, loc, missed, false = gospa_components(empty, three, c=10.0, p=p)
    assert (loc, missed, false) == (0.0, 3, 0)
    assert total == pytest.approx(expected, rel=1e-15)
    total, loc, missed, false = gospa_components(three, empty, c=10.0, p=p)
    assert (loc, missed, false) == (0.0, 0, 3)
    assert total == pytest.approx(expected, rel=1e-15)


def test_gospa_one_missed_target_p2() -> None:
    truth = _pts((0.0, 0.0), (40.0, 0.0))
    est = _pts((3.0, 4.0))  # 5 m from the first target; the second is missed
    total, loc, missed, false = gospa_components(est, truth, c=10.0, p=2.0)
    assert loc == pytest.approx(5.0, rel=1e-15)
    assert (missed, false) == (1, 0)
    assert total == pytest.approx(math.sqrt(25.0 + 100.0 / 2.0), rel=1e-15)


def test_gospa_one_false_estimate_p1() -> None:
    truth = _pts((0.0, 0.0))
    est = _pts((0.0, 2.0), (30.0, 30.0))  # 2 m from the target, and one false
    total, loc, missed, false = gospa_components(est, truth, c=10.0, p=1.0)
    assert loc == pytest.approx(2.0, rel=1e-15)
    assert (missed, false) == (0, 1)
    assert total == pytest.approx(2.0 + 10.0 / 2.0, rel=1e-15)
    g = gospa_assignment(est, truth, c=10.0, p=1.0)
    assert g.estimate_idx.tolist() == [0] and g.truth_idx.tolist() == [0]


@pytest.mark.parametrize("p", [1.0, 2.0])
def test_gospa_pair_at_or_beyond_cutoff_is_one_missed_and_one_false(p: float) -> None:
    truth = _pts((0.0, 0.0))
    for dist_m in (10.0, 12.0, 1000.0):  # d >= c: not a localisation error
        total, loc, missed, false = gospa_components(_pts((dist_m, 0.0)), truth, c=10.0, p=p)
        assert (loc, missed, false) == (0.0, 1, 1)
        assert total == pytest.approx(10.0, rel=1e-15)  # (c^p / 2 * 2)^(1/p) = c
        g = gospa_assignment(_pts((dist_m, 0.0)), truth, c=10.0, p=p)
        assert g.estimate_idx.size == g.truth_idx.size == 0
    total, loc, missed, false = gospa_components(_pts((9.0, 0.0)), truth, c=10.0, p=p)
    assert (missed, false) == (0, 0)
    assert loc == pytest.approx(9.0, rel=1e-15) and total == pytest.approx(9.0, rel=1e-15)


def test_gospa_assigns_on_d_power_p_and_reports_pairs_in_truth_order() -> None:
    # As in the OSPA case: p = 1 pairs (A-C, B-D) at (0, 10), p = 2 pairs (A-D, B-C) at (6, 6).
    est = _pts((0.0, 0.0), (6.0, 0.0))  # A, B
    truth = _pts((0.0, 0.0), (-7.0 / 3.0, math.sqrt(275.0) / 3.0))  # C = A, D
    g1 = gospa_assignment(est, truth, c=100.0, p=1.0)
    assert (g1.estimate_idx.tolist(), g1.truth_idx.tolist()) == ([0, 1], [0, 1])
    assert g1.total_m == pytest.approx(10.0, abs=1e-12)
    g2 = gospa_assignment(est, truth, c=100.0, p=2.0)
    assert (g2.estimate_idx.tolist(), g2.truth_idx.tolist()) == ([1, 0], [0, 1])
    assert g2.total_m == pytest.approx(math.sqrt(72.0), abs=1e-12)
    assert g2.localisation_m == g2.total_m


def test_gospa_default_order_is_2_and_inputs_are_not_mutated() -> None:
    est = _pts((1.0, 2.0), (30.0, 4.0))
    truth = _pts((1.5, 2.0))
    est0, truth0 = est.copy(), truth.copy()
    assert gospa_components(est, truth, 10.0) == gospa_components(est, truth, 10.0, p=2.0)
    np.testing.assert_array_equal(est, est0)
    np.testing.assert_array_equal(truth, truth0)


@pytest.mark.parametrize(
    ("p", "c"),
    [(0.5, 10.0), (math.nan, 10.0), (math.inf, 10.0), (2.0, 0.0), (2.0, -1.0), (2.0, math.inf)],
)
def test_gospa_rejects_bad_order_or_cutoff(p: float, c: float) -> None:
    with pytest.raises(InputError, match=r"GOSPA (order p|cut-off c)"):
        gospa_components(_pts((0.0, 0.0)), _pts((1.0, 1.0)), c=c, p=p)


@pytest.mark.parametrize(
    "bad",
    [np.array([[0.0, math.nan]]), np.array([[math.inf, 0.0]]), np.zeros((2, 3)), np.zeros(3),
     [["a", "b"]]],
)
def test_gospa_rejects_bad_points(bad: Any) -> None:
    with pytest.raises(InputError, match="estimates_xy"):
        gospa_components(bad, _pts((1.0, 1.0)), c=10.0)
    with pytest.raises(InputError, match="truth_xy"):
        gospa_assignment(_pts((1.0, 1.0)), bad, c=10.0)


# ----------------------------------------------------------- GOSPA against Stone Soup 1.9.1

# Stone Soup's GOSPAMetric (alpha = 2) reports its parts in the p-th power: localisation is
# sum d^p over the pairs with d < c, missed and false are the counts times c^p / 2.
GOSPA_REFERENCE_TOL = 1e-12  # measured: 4e-16 relative on the total, 3e-14 m on localisation


@pytest.mark.parametrize("p", [1.0, 2.0, 3.0])
@pytest.mark.parametrize("c", [5.0, 10.0, 40.0])
def test_gospa_matches_stonesoup_gospa_metric(p: float, c: float) -> None:
    ospametric = pytest.importorskip("stonesoup.metricgenerator.ospametric")
    metric = ospametric.GOSPAMetric(p=p, c=c)
    dummy = c**p / 2.0
    for est, truth in _random_sets(seed=int(10 * p + c)):
        tracks, truths = _stonesoup_states(est, truth)
        parts, _ = metric.compute_gospa_metric(tracks, truths)
        ref = parts.value
        total, loc, missed, false = gospa_components(est, truth, c=c, p=p)
        assert total == pytest.approx(ref["distance"], rel=GOSPA_REFERENCE_TOL)
        assert loc == pytest.approx(ref["localisation"] ** (1.0 / p), rel=GOSPA_REFERENCE_TOL,
                                    abs=GOSPA_REFERENCE_TOL)
        assert missed == pytest.approx(ref["missed"] / dummy, abs=1e-9)
        assert false == pytest.approx(ref["false"] / dummy, abs=1e-9)


# ---------------------------------------------------------------- GOSPA, metric properties


@settings(deadline=None, max_examples=150)
@given(x=_point_set, y=_point_set, p=_order, c=_cutoff)
def test_gospa_swapping_sets_swaps_missed_and_false(
    x: FloatArray, y: FloatArray, p: float, c: float
) -> None:
    total, loc, missed, false = gospa_components(x, y, c=c, p=p)
    total_r, loc_r, missed_r, false_r = gospa_components(y, x, c=c, p=p)
    assert total == pytest.approx(total_r, rel=1e-12, abs=1e-12)
    assert loc == pytest.approx(loc_r, rel=1e-12, abs=1e-12)
    assert (missed, false) == (false_r, missed_r)


@settings(deadline=None, max_examples=150)
@given(x=_point_set, y=_point_set, p=_order, c=_cutoff)
def test_gospa_parts_add_in_the_pth_power_and_pairs_lie_within_c(
    x: FloatArray, y: FloatArray, p: float, c: float
) -> None:
    g = gospa_assignment(x, y, c=c, p=p)
    assert g.total_m**p == pytest.approx(
        g.localisation_m**p + c**p / 2.0 * (g.missed + g.false), rel=1e-12, abs=1e-12
    )
    pairs = g.truth_idx.size
    assert g.estimate_idx.size == pairs == len(y) - g.missed == len(x) - g.false
    assert len(set(g.estimate_idx.tolist())) == len(set(g.truth_idx.tolist())) == pairs
    assert np.all(np.diff(g.truth_idx) > 0)
    dist_m = np.hypot(*(x[g.estimate_idx] - y[g.truth_idx]).T)
    assert np.all(dist_m < c)
    assert g.localisation_m == pytest.approx(float((dist_m**p).sum()) ** (1.0 / p), rel=1e-12)


@settings(deadline=None, max_examples=150)
@given(x=_point_set, y=_point_set, p=_order, c=_cutoff)
def test_gospa_relates_to_ospa(x: FloatArray, y: FloatArray, p: float, c: float) -> None:
    # With n >= m the set sizes: n OSPA^p = GOSPA^p + (c^p / 2)(n - m).
    n, m = max(len(x), len(y)), min(len(x), len(y))
    total = gospa_components(x, y, c=c, p=p)[0]
    assert n * ospa(x, y, p, c) ** p == pytest.approx(
        total**p + c**p / 2.0 * (n - m), rel=1e-9, abs=1e-9
    )


@settings(deadline=None, max_examples=100)
@given(x=_point_set, y=_point_set, z=_point_set, p=_order, c=_cutoff)
def test_gospa_triangle_inequality(
    x: FloatArray, y: FloatArray, z: FloatArray, p: float, c: float
) -> None:
    def d(a: FloatArray, b: FloatArray) -> float:
        return gospa_components(a, b, c=c, p=p)[0]

    assert d(x, z) <= d(x, y) + d(y, z) + 1e-9


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
