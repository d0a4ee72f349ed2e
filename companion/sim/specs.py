"""A scenario's parts as frozen, slotted specs with units in their field names."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from companion.geo import LocalNed, Utm
from companion.plan.planners import PlannerKind
from companion.sat.params import FilterSpec, FovKind
from companion.vision.camera import CameraModel

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
]

FloatArray = NDArray[np.float64]


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
    unseen_targets: float = 1.0  # search-track: expected targets beside the belief, spread evenly
    stop_when_left: float = 0.05  # search-track: the search ends below this many left to find


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
    """OSPA cut-off (m) and order; GOSPA cut-off (m), of the same order."""

    ospa_c: float
    ospa_p: float
    gospa_c: float


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
    offboard_failsafe: Literal["position", "hold", "land", "rtl"]
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

