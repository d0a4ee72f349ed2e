"""Where the vehicle should be now: the carrot along the plan, and the local NED setpoint of it.

Pure: the time step is passed in. The carrot moves along the planner's waypoints at the search
speed; a lawn mower's waypoint counts as reached once the carrot is on it and the vehicle within
REACHED_M of it. The search-frame target becomes a local NED setpoint at the search altitude
above home. `gate_limits` puts the configured geofence and altitude band into that local frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from companion.config import SafetyConfig, SearchConfig
from companion.geo import LocalNed
from companion.plan.gate import GateLimits, Setpoint
from companion.plan.keep_in import KeepIn
from companion.plan.planners import LawnMower, Planner, PlanProgress, move_towards
from companion.plan.search_track import SearchTrackParams, inscribed_radius_m
from companion.plan.world import World
from companion.sat.filter import SatParams
from companion.sat.mixture import Mixture
from companion.sat.tracks import Tracks
from companion.vision.camera import BodyPose, CameraModel, ground_footprint

if TYPE_CHECKING:
    from companion.pipeline import SearchFrame

__all__ = ["REACHED_M", "Carrot", "fence_keep_in", "gate_limits", "hold_setpoint", "ramp",
           "search_params", "search_setpoint", "tilt_cos", "vehicle_xy"]

FloatArray = NDArray[np.float64]
REACHED_M = 1.5  # the vehicle is this close to a waypoint: the planner moves on
_RAMP_SHARE = 0.99  # of the gate's speed limits, so that float rounding never trips them


@dataclass(frozen=True)
class Carrot:
    """The point the vehicle follows (None: not placed yet) and the planner's progress."""

    xy_m: FloatArray | None = None
    progress: PlanProgress = 0

    def advance(self, planner: Planner, vehicle_xy_m: FloatArray, mixture: Mixture,
                tracks: Tracks, world: World, speed_m_s: float,
                dt_s: float, t_s: float = 0.0) -> tuple[FloatArray, Carrot]:
        """The search-frame target now and the carrot moved on by speed_m_s * dt_s; t_s is the
        estimator's time."""
        carrot = vehicle_xy_m if self.xy_m is None else self.xy_m
        waypoint, progress = planner.next_waypoint(carrot, mixture, tracks, world,
                                                   self.progress, t_s)
        if waypoint is None:
            return carrot, Carrot(self.xy_m, progress)
        carrot = move_towards(carrot, waypoint, speed_m_s * dt_s)
        if (isinstance(planner, LawnMower) and np.allclose(carrot, waypoint)
                and np.hypot(*(vehicle_xy_m - waypoint)) <= REACHED_M):
            progress += 1
        return carrot, Carrot(carrot, progress)


def tilt_cos(q_wxyz: tuple[float, float, float, float]) -> float:
    """cos of the angle between the body's down axis and the vertical (roll and pitch)."""
    _, x, y, _ = q_wxyz
    return 1.0 - 2.0 * (x * x + y * y)


def gate_limits(safety: SafetyConfig, origin: LocalNed, home_amsl_m: float) -> GateLimits:
    """The safety limits in the autopilot's local NED frame (altitudes above home)."""
    fence = safety.geofence_latlon
    north, east, _ = origin.geodetic_to_ned(fence[:, 0], fence[:, 1], origin.alt_m)
    above_origin_m = home_amsl_m - origin.alt_m
    return GateLimits(np.column_stack([north, east]), safety.min_alt_m + above_origin_m,
                      safety.max_alt_m + above_origin_m, safety.max_speed_h_m_s,
                      safety.max_speed_v_m_s)


def fence_keep_in(safety: SafetyConfig, frame: SearchFrame) -> KeepIn:
    """The geofence in the search frame, with the clearance the plan keeps inside it."""
    fence = safety.geofence_latlon
    easting, northing = frame.utm.geodetic_to_utm(fence[:, 0], fence[:, 1])
    return KeepIn(frame.from_utm(np.column_stack([easting, northing])), safety.fence_clearance_m)


def vehicle_xy(frame: SearchFrame, lat_deg: float, lon_deg: float) -> FloatArray:
    """The vehicle's position in the search frame."""
    e, n = frame.utm.geodetic_to_utm(lat_deg, lon_deg)
    return frame.from_utm(np.array([float(e), float(n)]))


def hold_setpoint(vehicle_ned_m: FloatArray, yaw_deg: float) -> Setpoint:
    """Stay where the vehicle is."""
    return Setpoint(vehicle_ned_m[0], vehicle_ned_m[1], vehicle_ned_m[2], yaw_deg)


def ramp(wanted: Setpoint, from_ned_m: FloatArray, limits: GateLimits, dt_s: float) -> Setpoint:
    """The wanted setpoint, or the point a step of just under the gate's speed limits towards
    it from `from_ned_m` (the last setpoint sent, or the vehicle), horizontally and vertically."""
    step = np.array([wanted.north_m, wanted.east_m, wanted.down_m]) - from_ned_m
    max_h_m = _RAMP_SHARE * limits.max_speed_h_m_s * dt_s
    max_v_m = _RAMP_SHARE * limits.max_speed_v_m_s * dt_s
    length_h = float(np.hypot(step[0], step[1]))
    if length_h <= max_h_m and abs(step[2]) <= max_v_m:
        return wanted
    step[:2] *= min(1.0, max_h_m / length_h) if length_h > 0.0 else 1.0
    step[2] = float(np.clip(step[2], -max_v_m, max_v_m))
    north, east, down = from_ned_m + step
    return Setpoint(float(north), float(east), float(down), wanted.yaw_deg)


def search_setpoint(frame: SearchFrame, origin: LocalNed, target_xy_m: FloatArray,
                    alt_amsl_m: float, yaw_deg: float) -> Setpoint:
    """The local NED setpoint of a search-frame target at an altitude above sea level."""
    lat, lon = frame.to_latlon(target_xy_m)[0]
    north, east, down = origin.geodetic_to_ned(lat, lon, alt_amsl_m)
    return Setpoint(float(north), float(east), float(down), yaw_deg)


_FOOTPRINT_RANGE_M = 10_000.0
"""Farthest ground the footprint's rays are followed to (the service's camera looks down)."""


def search_params(search: SearchConfig, margin_m: float, camera: CameraModel, params: SatParams,
                  area_xy_m: FloatArray) -> SearchTrackParams:
    """What the search-and-track planner knows in flight: the disk inside the level camera's
    footprint at the search altitude (less the footprint margin), p(D|F), the targets' motion,
    the search area (search frame) and the configured stop rule."""
    pose = BodyPose.from_euler(0.0, 0.0, 0.0, -search.altitude_m,
                               yaw_rad=math.radians(search.heading_deg))
    ground_ne = ground_footprint(camera, pose, _FOOTPRINT_RANGE_M,
                                 8 if camera.has_distortion else 1)
    view_m = max(inscribed_radius_m(ground_ne[:, ::-1]) - margin_m, 0.5)
    return SearchTrackParams(
        view_radius_m=view_m, p_detect=params.p_detect,
        unseen_targets=float(search.expected_targets or 1), stop_below=search.stop_when_left,
        motion=params.tracks.motion, area_xy=area_xy_m)
