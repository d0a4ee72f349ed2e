"""The filter-only simulation's ground truth and sensor model, and the run's bookkeeping."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from companion.plan.world import World
from companion.sat.filter import initial_state, step
from companion.sat.fov import Disk
from companion.sat.gp import GpPredictor
from companion.sim.run import planned_steps, scans_of, simulate, start
from companion.sim.scenario import parse_scenario
from companion.sim.sensor import SensorModel, sense
from companion.sim.truth import advance_truth, initial_truth

WORLD = World(60.0, 40.0)


def test_moving_targets_stay_inside_and_turn_on_schedule() -> None:
    rng = np.random.default_rng(0)
    truth = initial_truth(np.zeros((0, 2)), 8, (), WORLD, rng)
    heading = truth.heading_rad.copy()
    for k in range(1, 2001):
        truth = advance_truth(truth, k, 1.0, 0.5, 100, (), (), 8, WORLD, rng)
        assert np.all(WORLD.contains(truth.xy))
        if k == 99:
            before_turn = truth.heading_rad.copy()
        if k == 100:
            assert not np.allclose(truth.heading_rad, before_turn)
    assert not np.allclose(truth.heading_rad, heading)


def test_targets_appear_and_disappear_on_their_steps() -> None:
    rng = np.random.default_rng(1)
    appear = ((5, 10.0, 10.0),)
    truth = initial_truth(np.array([[1.0, 1.0], [2.0, 2.0]]), 2, appear, WORLD, rng)
    assert truth.alive.tolist() == [True, True, False]
    for k in range(1, 11):
        truth = advance_truth(truth, k, 1.0, 0.0, 400, appear, ((8, 0),), 2, WORLD, rng)
        if k == 5:
            assert truth.alive.tolist() == [True, True, True]
    assert truth.alive.tolist() == [False, True, True]


def test_sensor_detects_in_view_with_p_d_and_adds_clutter_in_view() -> None:
    rng = np.random.default_rng(2)
    model = SensorModel(p_detect=0.9, noise_std_m=0.5, clutter_prob=0.3, clutter_rate=0.5)
    region = Disk(np.zeros(2), 10.0)
    targets = np.array([[1.0, 1.0], [50.0, 50.0]])  # one in view, one not
    detections = clutter = 0
    scans = 4000
    for _ in range(scans):
        z, is_clutter = sense(model, targets, region, rng)
        assert np.all(region.contains(z[is_clutter]))
        detections += int((~is_clutter).sum())
        clutter += int(is_clutter.sum())
    assert detections / scans == pytest.approx(0.9, abs=0.02)
    assert clutter / scans == pytest.approx(0.8, abs=0.05)


def test_non_lawnmower_planner_runs_as_long_as_the_lawn_mower_would() -> None:
    base: dict[str, Any] = {"world": {"size": [50.0, 50.0]},
                            "robot": {"lane_spacing": 25.0, "sweeps": 1}}
    lawn = parse_scenario(base)
    largest = parse_scenario({**base, "robot": {**base["robot"], "planner": "largest-gaussian"}})
    steps = planned_steps(lawn, World(50.0, 50.0))
    # start -> (12.5, 0) -> (12.5, 50) -> (37.5, 50) -> (37.5, 0) -> start, at 0.5 m/s
    assert steps == int(np.ceil((12.5 + 50 + 25 + 50 + 37.5) / 0.5))
    assert planned_steps(largest, World(50.0, 50.0)) == steps
    assert simulate(largest).t_s.size == steps


@pytest.mark.parametrize(
    ("extra", "expected"),
    [
        ({"sensor": {"fov": "polygon", "fov_polygon": [[-8, -6], [8, -6], [10, 6], [-10, 6]]}}, 3),
        ({"filter": {"linear_model": "cv", "process_noise": 0.05}}, 3),
        ({"filter": {"birth": "constant"}}, 3),
    ],
)
def test_variants_still_find_every_target(
    extra: dict[str, dict[str, object]], expected: int
) -> None:
    scenario: dict[str, Any] = {
        "seed": 2,
        "world": {"size": [50.0, 50.0]},
        "targets": {"positions": [[10.0, 12.0], [40.0, 20.0], [25.0, 42.0]]},
        "sensor": {"fov_radius": 12.0, "noise_std": 0.5, "clutter_prob": 0.1},
        "robot": {"speed": 1.0, "lane_spacing": 12.0, "sweeps": 2},
        "belief": {"kind": "empty"},
    }
    for table, values in extra.items():
        scenario[table] = {**scenario.get(table, {}), **values}
    summary = simulate(parse_scenario(scenario)).summary()
    assert summary["tracks_confirmed"] == expected
    assert summary["ospa_final"] < 2.0


def test_gospa_nees_and_time_to_all_confirmed_follow_the_series() -> None:
    scenario: dict[str, Any] = {
        "seed": 3,
        "steps": 300,
        "world": {"size": [50.0, 50.0]},
        "targets": {"positions": [[10.0, 12.0], [40.0, 20.0], [25.0, 42.0]]},
        "sensor": {"fov_radius": 12.0, "noise_std": 0.5, "clutter_prob": 0.1},
        "robot": {"speed": 1.0, "lane_spacing": 12.0, "sweeps": 2},
        "belief": {"kind": "empty"},
        "metrics": {"gospa_c": 5.0},
    }
    r = simulate(parse_scenario(scenario))
    summary = r.summary()
    k = r.t_s.size
    for name in ("gospa", "gospa_localisation", "gospa_missed", "gospa_false", "nees",
                 "nees_count"):
        assert getattr(r, name).shape == (k,)
    # Before the first confirmed track every true target is missed.
    first_conf = int(np.argmax(r.tracks_confirmed > 0))
    assert np.all(r.gospa_missed[:first_conf] == r.true_count[:first_conf])
    assert np.all(r.gospa_false + r.nees_count == r.tracks_confirmed)
    assert np.all(r.gospa_missed + r.nees_count == r.true_count)
    assert np.all(np.isnan(r.nees) == (r.nees_count == 0))
    # GOSPA^p = localisation^p + c^p / 2 (missed + false), with c = 5 and p = metrics.ospa_p = 2.
    np.testing.assert_allclose(
        r.gospa**2, r.gospa_localisation**2 + 25.0 / 2.0 * (r.gospa_missed + r.gospa_false),
        rtol=1e-12,
    )
    assert summary["gospa_final"] == r.gospa[-1]
    assert summary["gospa_tail_mean"] == pytest.approx(r.gospa[k - k // 5 :].mean(), rel=1e-12)
    assert summary["gospa_localisation_final"] == r.gospa_localisation[-1]
    assert (summary["gospa_missed_final"], summary["gospa_false_final"]) == (
        int(r.gospa_missed[-1]), int(r.gospa_false[-1]))
    # Pooled over (step, target) pairs, so steps with more assigned targets weigh more.
    has = r.nees_count > 0
    pooled = float((r.nees[has] * r.nees_count[has]).sum() / r.nees_count.sum())
    assert summary["nees_mean"] == pytest.approx(pooled, rel=1e-12)
    assert summary["tracks_confirmed"] == 3 and summary["gospa_missed_final"] == 0
    all_found = np.flatnonzero(r.gospa_missed == 0)
    assert summary["t_all_confirmed_s"] == r.t_s[all_found[0]]
    assert np.all(r.gospa_missed[: all_found[0]] > 0)


def test_the_scans_of_a_run_replay_it_exactly() -> None:
    """scans_of rebuilds what the filter was fed: stepping the filter through them from the
    run's start gives the run's final state, bit for bit."""
    s = parse_scenario({"name": "replayed", "seed": 4, "steps": 120,
                        "world": {"size": [60.0, 60.0]}, "targets": {"count": 4},
                        "sensor": {"fov_radius": 15.0, "clutter_rate": 0.5},
                        "belief": {"kind": "empty"}})
    result = simulate(s)
    begin = start(s)
    state = initial_state(begin.belief, 0.0, begin.params)
    gp = GpPredictor(begin.params.gp)
    scans = scans_of(result)
    assert len(scans) == 120
    assert sum(scan.measurements_xy.shape[0] for scan in scans) == result.measurements.shape[0]
    for scan in scans:
        state, _ = step(state, scan, begin.params, gp)
    np.testing.assert_array_equal(state.mixture.weights, result.final_state.mixture.weights)
    np.testing.assert_array_equal(state.mixture.means, result.final_state.mixture.means)
    np.testing.assert_array_equal(state.tracks.ids, result.final_state.tracks.ids)
