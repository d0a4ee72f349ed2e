"""The whole filter step, end to end on short seeded scenarios."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from companion.errors import InputError
from companion.sat.filter import SatParams, Scan, initial_state, step
from companion.sat.fov import Disk
from companion.sat.gp import GpPredictor
from companion.sat.mixture import Mixture, make_mixture
from companion.sim.run import simulate
from companion.sim.scenario import parse_scenario

SHORT: dict[str, Any] = {
    "name": "short",
    "seed": 4,
    "world": {"size": [60.0, 60.0]},
    "targets": {"positions": [[10.0, 12.0], [45.0, 20.0], [30.0, 50.0], [52.0, 53.0]]},
    "sensor": {"fov_radius": 12.0, "clutter_prob": 0.1, "noise_std": 0.5},
    "robot": {"speed": 1.0, "lane_spacing": 12.0, "sweeps": 2},
    "belief": {"kind": "exact", "offset": 8.0, "variance": 20.0},
}


def test_short_lawnmower_run_finds_every_target_and_nothing_else() -> None:
    result = simulate(parse_scenario(SHORT))
    summary = result.summary()
    assert summary["tracks_confirmed"] == 4
    assert summary["ospa_final"] < 1.0
    assert summary["mahal_closest_mean"] < 2.0
    tracks = result.final_state.tracks
    confirmed = tracks.means[tracks.confirmed, :2]
    truth = result.final_truth_xy
    error = np.hypot(*(confirmed[:, None, :] - truth[None, :, :]).transpose(2, 0, 1)).min(axis=0)
    assert error.max() < 0.5


def test_a_run_is_a_pure_function_of_scenario_and_seed() -> None:
    a = simulate(parse_scenario(SHORT)).summary()
    b = simulate(parse_scenario(SHORT)).summary()
    c = simulate(parse_scenario({**SHORT, "seed": 5})).summary()
    timing = {"wall_s", "step_ms_median", "step_ms_p95", "filter_s"}
    assert {k: v for k, v in a.items() if k not in timing} == {
        k: v for k, v in b.items() if k not in timing
    }
    assert a["ospa_mean"] != c["ospa_mean"]


def _scan(t_s: float, z: list[list[float]], region: Disk | None = None) -> Scan:
    return Scan(t_s, region or Disk(np.zeros(2), 10.0), np.array(z, dtype=float).reshape(-1, 2),
                np.eye(2), np.zeros(2))


def test_blind_step_predicts_without_erasing_unseen_targets() -> None:
    params = SatParams()
    mix = make_mixture([1.0], [[1.0, 1.0]], [np.eye(2)])
    state = initial_state(mix, 0.0, params)
    gp = GpPredictor(params.gp)
    blind = Scan(1.0, None, np.array([[1.0, 1.0]]), np.eye(2), np.zeros(2))
    after, report = step(state, blind, params, gp)
    assert report.blind and report.dropped_measurements == 1
    assert after.mixture.weights == pytest.approx([1.0])
    assert after.mixture.covs[0, 0, 0] == pytest.approx(1.0 + params.q_m2_per_s)
    # The same step with the target in view and no detection erases most of it.
    seen, _ = step(state, _scan(1.0, []), params, gp)
    assert seen.mixture.total_weight < 0.05


def test_nan_measurements_are_dropped_and_counted() -> None:
    params = SatParams()
    state = initial_state(Mixture.empty(), 0.0, params)
    after, report = step(state, _scan(1.0, [[1.0, np.nan], [2.0, 2.0]]), params,
                         GpPredictor(params.gp))
    assert report.dropped_measurements == 1
    assert after.mixture.size == 1


def test_missing_pose_makes_the_step_blind() -> None:
    params = SatParams()
    state = initial_state(make_mixture([1.0], [[0.0, 0.0]], [np.eye(2)]), 0.0, params)
    scan = Scan(1.0, Disk(np.zeros(2), 10.0), np.zeros((0, 2)), np.eye(2), np.array([np.nan, 0]))
    after, report = step(state, scan, params, GpPredictor(params.gp))
    assert report.blind
    assert after.mixture.weights == pytest.approx([1.0])


@pytest.mark.parametrize(
    ("scan", "message"),
    [
        (Scan(-1.0, None, np.zeros((0, 2)), np.eye(2), np.zeros(2)), "scan time"),
        (Scan(1.0, None, np.zeros((0, 2)), -np.eye(2), np.zeros(2)), "positive definite"),
        (Scan(1.0, None, np.zeros((0, 2)), np.eye(3), np.zeros(2)), "shape"),
        (Scan(1.0, None, np.zeros((2, 3)), np.eye(2), np.zeros(2)), "shape"),
    ],
)
def test_bad_scans_raise_input_errors(scan: Scan, message: str) -> None:
    params = SatParams()
    state = initial_state(Mixture.empty(), 0.0, params)
    with pytest.raises(InputError, match=message):
        step(state, scan, params, GpPredictor(params.gp))
