"""The paper's sensor model: detections of targets in the FOV with noise, and clutter in the FOV."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from companion.sat.fov import Region

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class SensorModel:
    """p(D|F), noise std per axis, and clutter: one false positive with a probability per scan,
    plus a Poisson number with a mean per scan, uniform in the FOV."""

    p_detect: float
    noise_std_m: float
    clutter_prob: float
    clutter_rate: float

    @property
    def clutter_per_scan(self) -> float:
        """Expected false positives per scan."""
        return self.clutter_prob + self.clutter_rate


def sense(
    model: SensorModel, targets_xy: FloatArray, region: Region, rng: np.random.Generator
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """One scan: (measurements (m, 2) in random order, is_clutter (m,))."""
    inside = targets_xy[region.contains(targets_xy)]
    seen = inside[rng.random(inside.shape[0]) < model.p_detect]
    noisy = seen + rng.normal(0.0, model.noise_std_m, size=seen.shape)
    n_clutter = int(rng.random() < model.clutter_prob)
    if model.clutter_rate > 0.0:
        n_clutter += int(rng.poisson(model.clutter_rate))
    clutter = region.sample_uniform(rng, n_clutter)
    z = np.concatenate([noisy, clutter])
    is_clutter = np.arange(z.shape[0]) >= noisy.shape[0]
    order = rng.permutation(z.shape[0])
    return z[order], is_clutter[order]
