"""The targets' motion class: how far a target may have gone since it was last seen.

A confirmed track's GP (companion.sat.gp) predicts where the trend of its recent detections
leads; it cannot know the manoeuvres made since, and its SE kernel's predictive variance
saturates at sigma_f^2 however long the target stays unseen. The class term models them: each
axis of the target's velocity is an Ornstein-Uhlenbeck process with variance sigma_v^2 =
speed^2 / 2 (a random heading at a typical speed) and correlation time tau_c = manoeuvre / 2 (a
new heading every `manoeuvre_s`: the triangular correlation of such legs integrates to T / 2),
so the displacement after tau seconds unseen has, per axis, the variance of integrated OU motion

    s^2(tau) = 2 sigma_v^2 tau_c^2 (tau / tau_c - 1 + exp(-tau / tau_c))      # Eq. iou_variance

ballistic (sigma_v^2 tau^2) at first and diffusive (2 sigma_v^2 tau_c tau) later: it never
saturates. speed = 0 (stationary targets) gives 0.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from numba import njit

from companion.errors import InputError

__all__ = ["TargetMotion", "iou_variance_m2"]


@dataclass(frozen=True, slots=True)
class TargetMotion:
    """The class of the targets: a typical ground speed (m/s) and time between manoeuvres (s)."""

    speed_m_s: float = 0.3
    manoeuvre_s: float = 200.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.speed_m_s) and self.speed_m_s >= 0.0):
            raise InputError(f"target speed must be finite and >= 0, got {self.speed_m_s!r}")
        if not (math.isfinite(self.manoeuvre_s) and self.manoeuvre_s > 0.0):
            raise InputError(
                f"time between manoeuvres must be finite and > 0, got {self.manoeuvre_s!r}"
            )

    @property
    def velocity_var_m2_s2(self) -> float:
        """sigma_v^2: the variance of one axis of the velocity at a random heading."""
        return 0.5 * self.speed_m_s**2

    @property
    def correlation_s(self) -> float:
        """tau_c: the velocity's correlation time."""
        return 0.5 * self.manoeuvre_s

    def displacement_var_m2(self, tau_s: float) -> float:
        """Per-axis variance (m^2) of the displacement after tau_s seconds (Eq. iou_variance)."""
        return iou_variance_m2(self.velocity_var_m2_s2, self.correlation_s, tau_s)


@njit(cache=True, nogil=True)
def iou_variance_m2(sv2: float, tau_c_s: float, tau_s: float) -> float:  # pragma: no cover
    """2 sv2 tau_c^2 (x - 1 + exp(-x)), x = tau / tau_c (Eq. iou_variance); 0 for tau <= 0."""
    if tau_s <= 0.0 or sv2 == 0.0:
        return 0.0
    x = tau_s / tau_c_s
    return 2.0 * sv2 * tau_c_s * tau_c_s * (x + math.expm1(-x))
