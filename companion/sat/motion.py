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
saturates. speed = 0 (stationary targets) gives 0. `learn_motion` fits the class to recorded or
simulated trajectories (companion learn-gp prints it beside the GP's hyperparameters).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.optimize import least_squares

from companion.errors import InputError

__all__ = ["TargetMotion", "iou_variance_m2", "learn_motion"]

FloatArray = npt.NDArray[np.float64]


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
        return float(iou_variance_m2(self.velocity_var_m2_s2, self.correlation_s, tau_s))


def iou_variance_m2(sv2: float, tau_c_s: float, tau_s: npt.ArrayLike) -> FloatArray:
    """2 sv2 tau_c^2 (x - 1 + exp(-x)), x = tau / tau_c, elementwise (Eq. iou_variance); 0 where
    tau <= 0."""
    x = np.maximum(np.asarray(tau_s, dtype=np.float64), 0.0) / tau_c_s
    result: FloatArray = 2.0 * sv2 * tau_c_s * tau_c_s * (x + np.expm1(-x))
    return result


def learn_motion(
    trajectories: Sequence[tuple[npt.ArrayLike, npt.ArrayLike]], max_lag: int = 600
) -> TargetMotion:
    """The motion class that best explains trajectories [(t_s (n,), y (n, 2)), ...] sampled at
    one fixed step: Eq. iou_variance plus twice the observation noise fitted, by least squares
    on a log scale, to each axis's empirical variance of displacements over lags 1..max_lag."""
    lags, variances = _displacement_variances(trajectories, max_lag)

    def residual(theta: FloatArray) -> FloatArray:
        sv2, tau_c, noise2 = np.exp(theta)
        model = iou_variance_m2(sv2, tau_c, lags) + 2.0 * noise2
        return np.asarray(np.log(model) - np.log(variances), dtype=np.float64)

    span = float(lags[-1])
    start = np.log([max(variances[0] / lags[0] ** 2, 1e-12), span / 4.0, 1e-2])
    fit = least_squares(residual, start, bounds=(np.log([1e-12, 1e-3 * span, 1e-8]),
                                                 np.log([1e6, 1e3 * span, 1e6])))
    sv2, tau_c, _ = (float(v) for v in np.exp(fit.x))
    return TargetMotion(math.sqrt(2.0 * sv2), 2.0 * tau_c)


def _displacement_variances(
    trajectories: Sequence[tuple[npt.ArrayLike, npt.ArrayLike]], max_lag: int
) -> tuple[FloatArray, FloatArray]:
    """Lags (s) and the per-axis variance of displacements over each, pooled over trajectories."""
    steps: list[float] = []
    paths: list[FloatArray] = []
    for i, (t_raw, y_raw) in enumerate(trajectories):
        t = np.asarray(t_raw, dtype=np.float64)
        y = np.asarray(y_raw, dtype=np.float64)
        if t.ndim != 1 or y.shape != (t.size, 2) or t.size < 3 or not np.all(np.isfinite(y)):
            raise InputError(f"trajectory {i}: needs t_s (n,) and finite y (n, 2), n >= 3")
        dt = np.diff(t)
        if not (np.all(dt > 0.0) and np.allclose(dt, dt[0])):
            raise InputError(f"trajectory {i}: samples must be evenly spaced in time")
        steps.append(float(dt[0]))
        paths.append(y)
    if not paths:
        raise InputError("learn_motion needs at least one trajectory")
    if not np.allclose(steps, steps[0]):
        raise InputError("learn_motion: every trajectory must have the same time step")
    longest = min(max_lag, min(p.shape[0] for p in paths) - 1)
    lag_steps = np.unique(np.geomspace(1, longest, 40).astype(np.int64))
    variances = np.array([
        np.mean(np.concatenate([(p[k:] - p[:-k]).ravel() ** 2 for p in paths]))
        for k in lag_steps.tolist()
    ])
    if not np.all(variances > 0.0):
        raise InputError("learn_motion needs trajectories that move")
    return lag_steps.astype(np.float64) * steps[0], variances.astype(np.float64)
