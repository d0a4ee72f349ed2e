"""The scenario keys, each declared once: TOML name, kind with its range, default, one-line doc.

`TOP_KEYS` (top level), `SECTION_KEYS` (one table each), `COMPONENT_KEYS` (each table of
`belief.components`); `CROSS_KEY_RULES` lists, for the reference, the rules the section builders
of companion.sim.scenario check across keys.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from companion.errors import ConfigError
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
    dump_table,
)
from companion.plan.planners import PlannerKind
from companion.sat.params import FILTER_KEYS, FovKind


class Components(Kind[tuple[Any, ...]]):
    """belief.components: an array of tables; `_belief` reads each table (see COMPONENT_KEYS)."""

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
        return [dump_table(c, COMPONENT_KEYS) for c in value]


# ---------------------------------------------------------------------------------------------
# The declarations: one per key
# ---------------------------------------------------------------------------------------------


DEFAULT_TARGET_COUNT = 10

TOP_KEYS: tuple[Key, ...] = (
    Key("name", Text(), Derived("the file's name without `.toml`"), "scenario name"),
    Key("seed", Int(ge=0), 0,
         "the run is a pure function of (file, seed); --seed overrides"),
    Key("dt", Float(gt=0), 1.0, "seconds per step", field="dt_s"),
    Key("steps", Int(ge=0), 0, "steps to run; 0 = until the planner's path ends"),
)

SECTION_KEYS: dict[str, tuple[Key, ...]] = {
    "world": (
        Key("size", Pair(Float(gt=0)), [150.0, 150.0], "metres, x by y", field="size_m"),
    ),
    "targets": (
        Key("count", Int(ge=0),
             Derived(f"{DEFAULT_TARGET_COUNT}, or the number of `positions`"),
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
        Key("unseen_targets", Float(ge=0), 1.0,
             "search-track: expected targets beside the initial belief, spread evenly over the "
             "world until the sensor has looked"),
        Key("stop_when_left", Float(ge=0), 0.05,
             "search-track: the search ends (then only tracks are revisited) once fewer targets "
             "than this are expected left to find"),
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
        Key("components", Components(), [],
             "for kind = \"explicit\": the initial components (keys below)"),
    ),
    "filter": FILTER_KEYS,
    "metrics": (
        Key("ospa_c", Float(gt=0), 100.0, "OSPA cut-off, metres"),
        Key("ospa_p", Float(ge=1), 2.0, "OSPA order"),
        Key("gospa_c", Float(gt=0), 10.0,
             "GOSPA cut-off, metres (alpha = 2, order = metrics.ospa_p)"),
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
        Key("offboard_failsafe", Choice("position", "hold", "land", "rtl"), "position",
             "SITL: the mode PX4 falls back to when offboard setpoints stop (COM_OBL_RC_ACT); "
             "it returns to OFFBOARD when they come back unless the mode was changed meanwhile"),
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

COMPONENT_KEYS: tuple[Key, ...] = (
    Key("weight", Float(gt=0), 1.0, "weight of the component"),
    Key("mean", Pair(Float()), REQUIRED, "mean [x, y], metres", field="mean_xy"),
    Key("cov", Matrix2(), Derived("`belief.variance` times the identity"),
         "covariance, m^2"),
)


CROSS_KEY_RULES = (
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

