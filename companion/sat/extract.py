"""Multitarget state estimation (Vo & Ma 2006, Table 3): heavy components become targets."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from companion.sat.mixture import Mixture


def extract(mix: Mixture, weight_threshold: float) -> NDArray[np.int64]:
    """Indices of the estimated targets: each component with w > threshold, round(w) times."""
    heavy = np.flatnonzero(mix.weights > weight_threshold)
    copies = np.maximum(np.floor(mix.weights[heavy] + 0.5), 1).astype(np.int64)
    return np.repeat(heavy, copies)
