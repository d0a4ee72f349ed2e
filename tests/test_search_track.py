"""The search-and-track planner: coverage, goals, stop rule, area, validation and speed."""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from companion.config import parse_config
from companion.errors import ConfigError, InputError
from companion.pipeline import SearchFrame
from companion.plan.planners import PlannerKind, make_planner, move_towards
from companion.plan.search_track import (
    SearchProgress,
    SearchTrack,
    SearchTrackParams,
    best_order,
    inscribed_radius_m,
    inside_polygon,
    make_search_track,
)
from companion.plan.setpoints import Carrot
from companion.plan.setpoints import search_params as setpoint_search_params
from companion.plan.world import World
from companion.sat.mixture import Mixture, make_mixture
from companion.sat.params import sat_params
from companion.sat.tracks import Tracks
from companion.scenario_lookup import resolve_scenario
from companion.sim.battery import family_scenario
from companion.sim.run import search_params, simulate
from companion.sim.scenario import load_scenario, parse_scenario, scenario_to_dict
from companion.vision.camera import CameraModel

WORLD = World(150.0, 150.0)
NO_TRACKS = Tracks.empty(2, 4)
PARAMS = SearchTrackParams(view_radius_m=25.0)


def _fly(planner: SearchTrack, mixture: Mixture, steps: int, step_m: float = 0.5,
         start: tuple[float, float] = (0.0, 0.0)) -> tuple[np.ndarray, SearchProgress]:
    """Fly the planner from start for `steps` steps of step_m over a fixed mixture."""
    robot = np.array(start)
    progress: SearchProgress | int = 0
    path = [robot]
    for k in range(steps):
        waypoint, progress = planner.next_waypoint(robot, mixture, NO_TRACKS, WORLD, progress,
                                                   float(k))
        robot = move_towards(robot, waypoint, step_m)
        path.append(robot)
    assert isinstance(progress, SearchProgress)
    return np.array(path), progress


def test_with_nothing_known_it_stops_once_the_expected_count_left_is_below_its_threshold() -> None:
    planner = make_search_track(WORLD, PARAMS)
    _, progress = _fly(planner, Mixture.empty(), 2000, step_m=1.0)
    assert planner.finished(progress) and progress.left < PARAMS.stop_below
    # 1 target expected over the area, 0.05 left: at least 95 % of the cells were looked at.
    assert (progress.looks > 0).mean() >= 0.95 and not (progress.looks > 0).all()


def test_when_one_look_is_not_enough_it_looks_again_until_its_stop_rule_holds() -> None:
    # 6 targets expected and p_D 0.95: one look everywhere leaves 0.3 > 0.05 to find. It used to
    # hover with no goal once every cell was looked at, its search never ending.
    params = replace(PARAMS, unseen_targets=6.0, p_detect=0.95, look_s=1e3)
    planner = make_search_track(WORLD, params)
    robot, stalled = np.zeros(2), 0
    progress: SearchProgress | int = 0
    for k in range(3000):
        waypoint, progress = planner.next_waypoint(robot, Mixture.empty(), NO_TRACKS, WORLD,
                                                   progress, float(k))
        if planner.finished(progress):
            break
        stalled += waypoint is None
        robot = move_towards(robot, waypoint, 1.0)
    assert isinstance(progress, SearchProgress)
    assert planner.finished(progress) and progress.left < params.stop_below and stalled == 0
    # left = 6 (0.05 f1 + 0.0025 (1 - f1)) < 0.05 with f1 the share of cells looked at once
    assert (progress.looks >= 2).mean() >= 0.85


def test_with_nothing_known_it_covers_the_whole_area() -> None:
    planner = make_search_track(WORLD, SearchTrackParams(view_radius_m=25.0, stop_below=0.0))
    path, progress = _fly(planner, Mixture.empty(), 2000, step_m=1.0)
    assert (progress.looks > 0).all()  # every cell was looked at
    # Every point of the world came within the view of the path.
    grid = np.stack(np.meshgrid(np.linspace(0, 150, 31), np.linspace(0, 150, 31)), -1)
    d = np.hypot(*(grid.reshape(-1, 1, 2) - path[None, :, :]).transpose(2, 0, 1))
    assert d.min(axis=1).max() <= PARAMS.view_radius_m
    # ... flying less than a lawn mower with lanes one view radius apart (about 1,150 m).
    assert np.hypot(*np.diff(path[: np.argmax(_covered(path))], axis=0).T).sum() < 1000.0


def _covered(path: np.ndarray) -> np.ndarray:
    """Whether the whole world is within 25 m of the path so far, per step (slow, small)."""
    axis = np.linspace(0, 150, 16)
    grid = np.stack(np.meshgrid(axis, axis), -1).reshape(-1, 2)
    seen = np.zeros(grid.shape[0], dtype=bool)
    out = np.zeros(path.shape[0], dtype=bool)
    for k, p in enumerate(path):
        seen |= np.hypot(*(grid - p).T) <= 25.0
        out[k] = seen.all()
    return out


def test_it_flies_to_unexplained_mass_before_sweeping() -> None:
    planner = make_search_track(WORLD, PARAMS)
    mix = make_mixture([3.0], np.array([[120.0, 120.0]]), np.array([50.0 * np.eye(2)]))
    _, progress = planner.next_waypoint(np.zeros(2), mix, NO_TRACKS, WORLD, 0, 0.0)
    assert not planner.finished(progress) and progress.left > 3.0
    path, _ = _fly(planner, mix, 400, step_m=1.0)
    # Three targets' worth 170 m away: it looks at them after one lane of sweep on the way.
    in_view = np.hypot(*(path - [120.0, 120.0]).T) <= planner.seen_m + 1.0
    assert 0 < int(np.argmax(in_view)) <= 250


def test_a_component_of_a_confirmed_track_is_not_searched_for() -> None:
    planner = make_search_track(WORLD, PARAMS)
    mix = make_mixture([1.0], np.array([[120.0, 120.0]]), np.array([np.eye(2)]))
    mix = Mixture(mix.weights, mix.means, mix.covs, np.array([7]))
    tracks = _one_track(7, [120.0, 120.0], var_m2=1.0, seen_t_s=0.0)
    waypoint, _ = planner.next_waypoint(np.zeros(2), mix, tracks, WORLD, 0, 0.0)
    assert waypoint is not None and not np.allclose(waypoint, [120.0, 120.0])  # it sweeps


def test_prior_mass_worn_down_with_no_track_is_still_searched_for_where_the_prior_put_it() -> None:
    planner = make_search_track(WORLD, SearchTrackParams(view_radius_m=25.0, unseen_targets=0.0))
    mean, cov = np.array([[120.0, 120.0]]), np.array([50.0 * np.eye(2)])
    _, progress = planner.next_waypoint(np.zeros(2), make_mixture([1.0], mean, cov), NO_TRACKS,
                                        WORLD, 0, 0.0)
    # The limited-FOV update wore the component down to 0.05 and no track holds the target.
    worn = make_mixture([0.05], mean, cov)
    waypoint, lost = planner.next_waypoint(np.zeros(2), worn, NO_TRACKS, WORLD, progress, 1.0)
    assert lost.left > 0.9 and not planner.finished(lost)
    assert waypoint is not None and np.hypot(*(waypoint - mean[0])) < planner.seen_m
    # A confirmed track near the prior's mean holds that target: nothing is lost.
    track = _one_track(3, [118.0, 121.0], var_m2=1.0, seen_t_s=1.0)
    _, held = planner.next_waypoint(np.zeros(2), worn, track, WORLD, progress, 1.0)
    assert held.left < 0.1


def test_lost_mass_left_on_both_sides_of_a_looked_band_is_flown_to_not_hovered_over() -> None:
    planner = make_search_track(WORLD, SearchTrackParams(view_radius_m=25.0, unseen_targets=0.0))
    mean, cov = np.array([[75.0, 75.0]]), np.array([50.0 * np.eye(2)])
    robot = mean[0].copy()
    _, progress = planner.next_waypoint(robot, make_mixture([1.0], mean, cov), NO_TRACKS, WORLD,
                                        0, 0.0)
    # A north-south band through the prior's mean was looked at and its target not found: what
    # is left lies west and east of it, and its centroid on the band, where the robot is.
    band = np.abs(planner.cells_xy[:, 0] - 75.0) < 10.0
    assert isinstance(progress, SearchProgress)
    progress = replace(progress, looks=np.where(band, 3, progress.looks))
    worn = make_mixture([0.01], mean, cov)
    _, after = planner.next_waypoint(robot, worn, NO_TRACKS, WORLD, progress, 1.0)
    assert after.left > 0.2
    for k in range(2, 1000):  # it goes to look at both parts, and its search ends
        waypoint, after = planner.next_waypoint(robot, worn, NO_TRACKS, WORLD, after, float(k))
        if waypoint is None:
            break
        robot = move_towards(robot, waypoint, 0.5)
    assert planner.finished(after), f"hovering at {robot} with {after.left:.2f} left"


def _one_track(track_id: int, xy: list[float], var_m2: float, seen_t_s: float) -> Tracks:
    """A confirmed track alone at xy with that position variance."""
    empty = Tracks.empty(2, 4)
    one: dict[str, Any] = {
        name: np.zeros((1, *getattr(empty, name).shape[1:]), getattr(empty, name).dtype)
        for name in ("ids", "hits", "life", "confirmed", "born_t_s", "last_t_s", "seen_t_s",
                     "score", "alone", "means", "covs", "win_t_s", "win_xy", "win_count",
                     "gp_mu", "gp_beta", "gp_ky_inv")}
    one["ids"][0], one["confirmed"][0], one["score"][0] = track_id, True, 10.0
    one["means"][0], one["covs"][0] = xy, var_m2 * np.eye(2)
    one["seen_t_s"][0] = one["last_t_s"][0] = seen_t_s
    return empty._replace(**one)


def test_an_uncertain_track_is_revisited_and_a_sharp_one_is_not() -> None:
    params = SearchTrackParams(view_radius_m=25.0, stop_below=100.0)  # no search left
    planner = make_search_track(WORLD, params)
    sharp = _one_track(1, [100.0, 100.0], var_m2=1.0, seen_t_s=0.0)
    assert planner.next_waypoint(np.zeros(2), Mixture.empty(), sharp, WORLD, 0, 0.0)[0] is None
    vague = _one_track(1, [100.0, 100.0], var_m2=150.0, seen_t_s=0.0)
    waypoint, _ = planner.next_waypoint(np.zeros(2), Mixture.empty(), vague, WORLD, 0, 0.0)
    assert waypoint is not None and np.allclose(waypoint, [100.0, 100.0])


def test_with_every_cell_looked_at_it_looks_at_what_is_left_before_revisiting_tracks() -> None:
    planner = make_search_track(WORLD, PARAMS)
    looked = replace(planner.start(), looks=np.ones(planner.cells_xy.shape[0], dtype=np.int64))
    # A clutter-born component far off holds 0.2 targets: the search cannot end until a look
    # wears it down, so the near track that wants a revisit must wait (else it never ends).
    far = make_mixture([0.2], np.array([[140.0, 140.0]]), np.array([np.eye(2)]))
    vague = _one_track(1, [20.0, 20.0], var_m2=150.0, seen_t_s=0.0)
    waypoint, progress = planner.next_waypoint(np.zeros(2), far, vague, WORLD, looked, 0.0)
    assert not planner.finished(progress)
    assert waypoint is not None and np.allclose(waypoint, [140.0, 140.0])


def test_best_order_takes_the_near_goal_first_when_both_are_worth_the_same() -> None:
    goals = np.array([[100.0, 0.0], [10.0, 0.0]])
    assert best_order(np.zeros(2), goals, np.array([1.0, 1.0]), 150.0).tolist() == [1, 0]
    # A far goal worth much more comes first.
    assert best_order(np.zeros(2), np.array([[10.0, 0.0], [-100.0, 0.0]]),
                      np.array([0.1, 5.0]), 150.0)[0] == 1


def test_goals_stay_inside_a_polygon_area() -> None:
    triangle = np.array([[0.0, 0.0], [150.0, 0.0], [0.0, 150.0]])
    planner = make_search_track(WORLD, SearchTrackParams(view_radius_m=10.0, area_xy=triangle))
    assert inside_polygon(planner.cells_xy, triangle).all()
    outside = make_mixture([3.0], np.array([[140.0, 140.0]]), np.array([np.eye(2)]))
    robot: np.ndarray = np.array([5.0, 5.0])
    progress: SearchProgress | int = 0
    for k in range(400):
        waypoint, progress = planner.next_waypoint(robot, outside, NO_TRACKS, WORLD, progress,
                                                   float(k))
        assert waypoint is not None and inside_polygon(waypoint[None, :], triangle)[0]
        robot = move_towards(robot, waypoint, 2.0)


def test_inscribed_radius_of_a_footprint() -> None:
    rect = np.array([[-10.0, -5.0], [10.0, -5.0], [10.0, 5.0], [-10.0, 5.0]])
    assert inscribed_radius_m(rect) == pytest.approx(5.0)
    assert inscribed_radius_m(rect[::-1]) == pytest.approx(5.0)  # either orientation
    assert inscribed_radius_m(rect + np.array([20.0, 0.0])) == 0.0  # the origin outside


@pytest.mark.parametrize(("key", "value"), [
    ("view_radius_m", 0.0), ("p_detect", 1.5), ("unseen_targets", -1.0),
    ("stop_below", float("nan")), ("goals", 9), ("look_s", 0.0),
])
def test_bad_parameters_are_refused_naming_them(key: str, value: float) -> None:
    kwargs: dict[str, float] = {"view_radius_m": 25.0, key: value}
    with pytest.raises(InputError, match=key):
        SearchTrackParams(**kwargs)  # type: ignore[arg-type]


def test_make_planner_builds_it_and_needs_its_parameters() -> None:
    planner = make_planner(PlannerKind.SEARCH_TRACK, WORLD, np.zeros(2), 25.0, 1, PARAMS)
    assert isinstance(planner, SearchTrack)
    with pytest.raises(InputError):
        make_planner(PlannerKind.SEARCH_TRACK, WORLD, np.zeros(2), 25.0, 1)


def test_it_is_pure_the_same_inputs_give_the_same_plan() -> None:
    planner = make_search_track(WORLD, PARAMS)
    mix = make_mixture([0.7, 0.4], np.array([[30.0, 90.0], [120.0, 20.0]]),
                       np.array([20.0 * np.eye(2)] * 2))
    a, _ = _fly(planner, mix, 300)
    b, _ = _fly(planner, mix, 300)
    np.testing.assert_array_equal(a, b)


def test_a_replan_takes_under_20_ms() -> None:
    rng = np.random.default_rng(3)
    planner = make_search_track(WORLD, SearchTrackParams(view_radius_m=10.0))  # 900 cells
    n = 100
    mix = make_mixture(rng.uniform(0.01, 1.0, n), rng.uniform(0, 150, (n, 2)),
                       np.array([20.0 * np.eye(2)] * n))
    progress: SearchProgress | int = 0
    robot = np.array([75.0, 75.0])
    times = []
    for k in range(50):
        started = time.perf_counter()
        _, progress = planner.next_waypoint(robot, mix, NO_TRACKS, WORLD, progress, float(k))
        times.append(time.perf_counter() - started)
    assert float(np.median(times)) < 0.020


# -- where the planner is configured and flown -------------------------------------------------

REPO = Path(__file__).resolve().parent.parent


def _paper(**robot: Any) -> dict[str, Any]:
    """The paper's exact-prior scenario as data, with [robot] overrides."""
    data = scenario_to_dict(load_scenario(resolve_scenario("paper-lawnmower-exact-c10")))
    data["robot"] = {**data["robot"], **robot}
    return data


def test_a_scenario_selects_it_and_its_keys_are_checked() -> None:
    s = parse_scenario(_paper(planner="search-track", stop_when_left=0.2, unseen_targets=3.0))
    assert s.robot.planner == PlannerKind.SEARCH_TRACK
    params = search_params(s)
    assert (params.view_radius_m, params.stop_below, params.unseen_targets) == (25.0, 0.2, 3.0)
    assert parse_scenario(_paper()).robot.stop_when_left == 0.05  # the documented default
    for key, bad in (("stop_when_left", -1.0), ("unseen_targets", "many")):
        with pytest.raises(ConfigError, match=rf"robot\.{key}"):
            parse_scenario(_paper(**{key: bad}))


def test_a_short_simulated_run_flies_it_with_a_camera_footprint() -> None:
    s = load_scenario(REPO / "sitl" / "scenarios" / "walkers-6-targets.toml")
    assert s.robot.planner == PlannerKind.SEARCH_TRACK and s.sensor.fov == "camera"
    # The disk inside the 1280x720, 90-degree camera's footprint at 15 m (30 m x 17 m).
    assert search_params(s).view_radius_m == pytest.approx(15.0 * 720 / 1280, rel=1e-3)
    result = simulate(replace(s, steps=120))
    assert result.summary()["steps"] == 120
    inside = (result.robot_xy >= 0.0) & (result.robot_xy <= np.array(s.world.size_m))
    assert inside.all()
    step_m = np.hypot(*np.diff(result.robot_xy, axis=0).T)
    assert step_m.max() <= s.robot.speed_m_s * s.dt_s + 1e-9 and step_m.sum() > 100.0


def test_the_service_configuration_selects_it_and_checks_its_stop_rule() -> None:
    area = [[47.3977420, 8.5455940], [47.3977420, 8.5459914], [47.3979579, 8.5459914],
            [47.3979579, 8.5455940]]
    base: dict[str, Any] = {"camera": {"source": "0"},
                            "search": {"area": area, "planner": "search-track"}}
    config = parse_config(base)
    assert config.search.planner == PlannerKind.SEARCH_TRACK
    assert config.search.stop_when_left == 0.05
    with pytest.raises(ConfigError, match=r"search\.stop_when_left"):
        parse_config({**base, "search": {**base["search"], "stop_when_left": -0.1}})


def test_in_flight_it_sees_the_camera_footprint_and_its_setpoints_stay_in_the_area() -> None:
    area = [[47.3977420, 8.5455940], [47.3977420, 8.5459914], [47.3979579, 8.5459914],
            [47.3979579, 8.5455940]]
    config = parse_config({"camera": {"source": "0", "hfov_deg": 90.0, "width_px": 1280,
                                      "height_px": 720},
                           "search": {"area": area, "planner": "search-track",
                                      "altitude_m": 15.0, "expected_targets": 4}})
    camera = CameraModel.from_hfov(90.0, 1280, 720)
    frame = SearchFrame.from_config(config.search)
    sat = sat_params(config.filter, 0.95, 0.1, 0.5)
    params = setpoint_search_params(config.search, 0.5, camera, sat, frame.area_xy_m)
    assert params.view_radius_m == pytest.approx(15.0 * 720 / 1280 - 0.5, rel=1e-3)
    assert params.unseen_targets == 4.0
    planner = make_planner(PlannerKind.SEARCH_TRACK, frame.world, np.zeros(2), 8.0, 1, params)
    carrot, vehicle = Carrot(), np.array([1.0, 1.0])
    speed_m_s, dt_s = config.search.speed_m_s, 0.05
    previous = vehicle
    grow = 1e-6 * np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])  # rounding
    for k in range(4000):
        target, carrot = carrot.advance(planner, vehicle, Mixture.empty(), NO_TRACKS,
                                        frame.world, speed_m_s, dt_s, k * dt_s)
        assert inside_polygon(target[None, :], frame.area_xy_m + grow)[0]
        assert np.hypot(*(target - previous)) <= speed_m_s * dt_s + 1e-9
        previous = vehicle = target  # the vehicle follows its carrot
    assert planner.finished(carrot.progress)  # the area was covered: mission.end = "covered"


def test_the_battery_flies_it_beside_the_lawn_mower() -> None:
    plain = family_scenario("moving-slow", 1, "defaults")
    flown = family_scenario("moving-slow", 1, "search-track")
    assert plain.robot.planner == PlannerKind.LAWNMOWER
    assert flown.robot.planner == PlannerKind.SEARCH_TRACK
    assert flown.filter == plain.filter and flown.targets == plain.targets


def test_a_sweep_point_is_flown_to_until_reached_not_swapped_for_a_nearer_one() -> None:
    """The sweep's next point is a goal like any other: moving away from it (say, to look at a
    track) does not make the planner swap it for whichever fresh point is now nearest, which let
    the robot hover between a far sweep point and the tracks beside it."""
    planner = make_search_track(WORLD, PARAMS)
    here = np.array([75.0, 75.0])
    goal, progress = planner.next_waypoint(here, Mixture.empty(), NO_TRACKS, WORLD, 0, 0.0)
    assert goal is not None and np.hypot(*(goal - here)) > 1.0
    away = here - 30.0 * (goal - here) / np.hypot(*(goal - here))
    fresh_nearer = planner.next_waypoint(away, Mixture.empty(), NO_TRACKS, WORLD, 0, 0.0)[0]
    assert fresh_nearer is not None and not np.allclose(fresh_nearer, goal)  # afresh: another
    again, _ = planner.next_waypoint(away, Mixture.empty(), NO_TRACKS, WORLD, progress, 1.0)
    assert again is not None and np.allclose(again, goal)
