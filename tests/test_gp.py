"""Tests for companion.sat.gp: GP prediction over time, the batched predictor and the fit."""

from __future__ import annotations

import itertools
import math

import numpy as np
import numpy.typing as npt
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.errors import ConfigError, InputError
from companion.sat.gp import (
    GpParams,
    GpPredictor,
    _chunk_trajectories,
    _ChunkGroup,
    _neg_reml,
    gp_predict,
    learn_gp_params,
)

FloatArray = npt.NDArray[np.float64]


def _textbook(
    params: GpParams, t: FloatArray, y: FloatArray, t_star: float
) -> tuple[FloatArray, float, FloatArray]:
    """Direct GP regression with a constant mean (the sample mean), element by element."""
    sf2, lam, sn2 = params.sigma_f_m**2, params.lengthscale_s, params.sigma_n_m**2
    n = len(t)
    ky = np.empty((n, n))
    for i in range(n):
        for j in range(n):
            ky[i, j] = sf2 * math.exp(-0.5 * ((t[i] - t[j]) / lam) ** 2) + (sn2 if i == j else 0.0)
    k_star = np.array([sf2 * math.exp(-0.5 * ((t_star - ti) / lam) ** 2) for ti in t])
    dk_star = np.array([k * (ti - t_star) / lam**2 for k, ti in zip(k_star, t, strict=True)])
    mu = y.mean(axis=0)
    mean = mu + k_star @ np.linalg.solve(ky, y - mu)
    var = sf2 - k_star @ np.linalg.solve(ky, k_star)
    vel = dk_star @ np.linalg.solve(ky, y - mu)
    return mean, float(var), vel


def _read_only(a: npt.ArrayLike) -> FloatArray:
    out = np.array(a, dtype=np.float64)
    out.setflags(write=False)
    return out


# ---------------------------------------------------------------------------------------------
# gp_predict
# ---------------------------------------------------------------------------------------------


def test_gp_predict_matches_textbook_small_case() -> None:
    params = GpParams(sigma_f_m=1.3, lengthscale_s=2.1, sigma_n_m=0.2, window=10)
    t = _read_only([0.0, 0.7, 1.9, 2.4, 3.6])
    y = _read_only([[1.0, -2.0], [1.4, -1.7], [2.1, -1.1], [2.2, -0.8], [3.0, -0.1]])
    mean, var, vel = gp_predict(params, t, y, 4.5)
    mean_ref, var_ref, vel_ref = _textbook(params, t, y, 4.5)
    np.testing.assert_allclose(mean, mean_ref, rtol=0, atol=1e-12)
    np.testing.assert_allclose(vel, vel_ref, rtol=0, atol=1e-12)
    assert var == pytest.approx(var_ref, abs=1e-12)
    assert mean.shape == (2,) and vel.shape == (2,)


def test_gp_predict_uses_only_the_window() -> None:
    rng = np.random.default_rng(3)
    params = GpParams(sigma_f_m=2.0, lengthscale_s=5.0, sigma_n_m=0.5, window=5)
    # Times on a 1 ms grid, so the 1 ns rounding of relative times changes nothing.
    t = np.asarray(np.round(np.cumsum(rng.uniform(0.5, 1.5, size=12)), 3), dtype=np.float64)
    y = rng.normal(size=(12, 3))
    mean, var, vel = gp_predict(params, t, y, t[-1] + 1.0)
    mean_ref, var_ref, vel_ref = _textbook(params, t[-5:], y[-5:], t[-1] + 1.0)
    np.testing.assert_allclose(mean, mean_ref, atol=1e-12)
    np.testing.assert_allclose(vel, vel_ref, atol=1e-12)
    assert var == pytest.approx(var_ref, abs=1e-12)
    # Garbage before the window is never read.
    y_bad = y.copy()
    y_bad[0] = np.nan
    mean_bad, _, _ = gp_predict(params, t, y_bad, t[-1] + 1.0)
    np.testing.assert_array_equal(mean_bad, mean)


def test_single_point_history() -> None:
    params = GpParams(sigma_f_m=1.5, lengthscale_s=10.0, sigma_n_m=0.4, window=8)
    mean, var, vel = gp_predict(params, [3.0], [[500000.25, 4000000.5]], 4.0)
    np.testing.assert_array_equal(mean, [500000.25, 4000000.5])
    np.testing.assert_array_equal(vel, [0.0, 0.0])
    k = 1.5**2 * math.exp(-0.5 * (1.0 / 10.0) ** 2)
    assert var == pytest.approx(1.5**2 - k * k / (1.5**2 + 0.4**2), rel=1e-12)


def test_constant_utm_trajectory_predicts_the_constant() -> None:
    t = np.arange(50.0)
    y = np.tile([500000.0, 4000000.0], (50, 1))
    mean, var, vel = gp_predict(GpParams(), t, y, 50.0)
    np.testing.assert_allclose(mean, [500000.0, 4000000.0], rtol=0, atol=1e-9)
    np.testing.assert_allclose(vel, [0.0, 0.0], atol=1e-12)
    assert 0.0 < var < GpParams().sigma_f_m ** 2


def test_linear_utm_trajectory_extrapolates_one_step() -> None:
    slope = np.array([0.05, -0.03])  # m/s, the paper's target speed
    t = np.arange(60.0)
    y = np.array([500000.0, 4000000.0]) + t[:, None] * slope
    truth = np.array([500000.0, 4000000.0]) + 60.0 * slope
    step = float(np.linalg.norm(slope))

    # Defaults: better than holding the last position (error = one step), slope within 25 %.
    mean, _, vel = gp_predict(GpParams(), t, y, 60.0)
    assert np.linalg.norm(mean - truth) < 0.8 * step
    np.testing.assert_allclose(vel, slope, rtol=0.25)

    # A long lengthscale with little noise follows the line: mm error, velocity within 2 %.
    sharp = GpParams(sigma_f_m=5.0, lengthscale_s=60.0, sigma_n_m=0.01, window=30)
    mean, _, vel = gp_predict(sharp, t, y, 60.0)
    assert np.linalg.norm(mean - truth) < 5e-3
    np.testing.assert_allclose(vel, slope, rtol=0.02)


def test_variance_positive_and_decreasing_with_more_points() -> None:
    params = GpParams(window=30)
    t = np.arange(30.0)
    y = np.zeros((30, 2))
    variances = [gp_predict(params, t[-n:], y[-n:], 30.0)[1] for n in range(1, 31)]
    assert all(v > 0.0 for v in variances)
    assert all(b < a for a, b in itertools.pairwise(variances))
    assert variances[0] < params.sigma_f_m**2


@settings(deadline=None, max_examples=40)
@given(
    gaps=st.lists(st.floats(0.05, 5.0), min_size=2, max_size=15),
    ahead=st.floats(0.0, 10.0),
    lam=st.floats(0.5, 50.0),
    noise=st.floats(0.05, 2.0),
)
def test_variance_never_grows_with_older_points(
    gaps: list[float], ahead: float, lam: float, noise: float
) -> None:
    params = GpParams(sigma_f_m=1.0, lengthscale_s=lam, sigma_n_m=noise, window=50)
    t = np.cumsum(gaps)
    y = np.zeros((len(t), 1))
    t_star = float(t[-1] + ahead)
    variances = [gp_predict(params, t[-n:], y[-n:], t_star)[1] for n in range(1, len(t) + 1)]
    assert all(0.0 < v <= 1.0 for v in variances)
    assert all(b <= a + 1e-12 for a, b in itertools.pairwise(variances))


@settings(deadline=None, max_examples=40)
@given(
    seed=st.integers(0, 2**32 - 1),
    offset=st.floats(-5e6, 5e6),
    shift_s=st.integers(-(10**6), 10**6),
)
def test_prediction_invariant_to_position_offset_and_time_shift(
    seed: int, offset: float, shift_s: int
) -> None:
    rng = np.random.default_rng(seed)
    params = GpParams(sigma_f_m=1.0, lengthscale_s=8.0, sigma_n_m=0.3, window=10)
    t = np.cumsum(rng.integers(1, 4, size=12)).astype(np.float64)
    y = rng.normal(scale=2.0, size=(12, 2))
    mean, var, vel = gp_predict(params, t, y, float(t[-1] + 1))
    mean2, var2, vel2 = gp_predict(params, t + shift_s, y + offset, float(t[-1] + 1 + shift_s))
    np.testing.assert_allclose(mean2 - offset, mean, atol=1e-9 * max(1.0, abs(offset)))
    np.testing.assert_allclose(vel2, vel, atol=1e-9 * max(1.0, abs(offset)))
    assert var2 == var


def _textbook_trend(
    params: GpParams, t: FloatArray, y: FloatArray, t_star: float
) -> tuple[FloatArray, FloatArray]:
    """Eqs. gp_trend, gp_prediction written out: the moving and standing models' restricted
    likelihoods (the intercept integrated out) per axis, y ~ N(a 1, Ky + sb2 r r^T) against
    N(a 1, Ky), weigh the moving model's GLS trend against the window's mean; (mean, velocity)."""
    sf2, lam, sn2 = params.sigma_f_m**2, params.lengthscale_s, params.sigma_n_m**2
    sb2 = params.slope_sd_m_s**2
    rel = t - t[-1]
    ky = sf2 * np.exp(-0.5 * ((t[:, None] - t[None, :]) / lam) ** 2) + sn2 * np.eye(len(t))
    ones = np.ones(len(t))

    def log_restricted(cov: FloatArray, v: FloatArray) -> float:
        inv = np.linalg.inv(cov)
        s = ones @ inv @ ones
        p = inv - np.outer(inv @ ones, ones @ inv) / s
        return float(-0.5 * v @ p @ v - 0.5 * np.linalg.slogdet(cov)[1] - 0.5 * math.log(s))

    yc = y - y.mean(axis=0)  # the restricted likelihood ignores offsets: centred for round-off
    log_bf = sum(
        log_restricted(ky + sb2 * np.outer(rel, rel), yc[:, d]) - log_restricted(ky, yc[:, d])
        for d in range(y.shape[1])
    )
    p_moving = 1.0 / (1.0 + math.exp(-log_bf))
    h = np.column_stack((ones, rel))
    ky_inv = np.linalg.inv(ky)
    coef = np.linalg.solve(h.T @ ky_inv @ h + np.diag([0.0, 1.0 / sb2]), h.T @ ky_inv @ y)
    a = p_moving * coef[0] + (1.0 - p_moving) * y.mean(axis=0)
    b = p_moving * coef[1]
    k_star = sf2 * np.exp(-0.5 * ((t_star - t) / lam) ** 2)
    beta = ky_inv @ (y - a - rel[:, None] * b)
    mean = a + b * min(t_star - t[-1], 0.0) + k_star @ beta
    return mean, b + (k_star * (t - t_star) / lam**2) @ beta


@pytest.mark.parametrize("speed_m_s", [0.0, 0.02, 0.3])
def test_trend_matches_its_textbook_form(speed_m_s: float) -> None:
    rng = np.random.default_rng(3)
    params = GpParams(sigma_f_m=2.0, lengthscale_s=40.0, sigma_n_m=1.0, window=30,
                      slope_sd_m_s=0.2)
    t = np.cumsum(rng.uniform(0.5, 1.5, 30))
    y = np.array([500000.0, 4000000.0]) + np.outer(t, [speed_m_s, -speed_m_s])
    y += rng.normal(size=y.shape)
    for t_star in (t[20], t[-1], t[-1] + 1.0, t[-1] + 30.0):
        want_mean, want_vel = _textbook_trend(params, t, y, float(t_star))
        mean, _, vel = gp_predict(params, t, y, float(t_star))
        np.testing.assert_allclose(mean, want_mean, rtol=0, atol=1e-6)
        np.testing.assert_allclose(vel, want_vel, rtol=0, atol=1e-9)
        fitted, _, fitted_vel = GpPredictor(params).predict(t[None], y[None], [30], float(t_star))
        np.testing.assert_allclose(fitted[0], mean, rtol=0, atol=1e-6)
        np.testing.assert_allclose(fitted_vel[0], vel, rtol=0, atol=1e-9)


def _walker_nowcast_errors(slope_sd_m_s: float, speed_m_s: float) -> FloatArray:
    """Errors (m) one second past the newest of 30 detections (1 m noise, 1 Hz) of targets going
    straight at speed_m_s, 200 seeded draws."""
    rng = np.random.default_rng(8)
    params = GpParams(sigma_n_m=1.0, slope_sd_m_s=slope_sd_m_s)
    t = np.arange(30.0)
    errors = []
    for _ in range(200):
        heading = rng.uniform(0.0, 2.0 * math.pi)
        velocity = speed_m_s * np.array([math.cos(heading), math.sin(heading)])
        y = np.outer(t, velocity) + rng.normal(size=(30, 2))
        mean, _, _ = gp_predict(params, t, y, 30.0)
        errors.append(float(np.linalg.norm(mean - 30.0 * velocity)))
    return np.array(errors)


def test_trend_takes_a_walkers_lag_out_and_leaves_a_standing_target_alone() -> None:
    sd = 0.3 / math.sqrt(2.0)  # the default motion class, as the filter sets it
    walker_se, walker_trend = _walker_nowcast_errors(0.0, 0.5), _walker_nowcast_errors(sd, 0.5)
    assert np.median(walker_trend) < 0.6 * np.median(walker_se)
    still_se, still_trend = _walker_nowcast_errors(0.0, 0.0), _walker_nowcast_errors(sd, 0.0)
    assert np.median(still_trend) < 1.1 * np.median(still_se)


def test_trend_is_held_past_the_newest_point() -> None:
    rng = np.random.default_rng(4)
    params = GpParams(sigma_n_m=0.5, slope_sd_m_s=0.5)
    t = np.arange(30.0)
    y = np.outer(t, [0.4, 0.1]) + rng.normal(scale=0.5, size=(30, 2))
    far, _, far_vel = gp_predict(params, t, y, 29.0 + 500.0)  # the SE part has died away
    farther, _, farther_vel = gp_predict(params, t, y, 29.0 + 5000.0)
    np.testing.assert_allclose(far, farther, rtol=0, atol=1e-9)
    np.testing.assert_allclose(far, y[-1], atol=1.0)  # where the walker was last seen
    np.testing.assert_allclose(far_vel, [0.4, 0.1], atol=0.05)  # its velocity is still known
    np.testing.assert_array_equal(far_vel, farther_vel)


# ---------------------------------------------------------------------------------------------
# GpPredictor
# ---------------------------------------------------------------------------------------------


def _padded_batch(
    rng: np.random.Generator, counts: list[int], width: int, dim: int
) -> tuple[FloatArray, FloatArray]:
    """Right-aligned windows with NaN padding, irregular times, UTM-sized positions."""
    t = np.full((len(counts), width), np.nan)
    y = np.full((len(counts), width, dim), np.nan)
    for i, c in enumerate(counts):
        t[i, width - c :] = 100.0 + np.cumsum(rng.uniform(0.2, 2.0, size=c)) - 2.0 * c
        y[i, width - c :] = [500000.0, 4000000.0][:dim] + rng.normal(scale=3.0, size=(c, dim))
    return t, y


def test_predictor_matches_gp_predict_row_by_row() -> None:
    rng = np.random.default_rng(11)
    params = GpParams(sigma_f_m=2.0, lengthscale_s=6.0, sigma_n_m=0.4, window=8)
    counts = [1, 2, 5, 8, 12, 12, 3, 8]
    t, y = _padded_batch(rng, counts, width=12, dim=2)
    t[7], y[7] = t[3], y[3] + 7.0  # same timing as row 3: shares its weights
    t_ro, y_ro = _read_only(t), _read_only(y)
    c_ro = np.array(counts)
    c_ro.setflags(write=False)
    mean, var, vel = GpPredictor(params).predict(t_ro, y_ro, c_ro, 101.0)
    assert mean.shape == (8, 2) and var.shape == (8,) and vel.shape == (8, 2)
    for i, c in enumerate(counts):
        m_i, v_i, vel_i = gp_predict(params, t[i, 12 - c :], y[i, 12 - c :], 101.0)
        # Ky^-1 is formed once per window here and solved per call there: equal to round-off.
        np.testing.assert_allclose(mean[i], m_i, rtol=1e-14, atol=1e-9)
        np.testing.assert_allclose(vel[i], vel_i, rtol=1e-8, atol=1e-12)
        assert var[i] == pytest.approx(v_i, rel=1e-9)
    np.testing.assert_allclose(mean[7], mean[3] + 7.0, rtol=1e-15)


def test_predictor_regular_full_windows_share_one_solve() -> None:
    rng = np.random.default_rng(5)
    params = GpParams()
    n_tracks, width = 10, params.window
    t = np.tile(np.arange(width, dtype=np.float64), (n_tracks, 1))
    y = rng.normal(size=(n_tracks, width, 2)) + np.array([500000.0, 4000000.0])
    predictor = GpPredictor(params)
    mean, var, vel = predictor.predict(t, y, np.full(n_tracks, width), float(width))
    assert predictor.cache_entries == 1
    np.testing.assert_array_equal(var, np.full(n_tracks, var[0]))
    for i in range(n_tracks):
        m_i, _, vel_i = gp_predict(params, t[i], y[i], float(width))
        np.testing.assert_allclose(mean[i], m_i, rtol=1e-15)
        np.testing.assert_allclose(vel[i], vel_i, rtol=1e-12, atol=1e-12)


def test_cache_is_a_pure_memo() -> None:
    rng = np.random.default_rng(21)
    params = GpParams(sigma_f_m=1.0, lengthscale_s=4.0, sigma_n_m=0.2, window=6)
    cached = GpPredictor(params, cache_size=3)
    for step in range(12):
        counts = list(rng.integers(1, 9, size=5))
        t, y = _padded_batch(rng, counts, width=8, dim=2)
        if step % 3 == 0:  # repeat a timing to get cache hits
            t[1:] = t[0]
            y[1:] = y[0] + rng.normal(size=(4, 1, 2))
            counts = [counts[0]] * 5
        cnt = np.array(counts)
        first = cached.predict(t, y, cnt, 101.0)
        again = cached.predict(t, y, cnt, 101.0)
        fresh = GpPredictor(params, cache_size=0).predict(t, y, cnt, 101.0)
        for a, b, c in zip(first, again, fresh, strict=True):
            np.testing.assert_array_equal(a, b)
            np.testing.assert_array_equal(a, c)
        assert cached.cache_entries <= 3


def test_predictor_empty_batch() -> None:
    mean, var, vel = GpPredictor(GpParams()).predict(
        np.zeros((0, 4)), np.zeros((0, 4, 2)), np.zeros(0, dtype=np.int64), 1.0
    )
    assert mean.shape == (0, 2) and var.shape == (0,) and vel.shape == (0, 2)


# ---------------------------------------------------------------------------------------------
# learn_gp_params
# ---------------------------------------------------------------------------------------------


def _sample_gp(
    rng: np.random.Generator, params: GpParams, n_traj: int, n_pts: int
) -> list[tuple[FloatArray, FloatArray]]:
    t = np.arange(n_pts, dtype=np.float64)
    d = t[:, None] - t[None, :]
    k = params.sigma_f_m**2 * np.exp(-0.5 * (d / params.lengthscale_s) ** 2)
    chol = np.linalg.cholesky(k + 1e-9 * np.eye(n_pts))
    out = []
    for _ in range(n_traj):
        f = chol @ rng.standard_normal((n_pts, 2))
        offset = np.array([500000.0, 4000000.0]) + rng.uniform(-1000.0, 1000.0, size=2)
        y = offset + f + params.sigma_n_m * rng.standard_normal((n_pts, 2))
        out.append((t + rng.uniform(0.0, 1e4), y))
    return out


def test_learn_recovers_known_hyperparameters() -> None:
    truth = GpParams(sigma_f_m=2.0, lengthscale_s=5.0, sigma_n_m=0.3, window=30)
    trajectories = _sample_gp(np.random.default_rng(2024), truth, n_traj=40, n_pts=60)
    learned = learn_gp_params(trajectories, window=30)
    assert learned.window == 30
    assert learned.sigma_f_m == pytest.approx(truth.sigma_f_m, rel=0.10)
    assert learned.lengthscale_s == pytest.approx(truth.lengthscale_s, rel=0.10)
    assert learned.sigma_n_m == pytest.approx(truth.sigma_n_m, rel=0.10)
    # A start far away ends in the same optimum.
    far = GpParams(sigma_f_m=50.0, lengthscale_s=0.5, sigma_n_m=5.0)
    again = learn_gp_params(trajectories, window=30, init=far)
    assert again.lengthscale_s == pytest.approx(learned.lengthscale_s, rel=1e-3)


def test_reml_gradient_matches_finite_differences() -> None:
    truth = GpParams(sigma_f_m=1.5, lengthscale_s=3.0, sigma_n_m=0.4)
    trajectories = _sample_gp(np.random.default_rng(8), truth, n_traj=3, n_pts=25)
    groups, n_obs = _chunk_trajectories(trajectories, 10)
    assert sorted(g.rel_s.shape[1] for g in groups) == [5, 10]
    theta = np.log([1.1, 2.5, 0.6])
    _, grad = _neg_reml(theta, groups, n_obs)
    h = 1e-6
    for i in range(3):
        e = np.zeros(3)
        e[i] = h
        fd = (_neg_reml(theta + e, groups, n_obs)[0] - _neg_reml(theta - e, groups, n_obs)[0]) / (
            2 * h
        )
        assert grad[i] == pytest.approx(fd, rel=1e-5, abs=1e-8)


def test_reml_is_the_limit_of_a_vague_constant_mean() -> None:
    """The restricted likelihood equals log N(y; 0, Ky + c^2 11^T) + log(c sqrt(2 pi)), c -> oo."""
    rng = np.random.default_rng(4)
    t = np.cumsum(rng.uniform(0.5, 1.5, size=8))
    y = rng.normal(size=(8, 1))
    sf, lam, sn = 1.2, 2.0, 0.5
    nll, _ = _neg_reml(np.log([sf, lam, sn]), [_ChunkGroup(t[None] - t[0], y[None])], 8)
    ky = sf**2 * np.exp(-0.5 * ((t[:, None] - t[None, :]) / lam) ** 2) + sn**2 * np.eye(8)
    c = 1e3
    cov = ky + c**2 * np.ones((8, 8))
    _, logdet = np.linalg.slogdet(cov)
    loglik = -0.5 * (y[:, 0] @ np.linalg.solve(cov, y[:, 0]) + logdet + 8 * math.log(2 * math.pi))
    assert -nll * 8 == pytest.approx(loglik + math.log(c * math.sqrt(2 * math.pi)), abs=1e-5)


# ---------------------------------------------------------------------------------------------
# Errors
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("field", "value", "name"),
    [
        ("sigma_f_m", 0.0, "sigma_f_m"),
        ("sigma_f_m", math.nan, "sigma_f_m"),
        ("lengthscale_s", -1.0, "lengthscale_s"),
        ("lengthscale_s", math.inf, "lengthscale_s"),
        ("sigma_n_m", 0.0, "sigma_n_m"),
        ("sigma_n_m", "0.3", "sigma_n_m"),
        ("window", 1, "window"),
        ("window", 2.5, "window"),
        ("window", True, "window"),
        ("slope_sd_m_s", -0.1, "slope_sd_m_s"),
        ("slope_sd_m_s", math.nan, "slope_sd_m_s"),
        ("slope_sd_m_s", "0.2", "slope_sd_m_s"),
    ],
)
def test_bad_params_name_the_parameter(field: str, value: object, name: str) -> None:
    """The core names its own parameter; the configuration layer names the key (filter.gp_*)."""
    with pytest.raises(InputError) as info:
        GpParams(**{field: value})  # type: ignore[arg-type]
    assert not isinstance(info.value, ConfigError)
    assert f"GP {name} must be" in str(info.value)


def test_bad_cache_size_and_learn_window() -> None:
    with pytest.raises(InputError, match="GP cache size must be >= 0"):
        GpPredictor(GpParams(), cache_size=-1)
    with pytest.raises(InputError, match="GP window must be an integer >= 2"):
        learn_gp_params([(np.arange(5.0), np.zeros((5, 2)))], window=1)


def test_non_finite_history_is_an_input_error() -> None:
    params = GpParams(window=4)
    t = np.arange(6.0)
    y = np.zeros((6, 2))
    y_nan = y.copy()
    y_nan[-2, 1] = np.nan
    t_inf = t.copy()
    t_inf[-1] = np.inf
    with pytest.raises(InputError, match="non-finite"):
        gp_predict(params, t, y_nan, 7.0)
    with pytest.raises(InputError, match="non-finite"):
        gp_predict(params, t_inf, y, 7.0)
    with pytest.raises(InputError, match="finite"):
        gp_predict(params, t, y, math.nan)
    with pytest.raises(InputError, match="non-finite"):
        GpPredictor(params).predict(t[None], y_nan[None], np.array([3]), 7.0)
    with pytest.raises(InputError, match="non-finite"):
        learn_gp_params([(t, y_nan)], window=4)


def test_malformed_input_is_an_input_error() -> None:
    params = GpParams(window=4)
    predictor = GpPredictor(params)
    t = np.arange(6.0)
    y = np.zeros((6, 2))
    with pytest.raises(InputError, match="shape"):
        gp_predict(params, t, y[:, 0], 7.0)
    with pytest.raises(InputError, match="shape"):
        gp_predict(params, [], np.zeros((0, 2)), 7.0)
    with pytest.raises(InputError, match="non-decreasing"):
        gp_predict(params, t[::-1].copy(), y, 7.0)
    with pytest.raises(InputError, match="within"):
        gp_predict(params, t, y, 1e12)
    with pytest.raises(InputError, match="counts"):
        predictor.predict(t[None], y[None], np.array([0]), 7.0)
    with pytest.raises(InputError, match="counts"):
        predictor.predict(t[None], y[None], np.array([7]), 7.0)
    with pytest.raises(InputError, match="counts"):
        predictor.predict(t[None], y[None], np.array([3.0]), 7.0)
    with pytest.raises(InputError, match="shape"):
        predictor.predict(t[None], y, np.array([3]), 7.0)
    with pytest.raises(InputError, match="at least one"):
        learn_gp_params([], window=4)
    with pytest.raises(InputError, match="at least 2"):
        learn_gp_params([(t[:1], y[:1])], window=4)
    with pytest.raises(InputError, match="vary"):
        learn_gp_params([(t, y)], window=4)
    with pytest.raises(InputError, match="pair"):
        learn_gp_params([t], window=4)  # type: ignore[list-item]


# ---------------------------------------------------------------------------------------------
# predict: a confirmed track's component (Eq. edge_shift)
# ---------------------------------------------------------------------------------------------


def _track_prediction(
    window_xy: FloatArray, shift_sd: float, keep: bool
) -> tuple[FloatArray, FloatArray]:
    """(GP mean at t = 31 s, predicted component mean) of one confirmed track whose window holds
    window_xy (30, 2) detected at t = 1..30 s and whose component at t = 30 s sits shift_sd of
    its standard deviation (0.5 m) east of the GP's mean there; `keep`: its edge shift."""
    from companion.sat.mixture import Mixture  # noqa: PLC0415
    from companion.sat.predict import predict  # noqa: PLC0415

    params = GpParams(sigma_f_m=2.0, lengthscale_s=40.0, sigma_n_m=1.0, window=30,
                      slope_sd_m_s=0.2)
    t = np.arange(1.0, 31.0)[None, :]
    fit = GpPredictor(params).fit(t, window_xy[None], np.array([30]))
    gp_mean, _, _ = GpPredictor(params).predict(t, window_xy[None], np.array([30]), 30.0)
    gp_next, _, _ = GpPredictor(params).predict(t, window_xy[None], np.array([30]), 31.0)
    prior = Mixture(np.array([1.0]), gp_mean + np.array([[0.5 * shift_sd, 0.0]]),
                    np.array([0.25 * np.eye(2)]), np.array([7]))
    out = predict(prior, np.eye(2), np.zeros((2, 2)), 1.0, params, fit, np.array([7]),
                  np.array([True]), 30.0, 31.0, keep_shift=np.array([keep]))
    return gp_next[0], out.means[0]


def test_a_standing_track_keeps_its_edge_shift_up_to_a_cap() -> None:
    from companion.sat.predict import SHIFT_CAP_SD  # noqa: PLC0415

    rng = np.random.default_rng(3)
    still = 100.0 + rng.normal(0.0, 1.0, size=(30, 2))
    small = 0.5 * SHIFT_CAP_SD
    # Missed at the frame's edge: the component keeps what the misses said, up to the cap.
    gp_next, mean = _track_prediction(still, small, keep=True)
    assert mean[0] - gp_next[0] == pytest.approx(0.5 * small, abs=1e-9)
    assert mean[1] == pytest.approx(gp_next[1], abs=1e-12)
    gp_next, mean = _track_prediction(still, 3.0, keep=True)
    assert mean[0] - gp_next[0] == pytest.approx(0.5 * SHIFT_CAP_SD, abs=1e-9)
    # Otherwise (detected, or the frame elsewhere): the GP's mean, as the paper predicts.
    gp_next, mean = _track_prediction(still, small, keep=False)
    np.testing.assert_allclose(mean, gp_next, atol=1e-12)
    # A walker's window (0.3 m/s east): its misses may be the walk, the GP's mean is kept.
    walking = still + np.column_stack([0.3 * np.arange(30.0), np.zeros(30)])
    gp_next, mean = _track_prediction(walking, small, keep=True)
    np.testing.assert_allclose(mean, gp_next, atol=1e-12)
