"""The update with a limited FOV against hand-derived cases and a per-component reference."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import NDArray

from companion.sat.fov import ConvexPolygon, Disk
from companion.sat.mixture import make_mixture
from companion.sat.update import (
    PushMode,
    PushRule,
    Visibility,
    detection,
    no_detection,
    visibility,
)

FloatArray = NDArray[np.float64]
EVERYWHERE = Disk(np.zeros(2), 1e6)


def test_one_component_one_measurement_by_hand() -> None:
    mix = make_mixture([0.8], [[0.0, 0.0]], [2.0 * np.eye(2)], [7])
    z = np.array([[1.0, 0.0]])
    p_d = visibility(mix, EVERYWHERE, 0.9).p_d
    assert p_d == pytest.approx([0.9], abs=1e-12)

    missed = no_detection(mix, Visibility(p_d, 0.9), np.zeros(2), None)
    assert missed.weights == pytest.approx([0.08])
    np.testing.assert_array_equal(missed.means, mix.means)
    np.testing.assert_array_equal(missed.covs, mix.covs)

    found = detection(mix, p_d, z, np.eye(2), clutter_intensity=0.01, birth_intensity=0.0)
    q = np.exp(-0.5 / 3.0) / (2.0 * np.pi * 3.0)  # N(z; 0, S), S = P + R = 3 I
    assert found.explained == pytest.approx([0.9 * 0.8 * q])
    assert found.children.weights == pytest.approx([0.72 * q / (0.01 + 0.72 * q)])
    np.testing.assert_allclose(found.children.means, [[2.0 / 3.0, 0.0]], atol=1e-15)
    np.testing.assert_allclose(found.children.covs, [2.0 / 3.0 * np.eye(2)], atol=1e-15)
    assert found.children.labels.tolist() == [7]


def _reference_update(weights: FloatArray, means: FloatArray, covs: FloatArray, p_d: FloatArray,
                      zs: FloatArray, r: FloatArray, kappa: float
                      ) -> list[tuple[float, FloatArray, FloatArray]]:
    """Vo & Ma Table 1 steps 3-4, one component and one measurement at a time."""
    out: list[tuple[float, FloatArray, FloatArray]] = []
    for z in zs:
        terms = []
        for w, m, p, pd in zip(weights, means, covs, p_d, strict=True):
            s = p + r
            k = p @ np.linalg.inv(s)
            nu = z - m
            q = np.exp(-0.5 * nu @ np.linalg.solve(s, nu)) / (2 * np.pi * np.sqrt(np.linalg.det(s)))
            terms.append((pd * w * q, m + k @ nu, (np.eye(2) - k) @ p))
        total = kappa + sum(t[0] for t in terms)
        out += [(t[0] / total, t[1], t[2]) for t in terms]
    return out


def test_detection_matches_per_component_reference() -> None:
    rng = np.random.default_rng(3)
    n, m = 6, 4
    a = rng.normal(size=(n, 2, 2))
    covs = a @ a.transpose(0, 2, 1) + 0.5 * np.eye(2)
    means = rng.uniform(0, 20, size=(n, 2))
    weights = rng.uniform(0.1, 1.5, size=n)
    mix = make_mixture(weights, means, covs)
    zs = rng.uniform(0, 20, size=(m, 2))
    r = np.array([[1.0, 0.3], [0.3, 2.0]])
    p_d = rng.uniform(0.2, 1.0, size=n)
    found = detection(mix, p_d, zs, r, clutter_intensity=1e-3, birth_intensity=2e-3)
    ref = _reference_update(weights, means, covs, p_d, zs, r, 3e-3)
    np.testing.assert_allclose(found.children.weights, [x[0] for x in ref], rtol=1e-10)
    np.testing.assert_allclose(found.children.means, [x[1] for x in ref], rtol=1e-10)
    np.testing.assert_allclose(found.children.covs, [x[2] for x in ref], rtol=1e-10, atol=1e-12)


def test_unlimited_fov_and_certain_detection_is_the_standard_gm_phd() -> None:
    # p_D = 1 everywhere: nothing survives the no-detection event, and without clutter every
    # measurement's detection weights sum to one (Vo & Ma's update with kappa = 0).
    mix = make_mixture([1.0, 1.0], [[0.0, 0.0], [30.0, 0.0]], [np.eye(2), np.eye(2)])
    p_d = visibility(mix, EVERYWHERE, 1.0).p_d
    assert p_d == pytest.approx([1.0, 1.0])
    missed = no_detection(mix, Visibility(p_d, 0.9), np.zeros(2), PushRule())
    assert missed.weights == pytest.approx([0.0, 0.0])
    z = np.array([[0.5, 0.2], [29.0, 1.0]])
    found = detection(mix, p_d, z, np.eye(2), 0.0, 0.0)
    per_measurement = found.children.weights.reshape(2, 2).sum(axis=1)
    assert per_measurement == pytest.approx([1.0, 1.0])


def test_fov_limits_detection_probability() -> None:
    mix = make_mixture(
        [1.0, 1.0, 1.0], [[0.0, 0.0], [10.0, 0.0], [100.0, 0.0]], [np.eye(2)] * 3
    )
    p_d = visibility(mix, Disk(np.zeros(2), 10.0), 0.98).p_d
    assert p_d[0] == pytest.approx(0.98, abs=1e-9)
    assert 0.4 < p_d[1] < 0.5  # on the boundary: a little under half the mass is inside
    assert p_d[2] == pytest.approx(0.0, abs=1e-12)


def test_push_rule_moves_band_components_away_from_the_sensor() -> None:
    mix = make_mixture(
        [1.0, 1.0, 1.0], [[10.0, 0.0], [0.0, 3.0], [0.0, -30.0]], [np.eye(2)] * 3
    )
    sensor = np.zeros(2)
    p_d = np.array([0.5, 0.9, 0.45])
    pushed = no_detection(mix, Visibility(p_d, 0.9), sensor, PushRule(0.4, 0.6))
    # Eq. push: mu <- p_D (mu - y) + mu inside the band, unchanged outside it.
    np.testing.assert_allclose(pushed.means, [[15.0, 0.0], [0.0, 3.0], [0.0, -43.5]])
    np.testing.assert_allclose(pushed.weights, 1.0 - p_d)
    unpushed = no_detection(mix, Visibility(p_d, 0.9), sensor, None)
    assert unpushed.means.tolist() == mix.means.tolist()


HALF_PLANE = ConvexPolygon(np.array([[-1e3, -1e3], [0.0, -1e3], [0.0, 1e3], [-1e3, 1e3]]))


def test_moment_rule_is_the_truncated_normal_at_a_straight_edge() -> None:
    # The FOV covers x <= 0 and detects for sure: half of N(0, I) is seen empty; what is left is
    # the half-normal on x > 0, mean sqrt(2/pi), variance 1 - 2/pi.
    mix = make_mixture([1.0], [[0.0, 0.0]], [np.eye(2)])
    vis = visibility(mix, HALF_PLANE, 1.0, with_moments=True)
    assert vis.p_d == pytest.approx([0.5], abs=1e-12)
    missed = no_detection(mix, vis, np.array([-10.0, 0.0]), PushRule(mode=PushMode.MOMENT))
    assert missed.weights == pytest.approx([0.5])
    np.testing.assert_allclose(missed.means, [[np.sqrt(2.0 / np.pi), 0.0]], atol=1e-9)
    np.testing.assert_allclose(missed.covs, [np.diag([1.0 - 2.0 / np.pi, 1.0])], atol=1e-9)


def test_moment_rule_leaves_claimed_components_and_keeps_a_velocity_state_valid() -> None:
    covs = np.eye(4)
    covs[0, 2] = covs[2, 0] = covs[1, 3] = covs[3, 1] = 0.5  # position-velocity correlation
    mix = make_mixture([1.0, 1.0], [[0.0, 0.0, 1.0, 0.0]] * 2, [covs] * 2)
    vis = visibility(mix, HALF_PLANE, 0.98, with_moments=True)
    rule = PushRule(mode=PushMode.MOMENT)
    missed = no_detection(mix, vis, np.array([-10.0, 0.0]), rule, np.array([False, True]))
    assert missed.means[0, 0] > 0.5  # pushed out of the FOV
    np.testing.assert_array_equal(missed.means[1], mix.means[1])  # claimed: left in place
    np.testing.assert_array_equal(missed.means[0, 2:], [1.0, 0.0])  # velocity kept
    np.testing.assert_array_equal(missed.covs[0, :2, 2:], 0.0)
    assert np.all(np.linalg.eigvalsh(missed.covs) > 0.0)
