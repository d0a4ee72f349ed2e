"""The plan's keep-in polygon: clearances, lanes cut to it, targets moved into it, and the lawn
mower flown inside a geofence."""

from __future__ import annotations

import numpy as np
import pytest

from companion.errors import InputError
from companion.plan.keep_in import KeepIn, clearance_m
from companion.plan.planners import lawnmower_path
from companion.plan.world import World

BOX = np.array([[0.0, 0.0], [30.0, 0.0], [30.0, 24.0], [0.0, 24.0]])
# A U: two arms 10 m wide joined along the south; the notch is x in (10, 20), y > 10.
U_SHAPE = np.array([[0.0, 0.0], [30.0, 0.0], [30.0, 40.0], [20.0, 40.0], [20.0, 10.0],
                    [10.0, 10.0], [10.0, 40.0], [0.0, 40.0]])


def _leg_points(starts: np.ndarray, ends: np.ndarray, step_m: float = 0.05) -> np.ndarray:
    """Points every step_m along each leg from starts[i] to ends[i]."""
    legs = [np.linspace(a, b, max(int(np.hypot(*(b - a)) / step_m), 1) + 1)
            for a, b in zip(starts, ends, strict=True)]
    return np.concatenate(legs)


def test_clearance_is_the_distance_to_the_boundary_and_negative_outside() -> None:
    got = clearance_m(np.array([[15.0, 12.0], [1.0, 5.0], [-2.0, 5.0], [33.0, 28.0]]), BOX)
    np.testing.assert_allclose(got, [12.0, 1.0, -2.0, -5.0])


def test_lane_runs_keep_the_clearance_and_skip_a_notch() -> None:
    keep = KeepIn(U_SHAPE, 2.0)
    runs = keep.lane_runs(15.0)  # across the notch: the bottom bar only
    assert len(runs) == 1 and runs[0][0] == pytest.approx(2.0, abs=0.1)
    assert runs[0][1] == pytest.approx(8.0, abs=0.1)
    assert keep.lane_runs(5.0)[0] == pytest.approx((2.0, 38.0), abs=0.1)
    assert keep.lane_runs(0.5) == []  # within the clearance of the west side all along
    assert keep.x_range() == (2.0, 28.0)


def test_nearest_moves_a_point_into_the_clearance_and_leaves_one_there_alone() -> None:
    keep = KeepIn(BOX, 3.0)
    inside = np.array([10.0, 10.0])
    assert keep.nearest(inside) is not None and np.array_equal(keep.nearest(inside), inside)
    for xy in ([-5.0, 30.0], [1.0, 1.0], [15.0, 0.0], [31.0, 12.0], [0.0, 0.0]):
        moved = keep.nearest(np.array(xy))
        assert clearance_m(moved, BOX)[0] >= 3.0 - 1e-9, xy
        assert np.hypot(*(moved - np.clip(xy, 3.0, [27.0, 21.0]))) < 1e-6, xy
    notch = KeepIn(U_SHAPE, 2.0).nearest(np.array([15.0, 30.0]))  # in the notch, outside
    assert clearance_m(notch, U_SHAPE)[0] >= 2.0 - 1e-9


def test_a_keep_in_needs_a_polygon_and_a_clearance() -> None:
    with pytest.raises(InputError, match="expected"):
        KeepIn(np.zeros((2, 2)), 1.0)
    with pytest.raises(InputError, match="clearance_m"):
        KeepIn(BOX, -1.0)


@pytest.mark.parametrize("polygon", [BOX, U_SHAPE], ids=["box", "u-shape"])
def test_the_lawn_mower_flies_its_lanes_inside_the_clearance(polygon: np.ndarray) -> None:
    """Every waypoint keeps 3 m inside, and every lane all along (to the 0.1 m the lanes are
    cut to); a transit from lane to lane may cut a corner (the gate keeps it inside)."""
    size = polygon.max(axis=0)
    world = World(float(size[0]), float(size[1]))
    path = lawnmower_path(world, np.zeros(2), 8.0, 2, KeepIn(polygon, 3.0))
    assert clearance_m(path, polygon).min() >= 3.0 - 1e-9
    lanes = path[:-1, 0] == path[1:, 0]  # legs along a lane
    along = _leg_points(path[:-1][lanes], path[1:][lanes])
    assert clearance_m(along, polygon).min() >= 3.0 - 0.05
    # Every lane's x keeps the clearance from the sides; the box's east lane is moved in.
    xs = np.unique(path[:, 0])
    assert xs.min() >= 3.0 and xs.max() <= size[0] - 3.0
    assert len(path) % 2 == 0 and np.array_equal(path[len(path) // 2 - 1], path[-1])


def test_a_fence_well_outside_the_world_leaves_the_lawn_mower_as_it_was() -> None:
    world = World(30.0, 24.0)
    grown = BOX + np.array([[-5.0, -5.0], [5.0, -5.0], [5.0, 5.0], [-5.0, 5.0]])
    np.testing.assert_array_equal(
        lawnmower_path(world, np.zeros(2), 8.0, 1, KeepIn(grown, 3.0)),
        lawnmower_path(world, np.zeros(2), 8.0, 1))


def test_a_side_not_quite_north_south_keeps_its_lane() -> None:
    """The area's UTM outline turned by a grid convergence of 0.3 degrees: the east lane, which
    the fence's extent alone would put where the turned side leaves it a metre, is moved in to
    where it runs the whole height."""
    turn = np.radians(0.3)
    rotation = np.array([[np.cos(turn), -np.sin(turn)], [np.sin(turn), np.cos(turn)]])
    polygon = BOX @ rotation.T
    polygon -= polygon.min(axis=0)
    size = polygon.max(axis=0)
    path = lawnmower_path(World(float(size[0]), float(size[1])), np.zeros(2), 8.0, 1,
                          KeepIn(polygon, 3.0))
    lanes = path[:-1].reshape(-1, 2, 2)
    assert len(lanes) == 4
    assert np.all(np.abs(lanes[:, 1, 1] - lanes[:, 0, 1]) > 24.0 - 2 * 3.0 - 0.5)
    assert 26.5 < lanes[-1, 0, 0] < size[0] - 3.0
