"""Multitarget state estimation (Vo & Ma 2006, Table 3): heavy components become targets."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from companion.kernel_cache import kernel
from companion.sat.mixture import Mixture

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


def extract(mix: Mixture, weight_threshold: float) -> NDArray[np.int64]:
    """Indices of the estimated targets: each component with w > threshold, round(w) times."""
    weights = mix.weights
    out = np.empty(count_estimates(weights, weight_threshold), dtype=np.int64)
    _fill_estimates(weights, weight_threshold, out)
    return out


@kernel
def _copies(weight: float) -> int:  # pragma: no cover - compiled
    """round(w), at least 1: the targets a heavy component stands for."""
    return max(math.floor(weight + 0.5), 1)


@kernel
def count_estimates(weights: FloatArray, threshold: float) -> int:  # pragma: no cover
    """The number of estimates: the sum of round(w) over the weights above threshold."""
    total = 0
    for w in weights:
        if w > threshold:
            total += _copies(w)
    return total


@kernel
def _fill_estimates(  # pragma: no cover - compiled; tested through extract
    weights: FloatArray, threshold: float, out: IntArray
) -> None:
    """Each index with w > threshold, round(w) times (at least once), in order."""
    at = 0
    for i in range(weights.shape[0]):
        if weights[i] > threshold:
            for _ in range(_copies(weights[i])):
                out[at] = i
                at += 1
