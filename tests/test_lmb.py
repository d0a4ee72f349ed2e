"""The labeled multi-Bernoulli filter: hand-derived updates, ranked assignment, and an
independent textbook LMB by full enumeration of the association hypotheses."""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, replace

import numpy as np
import pytest
from numpy.typing import NDArray
from scipy.stats import multivariate_normal

from companion.sat.filter import FilterKind, SatParams, SatState, Scan, initial_state, step
from companion.sat.fov import Disk, prob_in_region
from companion.sat.gp import GpPredictor
from companion.sat.hypotheses import EXACT_LIMIT, hypothesis_bound
from companion.sat.lmb import associate
from companion.sat.mixture import Mixture
from companion.sat.motion import TargetMotion
from companion.sat.tracks import TrackParams
from companion.sat.update import PushMode, PushRule
from companion.sim.battery import family_scenario
from companion.sim.run import simulate

FloatArray = NDArray[np.float64]
R = np.eye(2)


def _params(p_detect: float = 0.9, clutter: float = 0.5, **changes: object) -> SatParams:
    """The LMB with the linear model only (no GP, no process noise), stationary targets."""
    base = SatParams(
        kind=FilterKind.LMB, p_detect=p_detect, clutter_per_scan=clutter, use_gp=False,
        q_m2_per_s=0.0, push=PushRule(mode=PushMode.MOMENT),
        tracks=TrackParams(motion=TargetMotion(0.0, 200.0)),
    )
    return replace(base, **changes)  # type: ignore[arg-type]


def _one_bernoulli(r: float, mean: tuple[float, float], var: float, params: SatParams) -> SatState:
    mix = Mixture(np.array([r]), np.array([mean]), var * np.eye(2)[None], np.array([-1]))
    return initial_state(mix, 0.0, params)


def _step(state: SatState, region: Disk, z: FloatArray, params: SatParams) -> SatState:
    scan = Scan(state.t_s + 1.0, region, z.reshape(-1, 2), R, np.zeros(2))
    return step(state, scan, params, GpPredictor(params.gp))[0]


def _existence(state: SatState, track_id: int) -> float:
    return float(state.mixture.weights[state.mixture.labels == track_id].sum())


def test_one_bernoulli_one_measurement_full_view_is_the_textbook_update() -> None:
    params = _params(p_detect=1.0, clutter=500.0)
    region = Disk(np.zeros(2), 100.0)
    r, z = 0.6, np.array([1.0, 0.5])
    after = _step(_one_bernoulli(r, (0.0, 0.0), 2.0, params), region, z, params)
    kappa = (500.0 + params.birth_weight) / region.area_m2  # clutter and newborn intensity
    q = multivariate_normal(np.zeros(2), 3.0 * np.eye(2)).pdf(z)  # N(z; m, P + R)
    phi_undetected, phi = 1.0 - r * 1.0, r * q / kappa
    assert math.isclose(_existence(after, 0), phi / (phi_undetected + phi), rel_tol=1e-9)
    own = after.mixture.labels == 0
    assert own.sum() == 1  # p_D = 1: the missed branch has no weight
    np.testing.assert_allclose(after.mixture.means[own][0], 2.0 / 3.0 * z, atol=1e-12)
    np.testing.assert_allclose(after.mixture.covs[own][0], 2.0 / 3.0 * np.eye(2), atol=1e-12)
    assert after.tracks.ids.tolist() == [0]  # the birth from z explained by the track: pruned


@pytest.mark.parametrize(
    ("centre", "radius", "where"),
    [((0.0, 0.0), 100.0, "in view"), ((1000.0, 0.0), 10.0, "out of view"),
     ((2.0, 0.0), 2.0, "at the edge")],
)
def test_existence_after_a_missed_detection_weighs_the_exact_p_f(
    centre: tuple[float, float], radius: float, where: str
) -> None:
    params = _params(p_detect=0.9)
    region = Disk(np.array(centre), radius)
    r = 0.6
    after = _step(_one_bernoulli(r, (0.0, 0.0), 1.0, params), region, np.zeros((0, 2)), params)
    p_f = float(prob_in_region(np.zeros((1, 2)), np.eye(2)[None], region)[0])
    expected = r * (1.0 - 0.9 * p_f) / (1.0 - r * 0.9 * p_f)
    assert math.isclose(_existence(after, 0), expected, rel_tol=1e-9), where
    mean_x = after.tracks.means[0, 0]
    if where == "at the edge":  # the no-detection moments move the target away from the view
        assert 0.0 < p_f < 1.0 and mean_x < 0.0
    else:
        assert math.isclose(mean_x, 0.0, abs_tol=1e-9)


def test_a_measurement_nothing_explains_gives_a_birth_of_the_adaptive_existence() -> None:
    params = _params(clutter=0.5)
    region = Disk(np.zeros(2), 20.0)
    state = initial_state(Mixture.empty(2), 0.0, params)
    z = np.array([[3.0, -4.0]])
    after = _step(state, region, z, params)
    b = params.birth_weight / region.area_m2
    kappa = 0.5 / region.area_m2
    assert after.tracks.size == 1
    assert math.isclose(float(after.tracks.existence[0]), b / (b + kappa), rel_tol=1e-9)
    np.testing.assert_allclose(after.tracks.means[0], z[0])
    np.testing.assert_allclose(after.tracks.covs[0], R)
    assert after.tracks.hits[0] == 1 and not after.tracks.confirmed[0]


def _enumerated_marginals(
    phi_undetected: FloatArray, phi: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Every hypothesis (each Bernoulli undetected or one measurement, each used once)."""
    m, n = phi.shape
    undetected, detected, total = np.zeros(n), np.zeros((m, n)), 0.0
    for theta in itertools.product(range(-1, m), repeat=n):
        used = [i for i in theta if i >= 0]
        if len(used) != len(set(used)):
            continue
        weight = math.prod(phi_undetected[b] if i < 0 else phi[i, b] for b, i in enumerate(theta))
        total += weight
        for b, i in enumerate(theta):
            if i < 0:
                undetected[b] += weight
            else:
                detected[i, b] += weight
    return undetected / total, detected / total


@pytest.mark.parametrize("seed", range(15))
def test_association_marginals_equal_full_enumeration(seed: int) -> None:
    """Clusters small enough to enumerate: the marginals are exact."""
    rng = np.random.default_rng(seed)
    n, m = int(rng.integers(1, 5)), int(rng.integers(0, 4))
    phi_undetected = rng.uniform(0.05, 1.0, n)
    phi = rng.exponential(2.0, (m, n)) * (rng.random((m, n)) < 0.6)
    got = associate(phi_undetected, phi)
    undetected, detected = _enumerated_marginals(phi_undetected, phi)
    np.testing.assert_allclose(got.undetected, undetected, atol=1e-12)
    np.testing.assert_allclose(got.detected, detected, atol=1e-12)


def test_large_clusters_are_sampled_close_to_full_enumeration() -> None:
    """A crowd's cluster: seven Bernoullis, each likely for its own measurement and less so for
    its neighbours' (a hypotheses bound over EXACT_LIMIT): the Gibbs sampler's marginals within
    0.02 of the enumeration, and repeatable."""
    rng = np.random.default_rng(3)
    n = 7
    phi_undetected = rng.uniform(0.02, 0.3, n)
    phi = np.diag(rng.uniform(20.0, 80.0, n)) + rng.uniform(0.5, 5.0, (n, n)) * (
        rng.random((n, n)) < 0.6)
    assert hypothesis_bound(phi) > EXACT_LIMIT
    got = associate(phi_undetected, phi)
    undetected, detected = _enumerated_marginals(phi_undetected, phi)
    np.testing.assert_allclose(got.undetected, undetected, atol=0.02)
    np.testing.assert_allclose(got.detected, detected, atol=0.02)
    again = associate(phi_undetected, phi)
    np.testing.assert_array_equal(again.detected, got.detected)


# An independent LMB, written from the textbook (Reuter et al. 2014): Bernoullis as lists of
# Gaussians, the update by enumerating every joint association hypothesis, no gating.


@dataclass
class _Bernoulli:
    r: float
    parts: list[tuple[float, FloatArray, FloatArray]]  # (weight within, mean, cov)


def _reference_step(
    bern: list[_Bernoulli], z: FloatArray, p_d: float, kappa_c: float, b: float
) -> list[_Bernoulli]:
    kappa = kappa_c + b
    lik = [[sum(w * p_d * multivariate_normal(m, p + R).pdf(zi) for w, m, p in x.parts)
            for zi in z] for x in bern]
    phi_u = np.array([1.0 - x.r * p_d for x in bern])
    phi = np.array([[x.r * lik[k][i] / kappa for k, x in enumerate(bern)] for i in range(len(z))])
    phi = phi.reshape(len(z), len(bern))
    undetected, detected = _enumerated_marginals(phi_u, phi)
    out = []
    for k, x in enumerate(bern):
        parts = []
        p_miss = undetected[k] * x.r * (1.0 - p_d) / phi_u[k]
        parts += [(p_miss * w, m, p) for w, m, p in x.parts]
        for i, zi in enumerate(z):
            if detected[i, k] == 0.0:
                continue
            for w, m, p in x.parts:
                s = p + R
                gain = p @ np.linalg.inv(s)
                q = w * p_d * multivariate_normal(m, s).pdf(zi)
                share = detected[i, k] * q / lik[k][i]
                parts.append((share, m + gain @ (zi - m), p - gain @ p))
        r = min(sum(w for w, _, _ in parts), 0.9999)
        total = sum(w for w, _, _ in parts)
        parts = [(w / total, m, p) for w, m, p in parts if w / total * r >= 1e-3]
        out.append(_Bernoulli(r, parts))
    for i, zi in enumerate(z):
        r_b = (1.0 - detected[i].sum()) * b / kappa
        if r_b >= 1e-3:
            out.append(_Bernoulli(r_b, [(1.0, zi.copy(), R.copy())]))
    return [x for x in out if x.r >= 1e-3]


def _mean(x: _Bernoulli) -> FloatArray:
    weights = np.array([w for w, _, _ in x.parts])
    means = np.array([m for _, m, _ in x.parts])
    result: FloatArray = weights @ means / weights.sum()
    return result


def test_the_lmb_agrees_with_an_independent_textbook_lmb() -> None:
    """Constant p_D (every target deep inside the view), clutter, three stationary targets:
    the same measurements through both; expected cardinality within 0.02 and each target's
    Bernoulli mean within 1 cm at every step."""
    rng = np.random.default_rng(7)
    targets = np.array([[0.0, 0.0], [6.0, 0.0], [0.0, 8.0]])
    region = Disk(np.zeros(2), 40.0)
    clutter_area = Disk(np.zeros(2), 15.0)  # where clutter falls: p(F) = 1 for all it starts
    p_d, clutter = 0.9, 0.5
    params = _params(p_detect=p_d, clutter=clutter)
    state = initial_state(Mixture.empty(2), 0.0, params)
    reference: list[_Bernoulli] = []
    kappa_c, b = clutter / region.area_m2, params.birth_weight / region.area_m2
    for k in range(1, 9):
        seen = targets[rng.random(3) < p_d]
        z = np.vstack([seen + rng.normal(size=seen.shape),
                       clutter_area.sample_uniform(rng, int(rng.poisson(clutter)))])
        state = step(state, Scan(float(k), region, z, R, np.zeros(2)), params,
                     GpPredictor(params.gp))[0]
        reference = _reference_step(reference, z, p_d, kappa_c, b)
        ours = state.tracks.existence.sum()
        theirs = sum(x.r for x in reference)
        assert abs(ours - theirs) < 0.02, k
        for target in targets:
            mine = [x for x in reference if x.r > 0.5]
            if not mine:
                continue
            near = min(mine, key=lambda x: float(np.hypot(*(_mean(x) - target))))
            if np.hypot(*(_mean(near) - target)) > 3.0:
                continue
            ours_near = state.tracks.means[
                np.argmin(np.hypot(*(state.tracks.means[:, :2] - _mean(near)).T))]
            np.testing.assert_allclose(ours_near[:2], _mean(near), atol=0.01)
    assert sum(x.r > 0.5 for x in reference) == 3


def test_a_short_generated_scenario_finds_every_target_with_the_lmb() -> None:
    """A battery family at the LMB's defaults, end to end with seeded randomness."""
    scenario = family_scenario("clutter-0.5", 3, "lmb")
    assert scenario.filter.kind == FilterKind.LMB
    summary = simulate(scenario).summary()
    assert summary["tracks_confirmed"] == summary["true_count"]
    assert summary["gospa_missed_final"] == 0 and summary["gospa_false_final"] == 0
    assert summary["gospa_localisation_final"] < 3.0
