"""Scenario files (TOML) read into frozen, validated specs; the contract is scenario-format.md.

Every key is declared once below (`_TOP`, `_SECTIONS`, `_COMPONENT_KEYS`: dotted name, dataclass
field, value kind with its range, default, one-line doc), and parsing, `scenario_to_dict` and the
key reference `docs/scenario.md` (`python -m companion.sim.scenario --markdown`) are all driven by
those declarations. Adding a key is one declaration plus the dataclass field it fills. Rules that
tie several keys together live in the section builders (`_targets`, `_sensor`, ...) and are listed
in `_CROSS_KEY_RULES` for the reference.

Defaults reproduce the paper's set-up: ten stationary targets in a 150 m x 150 m world, a 25 m disk
FOV, 10 % clutter, three lawn-mower sweeps at 0.5 m/s, an exact initial belief. Coordinates are
metres in a local frame whose origin is the world's lower-left corner, x east, y north.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, TypeVar

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import ConvexHull

from companion.errors import ConfigError, ErrorCollector, InputError
from companion.geo import LocalNed, Utm, utm_zone_for
from companion.keys import (
    REQUIRED,
    Bool,
    Choice,
    Derived,
    Float,
    Floats,
    Int,
    Key,
    Kind,
    Matrix2,
    Pair,
    Points,
    Rows,
    Text,
    array_items,
    describe,
    frozen_rows,
    load_toml,
    markdown_rows,
    read_table,
    section_table,
    toml_text,
    unknown_key,
)
from companion.plan.planners import PlannerKind
from companion.sat.params import FILTER_KEYS, FilterSpec, FovKind
from companion.vision.camera import BodyPose, CameraModel, ground_footprint

__all__ = [
    "BeliefComponent",
    "BeliefSpec",
    "GeoSpec",
    "MetricsSpec",
    "RobotSpec",
    "Scenario",
    "SensorSpec",
    "TargetsSpec",
    "VehicleSpec",
    "WorldSpec",
    "load_scenario",
    "parse_scenario",
    "scenario_to_dict",
    "schema_markdown",
]

FloatArray = NDArray[np.float64]
T = TypeVar("T")


# ---------------------------------------------------------------------------------------------
# The result: frozen, slotted specs with units in their field names
# ---------------------------------------------------------------------------------------------


class _ArrayEq:
    """Mixin: field-wise equality in which array fields compare by shape and value."""

    __slots__ = ()

    def __eq__(self, other: object) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        for f in dataclasses.fields(self):  # type: ignore[arg-type]
            a, b = getattr(self, f.name), getattr(other, f.name)
            if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
                if not (isinstance(a, np.ndarray) and isinstance(b, np.ndarray)):
                    return False
                if a.shape != b.shape or not np.array_equal(a, b):
                    return False
            elif a != b:
                return False
        return True

    __hash__ = None  # type: ignore[assignment]  # arrays are unhashable, so are these specs


@dataclass(frozen=True, slots=True)
class WorldSpec:
    """The rectangular world [0, size_x] x [0, size_y], metres."""

    size_m: tuple[float, float]


@dataclass(frozen=True, slots=True, eq=False)
class TargetsSpec(_ArrayEq):
    """True targets: initial count or positions, motion, and later appearances/disappearances."""

    count: int
    positions_xy: FloatArray  # (n, 2) metres; shape (0, 2) when placed at random from the seed
    speed_m_s: float
    turn_every_steps: int
    appear: tuple[tuple[int, float, float], ...]  # (step, x_m, y_m)
    disappear: tuple[tuple[int, int], ...]  # (step, index into initial + appeared targets)
    tag_size_m: float  # SITL: edge of each target's AprilTag (black square)


@dataclass(frozen=True, slots=True, eq=False)
class SensorSpec(_ArrayEq):
    """Field of view, detection probability, noise and clutter of the simulated sensor."""

    fov: FovKind
    fov_radius_m: float
    fov_polygon_xy: FloatArray  # (k, 2) offsets from the robot, metres, counter-clockwise
    # (for fov = "camera": the level camera's footprint at the search altitude)
    p_detect: float
    noise_std_m: float
    clutter_prob: float
    clutter_rate: float


@dataclass(frozen=True, slots=True)
class RobotSpec:
    """Start, speed and planner of the robot carrying the sensor."""

    start_xy: tuple[float, float]
    speed_m_s: float
    planner: PlannerKind
    lane_spacing_m: float
    sweeps: int


@dataclass(frozen=True, slots=True, eq=False)
class BeliefComponent(_ArrayEq):
    """One Gaussian of an explicit initial PHD: weight, mean (m) and covariance (m^2)."""

    weight: float
    mean_xy: tuple[float, float]
    cov: FloatArray  # (2, 2), symmetric positive definite


@dataclass(frozen=True, slots=True)
class BeliefSpec:
    """How the initial GM-PHD is built (around the true targets, empty, or given explicitly)."""

    kind: Literal["exact", "under", "over", "empty", "explicit"]
    count: int
    offset_m: float
    variance_m2: float
    components: tuple[BeliefComponent, ...]


@dataclass(frozen=True, slots=True)
class MetricsSpec:
    """OSPA cut-off (m) and order."""

    ospa_c: float
    ospa_p: float


@dataclass(frozen=True, slots=True)
class GeoSpec:
    """Where the world lies on the Earth: its (0, 0) corner, and the UTM zone of the flight."""

    origin: tuple[float, float, float]  # lat_deg, lon_deg, alt_m (ground at the corner)
    utm_epsg: int

    def local_ned(self) -> LocalNed:
        """The local NED frame at the world's (0, 0) corner, on the ground."""
        return LocalNed(*self.origin)

    def utm(self) -> Utm:
        """The flight's UTM zone."""
        return Utm(self.utm_epsg)


@dataclass(frozen=True, slots=True)
class VehicleSpec:
    """The SITL's vehicle and autopilot: flavour, search altitude, limits, failsafes, sensors."""

    flavour: Literal["px4", "ardupilot"]
    altitude_m: float
    heading_deg: float
    max_speed_m_s: float
    max_accel_m_s2: float
    max_yaw_rate_deg_s: float
    takeoff_altitude_m: float
    rtl_altitude_m: float
    offboard_loss_timeout_s: float
    offboard_failsafe: Literal["hold", "land", "rtl"]
    # None: the flavour's measured value (sitl.autopilot.FLAVOUR_DEFAULTS), chosen at start-up,
    # so that a spec whose flavour is replaced behaves as the other firmware.
    armable_after_s: float | None
    gps_fix_after_s: float | None
    arm_unstable_s: float | None
    takeoff_spoolup_s: float | None
    rel_alt_bias_m: float | None
    position_noise_m: float
    gps_drift_m_per_sqrt_s: float
    heading_error_deg: float | None
    attitude_error_deg: float | None
    position_error_m: float | None
    height_error_m: float | None
    error_time_constant_s: float
    battery_flight_s: float
    battery_low_percent: float
    ekf_origin_offset_m: tuple[float, float]
    rangefinder: bool | None
    rangefinder_max_m: float


@dataclass(frozen=True, slots=True)
class Scenario:
    """A whole scenario; a run is a pure function of it (the seed included)."""

    name: str
    seed: int
    dt_s: float
    steps: int  # 0: until the planner's path ends
    world: WorldSpec
    targets: TargetsSpec
    sensor: SensorSpec
    robot: RobotSpec
    belief: BeliefSpec
    filter: FilterSpec
    metrics: MetricsSpec
    geo: GeoSpec
    camera: CameraModel
    vehicle: VehicleSpec


class _Components(Kind[tuple[Any, ...]]):
    """belief.components: an array of tables; `_belief` reads each table (see _COMPONENT_KEYS)."""

    doc = "array of tables {weight, mean, cov}"

    def parse(self, key: str, raw: object) -> tuple[Any, ...]:
        items = array_items(key, raw, "of tables {weight, mean, cov}")
        for i, item in enumerate(items):
            if not isinstance(item, Mapping):
                raise ConfigError(
                    f"{key}[{i}]", f"must be a table {{weight, mean, cov}}, got {describe(item)}"
                )
        return tuple(items)

    def dump(self, value: tuple[Any, ...]) -> object:
        return [_dump_table(c, _COMPONENT_KEYS) for c in value]


# ---------------------------------------------------------------------------------------------
# The declarations: one per key
# ---------------------------------------------------------------------------------------------


_DEFAULT_TARGET_COUNT = 10

_TOP: tuple[Key, ...] = (
    Key("name", Text(), Derived("the file's name without `.toml`"), "scenario name"),
    Key("seed", Int(ge=0), 0,
         "the run is a pure function of (file, seed); --seed overrides"),
    Key("dt", Float(gt=0), 1.0, "seconds per step", field="dt_s"),
    Key("steps", Int(ge=0), 0, "steps to run; 0 = until the planner's path ends"),
)

_SECTIONS: dict[str, tuple[Key, ...]] = {
    "world": (
        Key("size", Pair(Float(gt=0)), [150.0, 150.0], "metres, x by y", field="size_m"),
    ),
    "targets": (
        Key("count", Int(ge=0),
             Derived(f"{_DEFAULT_TARGET_COUNT}, or the number of `positions`"),
             "targets placed uniformly at random in the world (from the seed)"),
        Key("positions", Points(), [],
             "explicit initial [[x, y], ...] instead of random", field="positions_xy"),
        Key("speed", Float(ge=0), 0.0, "m/s; 0 = stationary", field="speed_m_s"),
        Key("turn_every", Int(ge=1), 400,
             "steps between random heading changes of moving targets", field="turn_every_steps"),
        Key("appear", Rows("[step, x, y]", Int(ge=0), Float(), Float()), [],
             "targets that enter the world later"),
        Key("disappear", Rows("[step, index]", Int(ge=0), Int(ge=0)), [],
             "targets that leave; index counts initial targets, then appearing ones in order"),
        Key("tag_size_m", Float(gt=0, le=10), 0.5,
             "SITL: edge of the black square of each target's tag36h11 AprilTag (target i wears "
             "tag id i), metres", project=True),
    ),
    "sensor": (
        Key("fov", Choice(FovKind.DISK, FovKind.POLYGON, FovKind.CAMERA), "disk",
             "disk (the paper's), polygon, or camera (SITL only)"),
        Key("fov_radius", Float(gt=0), 25.0, "metres, for fov = \"disk\"", field="fov_radius_m"),
        Key("fov_polygon", Points(), [],
             "for fov = \"polygon\": convex [[dx, dy], ...] offsets from the robot, metres",
             project=True, field="fov_polygon_xy"),
        Key("p_detect", Float(ge=0, le=1), 0.98, "p(D | in FOV)"),
        Key("noise_std", Float(gt=0), 1.0,
             "measurement noise std per axis, metres (R = noise_std^2 I)", field="noise_std_m"),
        Key("clutter_prob", Float(ge=0, le=1), 0.1,
             "probability of one false positive per step, uniform in the FOV"),
        Key("clutter_rate", Float(ge=0), 0.0,
             "Poisson mean of further false positives per step"),
    ),
    "robot": (
        Key("start", Pair(Float()), [0.0, 0.0], "metres, inside the world", field="start_xy"),
        Key("speed", Float(gt=0), 0.5, "m/s", field="speed_m_s"),
        Key("planner", Choice(*PlannerKind),
             "lawnmower", "path planner"),
        Key("lane_spacing", Float(gt=0), 25.0,
             "metres between lawn-mower lanes", field="lane_spacing_m"),
        Key("sweeps", Int(ge=1), 3,
             "lawn-mower passes over the whole world, each returning to start"),
    ),
    "belief": (
        Key("kind", Choice("exact", "under", "over", "empty", "explicit"), "exact",
             "how the initial GM-PHD is built"),
        Key("count", Int(ge=0), Derived("`targets.count`"),
             "components near true targets, for exact (= targets.count), under (<), over (>)"),
        Key("offset", Float(ge=0), 15.0,
             "mean distance of each component from a true target, metres", field="offset_m"),
        Key("variance", Float(gt=0), 50.0,
             "diagonal covariance entry of each component, m^2", field="variance_m2"),
        Key("components", _Components(), [],
             "for kind = \"explicit\": the initial components (keys below)"),
    ),
    "filter": FILTER_KEYS,
    "metrics": (
        Key("ospa_c", Float(gt=0), 100.0, "OSPA cut-off, metres"),
        Key("ospa_p", Float(ge=1), 2.0, "OSPA order"),
    ),
    "geo": (
        Key("origin",
             Floats("[lat, lon, alt]", Float(ge=-90, le=90), Float(ge=-180, le=180),
                     Float(ge=-500, le=9000)),
             [47.397742, 8.545594, 488.0],
             "WGS84 degrees and metres of the ground at the world's (0, 0) corner (default: PX4 "
             "SITL's home); the world's x runs east and y north from it"),
        Key("utm_epsg", Int(), Derived("the zone of the world's centre"),
             "EPSG code of the WGS84 / UTM zone the service's tracks and outputs use for the "
             "whole flight (326xx north, 327xx south)"),
    ),
    "camera": (
        Key("width_px", Int(ge=16), 640, "image width, pixels"),
        Key("height_px", Int(ge=16), 480, "image height, pixels"),
        Key("hfov_deg", Float(ge=1, le=170), Derived("90 unless fx_px is given"),
             "horizontal field of view (square pixels): sets fx_px = fy_px", stored=False),
        Key("fx_px", Float(gt=0), Derived("from `camera.hfov_deg`"),
             "focal length in x, pixels"),
        Key("fy_px", Float(gt=0), Derived("`camera.fx_px`"),
             "focal length in y, pixels"),
        Key("cx_px", Float(), Derived("the image centre, (width_px - 1) / 2"),
             "principal point x, pixels (OpenCV: pixel centres at integers)"),
        Key("cy_px", Float(), Derived("the image centre, (height_px - 1) / 2"),
             "principal point y, pixels"),
        Key("dist", Floats("[k1, k2, p1, p2, k3]", *(Float(),) * 5),
             [0.0, 0.0, 0.0, 0.0, 0.0], "OpenCV distortion coefficients"),
        Key("mount_rpy_deg", Floats("[roll, pitch, yaw]", *(Float(),) * 3),
             [0.0, 0.0, 0.0],
             "mounting relative to straight down (top of the image forward), degrees; positive "
             "pitch looks ahead of nadir"),
        Key("mount_offset_m",
             Floats("[forward, right, down]", *(Float(ge=-10, le=10),) * 3), [0.0, 0.0, 0.0],
             "camera centre in the body frame, metres"),
        Key("rate_hz", Float(gt=0, le=1000), 10.0, "frames per second"),
        Key("noise_std", Float(ge=0, le=64), 2.0,
             "SITL: exposure noise of the rendered frames, grey levels"),
    ),
    "vehicle": (
        Key("flavour", Choice("px4", "ardupilot"), "px4",
             "SITL autopilot: PX4 or ArduPilot Copter"),
        Key("altitude_m", Float(gt=0, le=500), 8.0,
             "search altitude above home, metres (the paper's field experiment: 8)"),
        Key("heading_deg", Float(ge=-360, le=360), 0.0,
             "heading at boot and while searching, degrees clockwise from north"),
        Key("max_speed_m_s", Float(gt=0), 8.0,
             "SITL: horizontal speed limit of the autopilot, m/s"),
        Key("max_accel_m_s2", Float(gt=0), 4.0,
             "SITL: acceleration limit, m/s^2 (it tilts the vehicle and its camera)"),
        Key("max_yaw_rate_deg_s", Float(gt=0), 60.0,
             "SITL: yaw-rate limit, degrees/s"),
        Key("takeoff_altitude_m", Float(gt=0), 2.5,
             "SITL: the autopilot's default take-off altitude (PX4 MIS_TAKEOFF_ALT), metres"),
        Key("rtl_altitude_m", Float(gt=0), 30.0,
             "SITL: return altitude (PX4 RTL_RETURN_ALT), metres"),
        Key("offboard_loss_timeout_s", Float(gt=0), 1.0,
             "SITL: setpoint silence before the offboard failsafe (PX4 COM_OF_LOSS_T), seconds"),
        Key("offboard_failsafe", Choice("hold", "land", "rtl"), "hold",
             "SITL: what PX4 does when offboard setpoints stop (COM_OBL_RC_ACT)"),
        Key("armable_after_s", Float(ge=0),
             Derived("40 for ardupilot, 2 for px4 (real PX4 SIH: 33-37)"),
             "SITL: estimator warm-up after boot before arming is allowed, seconds"),
        Key("gps_fix_after_s", Float(ge=0),
             Derived("25 for ardupilot, 0 for px4, never after `vehicle.armable_after_s`"),
             "SITL: GPS fix after boot, seconds; before it the position reads lat = lon = 0, "
             "GPS_RAW_INT has no fix, SYS_STATUS no GPS health and there is no local position"),
        Key("arm_unstable_s", Float(ge=0),
             Derived("3 for px4 with its own warm-up, 0 when `vehicle.armable_after_s` is "
                     "given; 0 for ardupilot"),
             "SITL: seconds after the warm-up during which ARM is TEMPORARILY_REJECTED "
             "(\"horizontal/vertical velocity unstable\", PX4: as an EVENT); 0 = never"),
        Key("takeoff_spoolup_s", Float(ge=0),
             Derived("1.75 for ardupilot, 0 for px4"),
             "SITL: motor spool-up from NAV_TAKEOFF until the vehicle leaves the ground, seconds"),
        Key("rel_alt_bias_m", Float(ge=-10, le=10),
             Derived("0.25 for ardupilot, 0 for px4"),
             "SITL: reported height minus true height, metres (GLOBAL_POSITION_INT alt and "
             "relative_alt, LOCAL_POSITION_NED z); the vehicle flies that much lower"),
        Key("position_noise_m", Float(ge=0), 0.0,
             "SITL: white noise on the reported position, metres per axis"),
        Key("gps_drift_m_per_sqrt_s", Float(ge=0), 0.0,
             "SITL: random walk of the reported position, m/sqrt(s)"),
        Key("heading_error_deg", Float(ge=0, le=90),
             Derived("0.4 for ardupilot, 1.5 for px4"),
             "SITL: 1-sigma of the slowly varying heading estimate error, degrees (measured: "
             "PX4 SIH 1-12 off, ArduPilot within 0.6)"),
        Key("attitude_error_deg", Float(ge=0, le=30),
             Derived("0.3 for ardupilot, 1 for px4"),
             "SITL: 1-sigma of the roll and pitch estimate errors, degrees (measured: PX4 1-2)"),
        Key("position_error_m", Float(ge=0, le=100),
             Derived("0.02 for ardupilot, 0.15 for px4"),
             "SITL: 1-sigma of the north and east estimate errors, metres (measured: PX4 "
             "median 0.13-0.25, ArduPilot about 0.02)"),
        Key("height_error_m", Float(ge=0, le=100),
             Derived("0.05 for ardupilot, 0.5 for px4"),
             "SITL: 1-sigma of the height estimate error, metres (measured: PX4 up to 1.8)"),
        Key("error_time_constant_s", Float(gt=0), 30.0,
             "SITL: correlation time of the estimate errors (Gauss-Markov), seconds"),
        Key("battery_flight_s", Float(gt=0), 1800.0,
             "SITL: flight time on a full battery, seconds"),
        Key("battery_low_percent", Float(ge=0, le=100), 20.0,
             "SITL: battery level at which the autopilot returns home"),
        Key("ekf_origin_offset_m", Pair(Float()), [4.0, -3.0],
             "SITL, ArduPilot: EKF origin minus home, [north, east] metres (its local NED is "
             "about the EKF origin)"),
        Key("rangefinder", Bool(), Derived("true for px4 (SIH has one), false for "
                                                          "ardupilot"),
             "SITL: a downward rangefinder (DISTANCE_SENSOR: PX4 at 10 Hz, ArduPilot in EXTRA3 "
             "or on request)"),
        Key("rangefinder_max_m", Float(gt=0, le=1000), 40.0,
             "SITL: the rangefinder's range, metres"),
    ),
}

_COMPONENT_KEYS: tuple[Key, ...] = (
    Key("weight", Float(gt=0), 1.0, "weight of the component"),
    Key("mean", Pair(Float()), REQUIRED, "mean [x, y], metres", field="mean_xy"),
    Key("cov", Matrix2(), Derived("`belief.variance` times the identity"),
         "covariance, m^2"),
)


_CROSS_KEY_RULES = (
    "`targets.positions` given: `targets.count` must equal its length or be omitted.",
    "`targets.positions`, `targets.appear` positions and `robot.start` must lie inside the world "
    "(0 <= x <= size[0], 0 <= y <= size[1]).",
    "`targets.disappear` index: 0 <= index < count + len(appear); a target disappears at most "
    "once, and an appearing target not before its appearance step.",
    '`sensor.fov = "polygon"` requires `sensor.fov_polygon` (>= 3 points, convex, positive '
    "area; stored counter-clockwise); `fov_polygon` given with another `fov` is an error.",
    '`sensor.fov = "camera"` needs the `[camera]` table of the SITL mission: an error in the '
    "filter-only simulation.",
    "`belief.count` must equal (exact), be below (under) or above (over) the number of initial "
    "targets; it is not read for empty and explicit.",
    '`belief.kind = "explicit"` requires `belief.components`; `components` given with another '
    "kind is an error.",
    "`vehicle.armable_after_s`, `gps_fix_after_s`, `arm_unstable_s`, `takeoff_spoolup_s` and "
    "`rel_alt_bias_m` left out take `vehicle.flavour`'s measured values when the SITL starts; "
    "`armable_after_s` given turns PX4's velocity-unstable refusals off unless `arm_unstable_s` "
    "is given too, and the GPS fix then comes no later than it.",
    "An integer key given a float (`3.0`) or a boolean is an error; a number key accepts integers.",
    "Numbers must be finite (no `nan`, `inf`).",
)


# ---------------------------------------------------------------------------------------------
# Parsing
# ---------------------------------------------------------------------------------------------


def _check_inside(key: str, x: float, y: float, world: WorldSpec, what: str = "") -> None:
    sx, sy = world.size_m
    if not (0.0 <= x <= sx and 0.0 <= y <= sy):
        raise ConfigError(
            key,
            f"{what}must be inside the world, 0 <= x <= {sx!r} and 0 <= y <= {sy!r}, "
            f"got {toml_text([x, y])}",
        )


def _targets(v: dict[str, Any], world: WorldSpec) -> TargetsSpec:
    positions: FloatArray = v["positions_xy"]
    n_given = positions.shape[0]
    if v["count"] is None:
        v["count"] = n_given if n_given else _DEFAULT_TARGET_COUNT
    elif n_given and v["count"] != n_given:
        raise ConfigError(
            "targets.count",
            f"must equal the number of targets.positions ({n_given}) or be omitted, "
            f"got {v['count']}",
        )
    for i, (x, y) in enumerate(positions):
        _check_inside(f"targets.positions[{i}]", float(x), float(y), world)
    for i, (_, x, y) in enumerate(v["appear"]):
        _check_inside(f"targets.appear[{i}]", x, y, world, what="[x, y] ")
    n_initial, n_total = v["count"], v["count"] + len(v["appear"])
    gone: dict[int, int] = {}
    for i, (step, index) in enumerate(v["disappear"]):
        if index >= n_total:
            raise ConfigError(
                f"targets.disappear[{i}][1]",
                f"must be a target index < {n_total} ({n_initial} initial + "
                f"{n_total - n_initial} appearing), got {index}",
            )
        if index in gone:
            raise ConfigError(
                f"targets.disappear[{i}][1]",
                f"target {index} already disappears in targets.disappear[{gone[index]}]",
            )
        gone[index] = i
        if index >= n_initial:
            appears = v["appear"][index - n_initial][0]
            if step < appears:
                raise ConfigError(
                    f"targets.disappear[{i}][0]",
                    f"must be >= {appears}, the step at which target {index} appears, got {step}",
                )
    return TargetsSpec(**v)


def _convex_ccw(key: str, points: FloatArray) -> FloatArray:
    """The polygon, counter-clockwise, after checking >= 3 vertices, positive area, convexity."""
    n = points.shape[0]
    if n < 3:
        raise ConfigError(key, f"must have at least 3 points, got {n}")
    scale = float(np.max(np.abs(points)))
    if scale == 0.0:
        raise ConfigError(key, "must enclose a positive area")
    q = points / scale  # in [-1, 1]: no overflow below
    area2 = float(np.sum(q[:, 0] * np.roll(q[:, 1], -1) - np.roll(q[:, 0], -1) * q[:, 1]))
    if area2 == 0.0:  # shoelace formula, twice the signed area
        raise ConfigError(key, "must enclose a positive area")
    if area2 < 0.0:
        points, q = points[::-1], q[::-1]
    edge = np.roll(q, -1, axis=0) - q
    nxt = np.roll(edge, -1, axis=0)
    cross = edge[:, 0] * nxt[:, 1] - edge[:, 1] * nxt[:, 0]
    dot = np.sum(edge * nxt, axis=1)
    # Strictly left turns everywhere, and one full turn in total (a star polygon makes two).
    turning = float(np.sum(np.arctan2(cross, dot)))
    if np.any(cross <= 0.0) or not math.isclose(turning, 2.0 * math.pi, rel_tol=1e-6):
        raise ConfigError(
            key, "must be convex, with its vertices in order and none repeated or collinear"
        )
    return frozen_rows(points.tolist(), 2)


_FOOTPRINT_MAX_RANGE_M = 10_000.0


def camera_footprint_xy(camera: CameraModel, altitude_m: float, heading_deg: float) -> FloatArray:
    """(k, 2) counter-clockwise (x east, y north) offsets of the ground a level camera sees."""
    pose = BodyPose.from_euler(0.0, 0.0, 0.0, -altitude_m, yaw_rad=math.radians(heading_deg))
    samples = 8 if camera.has_distortion else 1
    ne = ground_footprint(camera, pose, _FOOTPRINT_MAX_RANGE_M, samples)
    if np.max(np.hypot(ne[:, 0], ne[:, 1])) >= 0.999 * _FOOTPRINT_MAX_RANGE_M:
        raise ConfigError("sensor.fov", '"camera": the level camera sees the horizon (check '
                                        "camera.mount_rpy_deg); its footprint is unbounded")
    xy = ne[:, ::-1]
    hull = ConvexHull(xy)  # 2-D hull vertices come counter-clockwise
    return _convex_ccw("sensor.fov", xy[hull.vertices])


def _sensor(v: dict[str, Any], camera: CameraModel, vehicle: VehicleSpec) -> SensorSpec:
    polygon: FloatArray = v["fov_polygon_xy"]
    if v["fov"] == "camera":
        if polygon.shape[0]:
            raise ConfigError("sensor.fov_polygon",
                              'is only allowed when sensor.fov = "polygon", got fov "camera"')
        v["fov_polygon_xy"] = camera_footprint_xy(camera, vehicle.altitude_m, vehicle.heading_deg)
    elif v["fov"] == "polygon":
        if polygon.shape[0] == 0:
            raise ConfigError("sensor.fov_polygon", 'is required when sensor.fov = "polygon"')
        v["fov_polygon_xy"] = _convex_ccw("sensor.fov_polygon", polygon)
    elif polygon.shape[0]:
        raise ConfigError(
            "sensor.fov_polygon",
            f'is only allowed when sensor.fov = "polygon", got fov {toml_text(v["fov"])}',
        )
    return SensorSpec(**v)


def _geo(v: dict[str, Any], world: WorldSpec) -> GeoSpec:
    if v["utm_epsg"] is None:
        lat, lon, _ = GeoSpec(v["origin"], 0).local_ned().ned_to_geodetic(
            world.size_m[1] / 2.0, world.size_m[0] / 2.0, 0.0)
        try:
            v["utm_epsg"] = utm_zone_for(float(lat), float(lon))
        except InputError as exc:  # the world's centre is off the Earth's coordinates
            raise ConfigError("geo.origin", f"the world's centre: {exc.reason}") from exc
    try:
        Utm(v["utm_epsg"])
    except InputError as exc:
        raise ConfigError("geo.utm_epsg", exc.reason) from exc
    return GeoSpec(**v)


def _camera(v: dict[str, Any]) -> CameraModel:
    hfov_deg = v.pop("hfov_deg")
    if hfov_deg is not None:
        if v["fx_px"] is not None or v["fy_px"] is not None:
            raise ConfigError("camera.hfov_deg", "give either hfov_deg or fx_px (and fy_px)")
        v["fx_px"] = 0.5 * v["width_px"] / math.tan(math.radians(0.5 * hfov_deg))
    if v["fy_px"] is None:
        v["fy_px"] = v["fx_px"]
    # Left at NaN, CameraModel derives them: a 90 degree FOV, the principal point at the centre.
    given: dict[str, Any] = {k: (math.nan if x is None else x) for k, x in v.items()}
    return CameraModel(**given)


def _robot(v: dict[str, Any], world: WorldSpec) -> RobotSpec:
    x, y = v["start_xy"]
    _check_inside("robot.start", x, y, world)
    return RobotSpec(**v)


def _belief(v: dict[str, Any], n_targets: int) -> BeliefSpec:
    if v["count"] is None:
        v["count"] = n_targets
    count = v["count"]
    rules = {"exact": ("equal", count == n_targets), "under": ("be <", count < n_targets),
             "over": ("be >", count > n_targets)}
    if v["kind"] in rules and not rules[v["kind"]][1]:
        raise ConfigError(
            "belief.count",
            f"must {rules[v['kind']][0]} the number of initial targets ({n_targets}) for "
            f"belief.kind = {toml_text(v['kind'])}, got {count}",
        )
    tables: tuple[Mapping[Any, Any], ...] = v["components"]
    if v["kind"] == "explicit" and not tables:
        raise ConfigError("belief.components", 'is required when belief.kind = "explicit"')
    if v["kind"] != "explicit" and tables:
        raise ConfigError(
            "belief.components",
            f'is only allowed when belief.kind = "explicit", got kind {toml_text(v["kind"])}',
        )
    components = []
    for i, table in enumerate(tables):
        c = read_table(table, f"belief.components[{i}]", _COMPONENT_KEYS)
        if c["cov"] is None:
            c["cov"] = frozen_rows((np.eye(2) * v["variance_m2"]).tolist(), 2)
        components.append(BeliefComponent(**c))
    v["components"] = tuple(components)
    return BeliefSpec(**v)


def parse_scenario(data: Mapping[str, Any], name: str = "scenario") -> Scenario:
    """The Scenario described by TOML data (`name` when it has no name key); ConfigError if bad,
    AggregateConfigError listing every bad key when there are several."""
    if not isinstance(data, Mapping):
        raise ConfigError(name, f"must be a table of scenario keys, got {describe(data)}")
    errors = ErrorCollector()
    top_known = [k.leaf for k in _TOP] + list(_SECTIONS)
    for key in data:
        if key not in top_known:
            errors.add(unknown_key(str(key), str(key), top_known))

    def top_table() -> dict[str, Any]:
        top = read_table({k: data[k] for k in data if k in top_known and k not in _SECTIONS},
                         "", _TOP)
        if top["name"] is None:
            top["name"] = Text().parse("name", name)
        return top

    def read(section: str) -> dict[str, Any] | None:
        keys = _SECTIONS[section]
        return errors.attempt(lambda: read_table(section_table(data, section), section, keys))

    def build(make: Callable[..., T], values: dict[str, Any] | None, *needs: object) -> T | None:
        if values is None or any(n is None for n in needs):
            return None
        return errors.attempt(lambda: make(values, *needs))

    top = errors.attempt(top_table)
    world_v = read("world")
    world = None if world_v is None else WorldSpec(**world_v)
    targets = build(_targets, read("targets"), world)
    camera = build(_camera, read("camera"))
    vehicle_v = read("vehicle")
    vehicle = None if vehicle_v is None else VehicleSpec(**vehicle_v)
    sensor = build(_sensor, read("sensor"), camera, vehicle)
    robot = build(_robot, read("robot"), world)
    belief = build(_belief, read("belief"), None if targets is None else targets.count)
    filter_v, metrics_v = read("filter"), read("metrics")
    geo = build(_geo, read("geo"), world)
    errors.raise_any()
    assert top is not None and filter_v is not None and metrics_v is not None  # else raised
    return Scenario(
        **top,
        world=_sound(world),
        targets=_sound(targets),
        sensor=_sound(sensor),
        robot=_sound(robot),
        belief=_sound(belief),
        filter=FilterSpec(**filter_v),
        metrics=MetricsSpec(**metrics_v),
        geo=_sound(geo),
        camera=_sound(camera),
        vehicle=_sound(vehicle),
    )


def _sound(value: T | None) -> T:
    """A part that was read without error (every error has been raised before)."""
    assert value is not None
    return value


def load_scenario(path: str | Path, seed: int | None = None) -> Scenario:
    """The Scenario in a TOML file, `seed` (when given) replacing the file's; ConfigError if bad."""
    p = Path(path)
    data = load_toml(p, "scenario")
    scenario = parse_scenario(data, name=p.stem)
    if seed is not None:
        scenario = dataclasses.replace(scenario, seed=Int(ge=0).parse("seed", seed))
    return scenario


def _dump_table(spec: object, keys: Sequence[Key]) -> dict[str, Any]:
    """The stored keys' values; a None (a [vehicle] flavour default) is left out."""
    return {k.leaf: k.kind.dump(getattr(spec, k.field)) for k in keys
            if k.stored and getattr(spec, k.field) is not None}


def scenario_to_dict(s: Scenario) -> dict[str, Any]:
    """The scenario as plain TOML data with every key spelled out (but the [vehicle] flavour
    defaults left to the flavour); parse_scenario reads it back."""
    out = _dump_table(s, _TOP)
    for section, keys in _SECTIONS.items():
        out[section] = _dump_table(getattr(s, section), keys)
    return out


# ---------------------------------------------------------------------------------------------
# The generated key reference
# ---------------------------------------------------------------------------------------------


def schema_markdown() -> str:
    """The key reference (docs/scenario.md), generated from the declarations."""
    lines = [
        "# Scenario keys",
        "",
        "<!-- Generated by `python -m companion.sim.scenario --markdown > docs/scenario.md`;",
        "     edit the declarations in companion/sim/scenario.py, not this file. -->",
        "",
        "A scenario is a TOML file (contract: `scenario-format.md` in the shared docs). Every key",
        "below is optional unless marked required; an unknown key, a wrong type or an",
        "out-of-range value is an error that names the key (`targets.count: must be >= 0, got",
        "-1`); every such error of the file is listed at once, one line each. The defaults",
        "reproduce the paper's set-up (ten stationary targets, 150 m x 150 m,",
        "25 m disk FOV, 10 % clutter, three lawn-mower sweeps, exact initial belief). Keys",
        "marked *project key* are this project's additions to the contract.",
        "",
        "Coordinates are metres in a local frame whose origin is the world's lower-left corner,",
        "x east, y north.",
        "",
        "The `[geo]`, `[camera]` and `[vehicle]` tables (all their keys are the project's) place",
        "the world on the Earth and describe the camera and the vehicle of the",
        "software-in-the-loop mission (`companion-sitl`); keys marked *SITL* only shape the",
        "simulated drone, the others are also what the service is told about its own camera",
        "and search. In the SITL, `sensor.p_detect` hides each target's tag from a frame with",
        "probability 1 - p_detect and `sensor.clutter_prob` / `clutter_rate` draw distractor",
        "tags (ids above the targets') in a frame's footprint; `sensor.noise_std` is then only",
        "the filter's R, the measurement noise being whatever the camera pipeline makes.",
        "",
        "## Top level",
        "",
        *markdown_rows("", _TOP),
    ]
    for section, keys in _SECTIONS.items():
        lines += ["", f"## `[{section}]`", "", *markdown_rows(section, keys)]
    lines += [
        "",
        "### `belief.components[i]`",
        "",
        "Each entry of `belief.components` is a table with these keys:",
        "",
        *markdown_rows("belief.components[i]", _COMPONENT_KEYS),
        "",
        "## Rules across keys",
        "",
        *[f"- {rule}" for rule in _CROSS_KEY_RULES],
        "",
    ]
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """Print the key reference (--markdown) or check a scenario file; 2 on a bad file or usage."""
    parser = argparse.ArgumentParser(
        prog="python -m companion.sim.scenario", description="Scenario file keys and checks."
    )
    parser.add_argument("--markdown", action="store_true", help="print the key reference")
    parser.add_argument("file", nargs="?", help="a scenario file to check")
    args = parser.parse_args(argv)
    if args.markdown:
        sys.stdout.write(schema_markdown())
        return 0
    if args.file is None:
        parser.print_usage(sys.stderr)
        return 2
    try:
        scenario = load_scenario(args.file)
    except ConfigError as exc:
        print(exc, file=sys.stderr)
        return 2
    print(f"{args.file}: ok ({scenario.name})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
