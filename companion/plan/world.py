"""The search area in the filter's ground frame."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class World:
    """An axis-aligned rectangle [0, width] x [0, height], metres, x east, y north."""

    width_m: float
    height_m: float

    def clip(self, xy: FloatArray) -> FloatArray:
        """The nearest points inside the world."""
        return np.clip(xy, 0.0, [self.width_m, self.height_m])

    def contains(self, xy: FloatArray) -> NDArray[np.bool_]:
        """Whether each point (..., 2) lies inside the world (boundary included)."""
        upper = np.array([self.width_m, self.height_m])
        inside: NDArray[np.bool_] = np.all((xy >= 0.0) & (xy <= upper), axis=-1)
        return inside
