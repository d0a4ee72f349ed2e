"""Pruning and merging (Vo & Ma Table 2): hand cases and invariants."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.sat.extract import extract
from companion.sat.mixture import NO_LABEL, Mixture, make_mixture
from companion.sat.reduce import merge, prune


def _random_mixture(seed: int, n: int, spread: float) -> Mixture:
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(n, 2, 2))
    covs = a @ a.transpose(0, 2, 1) + 0.2 * np.eye(2)
    labels = rng.choice([NO_LABEL, 1, 2, 3], size=n)
    return make_mixture(rng.uniform(0.0, 2.0, n), rng.uniform(0, spread, (n, 2)), covs, labels)


def test_merge_by_hand() -> None:
    mix = make_mixture(
        [1.0, 0.5, 0.7],
        [[0.0, 0.0], [1.0, 0.0], [50.0, 0.0]],
        [np.eye(2), np.eye(2), np.eye(2)],
        [NO_LABEL, 4, NO_LABEL],
    )
    out = merge(mix, 10.0, 100)
    assert out.mixture.size == 2
    assert out.mixture.weights == pytest.approx([1.5, 0.7])
    mean = (1.0 * 0.0 + 0.5 * 1.0) / 1.5
    np.testing.assert_allclose(out.mixture.means[0], [mean, 0.0])
    spread = (1.0 * mean**2 + 0.5 * (1 - mean) ** 2) / 1.5
    np.testing.assert_allclose(out.mixture.covs[0], np.diag([1.0 + spread, 1.0]))
    assert out.mixture.labels.tolist() == [4, NO_LABEL]  # the only labelled member's label
    assert out.group_of.tolist() == [0, 0, 1]


def test_two_tracks_components_merge_only_when_both_were_just_detected() -> None:
    mix = make_mixture(
        [1.0, 0.5, 0.2], [[0.0, 0.0], [0.5, 0.0], [0.0, 0.5]], [np.eye(2)] * 3, [9, 3, NO_LABEL]
    )
    # Out of view, two tracks' components are two targets however close they are.
    assert sorted(merge(mix, 10.0, 100).mixture.labels.tolist()) == [3, 9]
    # Both updated by detections: one target seen twice; the older track (smaller id) lives on.
    out = merge(mix, 10.0, 100, detection=np.array([0, 0, -1])).mixture
    assert out.labels.tolist() == [3]
    assert out.total_weight == pytest.approx(1.7)


def test_just_detected_duplicates_merge_within_their_joint_uncertainty() -> None:
    # 1.9 m apart with P = 0.2 I each: d^2 = 18 under either P alone, 9 under their sum.
    mix = make_mixture([1.0, 0.8], [[0.0, 0.0], [1.9, 0.0]], [0.2 * np.eye(2)] * 2, [4, 7])
    assert merge(mix, 10.0, 100).mixture.size == 2
    assert merge(mix, 10.0, 100, detection=np.array([0, 0])).mixture.size == 1


def test_two_detections_of_one_scan_are_two_targets_unless_one_may_be_clutter() -> None:
    """Eq. one_detection: children of one parent updated by two detections 2.5 m apart sit
    0.4 m apart (the parent's gain is small), well inside each other's gate."""
    mix = make_mixture([1.0, 0.9], [[0.0, 0.0], [0.4, 0.0]], [0.2 * np.eye(2)] * 2, [5, 5])
    two = np.array([0, 1])
    # A parent counted as one target: the second detection may be clutter beside it; merged.
    assert merge(mix, 10.0, 100, detection=two).mixture.size == 1
    # A parent the PHD already counts as two targets: one per detection.
    split = merge(mix, 10.0, 100, detection=two, counts_two=np.array([True, True])).mixture
    assert split.size == 2
    assert split.labels.tolist() == [5, 5]  # the tracks sort the lineage out
    # Two tracks, each updated by its own detection: two targets, however close.
    tracks = make_mixture([1.0, 0.9], [[0.0, 0.0], [0.4, 0.0]], [0.2 * np.eye(2)] * 2, [5, 8])
    assert merge(tracks, 10.0, 100, detection=two).mixture.size == 2
    # Both updated by one detection: one target seen twice, as before.
    assert merge(tracks, 10.0, 100, detection=np.array([0, 0])).mixture.size == 1


def test_merge_uses_the_candidates_covariance_as_vo_and_ma() -> None:
    # d^2 from the leader (w = 1) to the candidate uses the candidate's P: 9/1 = 9 <= 10 merges,
    # while with the leader's own tighter P it would be 9/0.5 = 18.
    mix = make_mixture([1.0, 0.3], [[0.0, 0.0], [3.0, 0.0]], [0.5 * np.eye(2), np.eye(2)])
    assert merge(mix, 10.0, 100, symmetric=False).mixture.size == 1
    mix = make_mixture([1.0, 0.3], [[0.0, 0.0], [3.0, 0.0]], [np.eye(2), 0.5 * np.eye(2)])
    assert merge(mix, 10.0, 100, symmetric=False).mixture.size == 2


def test_symmetric_merge_keeps_a_wide_component_out_of_a_precise_one() -> None:
    # A wide belief (P = 50 I) 15 m from a well-localised target (P = 0.1 I): Vo & Ma's test
    # (225 / 50 = 4.5 <= 10) would merge them and blow the target's covariance up.
    mix = make_mixture([1.0, 0.5], [[0.0, 0.0], [15.0, 0.0]], [0.1 * np.eye(2), 50 * np.eye(2)])
    assert merge(mix, 10.0, 100, symmetric=False).mixture.size == 1
    out = merge(mix, 10.0, 100).mixture
    assert out.size == 2
    np.testing.assert_array_equal(out.covs[0], 0.1 * np.eye(2))


def test_cap_keeps_the_heaviest_groups() -> None:
    mix = make_mixture(
        [0.2, 0.9, 0.5, 0.7], [[0, 0], [100, 0], [200, 0], [300, 0]], [np.eye(2)] * 4
    )
    out = merge(mix, 10.0, 2)
    assert out.mixture.weights.tolist() == [0.9, 0.7]
    assert out.group_of.tolist() == [-1, 0, -1, 1]


def test_prune_drops_light_components() -> None:
    mix = make_mixture([1e-4, 0.5, 2e-3], [[0, 0], [1, 1], [2, 2]], [np.eye(2)] * 3)
    kept, mask = prune(mix, 1e-3)
    assert kept.weights.tolist() == [0.5, 2e-3]
    assert mask.tolist() == [False, True, True]


def test_extract_repeats_heavy_components() -> None:
    mix = make_mixture([0.4, 0.6, 1.6, 2.4], [[0, 0]] * 4, [np.eye(2)] * 4)
    assert extract(mix, 0.5).tolist() == [1, 2, 2, 3, 3]


@settings(deadline=None, max_examples=60)
@given(seed=st.integers(0, 10_000), n=st.integers(0, 40), spread=st.floats(1.0, 60.0))
def test_merge_preserves_weight_and_keeps_covariances_positive(
    seed: int, n: int, spread: float
) -> None:
    mix = _random_mixture(seed, n, spread)
    out = merge(mix, 10.0, 1000).mixture
    assert out.total_weight == pytest.approx(mix.total_weight, rel=1e-12, abs=1e-12)
    assert np.all(np.linalg.eigvalsh(out.covs) > 0)
    assert np.all(out.weights >= 0)


@settings(deadline=None, max_examples=60)
@given(seed=st.integers(0, 10_000), n=st.integers(0, 40), threshold=st.floats(0.0, 1.0))
def test_prune_accounts_for_every_unit_of_weight(seed: int, n: int, threshold: float) -> None:
    mix = _random_mixture(seed, n, 30.0)
    kept, mask = prune(mix, threshold)
    dropped = mix.weights[~mask].sum()
    assert kept.total_weight + dropped == pytest.approx(mix.total_weight)
    assert np.all(kept.weights > threshold)


@settings(deadline=None, max_examples=40)
@given(seed=st.integers(0, 10_000), n=st.integers(1, 30), cap=st.integers(1, 10))
def test_capped_merge_keeps_at_most_the_cap(seed: int, n: int, cap: int) -> None:
    mix = _random_mixture(seed, n, 200.0)
    out = merge(mix, 10.0, cap)
    assert out.mixture.size <= cap
    kept_weight = mix.weights[out.group_of >= 0].sum()
    assert out.mixture.total_weight == pytest.approx(kept_weight)
