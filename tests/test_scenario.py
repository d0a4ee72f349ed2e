"""Tests for companion.sim.scenario: the scenario-format.md contract, every key rule with its exact
message, defaults, round trips, the generated reference, and wrong types never escaping as
anything but ConfigError."""

from __future__ import annotations

import copy
import dataclasses
import json
import math
import tomllib
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.cli import main as companion_main
from companion.errors import ConfigError
from companion.plan.planners import PlannerKind
from companion.sat.gp import GpParams
from companion.sat.params import FilterSpec
from companion.sim import scenario as sc
from companion.sim import scenario_keys as sk
from companion.sim.run import filter_params
from companion.sim.scenario import (
    BeliefComponent,
    BeliefSpec,
    GeoSpec,
    MetricsSpec,
    RobotSpec,
    Scenario,
    SensorSpec,
    TargetsSpec,
    VehicleSpec,
    WorldSpec,
    load_scenario,
    parse_scenario,
    scenario_to_dict,
    schema_markdown,
)
from companion.vision.camera import CameraModel

REPO = Path(__file__).resolve().parent.parent

# The example of scenario-format.md, verbatim.
EXAMPLE = """
name = "paper-lawnmower-exact-c10"
seed = 1                 # the run is a pure function of (file, seed); --seed overrides
dt = 1.0                 # seconds per step
steps = 0                # 0: until the planner's path ends (lawn mower), else that many steps

[world]
size = [150.0, 150.0]    # metres, x by y

[targets]
count = 10               # placed uniformly at random in the world (from the seed) ...
positions = []           # ... or explicit [[x, y], ...]; when given, count must match or be omitted
speed = 0.0              # m/s; 0 = stationary
turn_every = 400         # steps between random heading changes of moving targets
appear = []              # optional [[step, x, y], ...]: targets that enter the world later
disappear = []           # optional [[step, index], ...]: targets that leave

[sensor]
fov = "disk"             # disk (the paper's) | camera (footprint of [camera], SITL)
fov_radius = 25.0        # metres, for fov = "disk"
p_detect = 0.98          # p(D | in FOV)
noise_std = 1.0          # measurement noise std per axis, metres (R = noise_std^2 I)
clutter_prob = 0.1       # probability of one false positive per step, uniform in the FOV
clutter_rate = 0.0       # optional Poisson mean of false positives per step (added to the above)

[robot]
start = [0.0, 0.0]
speed = 0.5              # m/s
planner = "lawnmower"    # lawnmower | nearest-gaussian | largest-gaussian (| others the project adds)
lane_spacing = 25.0      # metres, lawn mower
sweeps = 3               # lawn-mower passes over the whole world, each returning to start

[belief]                 # the initial GM-PHD
kind = "exact"           # exact | under | over | empty | explicit
count = 10               # components for exact/under/over
offset = 15.0            # mean distance of each component from a true target, metres
variance = 50.0          # diagonal covariance entry of each component
components = []          # kind = "explicit": [{weight=1.0, mean=[x,y], cov=[[..],[..]]}, ...]

[filter]
p_survive = 1.0
push_rule = true         # the paper's limited-FOV update rule
push_band = [0.4, 0.6]
extract_weight = 0.5
confirm_length = 3       # l_threshold
prune_weight = 0.001
merge_distance = 10.0    # threshold on the SQUARED Mahalanobis distance (Vo & Ma's U); also the track gate
max_components = 100
motion = "gp"            # gp | linear
process_noise = 0.01     # variance per step per axis of the linear model
birth_weight = 1.0       # weight of a measurement-driven new component (the paper uses 1)

[metrics]
ospa_c = 100.0
ospa_p = 2.0
"""  # noqa: E501

SECTIONS = ("world", "targets", "sensor", "robot", "belief", "filter", "metrics", "geo", "camera",
            "vehicle")


def _error(data: dict[str, Any]) -> str:
    """The message of the ConfigError that parsing data raises."""
    with pytest.raises(ConfigError) as info:
        parse_scenario(data)
    return str(info.value)


def _with(section: str, **keys: Any) -> dict[str, Any]:
    return {section: keys}


# --------------------------------------------------------------------------- the example, defaults


def test_example_parses_with_its_values() -> None:
    s = parse_scenario(tomllib.loads(EXAMPLE))
    assert s.name == "paper-lawnmower-exact-c10"
    assert (s.seed, s.dt_s, s.steps) == (1, 1.0, 0)
    assert s.world == WorldSpec(size_m=(150.0, 150.0))
    assert s.targets.count == 10
    assert s.targets.positions_xy.shape == (0, 2)
    assert (s.targets.speed_m_s, s.targets.turn_every_steps) == (0.0, 400)
    assert s.targets.appear == () and s.targets.disappear == ()
    assert (s.sensor.fov, s.sensor.fov_radius_m, s.sensor.p_detect) == ("disk", 25.0, 0.98)
    assert (s.sensor.noise_std_m, s.sensor.clutter_prob, s.sensor.clutter_rate) == (1.0, 0.1, 0.0)
    assert s.robot == RobotSpec((0.0, 0.0), 0.5, PlannerKind.LAWNMOWER, 25.0, 3)
    assert s.belief == BeliefSpec("exact", 10, 15.0, 50.0, ())
    f = s.filter
    assert (f.p_survive, f.push_rule, f.push_band, f.extract_weight) == (1.0, True, (0.4, 0.6), 0.5)
    assert (f.confirm_length, f.prune_weight, f.merge_distance) == (3, 0.001, 10.0)
    assert (f.max_components, f.motion, f.process_noise, f.birth_weight) == (100, "gp", 0.01, 1.0)
    assert s.metrics == MetricsSpec(ospa_c=100.0, ospa_p=2.0, gospa_c=10.0)


def test_empty_file_and_empty_tables_give_the_documented_defaults() -> None:
    empty_tables = parse_scenario({section: {} for section in SECTIONS}, name="x")
    assert empty_tables == parse_scenario({}, name="x")
    example = parse_scenario(tomllib.loads(EXAMPLE))
    # The defaults are the example's values (the paper's set-up) except name and seed.
    assert dataclasses.replace(example, name="x", seed=0) == empty_tables
    f = empty_tables.filter
    gp = GpParams()
    assert (f.gp_sigma_f, f.gp_lengthscale, f.gp_sigma_n, f.gp_window) == (
        gp.sigma_f_m, gp.lengthscale_s, None, gp.window,
    )
    # unset, the GP's observation noise is the sensor's (learn-gp finds it there)
    assert filter_params(empty_tables).gp.sigma_n_m == empty_tables.sensor.noise_std_m == 1.0
    noisy = parse_scenario({"sensor": {"noise_std": 2.0}}, name="x")
    assert filter_params(noisy).gp.sigma_n_m == 2.0
    told = parse_scenario({"sensor": {"noise_std": 2.0}, "filter": {"gp_sigma_n": 0.4}}, name="x")
    assert filter_params(told).gp.sigma_n_m == 0.4
    assert (f.birth, f.linear_model, f.velocity_variance, f.track_timeout) == (
        "adaptive", "cp", 1.0, 30.0,
    )
    assert empty_tables.sensor.fov_polygon_xy.shape == (0, 2)
    assert empty_tables.name == "x"
    assert parse_scenario({}).name == "scenario"


def test_every_declared_default_is_valid_and_declarations_cover_every_field() -> None:
    top_fields = {f.name for f in dataclasses.fields(Scenario)} - set(SECTIONS)
    assert {k.field for k in sk.TOP_KEYS} == top_fields
    spec_types = {
        "world": WorldSpec, "targets": TargetsSpec, "sensor": SensorSpec, "robot": RobotSpec,
        "belief": BeliefSpec, "filter": FilterSpec, "metrics": MetricsSpec, "geo": GeoSpec,
        "camera": CameraModel, "vehicle": VehicleSpec,
    }
    assert tuple(sk.SECTION_KEYS) == SECTIONS
    for section, keys in sk.SECTION_KEYS.items():
        stored = [k.field for k in keys if k.stored]
        assert stored == [f.name for f in dataclasses.fields(spec_types[section])]
    assert [k.field for k in sk.COMPONENT_KEYS] == [
        f.name for f in dataclasses.fields(BeliefComponent)
    ]


def test_arrays_are_read_only_and_caller_data_untouched() -> None:
    data = {
        "targets": {"positions": [[1.0, 2.0], [3.0, 4.0]]},
        "sensor": {"fov": "polygon", "fov_polygon": [[0, 0], [0, 5], [5, 0]]},  # clockwise
        "belief": {"kind": "explicit", "components": [{"mean": [1, 2]}]},
    }
    before = copy.deepcopy(data)
    s = parse_scenario(data)
    assert data == before
    for arr in (s.targets.positions_xy, s.sensor.fov_polygon_xy, s.belief.components[0].cov):
        assert arr.dtype == np.float64
        with pytest.raises(ValueError, match="read-only"):
            arr[0, 0] = 99.0


# --------------------------------------------------------------------------- round trips, files


ROUND_TRIP_CASES: list[dict[str, Any]] = [
    {},
    tomllib.loads(EXAMPLE),
    {
        "name": "dynamic",
        "seed": 7,
        "dt": 0.5,
        "steps": 100,
        "world": {"size": [30, 24]},
        "targets": {
            "positions": [[1, 2], [3.5, 4], [30, 24]],
            "speed": 0.05,
            "turn_every": 50,
            "appear": [[10, 5.0, 5.0], [20, 6, 7]],
            "disappear": [[30, 0], [40, 4]],
        },
        "sensor": {"fov": "polygon", "fov_polygon": [[-2, -1], [-2, 1], [2, 1], [2, -1]]},
        "robot": {"start": [15, 12], "planner": "largest-gaussian", "sweeps": 1},
        "belief": {
            "kind": "explicit",
            "components": [
                {"weight": 0.5, "mean": [1, 1], "cov": [[4, 1], [1, 3]]},
                {"mean": [10, 10]},
            ],
        },
        "filter": {"motion": "linear", "linear_model": "cv", "push_rule": False,
                   "push_band": [0.0, 1.0], "birth": "constant", "gp_window": 2},
        "metrics": {"ospa_c": 5, "ospa_p": 1},
    },
]


@pytest.mark.parametrize("data", ROUND_TRIP_CASES, ids=["defaults", "example", "everything"])
def test_scenario_to_dict_round_trips(data: dict[str, Any]) -> None:
    s = parse_scenario(data, name="rt")
    d = scenario_to_dict(s)
    json.dumps(d)  # plain data only
    again = parse_scenario(d, name="other")
    assert again == s
    assert scenario_to_dict(again) == d


def test_a_camera_footprint_scenario_round_trips() -> None:
    for path in sorted((REPO / "sitl" / "scenarios").glob("*.toml")):
        s = load_scenario(path)
        assert parse_scenario(scenario_to_dict(s), name=s.name) == s, path.name


def test_round_trip_case_values() -> None:
    s = parse_scenario(ROUND_TRIP_CASES[2])
    assert s.targets.count == 3  # omitted: the number of positions
    assert s.targets.appear == ((10, 5.0, 5.0), (20, 6.0, 7.0))
    assert s.targets.disappear == ((30, 0), (40, 4))
    # Clockwise input, stored counter-clockwise.
    np.testing.assert_array_equal(
        s.sensor.fov_polygon_xy, [[2, -1], [2, 1], [-2, 1], [-2, -1]]
    )
    c0, c1 = s.belief.components
    assert (c0.weight, c0.mean_xy) == (0.5, (1.0, 1.0))
    np.testing.assert_array_equal(c0.cov, [[4, 1], [1, 3]])
    assert c1.weight == 1.0
    np.testing.assert_array_equal(c1.cov, 50.0 * np.eye(2))  # belief.variance * I


def test_specs_compare_arrays_by_value() -> None:
    a = parse_scenario({"targets": {"positions": [[1, 2]]}})
    b = parse_scenario({"targets": {"positions": [[1, 2]]}})
    c = parse_scenario({"targets": {"positions": [[1, 3]]}})
    assert a == b and a != c
    assert a.targets != "not a spec"


def test_load_scenario_file_seed_override_and_name(tmp_path: Path) -> None:
    path = tmp_path / "paper.toml"
    path.write_text(EXAMPLE)
    assert load_scenario(path).seed == 1
    assert load_scenario(str(path), seed=42).seed == 42
    assert load_scenario(path, seed=42).name == "paper-lawnmower-exact-c10"
    nameless = tmp_path / "my-run.toml"
    nameless.write_text("seed = 3\n")
    assert load_scenario(nameless).name == "my-run"
    with pytest.raises(ConfigError, match=r"^seed: must be >= 0, got -1$"):
        load_scenario(path, seed=-1)
    with pytest.raises(ConfigError, match=r"^seed: must be an integer, got boolean true$"):
        load_scenario(path, seed=True)


def test_missing_file_and_toml_syntax_error(tmp_path: Path) -> None:
    missing = tmp_path / "nope.toml"
    with pytest.raises(ConfigError) as info:
        load_scenario(missing)
    assert str(info.value) == f"{missing}: no such scenario file"
    bad = tmp_path / "bad.toml"
    bad.write_text('name = "x"\n[world\nsize = [1, 2]\n')
    with pytest.raises(ConfigError) as info:
        load_scenario(bad)
    assert info.value.key == str(bad)
    assert str(info.value).startswith(f"{bad}: invalid TOML: ")
    assert "line 2" in str(info.value) and "column" in str(info.value)
    binary = tmp_path / "bin.toml"
    binary.write_bytes(b'name = "\xff"\n')
    with pytest.raises(ConfigError, match=r"invalid TOML"):
        load_scenario(binary)
    with pytest.raises(ConfigError, match=r"cannot read the file"):
        load_scenario(tmp_path)  # a directory


# --------------------------------------------------------------------------- unknown and reserved


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ({"sede": 1}, "sede: unknown key (did you mean 'seed'? known: name, seed, dt, steps, "
                      "world, targets, sensor, robot, belief, filter, metrics, geo, camera, "
                      "vehicle)"),
        ({"zzz": 1}, "zzz: unknown key (known: name, seed, dt, steps, world, targets, sensor, "
                     "robot, belief, filter, metrics, geo, camera, vehicle)"),
        (_with("targets", cout=3), "targets.cout: unknown key (did you mean 'count'? known: "
                                   "count, positions, speed, turn_every, appear, disappear, "
                                   "tag_size_m)"),
        (_with("metrics", ospa_cut=1), "metrics.ospa_cut: unknown key (did you mean 'ospa_c'? "
                                       "known: ospa_c, ospa_p, gospa_c)"),
        ({"belief": {"kind": "explicit", "components": [{"mean": [0, 0], "wieght": 2}]}},
         "belief.components[0].wieght: unknown key (did you mean 'weight'? known: weight, mean, "
         "cov)"),
    ],
)
def test_unknown_keys_are_named(data: dict[str, Any], message: str) -> None:
    assert _error(data) == message


def test_sitl_tables_default_to_px4_sitl_home_and_a_level_90_degree_camera() -> None:
    s = parse_scenario({})
    assert s.geo.origin == (47.397742, 8.545594, 488.0)
    assert s.geo.utm_epsg == 32632  # Zurich: UTM zone 32 north
    assert (s.camera.fx_px, s.camera.fy_px, s.camera.cx_px, s.camera.cy_px) == (
        320.0, 320.0, 319.5, 239.5)
    assert (s.vehicle.flavour, s.vehicle.altitude_m, s.vehicle.offboard_failsafe) == (
        "px4", 8.0, "position")
    assert s.targets.tag_size_m == 0.5


def test_utm_zone_follows_the_world_centre_unless_given() -> None:
    # A world whose corner is just west of the 6 E zone boundary and whose centre is east of it.
    data: dict[str, Any] = {"world": {"size": [2000.0, 100.0]}, "geo": {"origin": [45, 5.99, 0]}}
    assert parse_scenario(data).geo.utm_epsg == 32632
    data["geo"]["utm_epsg"] = 32631
    assert parse_scenario(data).geo.utm_epsg == 32631
    data["geo"]["utm_epsg"] = 4326
    assert _error(data) == "geo.utm_epsg: must be a WGS84 / UTM zone (326xx, 327xx), got 4326"


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ({"geo": {"origin": [95.0, 0.0, 0.0]}}, "geo.origin[0]: must be in [-90, 90], got 95.0"),
        ({"geo": {"origin": [45.0, 0.0]}},
         "geo.origin: must be an array of 3 numbers [lat, lon, alt], got 2 items"),
        ({"camera": {"hfov_deg": 90.0, "fx_px": 300.0}},
         "camera.hfov_deg: give either hfov_deg or fx_px (and fy_px)"),
        ({"camera": {"cx_px": 1000.0}},
         "camera.cx_px: must lie inside the image [-0.5, 639.5], got 1000.0"),
        ({"camera": {"dist": [-0.9, 0.0, 0.0, 0.0, 0.0]}},
         "camera.dist: distortion (-0.9, 0.0, 0.0, 0.0, 0.0) folds over or does not invert "
         "inside the image: each pixel must see exactly one ray"),
        ({"vehicle": {"flavour": "inav"}},
         'vehicle.flavour: must be one of "px4", "ardupilot", got string "inav"'),
        ({"sensor": {"fov": "camera"}, "camera": {"mount_rpy_deg": [0.0, 80.0, 0.0]}},
         'sensor.fov: "camera": the level camera sees the horizon (check camera.mount_rpy_deg); '
         "its footprint is unbounded"),
    ],
)
def test_sitl_table_errors_name_the_key(data: dict[str, Any], message: str) -> None:
    assert _error(data) == message


def test_section_must_be_a_table() -> None:
    assert _error({"world": 3}) == "world: must be a table, got integer 3"
    assert _error({"filter": [1]}) == "filter: must be a table, got array [1]"


def test_not_a_mapping() -> None:
    with pytest.raises(ConfigError, match=r"^scenario: must be a table of scenario keys"):
        parse_scenario([1, 2])  # type: ignore[arg-type]


# --------------------------------------------------------------------------- types


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ({"seed": True}, "seed: must be an integer, got boolean true"),
        (_with("targets", count=False), "targets.count: must be an integer, got boolean false"),
        ({"steps": 10.0}, "steps: must be an integer, got float 10.0"),
        (_with("robot", sweeps=3.0), "robot.sweeps: must be an integer, got float 3.0"),
        (_with("filter", gp_window=30.5), "filter.gp_window: must be an integer, got float 30.5"),
        (_with("targets", count="10"), 'targets.count: must be an integer, got string "10"'),
        ({"dt": "1"}, 'dt: must be a number, got string "1"'),
        ({"dt": True}, "dt: must be a number, got boolean true"),
        ({"dt": None}, "dt: must be a number, got nothing (None)"),
        ({"dt": math.nan}, "dt: must be finite, got float nan"),
        (_with("sensor", noise_std=math.inf), "sensor.noise_std: must be finite, got float inf"),
        (_with("sensor", noise_std=10**400), "sensor.noise_std: must be finite, got integer "
                                             + "1" + "0" * 36 + "..."),
        (_with("filter", push_rule=1), "filter.push_rule: must be true or false, got integer 1"),
        (_with("filter", push_rule="true"),
         'filter.push_rule: must be true or false, got string "true"'),
        ({"name": ""}, 'name: must be a non-empty string, got string ""'),
        ({"name": 5}, "name: must be a non-empty string, got integer 5"),
        (_with("sensor", fov="circle"),
         'sensor.fov: must be one of "disk", "polygon", "camera", got string "circle"'),
        (_with("robot", planner=1), 'robot.planner: must be one of "lawnmower", '
                                    '"nearest-gaussian", "largest-gaussian", "search-track", '
                                    'got integer 1'),
        (_with("belief", kind="exactly"), 'belief.kind: must be one of "exact", "under", "over", '
                                          '"empty", "explicit", got string "exactly"'),
        (_with("filter", motion="GP"), 'filter.motion: must be one of "gp", "linear", got string '
                                       '"GP"'),
        (_with("filter", birth="fixed"),
         'filter.birth: must be one of "adaptive", "constant", got string "fixed"'),
        (_with("filter", linear_model="ca"),
         'filter.linear_model: must be one of "cp", "cv", got string "ca"'),
        (_with("world", size=150.0), "world.size: must be an array of 2 numbers, got float 150.0"),
        (_with("world", size=[150.0]), "world.size: must be an array of 2 numbers, got 1 item"),
        (_with("world", size=[150.0, "a"]), 'world.size[1]: must be a number, got string "a"'),
        (_with("robot", start={"x": 0}),
         "robot.start: must be an array of 2 numbers, got table {'x': 0}"),
    ],
)
def test_wrong_types_are_named(data: dict[str, Any], message: str) -> None:
    assert _error(data) == message


def test_int_for_float_is_fine() -> None:
    s = parse_scenario({"dt": 2, "world": {"size": [100, 80]}, "filter": {"p_survive": 1}})
    assert s.dt_s == 2.0 and isinstance(s.dt_s, float)
    assert s.world.size_m == (100.0, 80.0) and all(isinstance(v, float) for v in s.world.size_m)
    assert isinstance(s.filter.p_survive, float)


def test_numpy_scalars_from_python_callers_are_accepted() -> None:
    s = parse_scenario({"seed": np.int64(3), "dt": np.float64(0.5)})
    assert (s.seed, s.dt_s) == (3, 0.5)
    assert type(s.seed) is int and type(s.dt_s) is float


# --------------------------------------------------------------------------- ranges


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ({"seed": -1}, "seed: must be >= 0, got -1"),
        ({"dt": 0}, "dt: must be > 0, got 0.0"),
        ({"steps": -1}, "steps: must be >= 0, got -1"),
        (_with("world", size=[150.0, 0.0]), "world.size[1]: must be > 0, got 0.0"),
        (_with("targets", count=-1), "targets.count: must be >= 0, got -1"),
        (_with("targets", speed=-0.1), "targets.speed: must be >= 0, got -0.1"),
        (_with("targets", turn_every=0), "targets.turn_every: must be >= 1, got 0"),
        (_with("sensor", fov_radius=0.0), "sensor.fov_radius: must be > 0, got 0.0"),
        (_with("sensor", p_detect=1.01), "sensor.p_detect: must be in [0, 1], got 1.01"),
        (_with("sensor", p_detect=-0.1), "sensor.p_detect: must be in [0, 1], got -0.1"),
        (_with("sensor", noise_std=0), "sensor.noise_std: must be > 0, got 0.0"),
        (_with("sensor", clutter_prob=2), "sensor.clutter_prob: must be in [0, 1], got 2.0"),
        (_with("sensor", clutter_rate=-1), "sensor.clutter_rate: must be >= 0, got -1.0"),
        (_with("robot", speed=0), "robot.speed: must be > 0, got 0.0"),
        (_with("robot", lane_spacing=-5), "robot.lane_spacing: must be > 0, got -5.0"),
        (_with("robot", sweeps=0), "robot.sweeps: must be >= 1, got 0"),
        (_with("belief", count=-2), "belief.count: must be >= 0, got -2"),
        (_with("belief", offset=-1), "belief.offset: must be >= 0, got -1.0"),
        (_with("belief", variance=0), "belief.variance: must be > 0, got 0.0"),
        (_with("filter", p_survive=1.5), "filter.p_survive: must be in [0, 1], got 1.5"),
        (_with("filter", extract_weight=0), "filter.extract_weight: must be > 0, got 0.0"),
        (_with("filter", confirm_length=0), "filter.confirm_length: must be >= 1, got 0"),
        (_with("filter", prune_weight=-1e-3), "filter.prune_weight: must be >= 0, got -0.001"),
        (_with("filter", merge_distance=-1), "filter.merge_distance: must be >= 0, got -1.0"),
        (_with("filter", max_components=0), "filter.max_components: must be >= 1, got 0"),
        (_with("filter", process_noise=-1), "filter.process_noise: must be >= 0, got -1.0"),
        (_with("filter", birth_weight=0), "filter.birth_weight: must be > 0, got 0.0"),
        (_with("filter", velocity_variance=0),
         "filter.velocity_variance: must be > 0, got 0.0"),
        (_with("filter", gp_sigma_f=0), "filter.gp_sigma_f: must be > 0, got 0.0"),
        (_with("filter", gp_lengthscale=-1), "filter.gp_lengthscale: must be > 0, got -1.0"),
        (_with("filter", gp_sigma_n=0), "filter.gp_sigma_n: must be > 0, got 0.0"),
        (_with("filter", gp_window=1), "filter.gp_window: must be >= 2, got 1"),
        (_with("filter", track_timeout=0), "filter.track_timeout: must be > 0, got 0.0"),
        (_with("metrics", ospa_c=0), "metrics.ospa_c: must be > 0, got 0.0"),
        (_with("metrics", ospa_p=0.5), "metrics.ospa_p: must be >= 1, got 0.5"),
        (_with("metrics", gospa_c=0), "metrics.gospa_c: must be > 0, got 0.0"),
    ],
)
def test_out_of_range_values_are_named(data: dict[str, Any], message: str) -> None:
    assert _error(data) == message


def test_boundary_values_are_accepted() -> None:
    s = parse_scenario({
        "steps": 0,
        "targets": {"count": 0, "speed": 0},
        "sensor": {"p_detect": 0, "clutter_prob": 1},
        "filter": {"p_survive": 0, "prune_weight": 0, "merge_distance": 0, "process_noise": 0,
                   "push_band": [0.5, 0.5]},
        "belief": {"count": 0, "offset": 0},
        "metrics": {"ospa_p": 1},
    })
    assert s.steps == 0 and s.targets.count == 0 and s.filter.push_band == (0.5, 0.5)


# --------------------------------------------------------------------------- push band


@pytest.mark.parametrize(
    ("band", "message"),
    [
        ([0.6, 0.4], "filter.push_band: must be [lo, hi] with lo <= hi, got [0.6, 0.4]"),
        ([-0.1, 0.6], "filter.push_band[0]: must be in [0, 1], got -0.1"),
        ([0.4, 1.2], "filter.push_band[1]: must be in [0, 1], got 1.2"),
        ([0.4], "filter.push_band: must be an array of 2 numbers, got 1 item"),
        ([0.1, 0.2, 0.3], "filter.push_band: must be an array of 2 numbers, got 3 items"),
        (0.5, "filter.push_band: must be an array of 2 numbers, got float 0.5"),
    ],
)
def test_push_band(band: Any, message: str) -> None:
    assert _error(_with("filter", push_band=band)) == message


# --------------------------------------------------------------------------- targets


def test_positions_set_the_count_when_it_is_omitted_and_must_match_it() -> None:
    assert parse_scenario(_with("targets", positions=[[1, 1], [2, 2]])).targets.count == 2
    assert parse_scenario(_with("targets", positions=[[1, 1]], count=1)).targets.count == 1
    assert parse_scenario(_with("targets", count=4)).targets.count == 4
    assert _error(_with("targets", positions=[[1, 1], [2, 2]], count=10)) == (
        "targets.count: must equal the number of targets.positions (2) or be omitted, got 10"
    )


@pytest.mark.parametrize(
    ("targets", "message"),
    [
        ({"positions": [[1, 1], [151, 3]]},
         "targets.positions[1]: must be inside the world, "
         "0 <= x <= 150.0 and 0 <= y <= 150.0, got [151.0, 3.0]"),
        ({"positions": [[1, -0.5]]}, "targets.positions[0]: must be inside the world, "
                                     "0 <= x <= 150.0 and 0 <= y <= 150.0, got [1.0, -0.5]"),
        ({"positions": [[1, 2, 3]]}, "targets.positions[0]: must be an array of 2 numbers, "
                                     "got 3 items"),
        ({"positions": [1, 2]}, "targets.positions[0]: must be an array of 2 numbers, got "
                                "integer 1"),
        ({"positions": [[1, True]]}, "targets.positions[0][1]: must be a number, got boolean "
                                     "true"),
        ({"appear": [[-1, 5.0, 5.0]]}, "targets.appear[0][0]: must be >= 0, got -1"),
        ({"appear": [[1.5, 5.0, 5.0]]}, "targets.appear[0][0]: must be an integer, got float 1.5"),
        ({"appear": [[1, 5.0, 5.0], [2, 5.0, 500.0]]},
         "targets.appear[1]: [x, y] must be inside the world, 0 <= x <= 150.0 and "
         "0 <= y <= 150.0, got [5.0, 500.0]"),
        ({"appear": [[1, 5.0]]}, "targets.appear[0]: must be an array [step, x, y], got 2 items"),
        ({"appear": [3]}, "targets.appear[0]: must be an array [step, x, y], got integer 3"),
        ({"appear": 3}, "targets.appear: must be an array of [step, x, y], got integer 3"),
        ({"disappear": [[-5, 0]]}, "targets.disappear[0][0]: must be >= 0, got -5"),
        ({"disappear": [[5, -1]]}, "targets.disappear[0][1]: must be >= 0, got -1"),
        ({"count": 3, "disappear": [[5, 3]]},
         "targets.disappear[0][1]: must be a target index < 3 (3 initial + 0 appearing), got 3"),
        ({"count": 3, "appear": [[10, 1, 1]], "disappear": [[5, 2], [20, 4]]},
         "targets.disappear[1][1]: must be a target index < 4 (3 initial + 1 appearing), got 4"),
        ({"count": 3, "disappear": [[5, 1], [9, 1]]},
         "targets.disappear[1][1]: target 1 already disappears in targets.disappear[0]"),
        ({"count": 3, "appear": [[10, 1, 1], [50, 2, 2]], "disappear": [[20, 4]]},
         "targets.disappear[0][0]: must be >= 50, the step at which target 4 appears, got 20"),
    ],
)
def test_target_rules(targets: dict[str, Any], message: str) -> None:
    assert _error({"targets": targets}) == message


def test_positions_on_the_world_boundary_and_valid_disappear() -> None:
    s = parse_scenario({
        "world": {"size": [10, 20]},
        "targets": {"positions": [[0, 0], [10, 20]], "appear": [[5, 10, 0]],
                    "disappear": [[5, 2], [0, 0]]},
        "robot": {"start": [10, 20]},
    })
    assert s.targets.disappear == ((5, 2), (0, 0))
    assert _error({"robot": {"start": [0, 151]}}) == (
        "robot.start: must be inside the world, 0 <= x <= 150.0 and 0 <= y <= 150.0, "
        "got [0.0, 151.0]"
    )


# --------------------------------------------------------------------------- sensor


def test_shrinking_the_world_is_checked_against_positions() -> None:
    data = copy.deepcopy(ROUND_TRIP_CASES[2])
    data["world"]["size"] = [20, 24]
    assert _error(data) == (
        "targets.positions[2]: must be inside the world, 0 <= x <= 20.0 and 0 <= y <= 24.0, "
        "got [30.0, 24.0]"
    )


def test_camera_fov_is_the_level_footprint_at_the_search_altitude() -> None:
    # 90 degree horizontal FOV at 8 m: 16 m across (east) by 12 m (north), centred below.
    s = parse_scenario(_with("sensor", fov="camera"))
    polygon = s.sensor.fov_polygon_xy
    np.testing.assert_allclose(np.sort(polygon, axis=0),
                               [[-8.0, -6.0], [-8.0, -6.0], [8.0, 6.0], [8.0, 6.0]], atol=1e-9)
    x, y = polygon[:, 0], polygon[:, 1]
    assert np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y) > 0  # counter-clockwise
    # Heading east turns it: 16 m north-south by 12 m east-west.
    turned = parse_scenario({"sensor": {"fov": "camera"}, "vehicle": {"heading_deg": 90.0}})
    np.testing.assert_allclose(np.ptp(turned.sensor.fov_polygon_xy, axis=0), [12.0, 16.0])
    wide = parse_scenario({"sensor": {"fov": "camera"}, "camera": {"hfov_deg": 120.0},
                           "vehicle": {"altitude_m": 20.0}})
    assert np.ptp(wide.sensor.fov_polygon_xy[:, 0]) == pytest.approx(
        2 * 20.0 * math.tan(math.radians(60.0)))
    assert _error({"sensor": {"fov": "camera", "fov_polygon": [[0, 0], [1, 0], [0, 1]]}}) == (
        'sensor.fov_polygon: is only allowed when sensor.fov = "polygon", got fov "camera"')


def test_polygon_fov_is_stored_counter_clockwise() -> None:
    ccw = [[-3.0, -2.0], [4.0, -2.0], [4.0, 3.0], [-3.0, 3.0]]
    s = parse_scenario(_with("sensor", fov="polygon", fov_polygon=ccw))
    np.testing.assert_array_equal(s.sensor.fov_polygon_xy, ccw)
    cw = parse_scenario(_with("sensor", fov="polygon", fov_polygon=ccw[::-1]))
    np.testing.assert_array_equal(cw.sensor.fov_polygon_xy, ccw[::-1][::-1])
    tiny = parse_scenario(_with("sensor", fov="polygon", fov_polygon=[[0, 0], [1e-300, 0],
                                                                      [0, 1e-300]]))
    assert tiny.sensor.fov_polygon_xy.shape == (3, 2)
    huge = parse_scenario(_with("sensor", fov="polygon", fov_polygon=[[-1e308, -1e308],
                                                                      [1e308, -1e308],
                                                                      [0, 1e308]]))
    assert huge.sensor.fov_polygon_xy.shape == (3, 2)


CONVEX_MSG = ("sensor.fov_polygon: must be convex, with its vertices in order and none repeated "
              "or collinear")


@pytest.mark.parametrize(
    ("sensor", "message"),
    [
        ({"fov": "polygon"}, 'sensor.fov_polygon: is required when sensor.fov = "polygon"'),
        ({"fov": "polygon", "fov_polygon": [[0, 0], [1, 0]]},
         "sensor.fov_polygon: must have at least 3 points, got 2"),
        ({"fov": "polygon", "fov_polygon": [[0, 0], [1, 1], [2, 2]]},
         "sensor.fov_polygon: must enclose a positive area"),
        ({"fov": "polygon", "fov_polygon": [[0, 0], [0, 0], [0, 0]]},
         "sensor.fov_polygon: must enclose a positive area"),
        # An L shape: not convex.
        ({"fov": "polygon", "fov_polygon": [[0, 0], [2, 0], [2, 1], [1, 1], [1, 2], [0, 2]]},
         CONVEX_MSG),
        # A bow tie: vertices out of order (self-intersecting), zero signed area.
        ({"fov": "polygon", "fov_polygon": [[0, 0], [1, 1], [1, 0], [0, 1]]},
         "sensor.fov_polygon: must enclose a positive area"),
        # A pentagram: every turn is to the same side, but it winds twice.
        ({"fov": "polygon", "fov_polygon": [
            [math.cos(a), math.sin(a)] for a in (2 * math.pi * k * 2 / 5 for k in range(5))
        ]}, CONVEX_MSG),
        # A repeated vertex.
        ({"fov": "polygon", "fov_polygon": [[0, 0], [1, 0], [1, 0], [0, 1]]}, CONVEX_MSG),
        # Three collinear vertices.
        ({"fov": "polygon", "fov_polygon": [[0, 0], [1, 0], [2, 0], [0, 1]]}, CONVEX_MSG),
        ({"fov": "disk", "fov_polygon": [[0, 0], [1, 0], [0, 1]]},
         'sensor.fov_polygon: is only allowed when sensor.fov = "polygon", got fov "disk"'),
        ({"fov": "polygon", "fov_polygon": [[0, 0], [1, 0], [0, "1"]]},
         'sensor.fov_polygon[2][1]: must be a number, got string "1"'),
    ],
)
def test_polygon_rules(sensor: dict[str, Any], message: str) -> None:
    assert _error({"sensor": sensor}) == message


# --------------------------------------------------------------------------- belief


@pytest.mark.parametrize(
    ("belief", "message"),
    [
        ({"kind": "explicit"}, 'belief.components: is required when belief.kind = "explicit"'),
        ({"kind": "explicit", "components": []},
         'belief.components: is required when belief.kind = "explicit"'),
        ({"components": [{"mean": [0, 0]}]},
         'belief.components: is only allowed when belief.kind = "explicit", got kind "exact"'),
        ({"kind": "empty", "components": [{"mean": [0, 0]}]},
         'belief.components: is only allowed when belief.kind = "explicit", got kind "empty"'),
        ({"kind": "explicit", "components": [{"mean": [0, 0]}, 3]},
         "belief.components[1]: must be a table {weight, mean, cov}, got integer 3"),
        ({"kind": "explicit", "components": {"mean": [0, 0]}},
         "belief.components: must be an array of tables {weight, mean, cov}, got table "
         "{'mean': [0, 0]}"),
        ({"kind": "explicit", "components": [{"weight": 1.0}]},
         "belief.components[0].mean: is required"),
        ({"kind": "explicit", "components": [{"mean": [0, 0], "weight": 0}]},
         "belief.components[0].weight: must be > 0, got 0.0"),
        ({"kind": "explicit", "components": [{"mean": [0, 0], "weight": -1}]},
         "belief.components[0].weight: must be > 0, got -1.0"),
        ({"kind": "explicit", "components": [{"mean": [0, 0, 0]}]},
         "belief.components[0].mean: must be an array of 2 numbers, got 3 items"),
        ({"kind": "explicit", "components": [{"mean": 5}]},
         "belief.components[0].mean: must be an array of 2 numbers, got integer 5"),
        ({"kind": "explicit", "components": [
            {"mean": [0, 0]}, {"mean": [1, 1]},
            {"mean": [2, 2], "cov": [[1, 2], [2, 1]]},  # indefinite
        ]}, "belief.components[2].cov: must be symmetric positive definite"),
        ({"kind": "explicit", "components": [{"mean": [0, 0], "cov": [[1, 0.5], [0.4, 1]]}]},
         "belief.components[0].cov: must be symmetric positive definite"),
        ({"kind": "explicit", "components": [{"mean": [0, 0], "cov": [[0, 0], [0, 1]]}]},
         "belief.components[0].cov: must be symmetric positive definite"),
        ({"kind": "explicit", "components": [{"mean": [0, 0], "cov": [[-1, 0], [0, -1]]}]},
         "belief.components[0].cov: must be symmetric positive definite"),
        ({"kind": "explicit", "components": [{"mean": [0, 0], "cov": [[1, 1], [1, 1]]}]},
         "belief.components[0].cov: must be symmetric positive definite"),
        ({"kind": "explicit", "components": [{"mean": [0, 0], "cov": [[1, 0]]}]},
         "belief.components[0].cov: must be a 2x2 array [[a, b], [b, d]], got 1 row"),
        ({"kind": "explicit", "components": [{"mean": [0, 0], "cov": [[1, 0, 0], [0, 1, 0]]}]},
         "belief.components[0].cov[0]: must be an array of 2 numbers, got 3 items"),
        ({"kind": "explicit", "components": [{"mean": [0, 0], "cov": 4.0}]},
         "belief.components[0].cov: must be an array [[a, b], [b, d]], got float 4.0"),
    ],
)
def test_belief_rules(belief: dict[str, Any], message: str) -> None:
    assert _error({"belief": belief}) == message


def test_belief_count_follows_the_kind() -> None:
    assert parse_scenario(_with("targets", count=4)).belief.count == 4  # default: targets.count
    assert parse_scenario({"targets": {"positions": [[1, 1]]}}).belief.count == 1
    assert parse_scenario({"belief": {"kind": "under", "count": 5}}).belief.count == 5
    assert parse_scenario({"belief": {"kind": "over", "count": 15}}).belief.count == 15
    assert parse_scenario({"belief": {"kind": "empty", "count": 99}}).belief.count == 99
    assert _error({"belief": {"count": 7}}) == (
        'belief.count: must equal the number of initial targets (10) for belief.kind = "exact", '
        "got 7"
    )
    assert _error({"belief": {"kind": "under"}}) == (
        'belief.count: must be < the number of initial targets (10) for belief.kind = "under", '
        "got 10"
    )
    assert _error({"targets": {"count": 3}, "belief": {"kind": "over", "count": 3}}) == (
        'belief.count: must be > the number of initial targets (3) for belief.kind = "over", '
        "got 3"
    )


def test_explicit_components_with_extreme_but_valid_covariances() -> None:
    comps = [{"mean": [0, 0], "cov": [[1e300, 1e299], [1e299, 1e300]]},
             {"mean": [0, 0], "cov": [[1e-300, 0], [0, 1e-300]]}]
    s = parse_scenario({"belief": {"kind": "explicit", "components": comps}})
    assert len(s.belief.components) == 2


# --------------------------------------------------------------------------- the reference


def test_committed_reference_is_the_generated_text() -> None:
    committed = (REPO / "docs" / "scenario.md").read_text(encoding="utf-8")
    assert committed == schema_markdown(), (
        "docs/scenario.md is stale: run "
        "`python -m companion.sim.scenario --markdown > docs/scenario.md`"
    )


def test_reference_names_every_key_of_the_contract() -> None:
    text = schema_markdown()
    contract = tomllib.loads(EXAMPLE)
    for key, value in contract.items():
        if isinstance(value, dict):
            for leaf in value:
                assert f"| `{key}.{leaf}` |" in text
        else:
            assert f"| `{key}` |" in text
    for project_key in ("sensor.fov_polygon", "filter.birth", "filter.gp_window",
                        "filter.track_timeout"):
        assert f"| `{project_key}` |" in text
    line = next(li for li in text.splitlines() if li.startswith("| `filter.track_timeout`"))
    assert "project key" in line
    assert line.count(" | ") == 3  # four cells: pipes inside docs are escaped


def test_main_prints_the_reference_and_checks_files(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert sc.main(["--markdown"]) == 0
    assert capsys.readouterr().out == schema_markdown()
    good = tmp_path / "good.toml"
    good.write_text(EXAMPLE)
    assert sc.main([str(good)]) == 0
    bad = tmp_path / "bad.toml"
    bad.write_text("[targets]\ncount = -1\n")
    assert sc.main([str(bad)]) == 2
    assert capsys.readouterr().err.strip() == "targets.count: must be >= 0, got -1"
    assert sc.main([]) == 2


# --------------------------------------------------------------------------- only ConfigError


_toml_like = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(min_value=-(10**400), max_value=10**400)
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=8)
    | st.sampled_from(["disk", "polygon", "camera", "explicit", "gp", "cv", "lawnmower"]),
    lambda children: st.lists(children, max_size=4)
    | st.dictionaries(
        st.sampled_from(["weight", "mean", "cov", "x"]) | st.text(max_size=4), children, max_size=3
    ),
    max_leaves=12,
)

_ALL_LEAVES = sorted({k.leaf for keys in sk.SECTION_KEYS.values() for k in keys})


@st.composite
def _scenario_like(draw: st.DrawFn) -> dict[str, Any]:
    data: dict[str, Any] = {}
    for key in draw(st.lists(st.sampled_from(["name", "seed", "dt", "steps", "bogus"]),
                             max_size=3)):
        data[key] = draw(_toml_like)
    for section in draw(st.lists(st.sampled_from([*SECTIONS, "geo"]), max_size=4)):
        if draw(st.booleans()):
            data[section] = draw(_toml_like)
        else:
            leaves = draw(st.lists(st.sampled_from(_ALL_LEAVES), max_size=4))
            data[section] = {leaf: draw(_toml_like) for leaf in leaves}
    return data


@settings(deadline=None, max_examples=300, derandomize=True)
@given(_scenario_like())
def test_wrong_types_raise_only_config_error(data: dict[str, Any]) -> None:
    try:
        s = parse_scenario(data)
    except ConfigError as exc:
        assert exc.key and exc.problem
        return
    assert parse_scenario(scenario_to_dict(s)) == s


_VALID = scenario_to_dict(parse_scenario(ROUND_TRIP_CASES[2]))
_LEAF_PATHS = [(section, leaf) for section in SECTIONS for leaf in _VALID[section]]


@settings(deadline=None, max_examples=300, derandomize=True)
@given(st.sampled_from(_LEAF_PATHS), _toml_like)
def test_any_value_for_any_key_raises_only_config_error_naming_it(
    path: tuple[str, str], value: Any
) -> None:
    section, leaf = path
    data = copy.deepcopy(_VALID)
    data[section][leaf] = value
    try:
        s = parse_scenario(data)
    except ConfigError as exc:
        # The bad key itself, an entry inside it, or a key whose rule ties it to this one.
        tied = {"world": ("targets.", "robot.start"), "targets": ("belief.count",),
                "camera": ("sensor.fov",), "vehicle": ("sensor.fov",)}
        assert exc.key.startswith((f"{section}.", *tied.get(section, ())))
        return
    assert parse_scenario(scenario_to_dict(s)) == s


@settings(deadline=None, max_examples=100, derandomize=True)
@given(
    st.lists(st.tuples(st.floats(-1e300, 1e300), st.floats(-1e300, 1e300)), max_size=7),
)
def test_random_polygons_are_accepted_only_when_convex(points: list[tuple[float, float]]) -> None:
    try:
        s = parse_scenario(_with("sensor", fov="polygon", fov_polygon=[list(p) for p in points]))
    except ConfigError as exc:
        assert exc.key == "sensor.fov_polygon" or exc.key.startswith("sensor.fov_polygon[")
        return
    poly = s.sensor.fov_polygon_xy
    assert poly.shape == (len(points), 2)
    # Accepted: every vertex is on the inner (left) side of every edge's line, i.e. a convex,
    # counter-clockwise polygon. Scaled to [-1, 1] so that the products cannot overflow.
    q = poly / float(np.max(np.abs(poly)))
    edges = np.roll(q, -1, axis=0) - q
    for i in range(len(q)):
        rel = q - q[i]
        side = edges[i, 0] * rel[:, 1] - edges[i, 1] * rel[:, 0]
        assert np.all(side >= -1e-12)


@settings(deadline=None, max_examples=100, derandomize=True)
@given(
    st.lists(st.integers(0, 359), min_size=3, max_size=12, unique=True),
    st.floats(1e-3, 1e3),
    st.booleans(),
)
def test_points_on_a_circle_in_order_are_accepted(
    degrees: list[int], radius_m: float, clockwise: bool
) -> None:
    angles = np.radians(sorted(degrees))  # distinct points on a circle, in order: convex
    ccw = np.column_stack([radius_m * np.cos(angles), radius_m * np.sin(angles)])
    given_xy = ccw[::-1] if clockwise else ccw
    s = parse_scenario(_with("sensor", fov="polygon", fov_polygon=given_xy.tolist()))
    np.testing.assert_array_equal(s.sensor.fov_polygon_xy, ccw)


def test_a_scenario_check_lists_every_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A wrong type, an unknown key and an out-of-range value: all three, in one run, exit 2,
    from the scenario checker and from `companion simulate` alike."""
    bad = tmp_path / "three.toml"
    bad.write_text('seed = "one"\n[robot]\nwings = 2\n[sensor]\np_detect = 1.5\n')
    assert sc.main([str(bad)]) == 2
    lines = capsys.readouterr().err.splitlines()
    assert lines == [
        'seed: must be an integer, got string "one"',
        "sensor.p_detect: must be in [0, 1], got 1.5",
        "robot.wings: unknown key (known: start, speed, planner, lane_spacing, sweeps, "
        "unseen_targets, stop_when_left)",
    ]
    assert companion_main(["simulate", str(bad)]) == 2
    err = capsys.readouterr().err
    assert all(key in err for key in ("seed:", "robot.wings:", "sensor.p_detect:")), err
