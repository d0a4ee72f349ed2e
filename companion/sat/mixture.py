"""A Gaussian mixture (the GM-PHD intensity) as arrays: weights, means, covariances and labels."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from companion.errors import InputError
from companion.sat.linalg import SYMMETRY_RTOL, spd_2x2_faults

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

NO_LABEL = -1
"""Label of a component that belongs to no track."""


class Mixture(NamedTuple):
    """v(x) = sum_i w_i N(x; m_i, P_i) (Eq. general_gm_phd_intensity), one row per component.

    `labels[i]` is the id of the track that component i supports, or NO_LABEL. Positions are the
    first two state coordinates (metres); a constant-velocity state appends (vx, vy) in m/s.
    """

    weights: FloatArray  # (n,)
    means: FloatArray  # (n, d)
    covs: FloatArray  # (n, d, d)
    labels: IntArray  # (n,)

    @property
    def size(self) -> int:
        """Number of components."""
        return int(self.weights.shape[0])

    @property
    def dim(self) -> int:
        """State dimension d."""
        return int(self.means.shape[1])

    @property
    def total_weight(self) -> float:
        """Sum of weights: the expected number of targets."""
        return float(self.weights.sum())

    def take(self, index: NDArray[np.int64] | NDArray[np.bool_]) -> Mixture:
        """The components selected by an index or boolean mask, in that order."""
        return Mixture(
            self.weights[index], self.means[index], self.covs[index], self.labels[index]
        )

    @staticmethod
    def empty(dim: int = 2) -> Mixture:
        """A mixture with no components."""
        return Mixture(
            np.zeros(0), np.zeros((0, dim)), np.zeros((0, dim, dim)), np.zeros(0, dtype=np.int64)
        )

    @staticmethod
    def concat(parts: list[Mixture]) -> Mixture:
        """Components of all parts, in order."""
        return Mixture(
            np.concatenate([p.weights for p in parts]),
            np.concatenate([p.means for p in parts]),
            np.concatenate([p.covs for p in parts]),
            np.concatenate([p.labels for p in parts]),
        )


def make_mixture(
    weights: object, means: object, covs: object, labels: object | None = None
) -> Mixture:
    """A validated Mixture from array-likes; InputError names what is wrong."""
    w = np.asarray(weights, dtype=np.float64).reshape(-1)
    m = np.asarray(means, dtype=np.float64)
    n = w.shape[0]
    if m.ndim != 2 or m.shape[0] != n or m.shape[1] < 2:
        raise InputError(f"mixture means: expected shape ({n}, d>=2), got {m.shape}")
    d = m.shape[1]
    p = np.asarray(covs, dtype=np.float64)
    if p.shape != (n, d, d):
        raise InputError(f"mixture covariances: expected shape ({n}, {d}, {d}), got {p.shape}")
    lab = (
        np.full(n, NO_LABEL, dtype=np.int64)
        if labels is None
        else np.asarray(labels, dtype=np.int64).reshape(-1)
    )
    if lab.shape != (n,):
        raise InputError(f"mixture labels: expected shape ({n},), got {lab.shape}")
    if not (np.all(np.isfinite(w)) and np.all(w >= 0.0)):
        raise InputError("mixture weights: must be finite and >= 0")
    if not np.all(np.isfinite(m)):
        raise InputError("mixture means: must be finite")
    check_covariances(p, "mixture covariances")
    return Mixture(w.copy(), m.copy(), p.copy(), lab.copy())


def check_covariances(covs: FloatArray, what: str) -> None:
    """Raise InputError unless every matrix in covs (n, d, d) is finite, symmetric and PD."""
    if not np.all(np.isfinite(covs)):
        raise InputError(f"{what}: must be finite")
    if covs.shape[0] == 0:
        return
    scale = np.maximum(np.abs(covs).max(axis=(1, 2)), 1e-300)
    asym = np.abs(covs - np.swapaxes(covs, 1, 2)).max(axis=(1, 2))
    if np.any(asym > SYMMETRY_RTOL * scale):
        raise InputError(f"{what}: must be symmetric")
    # The position block as every 2x2 covariance, and a larger state positive definite as well.
    if np.any(spd_2x2_faults(covs[:, :2, :2])[1]) or (
            covs.shape[1] > 2 and np.any(np.linalg.eigvalsh(covs)[:, 0] <= 0.0)):
        raise InputError(f"{what}: must be positive definite")


def lift_positions(
    means_xy: FloatArray, covs_xy: FloatArray, state_dim: int, velocity_var_m2_s2: float
) -> tuple[FloatArray, FloatArray]:
    """Means (n, d) and covariances (n, d, d) for components known by position only: a 4-D
    (constant-velocity) state gets zero mean velocity with variance velocity_var_m2_s2."""
    n = means_xy.shape[0]
    means = np.zeros((n, state_dim))
    means[:, :2] = means_xy
    covs = np.zeros((n, state_dim, state_dim))
    covs[:, :2, :2] = covs_xy
    if state_dim == 4:
        covs[:, 2, 2] = covs[:, 3, 3] = velocity_var_m2_s2
    return means, covs
