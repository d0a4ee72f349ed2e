"""Evaluation metrics over 2-D positions in metres: OSPA, GOSPA, Mahalanobis distance to tracks.

Pure functions over numpy arrays; nothing here reads a clock, logs or keeps state.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.optimize import linear_sum_assignment

from companion.errors import InputError
from companion.sat.linalg import spd_2x2_faults

__all__ = [
    "GospaAssignment",
    "gospa_assignment",
    "gospa_components",
    "mahalanobis_to_tracks",
    "ospa",
    "ospa_components",
    "summarize_mahalanobis",
]

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.intp]


def _positions_xy(points_xy: object, name: str) -> FloatArray:
    """Return `points_xy` as a finite float64 (k, 2) array (a copy-free view when possible)."""
    try:
        arr = np.asarray(points_xy, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name}: not convertible to a float array ({exc})") from exc
    if arr.size == 0:
        return np.empty((0, 2), dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise InputError(f"{name}: expected shape (k, 2), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{name}: contains NaN or infinite coordinates")
    return arr


def _check_order_cutoff(p: float, c: float, metric: str = "OSPA") -> tuple[float, float]:
    """Validate the order p (finite, >= 1) and cut-off c (finite, > 0) of `metric`."""
    try:
        p_f, c_f = float(p), float(c)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{metric} order p and cut-off c must be numbers ({exc})") from exc
    if not (math.isfinite(p_f) and p_f >= 1.0):
        raise InputError(f"{metric} order p must be finite and >= 1, got {p!r}")
    if not (math.isfinite(c_f) and c_f > 0.0):
        raise InputError(f"{metric} cut-off c must be finite and > 0, got {c!r}")
    return p_f, c_f


def _distances_m(est: FloatArray, tru: FloatArray) -> FloatArray:
    """Euclidean distance (m) from every estimate (rows) to every true target (columns)."""
    diff = est[:, None, :] - tru[None, :, :]
    return np.hypot(diff[..., 0], diff[..., 1])


def ospa_components(
    estimates_xy: FloatArray, truth_xy: FloatArray, p: float, c: float
) -> tuple[float, float, float]:
    """OSPA of order p, cut-off c (m) as (total, localisation, cardinality), all in metres.

    Schuhmacher, Vo & Vo 2008 (the OSPA definition and its two components). With n >= m the
    larger and smaller set sizes, total^p = localisation^p + cardinality^p: the components add
    in the p-th power, not linearly. Both empty gives (0, 0, 0); one empty gives (c, 0, c).
    Raises InputError for p < 1, c <= 0, non-finite values or arrays not of shape (k, 2).
    """
    p_f, c_f = _check_order_cutoff(p, c)
    est = _positions_xy(estimates_xy, "estimates_xy")
    tru = _positions_xy(truth_xy, "truth_xy")
    n_big = max(len(est), len(tru))
    n_small = min(len(est), len(tru))
    if n_big == 0:
        return 0.0, 0.0, 0.0
    if n_small == 0:
        return c_f, 0.0, c_f

    dist_m = _distances_m(est, tru)
    # d^(c)(x, y)^p = min(d, c)^p (cut-off distance), divided by c^p so every cost lies in
    # [0, 1]: the optimal assignment is unchanged by the positive factor and c^p cannot overflow.
    cost = (np.minimum(dist_m, c_f) / c_f) ** p_f
    rows, cols = linear_sum_assignment(cost)  # min over pi of sum d^(c)(x_i, y_pi(i))^p
    loc_sum = float(cost[rows, cols].sum())
    card_sum = float(n_big - n_small)  # c^p (n - m), in units of c^p
    # OSPA = ((min_pi sum d^(c)(x_i, y_pi(i))^p + c^p (n - m)) / n)^(1/p)
    total_m = c_f * ((loc_sum + card_sum) / n_big) ** (1.0 / p_f)
    loc_m = c_f * (loc_sum / n_big) ** (1.0 / p_f)  # localisation: (min_pi sum d^(c)^p / n)^(1/p)
    card_m = c_f * (card_sum / n_big) ** (1.0 / p_f)  # cardinality: (c^p (n - m) / n)^(1/p)
    return total_m, loc_m, card_m


def ospa(estimates_xy: FloatArray, truth_xy: FloatArray, p: float, c: float) -> float:
    """OSPA distance (m) of order p with cut-off c (m) between two point sets (Schuhmacher 2008).

    Both empty gives 0; exactly one empty gives c. Raises InputError on bad p, c or points.
    """
    return ospa_components(estimates_xy, truth_xy, p, c)[0]


@dataclass(frozen=True, slots=True, eq=False)
class GospaAssignment:
    """GOSPA (alpha = 2) of two point sets: the total, its parts, and the pairs it assigns.

    total_m^p = localisation_m^p + c^p / 2 (missed + false). `estimate_idx[k]` and
    `truth_idx[k]` are the k-th assigned pair (distance < c), in ascending truth index.
    """

    total_m: float
    localisation_m: float
    missed: int
    false: int
    estimate_idx: IntArray
    truth_idx: IntArray


def gospa_assignment(
    estimates_xy: FloatArray, truth_xy: FloatArray, c: float, p: float = 2.0
) -> GospaAssignment:
    """GOSPA (alpha = 2, order p, cut-off c in m) with its parts and the pairs within c.

    Rahmathullah, García-Fernández & Svensson 2017. An optimal assignment on min(d, c)^p that
    pairs an estimate and a true target at distance d >= c leaves both unassigned instead: one
    missed and one false target, at the same cost. The localisation part is reported as a
    distance, (sum over assigned pairs of d^p)^(1/p) in metres; missed and false are counts.
    Both empty gives zeros. Raises InputError for p < 1, c <= 0, non-finite values or arrays
    not of shape (k, 2).
    """
    p_f, c_f = _check_order_cutoff(p, c, "GOSPA")
    est = _positions_xy(estimates_xy, "estimates_xy")
    tru = _positions_xy(truth_xy, "truth_xy")
    est_idx = tru_idx = np.empty(0, dtype=np.intp)
    loc_sum = 0.0  # sum over assigned pairs of (d / c)^p: in units of c^p, so no overflow
    if len(est) and len(tru):
        dist_m = _distances_m(est, tru)
        # min(d, c)^p / c^p: the positive factor leaves the optimal assignment unchanged.
        cost = (np.minimum(dist_m, c_f) / c_f) ** p_f
        # On the transpose: pairs come in ascending truth index.
        tru_all, est_all = linear_sum_assignment(cost.T)
        within = dist_m[est_all, tru_all] < c_f
        est_idx, tru_idx = est_all[within].astype(np.intp), tru_all[within].astype(np.intp)
        loc_sum = float(cost[est_idx, tru_idx].sum())
    missed = len(tru) - len(tru_idx)
    false = len(est) - len(est_idx)
    # GOSPA^p = min over assignments gamma of sum_{(i,j) in gamma} d(x_i, y_j)^p
    #           + c^p / 2 (|X| + |Y| - 2 |gamma|),  with |X| + |Y| - 2 |gamma| = missed + false
    total_m = c_f * (loc_sum + 0.5 * (missed + false)) ** (1.0 / p_f)
    loc_m = c_f * loc_sum ** (1.0 / p_f)  # (sum_{(i,j) in gamma} d(x_i, y_j)^p)^(1/p)
    return GospaAssignment(total_m, loc_m, missed, false, est_idx, tru_idx)


def gospa_components(
    estimates_xy: FloatArray, truth_xy: FloatArray, c: float, p: float = 2.0
) -> tuple[float, float, int, int]:
    """GOSPA (alpha = 2) as (total_m, localisation_m, missed, false); see `gospa_assignment`."""
    g = gospa_assignment(estimates_xy, truth_xy, c, p)
    return g.total_m, g.localisation_m, g.missed, g.false


def mahalanobis_to_tracks(
    truth_xy: FloatArray, track_means_xy: FloatArray, track_covs_xy: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Per true target, the Mahalanobis distance (not squared) to its closest and second track.

    The distance to track j is sqrt(d^T P_j^{-1} d), d = target - mean_j, with the TRACK's
    covariance P_j (m^2). Returns (closest, second), each of shape (m,); +inf where fewer than
    one / two tracks exist. Raises InputError for bad shapes, non-finite values, or a covariance
    that is not symmetric positive definite.
    """
    tru = _positions_xy(truth_xy, "truth_xy")
    means = _positions_xy(track_means_xy, "track_means_xy")
    try:
        covs = np.asarray(track_covs_xy, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"track_covs_xy: not convertible to a float array ({exc})") from exc
    n_tracks = len(means)
    if n_tracks == 0 and covs.size == 0:
        covs = np.empty((0, 2, 2), dtype=np.float64)
    if covs.shape != (n_tracks, 2, 2):
        raise InputError(
            f"track_covs_xy: expected shape ({n_tracks}, 2, 2) to match track_means_xy, "
            f"got {covs.shape}"
        )
    if not np.all(np.isfinite(covs)):
        raise InputError("track_covs_xy: contains NaN or infinite entries")

    bad_sym, bad_pd = spd_2x2_faults(covs)
    if np.any(bad_sym):
        raise InputError(
            f"track_covs_xy: covariance(s) not symmetric at track index "
            f"{np.flatnonzero(bad_sym).tolist()}"
        )
    if np.any(bad_pd):
        raise InputError(
            f"track_covs_xy: covariance(s) not positive definite at track index "
            f"{np.flatnonzero(bad_pd).tolist()}"
        )
    # Closed-form Cholesky P = L L^T, L = [[l11, 0], [l21, l22]], with the Schur complement
    # d - b^2 / a > 0 of a positive definite P.
    a, d = covs[:, 0, 0], covs[:, 1, 1]
    b = 0.5 * (covs[:, 0, 1] + covs[:, 1, 0])
    l11 = np.sqrt(a)
    l21 = b / l11
    l22 = np.sqrt(d - b * b / a)

    m = len(tru)
    closest = np.full(m, np.inf)
    second = np.full(m, np.inf)
    if n_tracks == 0 or m == 0:
        return closest, second

    diff = tru[:, None, :] - means[None, :, :]  # (m, T, 2)
    # d^T P^{-1} d = |L^{-1} d|^2: forward substitution z = L^{-1} d, then |z| by hypot so a
    # far target with a tight covariance saturates to +inf rather than warning on overflow.
    with np.errstate(over="ignore"):
        z0 = diff[..., 0] / l11
        z1 = (diff[..., 1] - l21 * z0) / l22
        mahal = np.hypot(z0, z1)  # (m, T)
    if n_tracks == 1:
        closest[:] = mahal[:, 0]
        return closest, second
    two_smallest = np.partition(mahal, 1, axis=1)[:, :2]  # column 0 <= column 1
    return two_smallest[:, 0].copy(), two_smallest[:, 1].copy()


def summarize_mahalanobis(closest: FloatArray, second: FloatArray) -> dict[str, float]:
    """Mean and population std (ddof=0) over targets of the closest / second-closest distances.

    Returns {"mahal_closest_mean", "mahal_closest_std", "mahal_second_mean"}. A +inf entry (a
    target with no track) makes the values it enters +inf; zero targets give NaN. Callers
    serialise inf and NaN as JSON null. Raises InputError for NaN or negative entries, or
    arrays that are not 1-D of equal length.
    """
    arrays: list[FloatArray] = []
    for name, values in (("closest", closest), ("second", second)):
        try:
            arr = np.asarray(values, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise InputError(f"{name}: not convertible to a float array ({exc})") from exc
        if arr.ndim != 1:
            raise InputError(f"{name}: expected a 1-D array, got shape {arr.shape}")
        if np.any(np.isnan(arr)) or np.any(arr < 0.0):
            raise InputError(f"{name}: distances must be >= 0 (or +inf), found NaN or negative")
        arrays.append(arr)
    close_arr, second_arr = arrays
    if close_arr.shape != second_arr.shape:
        raise InputError(
            f"closest and second differ in length: {close_arr.shape} vs {second_arr.shape}"
        )
    if close_arr.size == 0:
        return {
            "mahal_closest_mean": math.nan,
            "mahal_closest_std": math.nan,
            "mahal_second_mean": math.nan,
        }
    # Explicit inf handling: np.std over an inf entry would compute inf - inf = NaN.
    close_inf = bool(np.any(np.isinf(close_arr)))
    return {
        "mahal_closest_mean": math.inf if close_inf else float(np.mean(close_arr)),
        "mahal_closest_std": math.inf if close_inf else float(np.std(close_arr)),
        "mahal_second_mean": (
            math.inf if np.any(np.isinf(second_arr)) else float(np.mean(second_arr))
        ),
    }
