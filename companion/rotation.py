"""Attitude rotations: ZYX (yaw, pitch, roll) Euler angles, Hamilton quaternions, 3x3 matrices.

Quaternions are Hamilton, scalar first (w, x, y, z), and rotate body vectors into the parent
frame (NED for a vehicle): q = qz(yaw) qy(pitch) qx(roll). Pure math.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TypeVar

import numpy as np
from numpy.typing import NDArray

from companion.errors import InputError

__all__ = [
    "quaternion_from_euler",
    "quaternions_from_euler",
    "rotation_from_quaternion",
    "rotation_zyx",
]

FloatArray = NDArray[np.float64]
_Angle = TypeVar("_Angle", float, FloatArray)


def _hamilton_zyx(cr: _Angle, sr: _Angle, cp: _Angle, sp: _Angle, cy: _Angle,
                  sy: _Angle) -> tuple[_Angle, _Angle, _Angle, _Angle]:
    """w, x, y, z of qz(yaw) qy(pitch) qx(roll) from the cosines and sines of the half angles."""
    return (cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy)


def quaternion_from_euler(roll_rad: float, pitch_rad: float,
                          yaw_rad: float) -> tuple[float, float, float, float]:
    """Hamilton q_wxyz of the ZYX (yaw, pitch, roll) attitude: q = qz(yaw) qy(pitch) qx(roll)."""
    return _hamilton_zyx(math.cos(0.5 * roll_rad), math.sin(0.5 * roll_rad),
                         math.cos(0.5 * pitch_rad), math.sin(0.5 * pitch_rad),
                         math.cos(0.5 * yaw_rad), math.sin(0.5 * yaw_rad))


def quaternions_from_euler(roll_rad: FloatArray, pitch_rad: FloatArray,
                           yaw_rad: FloatArray) -> FloatArray:
    """(k, 4) w, x, y, z of k ZYX attitudes given as (k,) roll, pitch and yaw arrays."""
    cr, sr = np.cos(0.5 * roll_rad), np.sin(0.5 * roll_rad)
    cp, sp = np.cos(0.5 * pitch_rad), np.sin(0.5 * pitch_rad)
    cy, sy = np.cos(0.5 * yaw_rad), np.sin(0.5 * yaw_rad)
    return np.stack(_hamilton_zyx(cr, sr, cp, sp, cy, sy), axis=1)


def rotation_zyx(roll_rad: float, pitch_rad: float, yaw_rad: float) -> FloatArray:
    """Rz(yaw) @ Ry(pitch) @ Rx(roll): the aerospace sequence, rotating body into parent."""
    cr, sr = math.cos(roll_rad), math.sin(roll_rad)
    cp, sp = math.cos(pitch_rad), math.sin(pitch_rad)
    cy, sy = math.cos(yaw_rad), math.sin(yaw_rad)
    return np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                     [-sp, cp * sr, cp * cr]])


def rotation_from_quaternion(q_wxyz: Sequence[float]) -> FloatArray:
    """The 3x3 rotation matrix of a Hamilton quaternion (normalised first)."""
    w, x, y, z = (float(c) for c in q_wxyz)
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if not math.isfinite(n) or n == 0.0:
        raise InputError(f"quaternion {tuple(q_wxyz)} has no rotation")
    w, x, y, z = w / n, x / n, y / n, z / n
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
