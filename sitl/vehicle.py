"""The simulated multicopter: a point mass with speed, acceleration and yaw-rate limits.

It follows a position or velocity target (and a yaw) with a first-order velocity loop, and its
roll and pitch are those that would produce its horizontal acceleration, so a camera on it
tilts as a real one does. Pure: `step` maps (state, target, dt) to the next state.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from companion.rotation import quaternion_from_euler

FloatArray = NDArray[np.float64]

GRAVITY_M_S2 = 9.80665


@dataclass(frozen=True, slots=True)
class VehicleLimits:
    """How hard the vehicle can move (the autopilot's tuning)."""

    max_speed_h_m_s: float = 8.0
    max_speed_up_m_s: float = 3.0
    max_speed_down_m_s: float = 1.5
    max_accel_m_s2: float = 4.0
    max_yaw_rate_deg_s: float = 60.0
    position_gain_1_s: float = 1.0  # desired velocity per metre of position error
    velocity_time_constant_s: float = 0.5


@dataclass(frozen=True, slots=True)
class Target:
    """What the vehicle should do now: hold a position, or fly a velocity; with a yaw."""

    position_ned: FloatArray | None = None  # (3,) metres
    velocity_ned: FloatArray | None = None  # (3,) m/s, used when position is None
    yaw_rad: float | None = None  # None: keep the current yaw


@dataclass(frozen=True, slots=True)
class VehicleState:
    """Where the vehicle is and how it moves, in the local NED frame of its simulation."""

    position_ned: FloatArray  # (3,) metres; down = 0 is the ground
    velocity_ned: FloatArray  # (3,) m/s
    accel_ned: FloatArray  # (3,) m/s^2, of the last step
    yaw_rad: float
    on_ground: bool = True

    @staticmethod
    def at_rest(north_m: float = 0.0, east_m: float = 0.0, yaw_rad: float = 0.0) -> VehicleState:
        """On the ground, still."""
        zero = np.zeros(3)
        return VehicleState(np.array([north_m, east_m, 0.0]), zero, zero, yaw_rad, True)

    def roll_pitch_rad(self) -> tuple[float, float]:
        """Roll and pitch that tilt the thrust to give this horizontal acceleration."""
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        a_forward = c * self.accel_ned[0] + s * self.accel_ned[1]
        a_right = -s * self.accel_ned[0] + c * self.accel_ned[1]
        return math.atan2(a_right, GRAVITY_M_S2), math.atan2(-a_forward, GRAVITY_M_S2)

    def quaternion_wxyz(self) -> tuple[float, float, float, float]:
        """Body (FRD) to NED rotation, Hamilton, scalar first (ZYX Euler: yaw, pitch, roll)."""
        roll, pitch = self.roll_pitch_rad()
        return quaternion_from_euler(roll, pitch, self.yaw_rad)


def wrap_rad(angle_rad: float) -> float:
    """The angle in [-pi, pi)."""
    return (angle_rad + math.pi) % (2.0 * math.pi) - math.pi


def step(
    state: VehicleState, target: Target | None, dt_s: float, limits: VehicleLimits, armed: bool
) -> VehicleState:
    """The state dt_s later; a disarmed or target-less vehicle on the ground stays put."""
    if not armed or target is None:
        if state.on_ground or not armed:
            # Disarmed in the air: it falls; the simulation lands it at once (no crash model).
            still = np.zeros(3)
            pos = state.position_ned.copy()
            pos[2] = 0.0 if not armed else pos[2]
            return replace(state, position_ned=pos, velocity_ned=still, accel_ned=still,
                           on_ground=pos[2] >= 0.0)
        target = Target(position_ned=state.position_ned)  # no target in the air: hover
    if target.position_ned is not None:
        wanted = limits.position_gain_1_s * (target.position_ned - state.position_ned)
    else:
        assert target.velocity_ned is not None
        wanted = np.asarray(target.velocity_ned, dtype=np.float64)
    wanted = _limit_velocity(wanted, limits)
    accel = (wanted - state.velocity_ned) / limits.velocity_time_constant_s
    norm = float(np.linalg.norm(accel))
    if norm > limits.max_accel_m_s2:
        accel *= limits.max_accel_m_s2 / norm
    velocity = _limit_velocity(state.velocity_ned + accel * dt_s, limits)
    position = state.position_ned + 0.5 * (state.velocity_ned + velocity) * dt_s
    on_ground = False
    if position[2] >= 0.0:  # the ground
        position[2] = 0.0
        velocity[2] = min(velocity[2], 0.0)
        on_ground = velocity[2] == 0.0 and float(np.hypot(*velocity[:2])) < 0.1
        if on_ground:
            velocity[:] = 0.0
    yaw = state.yaw_rad
    if target.yaw_rad is not None and not on_ground:
        max_turn = math.radians(limits.max_yaw_rate_deg_s) * dt_s
        yaw = wrap_rad(yaw + float(np.clip(wrap_rad(target.yaw_rad - yaw), -max_turn, max_turn)))
    return VehicleState(position, velocity, (velocity - state.velocity_ned) / dt_s, yaw,
                        on_ground)


def _limit_velocity(velocity: FloatArray, limits: VehicleLimits) -> FloatArray:
    out = np.array(velocity, dtype=np.float64)
    h = float(np.hypot(out[0], out[1]))
    if h > limits.max_speed_h_m_s:
        out[:2] *= limits.max_speed_h_m_s / h
    out[2] = float(np.clip(out[2], -limits.max_speed_up_m_s, limits.max_speed_down_m_s))
    return out
