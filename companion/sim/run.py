"""The filter-only simulation: one scenario, one seed -> time series and the contract's summary.

The run is a pure function of (scenario, seed) except for the measured step times. Measurements
come straight from the sensor model (no camera, no projection), as in the paper's study.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from companion.metrics import (
    gospa_assignment,
    mahalanobis_to_tracks,
    ospa,
    summarize_mahalanobis,
)
from companion.plan.planners import (
    LawnMower,
    Planner,
    PlannerKind,
    PlanProgress,
    lawnmower_path,
    make_planner,
    move_towards,
)
from companion.plan.search_track import SearchTrackParams, inscribed_radius_m
from companion.plan.world import World
from companion.sat.filter import SatParams, SatState, Scan, initial_state, step
from companion.sat.fov import ConvexPolygon, Disk, Region
from companion.sat.gp import GpPredictor
from companion.sat.mixture import Mixture
from companion.sat.params import FovKind, sat_params
from companion.sat.tracks import grown_covs
from companion.sim.belief import initial_belief
from companion.sim.scenario import Scenario
from companion.sim.sensor import SensorModel, sense
from companion.sim.truth import Truth, advance_truth, initial_truth

FloatArray = NDArray[np.float64]
Progress = Callable[[int, int], None]


def filter_params(s: Scenario) -> SatParams:
    """The filter's parameters from a scenario's [filter] and [sensor] tables; the world is the
    search area."""
    width_m, height_m = s.world.size_m
    area_xy = np.array([[0.0, 0.0], [width_m, 0.0], [width_m, height_m], [0.0, height_m]])
    return sat_params(s.filter, s.sensor.p_detect, s.sensor.clutter_prob + s.sensor.clutter_rate,
                      s.dt_s, area_xy, s.sensor.noise_std_m)


def scenario_planner(s: Scenario, world: World) -> Planner:
    """The scenario's planner."""
    r = s.robot
    search = search_params(s) if r.planner == PlannerKind.SEARCH_TRACK else None
    return make_planner(r.planner, world, np.array(r.start_xy), r.lane_spacing_m, r.sweeps,
                        search)


def search_params(s: Scenario) -> SearchTrackParams:
    """What the search-and-track planner knows in a scenario: the sure view (the FOV disk, or
    the disk inside the camera footprint), p(D|F), the targets' motion class and its stop rule."""
    if s.sensor.fov == FovKind.DISK:
        view_m = s.sensor.fov_radius_m
    else:
        view_m = inscribed_radius_m(s.sensor.fov_polygon_xy)
    return SearchTrackParams(
        view_radius_m=view_m, p_detect=s.sensor.p_detect, unseen_targets=s.robot.unseen_targets,
        stop_below=s.robot.stop_when_left, motion=filter_params(s).tracks.motion,
    )


def planned_steps(s: Scenario, world: World) -> int:
    """Steps to run: the scenario's, or the lawn mower's duration when it says 0.

    A non-lawn-mower planner with steps = 0 gets the lawn mower's duration over the same world,
    so that planners are compared over equal time, as in the paper.
    """
    if s.steps > 0:
        return s.steps
    path = lawnmower_path(world, np.array(s.robot.start_xy), s.robot.lane_spacing_m, s.robot.sweeps)
    legs = np.diff(np.vstack([s.robot.start_xy, path]), axis=0)
    return math.ceil(float(np.hypot(*legs.T).sum()) / (s.robot.speed_m_s * s.dt_s) - 1e-9)


def sensing_region(s: Scenario, robot_xy: FloatArray) -> Region:
    """The FOV on the ground for a robot at robot_xy."""
    if s.sensor.fov != FovKind.DISK:
        return ConvexPolygon(s.sensor.fov_polygon_xy + robot_xy)
    return Disk(robot_xy.copy(), s.sensor.fov_radius_m)


def _fly(
    planner: Planner,
    robot_xy: FloatArray,
    state: SatState,
    world: World,
    progress: PlanProgress,
    budget_m: float,
) -> tuple[FloatArray, PlanProgress]:
    """Move the robot by up to budget_m along its plan (through several waypoints if need be)."""
    while budget_m > 1e-12:
        waypoint, progress = planner.next_waypoint(
            robot_xy, state.mixture, state.tracks, world, progress, state.t_s
        )
        if waypoint is None:
            break
        nxt = move_towards(robot_xy, waypoint, budget_m)
        moved = float(np.hypot(*(nxt - robot_xy)))
        robot_xy = nxt
        budget_m -= moved
        if moved == 0.0 or not isinstance(planner, LawnMower):
            break
    return robot_xy, progress


@dataclass(frozen=True, slots=True)
class SimResult:
    """Time series of one run (index k = step k, k = 1..K) and its final state."""

    scenario: Scenario
    seed: int
    wall_s: float
    t_s: FloatArray
    robot_xy: FloatArray  # (K + 1, 2), the start included
    true_count: NDArray[np.int64]
    tracks_confirmed: NDArray[np.int64]
    weight_sum: FloatArray
    components: NDArray[np.int64]
    ospa: FloatArray
    gospa: FloatArray  # GOSPA (alpha = 2, c = metrics.gospa_c, p = metrics.ospa_p), m
    gospa_localisation: FloatArray  # its localisation part, m
    gospa_missed: NDArray[np.int64]  # true targets without a confirmed track within gospa_c
    gospa_false: NDArray[np.int64]  # confirmed tracks without a true target within gospa_c
    nees: FloatArray  # mean NEES over the true targets GOSPA assigns a track (nan: none)
    nees_count: NDArray[np.int64]  # how many true targets that mean is over
    mahal_closest_mean: FloatArray
    mahal_second_mean: FloatArray
    max_track_var_m2: FloatArray  # largest position variance among confirmed tracks (nan: none)
    step_ms: FloatArray
    measurements: FloatArray  # (M, 3): step, x, y
    is_clutter: NDArray[np.bool_]  # (M,)
    final_truth_xy: FloatArray
    final_state: SatState

    def summary(self) -> dict[str, Any]:
        """The JSON object of the `simulate --json` contract."""
        state = self.final_state
        confirmed = state.tracks.confirmed
        track_params = filter_params(self.scenario).tracks
        covs = grown_covs(state.tracks, state.t_s, track_params.motion)
        coasting = confirmed & state.tracks.coasting(state.t_s, track_params.coast_after_s)
        closest, second = mahalanobis_to_tracks(
            self.final_truth_xy, state.tracks.means[confirmed, :2], covs[confirmed, :2, :2]
        )
        k = self.t_s.size
        tail = slice(k - max(1, k // 5), None)  # the last 20 % of steps
        assigned = self.nees_count > 0
        nees_sums = self.nees[assigned] * self.nees_count[assigned]  # per step
        all_confirmed = np.flatnonzero((self.true_count > 0) & (self.gospa_missed == 0))
        out: dict[str, Any] = {
            "scenario": self.scenario.name,
            "seed": self.seed,
            "steps": k,
            "wall_s": self.wall_s,
            "step_ms_median": float(np.median(self.step_ms)),
            "step_ms_p95": float(np.percentile(self.step_ms, 95)),
            "filter_s": float(self.step_ms.sum() / 1e3),
            "true_count": int(self.true_count[-1]),
            "tracks_confirmed": int(self.tracks_confirmed[-1]),
            "tracks_coasting": int(coasting.sum()),
            "weight_sum": float(self.weight_sum[-1]),
            "components": int(self.components[-1]),
            **summarize_mahalanobis(closest, second),
            "ospa_mean": float(self.ospa.mean()),
            "ospa_tail_mean": float(self.ospa[tail].mean()),
            "ospa_final": float(self.ospa[-1]),
            "gospa_final": float(self.gospa[-1]),
            "gospa_tail_mean": float(self.gospa[tail].mean()),
            "gospa_localisation_final": float(self.gospa_localisation[-1]),
            "gospa_missed_final": int(self.gospa_missed[-1]),
            "gospa_false_final": int(self.gospa_false[-1]),
            # Pooled over every (step, true target) pair, not a mean of the per-step means.
            "nees_mean": (
                float(nees_sums.sum() / self.nees_count.sum()) if assigned.any() else math.nan
            ),
            "t_all_confirmed_s": float(self.t_s[all_confirmed[0]]) if all_confirmed.size else None,
        }
        return {key: _json_number(value) for key, value in out.items()}


def _json_number(value: Any) -> Any:
    """inf and nan become None (JSON null); everything else passes."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


@dataclass(frozen=True, slots=True)
class Start:
    """What a run starts from: its world, filter parameters, sensor model, random generators
    (truth and sensor, derived from the seed), the truth at step 0 and the initial belief."""

    world: World
    params: SatParams
    sensor: SensorModel
    truth_rng: np.random.Generator
    sensor_rng: np.random.Generator
    truth: Truth
    belief: Mixture


def start(s: Scenario) -> Start:
    """The start of a run of scenario s with its seed."""
    world = World(*s.world.size_m)
    params = filter_params(s)
    sensor = SensorModel(
        s.sensor.p_detect, s.sensor.noise_std_m, s.sensor.clutter_prob, s.sensor.clutter_rate
    )
    truth_rng, sensor_rng, belief_rng = (
        np.random.default_rng(child) for child in np.random.SeedSequence(s.seed).spawn(3)
    )
    tg = s.targets
    truth = initial_truth(tg.positions_xy, tg.count, tg.appear, world, truth_rng)
    belief = initial_belief(
        s.belief.kind,
        s.belief.count,
        s.belief.offset_m,
        s.belief.variance_m2,
        [(c.weight, np.array(c.mean_xy), c.cov) for c in s.belief.components],
        truth.alive_xy,
        world,
        belief_rng,
        params.linear_model.state_dim,
        params.velocity_var_m2_s2,
    )
    return Start(world, params, sensor, truth_rng, sensor_rng, truth, belief)


def scans_of(result: SimResult) -> list[Scan]:
    """The scans a run fed its filter, step by step, rebuilt from its robot track and
    measurements (the sensing region follows from the robot's position)."""
    s = result.scenario
    r_cov = s.sensor.noise_std_m**2 * np.eye(2)
    step_of = result.measurements[:, 0].astype(np.int64)
    return [
        Scan(t_s, sensing_region(s, result.robot_xy[k]), result.measurements[step_of == k, 1:],
             r_cov, result.robot_xy[k].copy())
        for k, t_s in enumerate(result.t_s.tolist(), start=1)
    ]


def simulate(s: Scenario, progress: Progress | None = None) -> SimResult:
    """Run one scenario with its seed."""
    wall_start = time.perf_counter()
    begin = start(s)
    world, params, truth, truth_rng = begin.world, begin.params, begin.truth, begin.truth_rng
    tg = s.targets
    n_initial = int(truth.alive.sum())
    state = initial_state(begin.belief, 0.0, params)
    gp = GpPredictor(params.gp)
    planner = scenario_planner(s, world)
    r_cov = s.sensor.noise_std_m**2 * np.eye(2)

    n_steps = planned_steps(s, world)
    robot = np.array(s.robot.start_xy, dtype=np.float64)
    progress_idx: PlanProgress = 0
    series: dict[str, list[float]] = {
        key: []
        for key in (
            "t", "true", "conf", "wsum", "comp", "ospa", "gospa", "gospa_loc", "gospa_missed",
            "gospa_false", "nees", "nees_count", "mc", "ms", "maxvar", "ms_step", "x", "y",
        )
    }
    series["x"].append(float(robot[0]))
    series["y"].append(float(robot[1]))
    meas_rows: list[FloatArray] = []
    clutter_flags: list[NDArray[np.bool_]] = []
    for k in range(1, n_steps + 1):
        t_s = k * s.dt_s
        truth = advance_truth(
            truth, k, s.dt_s, tg.speed_m_s, tg.turn_every_steps, tg.appear, tg.disappear,
            n_initial, world, truth_rng,
        )
        robot, progress_idx = _fly(
            planner, robot, state, world, progress_idx, s.robot.speed_m_s * s.dt_s
        )
        region = sensing_region(s, robot)
        z, is_clutter = sense(begin.sensor, truth.alive_xy, region, begin.sensor_rng)
        scan = Scan(t_s, region, z, r_cov, robot)
        started = time.perf_counter_ns()
        state, _ = step(state, scan, params, gp)
        series["ms_step"].append((time.perf_counter_ns() - started) / 1e6)

        tracks = state.tracks
        conf = tracks.confirmed
        truth_xy = truth.alive_xy
        covs = grown_covs(tracks, t_s, params.tracks.motion)
        conf_xy, conf_covs = tracks.means[conf, :2], covs[conf, :2, :2]
        closest, second = mahalanobis_to_tracks(truth_xy, conf_xy, conf_covs)
        mahal = summarize_mahalanobis(closest, second)
        var = covs[conf][:, [0, 1], [0, 1]]
        series["t"].append(t_s)
        series["true"].append(truth_xy.shape[0])
        series["conf"].append(int(conf.sum()))
        series["wsum"].append(state.mixture.total_weight)
        series["comp"].append(state.mixture.size)
        series["ospa"].append(ospa(conf_xy, truth_xy, s.metrics.ospa_p, s.metrics.ospa_c))
        g = gospa_assignment(conf_xy, truth_xy, s.metrics.gospa_c, s.metrics.ospa_p)
        series["gospa"].append(g.total_m)
        series["gospa_loc"].append(g.localisation_m)
        series["gospa_missed"].append(g.missed)
        series["gospa_false"].append(g.false)
        # NEES of each assigned true target: d^T P^-1 d, d = target - track, P its 2x2 covariance.
        err = truth_xy[g.truth_idx] - conf_xy[g.estimate_idx]  # (n, 2)
        p_inv_err = np.linalg.solve(conf_covs[g.estimate_idx], err[..., None])[..., 0]
        nees = np.einsum("ki,ki->k", err, p_inv_err)
        series["nees"].append(float(nees.mean()) if nees.size else math.nan)
        series["nees_count"].append(nees.size)
        series["mc"].append(mahal["mahal_closest_mean"])
        series["ms"].append(mahal["mahal_second_mean"])
        series["maxvar"].append(float(var.max()) if var.size else math.nan)
        series["x"].append(float(robot[0]))
        series["y"].append(float(robot[1]))
        if z.shape[0]:
            meas_rows.append(np.column_stack([np.full(z.shape[0], k), z]))
            clutter_flags.append(is_clutter)
        if progress is not None:
            progress(k, n_steps)

    return SimResult(
        scenario=s,
        seed=s.seed,
        wall_s=time.perf_counter() - wall_start,
        t_s=np.array(series["t"]),
        robot_xy=np.column_stack([series["x"], series["y"]]),
        true_count=np.array(series["true"], dtype=np.int64),
        tracks_confirmed=np.array(series["conf"], dtype=np.int64),
        weight_sum=np.array(series["wsum"]),
        components=np.array(series["comp"], dtype=np.int64),
        ospa=np.array(series["ospa"]),
        gospa=np.array(series["gospa"]),
        gospa_localisation=np.array(series["gospa_loc"]),
        gospa_missed=np.array(series["gospa_missed"], dtype=np.int64),
        gospa_false=np.array(series["gospa_false"], dtype=np.int64),
        nees=np.array(series["nees"]),
        nees_count=np.array(series["nees_count"], dtype=np.int64),
        mahal_closest_mean=np.array(series["mc"]),
        mahal_second_mean=np.array(series["ms"]),
        max_track_var_m2=np.array(series["maxvar"]),
        step_ms=np.array(series["ms_step"]),
        measurements=np.concatenate(meas_rows) if meas_rows else np.zeros((0, 3)),
        is_clutter=np.concatenate(clutter_flags) if clutter_flags else np.zeros(0, dtype=bool),
        final_truth_xy=truth.alive_xy,
        final_state=state,
    )
