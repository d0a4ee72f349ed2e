"""Planners: the lawn-mower path, nearest- and largest-Gaussian, and the robot's motion."""

from __future__ import annotations

import numpy as np

from companion.plan.planners import (
    LargestGaussian,
    LawnMower,
    NearestGaussian,
    lawnmower_path,
    move_towards,
)
from companion.plan.world import World
from companion.sat.mixture import Mixture, make_mixture
from companion.sat.tracks import Tracks

WORLD = World(150.0, 150.0)
NO_TRACKS = Tracks.empty(2, 4)


def test_lawnmower_lanes_cover_the_world_and_return_to_start() -> None:
    path = lawnmower_path(WORLD, np.zeros(2), 25.0, sweeps=2)
    lanes = np.unique(path[:, 0][path[:, 0] > 0])
    np.testing.assert_allclose(lanes, [12.5, 37.5, 62.5, 87.5, 112.5, 137.5])
    assert path.shape == (2 * (2 * 6 + 1), 2)
    np.testing.assert_array_equal(path[12], [0.0, 0.0])  # back to the start after a sweep
    np.testing.assert_array_equal(path[-1], [0.0, 0.0])
    # Boustrophedon: north on the first lane, south on the second.
    assert path[0, 1] == 0.0 and path[1, 1] == 150.0 and path[2, 1] == 150.0


def test_lawnmower_advances_past_reached_waypoints_and_finishes() -> None:
    planner = LawnMower(np.array([[0.0, 0.0], [10.0, 0.0]]))
    waypoint, progress = planner.next_waypoint(np.zeros(2), Mixture.empty(), NO_TRACKS, WORLD, 0)
    assert progress == 1 and waypoint is not None and waypoint.tolist() == [10.0, 0.0]
    waypoint, progress = planner.next_waypoint(
        np.array([10.0, 0.0]), Mixture.empty(), NO_TRACKS, WORLD, progress
    )
    assert waypoint is None and planner.finished(progress)


def test_nearest_and_largest_gaussian() -> None:
    mix = make_mixture(
        [1.0, 0.2, 0.5],
        [[10.0, 0.0], [100.0, 100.0], [50.0, 50.0]],
        [np.eye(2), 40.0 * np.eye(2), 5.0 * np.eye(2)],
    )
    robot = np.array([12.0, 1.0])
    near, _ = NearestGaussian().next_waypoint(robot, mix, NO_TRACKS, WORLD, 0)
    large, _ = LargestGaussian().next_waypoint(robot, mix, NO_TRACKS, WORLD, 0)
    assert near is not None and near.tolist() == [10.0, 0.0]
    assert large is not None and large.tolist() == [100.0, 100.0]
    outside = make_mixture([1.0], [[-30.0, 200.0]], [np.eye(2)])
    clipped, _ = NearestGaussian().next_waypoint(robot, outside, NO_TRACKS, WORLD, 0)
    assert clipped is not None and clipped.tolist() == [0.0, 150.0]  # waypoints stay inside
    assert NearestGaussian().next_waypoint(robot, Mixture.empty(), NO_TRACKS, WORLD, 0)[0] is None


def test_move_towards_caps_the_step() -> None:
    np.testing.assert_allclose(move_towards(np.zeros(2), np.array([3.0, 4.0]), 1.0), [0.6, 0.8])
    np.testing.assert_allclose(move_towards(np.zeros(2), np.array([0.3, 0.4]), 1.0), [0.3, 0.4])
    np.testing.assert_array_equal(move_towards(np.ones(2), None, 1.0), [1.0, 1.0])
