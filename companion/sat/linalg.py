"""Small batched linear algebra for stacks of 2x2 (or d x d) matrices, closed form where it pays."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


def inv_det_2x2(a: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Inverse and determinant of each 2x2 matrix in a stack (..., 2, 2), in closed form."""
    det = a[..., 0, 0] * a[..., 1, 1] - a[..., 0, 1] * a[..., 1, 0]
    inv = np.empty_like(a)
    inv[..., 0, 0] = a[..., 1, 1]
    inv[..., 1, 1] = a[..., 0, 0]
    inv[..., 0, 1] = -a[..., 0, 1]
    inv[..., 1, 0] = -a[..., 1, 0]
    inv /= det[..., None, None]
    return inv, det


def inv_stack(a: FloatArray) -> FloatArray:
    """Inverse of each d x d matrix in a stack (n, d, d); closed form for d = 2."""
    if a.shape[-1] == 2:
        return inv_det_2x2(a)[0]
    return np.asarray(np.linalg.inv(a), dtype=np.float64)
