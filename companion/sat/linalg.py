"""Small batched linear algebra for stacks of 2x2 (or d x d) matrices, closed form where it pays."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from companion.kernel_cache import kernel

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

SYMMETRY_RTOL = 1e-8
"""Largest |P01 - P10| of a covariance taken for round-off, relative to its larger diagonal entry:
a Kalman update leaves ~1e-16, so this is a wide margin that still catches a transposed matrix."""

CORRELATION_TOL = 1e-12
"""Smallest 1 - rho^2 of a positive definite 2x2 covariance: closer to singular, determinants
computed downstream can round to <= 0."""


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


def spd_2x2_faults(covs: FloatArray) -> tuple[BoolArray, BoolArray]:
    """(not symmetric, not positive definite) of each finite 2x2 in a stack (..., 2, 2).

    Symmetric: |P01 - P10| <= SYMMETRY_RTOL max(|P00|, |P11|). Positive definite, of the
    symmetric part: P00 > 0 and P01^2 < (1 - CORRELATION_TOL) P00 P11 (so P11 > 0, det P > 0).
    """
    if covs.shape == (2, 2):  # one matrix (a scan's R): the same tests on Python floats
        return _spd_2x2_faults_one(covs)
    p00, p10, p01, p11 = covs[..., 0, 0], covs[..., 1, 0], covs[..., 0, 1], covs[..., 1, 1]
    asymmetric = np.abs(p01 - p10) > SYMMETRY_RTOL * np.maximum(np.abs(p00), np.abs(p11))
    with np.errstate(over="ignore", under="ignore"):  # P00 P11 rounds to inf (kept) or 0 (refused)
        p01 = np.where(p01 == p10, p01, 0.5 * (p01 + p10))
        definite = (p00 > 0.0) & (p01 * p01 < (1.0 - CORRELATION_TOL) * (p00 * p11))
    return np.asarray(asymmetric), np.asarray(~definite)


def _spd_2x2_faults_one(cov: FloatArray) -> tuple[BoolArray, BoolArray]:
    """spd_2x2_faults of a single 2x2."""
    (p00, p01), (p10, p11) = cov.tolist()
    asymmetric, indefinite = spd_2x2_faults_of(p00, p01, p10, p11)
    return np.asarray(asymmetric), np.asarray(indefinite)


@kernel
def spd_2x2_faults_of(p00: float, p01: float, p10: float, p11: float) -> tuple[bool, bool]:
    """spd_2x2_faults of one 2x2 given by its entries, without numpy's per-call overhead (same
    IEEE results: Python floats round, overflow to inf and underflow to 0 as float64 arrays
    do)."""
    scale = math.nan if math.isnan(p00) or math.isnan(p11) else max(abs(p00), abs(p11))
    asymmetric = abs(p01 - p10) > SYMMETRY_RTOL * scale  # np.maximum propagates NaN, max not
    if p01 != p10:
        p01 = 0.5 * (p01 + p10)
    definite = p00 > 0.0 and p01 * p01 < (1.0 - CORRELATION_TOL) * (p00 * p11)
    return asymmetric, not definite


def inv_stack(a: FloatArray) -> FloatArray:
    """Inverse of each d x d matrix in a stack (n, d, d); closed form for d = 2."""
    if a.shape[-1] == 2:
        return inv_det_2x2(a)[0]
    return np.asarray(np.linalg.inv(a), dtype=np.float64)
