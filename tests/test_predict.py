"""GP prediction of the components of confirmed tracks (sat.predict), Eq. kept_shift."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import NDArray

from companion.sat.gp import GpFit, GpParams, GpPredictor, predict_fit
from companion.sat.mixture import Mixture
from companion.sat.predict import (
    KEPT_SHIFT_SD,
    STANDING_P,
    LinearModel,
    predict,
    transition,
)
from companion.scenario_lookup import resolve_scenario
from companion.sim.run import simulate
from companion.sim.scenario import load_scenario

FloatArray = NDArray[np.float64]

PARAMS = GpParams(sigma_f_m=2.0, lengthscale_s=40.0, sigma_n_m=1.0, window=30, slope_sd_m_s=0.2)
TRACK_ID = 7
SD_M = 0.5  # the component's position standard deviation


def _window_fit(speed_m_s: float, params: GpParams = PARAMS) -> GpFit:
    """The fit of 30 detections one a second (t = 0..29 s, 1 m noise) of a target going east."""
    rng = np.random.default_rng(5)
    t = np.arange(30.0)
    y = np.array([500.0, 300.0]) + np.outer(t, [speed_m_s, 0.0]) + rng.normal(size=(30, 2))
    return GpPredictor(params).fit(t[None], y[None], [30])


def _gp_mean(fit: GpFit, t_s: float) -> FloatArray:
    mean: FloatArray = predict_fit(PARAMS, fit, t_s)[0][0]
    return mean


def _predicted_mean(fit: GpFit, shift_m: FloatArray, t_before_s: float) -> FloatArray:
    """The predicted mean of a confirmed track's component whose prior mean lies shift_m off the
    GP's mean at t_before_s, one second later."""
    prior = Mixture(
        np.array([0.9]), (_gp_mean(fit, t_before_s) + shift_m)[None, :],
        (SD_M**2 * np.eye(2))[None], np.array([TRACK_ID]),
    )
    f, q = transition(LinearModel.CONSTANT_POSITION, 1.0, 0.01)
    predicted = predict(prior, f, q, 1.0, PARAMS, fit, np.array([TRACK_ID]), np.array([True]),
                        t_before_s, t_before_s + 1.0)
    mean: FloatArray = predicted.means[0]
    return mean


def test_the_fit_says_how_likely_the_target_stands() -> None:
    assert _window_fit(0.0).mu[0, -1] > STANDING_P
    assert 0.05 < _window_fit(0.05).mu[0, -1] < STANDING_P  # 1.5 m in 30 s under 1 m noise
    assert _window_fit(0.5).mu[0, -1] < 1e-6
    no_trend = GpParams(sigma_f_m=2.0, lengthscale_s=40.0, sigma_n_m=1.0, window=30)
    assert _window_fit(0.5, no_trend).mu[0, -1] == 1.0


def test_a_track_detected_at_the_last_step_takes_the_gp_mean() -> None:
    fit = _window_fit(0.0)
    got = _predicted_mean(fit, np.array([0.1, -0.1]), t_before_s=29.0)
    np.testing.assert_array_equal(got, _gp_mean(fit, 30.0))


@pytest.mark.parametrize("shift_sd", [0.2, 3.0])
def test_a_still_targets_track_keeps_what_misses_told_it(shift_sd: float) -> None:
    """Eq. kept_shift: the shift, at most KEPT_SHIFT_SD standard deviations."""
    fit = _window_fit(0.0)
    shift = shift_sd * SD_M * np.array([0.6, 0.8])
    kept = _predicted_mean(fit, shift, t_before_s=35.0) - _gp_mean(fit, 36.0)
    want = shift * min(1.0, KEPT_SHIFT_SD / shift_sd)
    np.testing.assert_allclose(kept, want, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("speed_m_s", [0.05, 0.5])
def test_a_track_whose_window_may_move_keeps_no_shift(speed_m_s: float) -> None:
    fit = _window_fit(speed_m_s)
    got = _predicted_mean(fit, np.array([0.2, 0.0]), t_before_s=35.0)
    np.testing.assert_array_equal(got, _gp_mean(fit, 36.0))


def test_the_tag_at_the_edge_of_the_lanes_keeps_its_track_at_the_defaults() -> None:
    """The paper's exact prior with the GP at its defaults, seed 6: a lane passes 25.5 m from a tag
    whose track's mean lies just inside the 25 m view; resetting the mean at each step wore the
    track down (docs/estimator.md, "Edge erosion")."""
    scenario = load_scenario(resolve_scenario("paper-lawnmower-exact-c10-untuned"), seed=6)
    summary = simulate(scenario).summary()
    assert summary["tracks_confirmed"] == summary["true_count"] == 10
