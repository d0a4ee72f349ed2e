"""The targets' motion class: the integrated Ornstein-Uhlenbeck displacement variance."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from companion.errors import InputError
from companion.keys import read_table
from companion.sat.motion import TargetMotion, learn_motion
from companion.sat.params import FILTER_KEYS, FilterSpec, sat_params


def test_displacement_is_ballistic_at_first_and_diffusive_later() -> None:
    walker = TargetMotion(speed_m_s=0.5, manoeuvre_s=200.0)
    sv2, tau_c = walker.velocity_var_m2_s2, walker.correlation_s
    assert (sv2, tau_c) == (0.125, 100.0)
    # tau << tau_c: straight on at a random heading, variance sigma_v^2 tau^2 per axis
    assert walker.displacement_var_m2(1.0) == pytest.approx(sv2 * 1.0**2, rel=1e-2)
    # tau >> tau_c: a random walk, 2 sigma_v^2 tau_c (tau - tau_c) per axis
    assert walker.displacement_var_m2(1e5) == pytest.approx(2 * sv2 * tau_c * (1e5 - tau_c))
    grid = np.linspace(0.0, 5000.0, 101)
    var = np.array([walker.displacement_var_m2(t) for t in grid])
    assert var[0] == 0.0 and np.all(np.diff(var) > 0.0), "never saturates"


def test_simulated_walkers_match_the_variance() -> None:
    """Targets that go straight at 0.5 m/s and take a new random heading every 200 s, from a
    random phase: their per-axis displacement variance is that of the model to within 18 %
    (a renewal process of fixed legs is not exactly an OU velocity)."""
    rng = np.random.default_rng(3)
    speed, leg_s, n = 0.5, 200, 4000
    walker = TargetMotion(speed, float(leg_s))
    for tau in (20, 200, 1000):
        phase = rng.integers(0, leg_s, size=n)
        x = np.zeros(n)
        heading = rng.uniform(0.0, 2.0 * math.pi, size=n)
        for k in range(tau):
            turn = (phase + k) % leg_s == 0
            heading[turn] = rng.uniform(0.0, 2.0 * math.pi, size=int(turn.sum()))
            x += speed * np.cos(heading)
        assert np.var(x) == pytest.approx(walker.displacement_var_m2(float(tau)), rel=0.25)


def test_stationary_targets_do_not_move() -> None:
    assert TargetMotion(0.0).displacement_var_m2(1e6) == 0.0


@pytest.mark.parametrize(("speed", "manoeuvre"), [(-1.0, 100.0), (math.nan, 100.0),
                                                  (1.0, 0.0), (1.0, math.inf)])
def test_bad_motion_class_is_refused(speed: float, manoeuvre: float) -> None:
    with pytest.raises(InputError):
        TargetMotion(speed, manoeuvre)


def test_the_linear_models_noise_follows_the_motion_class() -> None:
    spec = FilterSpec(**read_table({}, "filter", FILTER_KEYS))
    still = sat_params(replace(spec, target_speed=0.0), 0.98, 0.1, 0.5)
    assert still.q_m2_per_s == pytest.approx(spec.process_noise / 0.5)
    runner = sat_params(replace(spec, target_speed=2.0), 0.98, 0.1, 0.5)
    motion = runner.tracks.motion
    assert motion == TargetMotion(2.0, spec.manoeuvre_time)
    # one step's displacement variance, ~ (v^2 / 2) dt^2 = 0.5 m^2, per second of the step
    assert runner.q_m2_per_s == pytest.approx(motion.displacement_var_m2(0.5) / 0.5)
    assert runner.q_m2_per_s > 0.9


def test_the_gp_trend_takes_the_classs_velocity_as_its_prior() -> None:
    spec = FilterSpec(**read_table({}, "filter", FILTER_KEYS))
    assert sat_params(replace(spec, target_speed=0.0), 0.98, 0.1, 1.0).gp.slope_sd_m_s == 0.0
    walker = sat_params(replace(spec, target_speed=0.5), 0.98, 0.1, 1.0)
    assert walker.gp.slope_sd_m_s == pytest.approx(0.5 / math.sqrt(2.0))


def test_the_class_is_learned_from_simulated_walkers() -> None:
    """Walkers at 0.3 m/s turning every 200 s, seen every second with 1 m noise: the speed
    within 10 % and the time between manoeuvres within 25 %."""
    rng = np.random.default_rng(11)
    trajectories = []
    for _ in range(30):
        heading = rng.uniform(0.0, 2.0 * math.pi)
        phase = int(rng.integers(0, 200))
        xy = np.zeros((2001, 2))
        for k in range(1, 2001):
            if (k + phase) % 200 == 0:
                heading = rng.uniform(0.0, 2.0 * math.pi)
            xy[k] = xy[k - 1] + 0.3 * np.array([math.cos(heading), math.sin(heading)])
        noisy = xy + rng.normal(0.0, 1.0, size=xy.shape)
        trajectories.append((np.arange(2001, dtype=np.float64), noisy))
    learned = learn_motion(trajectories)
    assert learned.speed_m_s == pytest.approx(0.3, rel=0.1)
    assert learned.manoeuvre_s == pytest.approx(200.0, rel=0.25)


def test_learning_refuses_bad_trajectories() -> None:
    t = np.arange(10, dtype=np.float64)
    with pytest.raises(InputError, match="evenly spaced"):
        learn_motion([(t**2, np.zeros((10, 2)))])
    with pytest.raises(InputError, match="move"):
        learn_motion([(t, np.zeros((10, 2)))])
    with pytest.raises(InputError, match="at least one"):
        learn_motion([])
