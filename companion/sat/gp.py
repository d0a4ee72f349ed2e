"""GP regression over time that predicts a confirmed track's next position (paper Eqs. gp_kernel,
gp_prediction), with a batched, cached predictor for the filter and an offline hyperparameter fit.

Model, per axis d (axes are independent GPs sharing one set of hyperparameters):

    y_i = mu + f(t_i) + e_i,   f ~ GP(0, K),   e_i ~ N(0, sigma_n^2),
    K(k, k') = sigma_f^2 exp(-0.5 ((k - k') / lambda)^2)                      # Eq. gp_kernel

where mu is the prior mean, so that UTM-sized coordinates (500000 m, 4e6 m) are not shrunk
towards 0: a constant, the mean of the window's points; or, when the targets move
(slope_sd_m_s > 0), a trend through the window's newest time t_n, held past it:

    mu(t) = a + b min(t - t_n, 0)                                              # Eq. gp_trend

averaged over two models of the target: moving, with a flat prior on a and N(0, slope_sd^2) on
each axis of the velocity b, both by generalised least squares (Rasmussen & Williams 2006, Sec.
2.7: [a, b] = (H^T Ky^{-1} H + diag(0, slope_sd^-2))^{-1} H^T Ky^{-1} M, H = [1, t_i - t_n]);
and standing, b = 0 and a the window's mean; each weighted by its posterior probability at even
prior odds (the data's evidence on b alone). The SE kernel alone reverts to the window's mean,
so a track on a walker lags behind it (0.5 m/s, 30 detections with 1 m noise: 1.6 m one second
past the newest; the trend: 0.9 m); a standing target's window shows no slope and keeps the
constant mean. The trend is not extrapolated: a straight line run on past the last detection
carried coasting tracks away from their walkers (docs/estimator.md); the motion class's term
(companion.sat.motion) grows the covariance instead. With Ky = K(K, K) + sigma_n^2 I and the
weight vector alpha = Ky^{-1} K(K, k) (which depends only on the times, not on the positions):

    mean      m_k   = mu(k) + alpha^T (M - mu)                                 # Eq. gp_prediction
    velocity  v     = b + (Ky^{-1} dK(K, k)/dk)^T (M - mu)    (dm/dk up to t_n; b held past it)
    variance  v_k   = sigma_f^2 - K(k, K) alpha

v_k is the variance of the latent position f(k) (no sigma_n^2 added, no term for the uncertainty of
mu): it is the position uncertainty the filter's covariance grows by, and measurement noise enters
later through the update's R (the motion class's term, companion.sat.motion, covers an unseen
target's manoeuvres). Times are handled relative to the prediction time and rounded to
1 ns, so that equal relative timings give bit-identical weights (and can share a cache entry).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import numpy.typing as npt
from scipy.optimize import minimize

from companion.errors import InputError
from companion.kernel_cache import kernel

__all__ = ["GpFit", "GpParams", "GpPredictor", "gp_predict", "learn_gp_params", "predict_fit"]

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

# Relative times are keyed in integer nanoseconds; int64 holds +-292 years, and refusing more than
# ~31 years keeps every conversion exact and far from overflow.
_NS_PER_S = 1e9
_MAX_ABS_REL_S = 1e9
# Floor on the predictive variance, as a fraction of sigma_f^2: sigma_f^2 - k^T alpha can round to
# <= 0 when the prediction time coincides with many low-noise points.
_VAR_FLOOR_REL = float(np.finfo(np.float64).eps)
_LOG_2PI = math.log(2.0 * math.pi)
# Hyperparameter search box for learn_gp_params, relative to the data's scale (std of the centred
# positions) and timing: wide enough for any physically sensible answer, narrow enough that
# sigma_f / sigma_n <= 1e5 keeps Ky's condition number below ~1e10 * window.
_SF_BOUNDS_REL = (1e-3, 1e2)
_SN_BOUNDS_REL = (1e-3, 1e2)
# The lengthscale's lower bound is two sampling intervals: a shorter one turns the signal into
# white noise, indistinguishable from sigma_n, and white-noise data then has a degenerate optimum
# (sigma_f^2 + sigma_n^2 = noise, lambda -> 0) that would make every prediction jump by sigma_f.
_LAMBDA_BOUNDS_REL = (2.0, 1e2)  # x median time step (low), x longest chunk span (high)


def _check_positive(name: str, value: float, zero: bool = False) -> None:
    """InputError naming the parameter unless value is a finite number > 0 (>= 0 with zero)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise InputError(f"GP {name} must be a number, got {value!r}")
    if not math.isfinite(value) or value < 0.0 or (value == 0.0 and not zero):
        raise InputError(f"GP {name} must be finite and {'>=' if zero else '>'} 0, got {value!r}")


STANDING_P_MOVING = 0.1
"""A window at most this likely to move (odds of 9:1 on standing) is taken to stand (Eqs.
edge_shift, held_gate)."""


@dataclass(frozen=True, slots=True)
class GpParams:
    """Hyperparameters of the per-axis SE-kernel GP over time, and the history window it reads.

    Defaults suit slowly moving ground targets (the paper's: 0.05 m/s straight legs, a new heading
    every 400 s) observed at 1 Hz through a filter whose track positions carry ~0.1-1 m noise:

    - window = 30 points (30 s): enough points to average 0.3 m noise down to a velocity error of
      ~0.01 m/s (least-squares slope, sigma * sqrt(12 / W^3)), short enough to follow a turn
      within ~15 s, and one 30 x 30 solve costs ~10 us;
    - lengthscale_s = 40 s, longer than the window span, so within a window the GP behaves like a
      smooth trend and extrapolates a straight leg instead of reverting to the window mean;
    - sigma_f_m = 2 m: the prior slope std sigma_f / lambda = 0.05 m/s covers the targets' speed
      (a smaller ratio shrinks the extrapolated velocity, a larger one follows the noise);
    - sigma_n_m = 0.3 m, mid-range of the track-position noise.

    On simulated paper-style targets (0.05 m/s, turns every 400 s, white noise 0.1 / 0.3 / 1 m)
    these give a one-step RMSE of 0.058 / 0.131 / 0.338 m per axis (sigma_n set to the noise),
    with a predictive std that matches it within ~10 %, and sit within 12 % of the best of a
    (sigma_f, lambda, window) grid. Their weakness is mean reversion: a straight leg at speed v is
    predicted ~0.75 v x 1 s behind one step ahead, and the velocity ~20 % low; for faster targets
    learn the parameters. learn_gp_params replaces these by values fitted to recorded tracks.

    slope_sd_m_s > 0 replaces the constant prior mean by a trend whose velocity has that prior
    std per axis (see the module's docstring); the filter sets it from the targets' motion
    class, and 0 (the default here) keeps the constant mean.
    """

    sigma_f_m: float = 2.0
    lengthscale_s: float = 40.0
    sigma_n_m: float = 0.3
    window: int = 30
    slope_sd_m_s: float = 0.0

    def __post_init__(self) -> None:
        _check_positive("sigma_f_m", self.sigma_f_m)
        _check_positive("lengthscale_s", self.lengthscale_s)
        _check_positive("sigma_n_m", self.sigma_n_m)
        if isinstance(self.window, bool) or not isinstance(self.window, (int, np.integer)):
            raise InputError(f"GP window must be an integer, got {self.window!r}")
        if self.window < 2:
            raise InputError(f"GP window must be >= 2, got {self.window!r}")
        _check_positive("slope_sd_m_s", self.slope_sd_m_s, zero=True)


# ---------------------------------------------------------------------------------------------
# Shared prediction core
# ---------------------------------------------------------------------------------------------


def _quantise_rel(rel_s: FloatArray) -> tuple[FloatArray, IntArray]:
    """Relative times rounded to whole nanoseconds: (seconds, integer nanoseconds)."""
    rel_ns = np.rint(rel_s * _NS_PER_S)
    return rel_ns / _NS_PER_S, rel_ns.astype(np.int64)


def _weights(params: GpParams, rel_s: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Mean weights alpha (U, n), velocity weights (U, n) and latent variance (U,) for U rows of
    n times relative to the prediction time (t_i - t_star, seconds)."""
    sf2 = params.sigma_f_m**2
    lam = params.lengthscale_s
    n = rel_s.shape[1]
    diff = (rel_s[:, :, None] - rel_s[:, None, :]) / lam
    ky = sf2 * np.exp(-0.5 * diff * diff)  # Eq. gp_kernel: K(K, K)
    idx = np.arange(n)
    ky[:, idx, idx] += params.sigma_n_m**2  # Ky = K(K, K) + sigma_n^2 I
    scaled = rel_s / lam
    k_star = sf2 * np.exp(-0.5 * scaled * scaled)  # Eq. gp_kernel: K(k, K)
    dk_star = k_star * (rel_s / lam**2)  # d/dk K(k, K) = K(k, K) (t_i - k) / lambda^2
    rhs = np.stack((k_star, dk_star), axis=-1)
    try:
        sol = np.asarray(np.linalg.solve(ky, rhs), dtype=np.float64)  # Ky^{-1} [k_*, dk_*/dk]
    except np.linalg.LinAlgError as exc:
        raise InputError(
            "GP covariance K + sigma_n^2 I is numerically singular: sigma_n is too small "
            "relative to sigma_f for these times"
        ) from exc
    alpha = sol[..., 0]
    alpha_vel = sol[..., 1]
    var = sf2 - np.einsum("un,un->u", k_star, alpha)  # sigma_f^2 - K(k,K) Ky^{-1} K(K,k)
    return alpha, alpha_vel, np.maximum(var, _VAR_FLOOR_REL * sf2)


def _trend(params: GpParams, rel_s: FloatArray, y: FloatArray) -> tuple[FloatArray, FloatArray]:
    """The prior mean's intercept a (d,) at rel_s = 0 and slope b (d,) for one window of n times
    rel_s (n,) [s] and positions y (n, d) [m]: the window's mean and 0 when slope_sd_m_s = 0,
    else the generalised least-squares trend (see the module's docstring)."""
    if params.slope_sd_m_s == 0.0:
        return y.mean(axis=0), np.zeros(y.shape[1])
    diff = (rel_s[:, None] - rel_s[None, :]) / params.lengthscale_s
    ky = params.sigma_f_m**2 * np.exp(-0.5 * diff * diff)  # Eq. gp_kernel
    ky[np.diag_indices(rel_s.size)] += params.sigma_n_m**2
    out = np.empty(2 * y.shape[1] + 1)
    ky_inv = np.asarray(np.linalg.inv(ky), dtype=np.float64)
    beta = np.zeros(y.shape)
    _trend_kernel(ky_inv, rel_s, np.ascontiguousarray(y), params.slope_sd_m_s**2, out, beta)
    return out[: y.shape[1]], out[y.shape[1] : 2 * y.shape[1]]


def _check_t_star(t_star_s: float) -> float:
    t_star = float(t_star_s)
    if not math.isfinite(t_star):
        raise InputError(f"GP prediction time must be finite, got {t_star_s!r}")
    return t_star


def _check_rel(rel_s: FloatArray) -> None:
    if np.any(np.abs(rel_s) > _MAX_ABS_REL_S):
        raise InputError(
            f"GP history times must lie within {_MAX_ABS_REL_S:.0e} s of the prediction time"
        )


def gp_predict(
    params: GpParams, t_s: npt.ArrayLike, y: npt.ArrayLike, t_star_s: float
) -> tuple[FloatArray, float, FloatArray]:
    """Predict the position (d,) [m], its latent variance [m^2] and velocity (d,) [m/s] at t_star_s
    from a track history t_s (n,) [s], y (n, d) [m], using only its last params.window points.

    Only those points are read (and checked: finite, times non-decreasing). With one point the
    mean is that point, the velocity 0 and the variance sigma_f^2 - k^2 / (sigma_f^2 + sigma_n^2)
    with k = K(t_star, t_1): the same formula as for any n.
    """
    t_arr = np.asarray(t_s, dtype=np.float64)
    y_arr = np.asarray(y, dtype=np.float64)
    if t_arr.ndim != 1 or t_arr.shape[0] < 1:
        raise InputError(f"GP history times must have shape (n,) with n >= 1, got {t_arr.shape}")
    if y_arr.ndim != 2 or y_arr.shape[0] != t_arr.shape[0] or y_arr.shape[1] < 1:
        raise InputError(
            f"GP history positions must have shape ({t_arr.shape[0]}, d), got {y_arr.shape}"
        )
    t_star = _check_t_star(t_star_s)
    n = min(t_arr.shape[0], params.window)
    t_w = t_arr[-n:]
    y_w = y_arr[-n:]
    if not (np.all(np.isfinite(t_w)) and np.all(np.isfinite(y_w))):
        raise InputError("GP history contains a non-finite time or position")
    if n > 1 and np.any(np.diff(t_w) < 0.0):
        raise InputError("GP history times must be non-decreasing")
    rel = t_w - t_star
    _check_rel(rel)
    rel_q, _ = _quantise_rel(rel)
    alpha, alpha_vel, var = _weights(params, rel_q[None, :])
    from_newest = rel_q - rel_q[-1]
    intercept, slope = _trend(params, from_newest, y_w)
    resid = y_w - intercept - from_newest[:, None] * slope  # M - mu
    held = min(-rel_q[-1], 0.0)  # Eq. gp_trend: t_star - t_n, held at 0 past the newest point
    mean = intercept + held * slope + alpha[0] @ resid  # Eq. gp_prediction
    return mean, float(var[0]), slope + alpha_vel[0] @ resid


# ---------------------------------------------------------------------------------------------
# Batched, cached predictor
# ---------------------------------------------------------------------------------------------



class GpFit(NamedTuple):
    """What prediction needs of T right-aligned windows, computed once per window.

    mu (T, 2d + 1) is the prior mean's intercept a (the first d columns) and slope b (the next
    d, zero for a constant mean) at the window's newest time t_n, then the probability that the
    window's target moves (the trend's moving model; 0 for a constant mean), beta (T, W, d) =
    Ky^-1 (y - mu(K)) and ky_inv (T, W, W) = Ky^-1 with Ky = K(K, K) + sigma_n^2 I, all zero
    outside a row's last counts[i] columns; then at any time t*, with k = K(t*, K): mean = a +
    b min(t* - t_n, 0) + k^T beta (Eqs. gp_trend, gp_prediction), velocity = b + (dk/dt*)^T
    beta and variance = sigma_f^2 - k^T Ky^-1 k, a few products per row.
    """

    t_s: FloatArray  # (T, W)
    counts: IntArray  # (T,)
    mu: FloatArray  # (T, d)
    beta: FloatArray  # (T, W, d)
    ky_inv: FloatArray  # (T, W, W)

    @staticmethod
    def empty(width: int, dim: int = 2) -> GpFit:
        """No windows."""
        return GpFit(
            np.zeros((0, width)),
            np.zeros(0, dtype=np.int64),
            np.zeros((0, 2 * dim + 1)),
            np.zeros((0, width, dim)),
            np.zeros((0, width, width)),
        )


def predict_fit(
    params: GpParams, fit: GpFit, t_star_s: float | FloatArray, rows: IntArray | None = None
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Mean [m], latent variance [m^2] and velocity [m/s] of the windows `rows` (all by default)
    at t_star_s: shapes (T, d), (T,), (T, d), each with a leading axis of length k when t_star_s
    is an array of k times."""
    times = np.atleast_1d(np.asarray(t_star_s, dtype=np.float64))
    picked = np.arange(fit.counts.shape[0]) if rows is None else rows
    dim = fit.beta.shape[2]
    mean = np.empty((times.size, picked.size, dim))
    var = np.empty((times.size, picked.size))
    velocity = np.empty((times.size, picked.size, dim))
    gp_predict_rows(
        fit.t_s, fit.counts, fit.mu, fit.beta, fit.ky_inv, picked, times,
        params.sigma_f_m**2, params.lengthscale_s, mean, var, velocity,
    )
    if np.ndim(t_star_s) == 0:
        return mean[0], var[0], velocity[0]
    return mean, var, velocity


@kernel
def gp_predict_rows(  # pragma: no cover - compiled; tested through predict_fit
    t_s: FloatArray,
    count: IntArray,
    mu: FloatArray,
    beta: FloatArray,
    ky_inv: FloatArray,
    rows: IntArray,
    times: FloatArray,
    sf2: float,
    lam: float,
    mean: FloatArray,
    var: FloatArray,
    velocity: FloatArray,
) -> None:
    """mean = mu(t*) + k^T beta (Eq. gp_prediction), velocity = b + (dk/dt*)^T beta,
    var = sigma_f^2 - k^T Ky^-1 k, with k = K(t*, K) (Eq. gp_kernel), per row and time (see
    GpFit)."""
    width, dim = beta.shape[1], beta.shape[2]
    k = np.empty((times.shape[0], width))
    floor = _VAR_FLOOR_REL * sf2
    for out in range(rows.shape[0]):
        r = rows[out]
        first = width - count[r]
        for a in range(times.shape[0]):
            for w in range(width):
                if w < first:
                    k[a, w] = 0.0
                else:
                    scaled = (t_s[r, w] - times[a]) / lam
                    k[a, w] = sf2 * math.exp(-0.5 * scaled * scaled)
            for c in range(dim):
                m = mu[r, c]
                v = 0.0
                for w in range(first, width):
                    m += k[a, w] * beta[r, w, c]
                    v += k[a, w] * (t_s[r, w] - times[a]) / (lam * lam) * beta[r, w, c]
                slope = mu[r, dim + c]  # Eq. gp_trend: held past the newest point
                mean[a, out, c] = m + slope * min(times[a] - t_s[r, width - 1], 0.0)
                velocity[a, out, c] = v + slope
        for a in range(0, times.shape[0], 2):  # two times at a time, reading Ky^-1 once
            b = min(a + 1, times.shape[0] - 1)
            quad_a, quad_b = _quad_forms(ky_inv[r], k[a], k[b], first)
            var[a, out] = max(sf2 - quad_a, floor)
            var[b, out] = max(sf2 - quad_b, floor)


@kernel
def _quad_forms(  # pragma: no cover - compiled; tested through predict_fit
    ky_inv: FloatArray, k_a: FloatArray, k_b: FloatArray, first: int
) -> tuple[float, float]:
    """(k_a^T Ky^-1 k_a, k_b^T Ky^-1 k_b) over the columns from `first` on: sum_w k[w] (row w
    of Ky^-1 . k), each row product summed in column order; four rows at a time, as
    independent sums that the CPU overlaps."""
    width = k_a.shape[0]
    quad_a = quad_b = 0.0
    w = first
    while w + 3 < width:
        a0 = a1 = a2 = a3 = b0 = b1 = b2 = b3 = 0.0
        for u in range(first, width):
            ka, kb = k_a[u], k_b[u]
            c0, c1, c2, c3 = ky_inv[w, u], ky_inv[w + 1, u], ky_inv[w + 2, u], ky_inv[w + 3, u]
            a0 += c0 * ka
            a1 += c1 * ka
            a2 += c2 * ka
            a3 += c3 * ka
            b0 += c0 * kb
            b1 += c1 * kb
            b2 += c2 * kb
            b3 += c3 * kb
        quad_a += k_a[w] * a0
        quad_a += k_a[w + 1] * a1
        quad_a += k_a[w + 2] * a2
        quad_a += k_a[w + 3] * a3
        quad_b += k_b[w] * b0
        quad_b += k_b[w + 1] * b1
        quad_b += k_b[w + 2] * b2
        quad_b += k_b[w + 3] * b3
        w += 4
    while w < width:
        row_a = row_b = 0.0
        for u in range(first, width):
            row_a += ky_inv[w, u] * k_a[u]
            row_b += ky_inv[w, u] * k_b[u]
        quad_a += k_a[w] * row_a
        quad_b += k_b[w] * row_b
        w += 1
    return quad_a, quad_b


@kernel
def _fit_kernel(  # pragma: no cover - compiled; tested through GpPredictor.fit
    t_s: FloatArray,
    y: FloatArray,
    counts: IntArray,
    rows: IntArray,
    window: int,
    sf2: float,
    lam: float,
    sn2: float,
    sb2: float,
    keys: IntArray,
    lengths: IntArray,
    invs: FloatArray,
    stamps: IntArray,
    memo: IntArray,
    mu: FloatArray,
    beta: FloatArray,
    ky_inv: FloatArray,
) -> bool:
    """Fit the windows `rows` of t_s (T, W) [s], y (T, W, d) [m] with counts[i] valid points
    into those rows of mu (T, 2d + 1), beta (T, W, d) and ky_inv (T, W, W), in place (see GpFit),
    with the trend's slope prior variance sb2 (0: a constant mean);
    False if a Ky is not positive definite to working precision.

    A row's last c = min(counts[i], window) times are taken as offsets from its newest point,
    rounded to whole nanoseconds; Ky^-1 of those offsets comes from the memo (slot s: offsets
    keys[s, :lengths[s]], Ky^-1 invs[s], last use stamps[s]; memo = (slots used, clock)) or from
    _ky_inv_kernel, and then enters the memo in a free slot or the least recently used one
    (none if the memo has no slots)."""
    width = t_s.shape[1]
    rel_q = np.empty(width)
    rel_ns = np.empty(width, dtype=np.int64)
    for k in range(rows.shape[0]):
        i = rows[k]
        c = min(counts[i], window)
        first = width - c
        for w in range(c):
            ns = np.rint((t_s[i, first + w] - t_s[i, width - 1]) * _NS_PER_S)
            rel_q[w] = ns / _NS_PER_S
            rel_ns[w] = np.int64(ns)
        ky_inv[i] = 0.0
        block = ky_inv[i, first:, first:]
        slot = -1
        for s in range(memo[0]):
            if lengths[s] != c:
                continue
            w = 0
            while w < c and keys[s, w] == rel_ns[w]:
                w += 1
            if w == c:
                slot = s
                break
        if slot >= 0:
            block[:, :] = invs[slot, :c, :c]
        else:
            if not _ky_inv_kernel(rel_q[:c], sf2, lam, sn2, block):
                return False
            if lengths.shape[0]:
                if memo[0] < lengths.shape[0]:
                    slot = memo[0]
                    memo[0] += 1
                else:
                    slot = int(np.argmin(stamps))
                keys[slot, :c] = rel_ns[:c]
                lengths[slot] = c
                invs[slot, :c, :c] = block
        if slot >= 0:
            memo[1] += 1
            stamps[slot] = memo[1]
        dim = y.shape[2]
        beta[i, :first] = 0.0
        if sb2 > 0.0:
            _trend_kernel(block, rel_q[:c], y[i, first:], sb2, mu[i], beta[i, first:])
            continue
        for d in range(dim):
            total = 0.0
            for w in range(first, width):
                total += y[i, w, d]
            mu[i, d] = total / c  # constant prior mean: the window's mean
            mu[i, dim + d] = 0.0
        mu[i, 2 * dim] = 0.0  # no trend: the window is taken to stand
        for w in range(first, width):
            for d in range(dim):
                acc = 0.0
                for v in range(first, width):
                    acc += ky_inv[i, w, v] * (y[i, v, d] - mu[i, d])
                beta[i, w, d] = acc  # Ky^-1 (y - mu)
    return True


@kernel
def _trend_kernel(  # pragma: no cover - compiled; tested through GpPredictor.fit
    ky_inv: FloatArray, rel_q: FloatArray, y: FloatArray, sb2: float, out: FloatArray,
    beta: FloatArray,
) -> None:
    """out <- (intercept (d,), slope (d,), P(moving)) of one window's prior mean (Eq. gp_trend)
    and beta (c, d) <- Ky^-1 (y - mu(K)), for times rel_q (c,) [s], positions y (c, d) [m] and Ky^-1
    (c, c): the mean averaged over a standing model (slope 0, the window's mean) and a moving one
    (slope ~ N(0, sb2) per axis, a flat prior on the intercept, by generalised least squares),
    each weighted by its posterior probability at even prior odds. One pass over Ky^-1 forms
    Ky^-1 [1, t, y - mean]; beta follows from it, linear in the trend."""
    c = rel_q.shape[0]
    dim = y.shape[1]
    mean = np.zeros(dim)  # the window's mean: the standing model's intercept
    for d in range(dim):
        for w in range(c):
            mean[d] += y[w, d]
        mean[d] /= c
    u = np.zeros(c)  # Ky^-1 1
    v = np.zeros(c)  # Ky^-1 t
    for w in range(c):
        acc_u = acc_v = acc_0 = acc_1 = 0.0  # one pass over the row, the first two axes
        for x in range(c):
            k = ky_inv[w, x]
            acc_u += k
            acc_v += k * rel_q[x]
            acc_0 += k * (y[x, 0] - mean[0])
            if dim > 1:
                acc_1 += k * (y[x, 1] - mean[1])
        u[w], v[w] = acc_u, acc_v
        beta[w, 0] = acc_0  # Ky^-1 (y - mean), less the trend's part below
        if dim > 1:
            beta[w, 1] = acc_1
        for d in range(2, dim):
            total = 0.0
            for x in range(c):
                total += ky_inv[w, x] * (y[x, d] - mean[d])
            beta[w, d] = total
    a00 = a01 = a11 = 0.0
    r0 = np.zeros(dim)  # 1^T Ky^-1 (y - mean)
    r1 = np.zeros(dim)  # t^T Ky^-1 (y - mean)
    for w in range(c):
        a00 += u[w]
        a01 += v[w]
        a11 += v[w] * rel_q[w]
        for d in range(dim):
            r0[d] += u[w] * (y[w, d] - mean[d])
            r1[d] += v[w] * (y[w, d] - mean[d])
    info = a11 - a01 * a01 / a00  # the data's information on the slope, the intercept unknown
    shrink = p_moving = 0.0
    slope = np.zeros(dim)
    if info > 0.0:
        s0 = 1.0 / info  # the slope's variance from the data alone
        log_bf = 0.0  # log p(y | moving) - log p(y | standing)
        for d in range(dim):
            slope[d] = (r1[d] - a01 * r0[d] / a00) / info
            log_bf += -0.5 * math.log1p(sb2 / s0) + 0.5 * slope[d] ** 2 * (
                1.0 / s0 - 1.0 / (s0 + sb2))
        p_moving = 1.0 / (1.0 + math.exp(-log_bf)) if log_bf > -700.0 else 0.0
        shrink = sb2 / (sb2 + s0)  # the moving model's posterior mean of the slope: shrunk
    for d in range(dim):
        moving_slope = shrink * slope[d]
        offset = p_moving * (r0[d] - a01 * moving_slope) / a00  # intercept - mean
        out[d] = mean[d] + offset
        out[dim + d] = p_moving * moving_slope
        for w in range(c):
            beta[w, d] -= offset * u[w] + out[dim + d] * v[w]
    out[2 * dim] = p_moving


@kernel
def _refit_kernel(  # pragma: no cover - compiled; tested through GpPredictor.refit
    t_s: FloatArray,
    y: FloatArray,
    counts: IntArray,
    eligible: npt.NDArray[np.bool_],
    t_now: float,
    window: int,
    sf2: float,
    lam: float,
    sn2: float,
    sb2: float,
    keys: IntArray,
    lengths: IntArray,
    invs: FloatArray,
    stamps: IntArray,
    memo: IntArray,
    mu: FloatArray,
    beta: FloatArray,
    ky_inv: FloatArray,
) -> tuple[int, FloatArray, FloatArray, FloatArray]:
    """(1, copies of mu, beta, ky_inv with the changed rows refitted), (0, the arrays given)
    when no row changed, or (-1, ...) when a Ky is not positive definite; a row changed when it
    is eligible and its newest point (it has one) is at t_now. See _fit_kernel."""
    changed = np.zeros(counts.shape[0], dtype=np.bool_)
    for i in range(counts.shape[0]):
        changed[i] = eligible[i] and counts[i] > 0 and t_s[i, t_s.shape[1] - 1] == t_now
    rows = np.flatnonzero(changed)
    if rows.shape[0] == 0:
        return 0, mu, beta, ky_inv
    mu, beta, ky_inv = mu.copy(), beta.copy(), ky_inv.copy()
    ok = _fit_kernel(t_s, y, counts, rows, window, sf2, lam, sn2, sb2, keys, lengths, invs,
                     stamps, memo, mu, beta, ky_inv)
    return 1 if ok else -1, mu, beta, ky_inv


@kernel
def _ky_inv_kernel(  # pragma: no cover - compiled; tested through GpPredictor.fit
    rel_q: FloatArray, sf2: float, lam: float, sn2: float, out: FloatArray
) -> bool:
    """out <- Ky^-1 = (K(K, K) + sigma_n^2 I)^-1 (Eq. gp_kernel) for one window's times, by
    Cholesky, Ky = L L^T, and Ky^-1 = L^-T L^-1, symmetric by construction; False (out
    unfinished) when Ky is not positive definite to working precision."""
    n = rel_q.shape[0]
    low = np.empty((n, n))  # K(K, K) + sigma_n^2 I, lower triangle, then L in place
    for i in range(n):
        for j in range(i + 1):
            diff = (rel_q[i] - rel_q[j]) / lam
            low[i, j] = sf2 * math.exp(-0.5 * diff * diff)  # Eq. gp_kernel
        low[i, i] += sn2
    for j in range(n):
        for i in range(j, n):
            total = low[i, j]
            for k in range(j):
                total -= low[i, k] * low[j, k]
            if i == j:
                if not total > 0.0:
                    return False
                low[j, j] = math.sqrt(total)
            else:
                low[i, j] = total / low[j, j]
    upper = np.zeros((n, n))  # (L^-1)^T, row by row: U[j, i] = (L^-1)[i, j]
    for j in range(n):
        upper[j, j] = 1.0 / low[j, j]
        for i in range(j + 1, n):
            total = 0.0
            for k in range(j, i):
                total -= low[i, k] * upper[j, k]
            upper[j, i] = total / low[i, i]
    for a in range(n):  # Ky^-1 = L^-T L^-1: (a, b) = sum_k U[a, k] U[b, k]
        for b in range(a + 1):
            total = 0.0
            for k in range(a, n):
                total += upper[a, k] * upper[b, k]
            out[a, b] = out[b, a] = total
    return True


_SINGULAR = (
    "GP covariance K + sigma_n^2 I is numerically singular: sigma_n is too small relative to "
    "sigma_f for these times"
)


class GpPredictor:
    """Fits windows for prediction, memoising Ky^-1 by the window's internal timing.

    Windows sampled alike (a track detected every frame, or one whose window stopped changing)
    share Ky^-1: the cache keys it by the time offsets within the window in whole nanoseconds and
    computes it from those rounded offsets, so results are the same with or without the cache.
    Bounded to cache_size entries, least recently used first out; cache_size = 0 disables it.
    """

    def __init__(self, params: GpParams, cache_size: int = 256) -> None:
        if isinstance(cache_size, bool) or not isinstance(cache_size, (int, np.integer)):
            raise InputError(f"GP cache size must be an integer, got {cache_size!r}")
        if cache_size < 0:
            raise InputError(f"GP cache size must be >= 0, got {cache_size!r}")
        self._params = params
        self._cache_size = int(cache_size)
        # The memo as arrays for _fit_kernel, grown as it fills up to cache_size slots.
        self._keys = np.zeros((0, params.window), dtype=np.int64)
        self._lengths = np.zeros(0, dtype=np.int64)
        self._invs = np.zeros((0, params.window, params.window))
        self._stamps = np.zeros(0, dtype=np.int64)
        self._memo = np.zeros(2, dtype=np.int64)

    @property
    def cache_entries(self) -> int:
        """The number of windows' Ky^-1 memoised."""
        return int(self._memo[0])

    def _reserve(self, rows: int) -> None:
        """Slots for `rows` more windows in the memo, up to cache_size (beyond, the least
        recently used make room)."""
        need = min(self._cache_size, int(self._memo[0]) + rows)
        slots = self._lengths.shape[0]
        if need <= slots:
            return
        slots = min(self._cache_size, max(need, 2 * slots, 16))
        for name in ("_keys", "_lengths", "_invs", "_stamps"):
            old = getattr(self, name)
            grown = np.zeros((slots, *old.shape[1:]), dtype=old.dtype)
            grown[: old.shape[0]] = old
            setattr(self, name, grown)

    @property
    def params(self) -> GpParams:
        """The hyperparameters this predictor uses."""
        return self._params

    def fit(
        self, t_s: npt.ArrayLike, y: npt.ArrayLike, counts: npt.ArrayLike, check: bool = True
    ) -> GpFit:
        """Fit T windows t_s (T, W) [s], y (T, W, d) [m] whose last counts[i] columns are valid
        (right-aligned; the rest is ignored); a row uses at most params.window points.

        check=False skips the input checks, for windows the tracker built itself.
        """
        if not check:
            return self._fit(np.asarray(t_s), np.asarray(y), np.asarray(counts))
        t_arr = np.asarray(t_s, dtype=np.float64)
        y_arr = np.asarray(y, dtype=np.float64)
        c_arr = np.asarray(counts)
        if t_arr.ndim != 2:
            raise InputError(f"GP window times must have shape (T, W), got {t_arr.shape}")
        n_rows, width = t_arr.shape
        if y_arr.ndim != 3 or y_arr.shape[:2] != (n_rows, width) or y_arr.shape[2] < 1:
            raise InputError(
                f"GP window positions must have shape ({n_rows}, {width}, d), got {y_arr.shape}"
            )
        if c_arr.shape != (n_rows,) or not np.issubdtype(c_arr.dtype, np.integer):
            raise InputError(f"GP counts must be integers of shape ({n_rows},), got {c_arr.shape}")
        if n_rows == 0:
            return GpFit.empty(width, y_arr.shape[2])
        if np.any(c_arr < 1) or np.any(c_arr > width):
            raise InputError(f"GP counts must lie in 1..{width}")
        count = np.minimum(c_arr, self._params.window).astype(np.int64)
        valid = np.arange(width)[None, :] >= (width - count)[:, None]
        if not (
            np.all(np.isfinite(t_arr) | ~valid) and np.all(np.isfinite(y_arr) | ~valid[:, :, None])
        ):
            raise InputError("GP history contains a non-finite time or position")
        rel = np.where(valid, t_arr - t_arr[:, -1:], 0.0)  # offsets from the newest point
        if width > 1 and np.any((np.diff(rel, axis=1) < 0.0) & valid[:, :-1]):
            raise InputError("GP history times must be non-decreasing")
        _check_rel(rel)
        return self._fit(t_arr, y_arr, c_arr)

    def _fit(self, t_arr: FloatArray, y_arr: FloatArray, c_arr: IntArray) -> GpFit:
        """fit() after its checks."""
        n_rows, width = t_arr.shape
        t_w = np.ascontiguousarray(t_arr, dtype=np.float64)
        mu = np.empty((n_rows, 2 * y_arr.shape[2] + 1))
        beta = np.empty(y_arr.shape)
        ky_inv = np.zeros((n_rows, width, width))
        self._reserve(n_rows)
        params = self._params
        if not _fit_kernel(
            t_w, np.ascontiguousarray(y_arr, dtype=np.float64), c_arr, np.arange(n_rows),
            params.window, params.sigma_f_m**2, params.lengthscale_s, params.sigma_n_m**2,
            params.slope_sd_m_s**2, self._keys, self._lengths, self._invs, self._stamps,
            self._memo, mu, beta, ky_inv,
        ):
            raise InputError(_SINGULAR)
        count = np.minimum(c_arr, params.window).astype(np.int64)
        return GpFit(t_w.copy() if t_w is t_arr else t_w, count, mu, beta, ky_inv)

    def refit(
        self, t_s: FloatArray, y: FloatArray, counts: IntArray, eligible: npt.NDArray[np.bool_],
        t_now_s: float, fit: GpFit,
    ) -> GpFit:
        """The fit of T windows t_s (T, W) [s], y (T, W, d) [m] with counts[i] valid points
        (float64, unchecked: windows the tracker built itself) given their previous `fit`: the
        rows that are `eligible` and whose newest point is at t_now_s refitted in copies of
        fit's arrays, the others shared; `fit` itself when there is no such row."""
        self._reserve(counts.shape[0])
        params = self._params
        status, mu, beta, ky_inv = _refit_kernel(
            t_s, y, counts, eligible, t_now_s, params.window, params.sigma_f_m**2,
            params.lengthscale_s, params.sigma_n_m**2, params.slope_sd_m_s**2, self._keys,
            self._lengths, self._invs, self._stamps, self._memo, fit.mu, fit.beta, fit.ky_inv,
        )
        if status < 0:
            raise InputError(_SINGULAR)
        return fit if status == 0 else GpFit(t_s, counts, mu, beta, ky_inv)

    def predict(
        self, t_s: npt.ArrayLike, y: npt.ArrayLike, counts: npt.ArrayLike, t_star_s: float
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Predict mean (T, d) [m], latent variance (T,) [m^2] and velocity (T, d) [m/s] at
        t_star_s for T tracks whose histories t_s (T, W) [s], y (T, W, d) [m] hold counts[i]
        valid points right-aligned (columns W - counts[i] .. W - 1; the rest is ignored).

        Row i uses its last min(counts[i], params.window) points, exactly as gp_predict would.
        """
        t_star = _check_t_star(t_star_s)
        fit = self.fit(t_s, y, counts)
        if fit.counts.size:
            _check_rel(fit.t_s[:, -1:] - t_star)
        return predict_fit(self._params, fit, t_star)


# ---------------------------------------------------------------------------------------------
# Hyperparameter learning
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class _ChunkGroup:
    """Chunks of one length L: times from the chunk start (C, L) [s] and positions minus the
    chunk mean (C, L, d) [m]."""

    rel_s: FloatArray
    y: FloatArray


def _chunk_trajectories(
    trajectories: Sequence[tuple[npt.ArrayLike, npt.ArrayLike]], window: int
) -> tuple[list[_ChunkGroup], int]:
    """Split every trajectory into consecutive chunks of `window` points (the last one may be
    shorter, >= 2 points), grouped by length; also return the number of scalar observations."""
    if len(trajectories) == 0:
        raise InputError("learn_gp_params needs at least one trajectory")
    by_len: dict[int, tuple[list[FloatArray], list[FloatArray]]] = {}
    dim: int | None = None
    n_obs = 0
    for i, item in enumerate(trajectories):
        try:
            t_raw, y_raw = item
        except (TypeError, ValueError) as exc:
            raise InputError(f"trajectory {i} must be a pair (t_s, y)") from exc
        t = np.asarray(t_raw, dtype=np.float64)
        y = np.asarray(y_raw, dtype=np.float64)
        if t.ndim != 1 or y.ndim != 2 or y.shape[0] != t.shape[0] or y.shape[1] < 1:
            raise InputError(
                f"trajectory {i} must have t_s of shape (n,) and y of shape (n, d); "
                f"got {t.shape} and {y.shape}"
            )
        if dim is None:
            dim = y.shape[1]
        elif y.shape[1] != dim:
            raise InputError(f"trajectory {i} has {y.shape[1]} axes, the first has {dim}")
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(y))):
            raise InputError(f"trajectory {i} contains a non-finite time or position")
        if np.any(np.diff(t) < 0.0):
            raise InputError(f"trajectory {i} times must be non-decreasing")
        for start in range(0, t.shape[0], window):
            t_c = t[start : start + window]
            if t_c.shape[0] < 2:
                continue
            times, values = by_len.setdefault(t_c.shape[0], ([], []))
            times.append(t_c - t_c[0])
            y_c = y[start : start + window]
            values.append(y_c - y_c.mean(axis=0))  # centred: REML is offset-free, and so exact
            n_obs += t_c.size * y.shape[1]
    if not by_len:
        raise InputError("learn_gp_params needs a trajectory with at least 2 points")
    groups = [_ChunkGroup(np.stack(ts), np.stack(ys)) for ts, ys in by_len.values()]
    return groups, n_obs


def _neg_reml(
    theta: FloatArray, groups: Sequence[_ChunkGroup], n_obs: int
) -> tuple[float, FloatArray]:
    """Negative restricted log marginal likelihood per observation, and its gradient, over
    theta = (log sigma_f, log lambda, log sigma_n).

    Each chunk and axis is y ~ N(mu 1, Ky) with an unknown constant mu (flat prior), i.e. the
    likelihood of the chunk centred on its own mean (Rasmussen & Williams 2006, Sec. 2.7):
        log L = -1/2 y^T P y - 1/2 log|Ky| - 1/2 log(1^T Ky^{-1} 1) - (L - 1)/2 log 2 pi,
        P = Ky^{-1} - Ky^{-1} 1 1^T Ky^{-1} / (1^T Ky^{-1} 1),
        d log L / d theta = 1/2 tr((P y y^T P - P) dKy/dtheta).
    """
    sf2 = math.exp(2.0 * theta[0])
    lam = math.exp(theta[1])
    sn2 = math.exp(2.0 * theta[2])
    total = 0.0
    grad = np.zeros(3, dtype=np.float64)
    for g in groups:
        n = g.rel_s.shape[1]
        dim = g.y.shape[2]
        d2 = ((g.rel_s[:, :, None] - g.rel_s[:, None, :]) / lam) ** 2
        k = sf2 * np.exp(-0.5 * d2)  # Eq. gp_kernel
        ky = k + sn2 * np.eye(n)
        chol = np.linalg.cholesky(ky)
        log_det = 2.0 * np.log(np.diagonal(chol, axis1=1, axis2=2)).sum(axis=1)
        ky_inv = np.linalg.inv(ky)
        ky_inv = 0.5 * (ky_inv + np.swapaxes(ky_inv, 1, 2))
        u = ky_inv.sum(axis=2)  # Ky^{-1} 1
        s = u.sum(axis=1)  # 1^T Ky^{-1} 1
        p = ky_inv - u[:, :, None] * u[:, None, :] / s[:, None, None]
        py = p @ g.y  # (C, L, d)
        quad = np.einsum("cld,cld->c", g.y, py)
        total += float(np.sum(0.5 * quad + 0.5 * dim * (log_det + np.log(s) + (n - 1) * _LOG_2PI)))
        w = np.einsum("cid,cjd->cij", py, py) - dim * p  # P y y^T P - P, summed over axes
        grad[0] -= 0.5 * float(np.sum(w * (2.0 * k)))  # dKy/dlog sigma_f = 2 K
        grad[1] -= 0.5 * float(np.sum(w * (k * d2)))  # dKy/dlog lambda = K (dt / lambda)^2
        grad[2] -= 0.5 * float(np.trace(w, axis1=1, axis2=2).sum() * 2.0 * sn2)  # 2 sn^2 I
    return total / n_obs, grad / n_obs


def learn_gp_params(
    trajectories: Sequence[tuple[npt.ArrayLike, npt.ArrayLike]],
    window: int,
    init: GpParams | None = None,
) -> GpParams:
    """Fit sigma_f, lambda, sigma_n by maximum (restricted) marginal likelihood over trajectories
    [(t_s (n,) [s], y (n, d) [m]), ...], cut into chunks of `window` points centred on their means.

    L-BFGS-B with the analytic gradient over the logs of the three hyperparameters, started from
    `init` (if given) and a few data-driven guesses; the best optimum wins.
    """
    if isinstance(window, bool) or not isinstance(window, (int, np.integer)) or window < 2:
        raise InputError(f"GP window must be an integer >= 2, got {window!r}")
    groups, n_obs = _chunk_trajectories(trajectories, int(window))

    resid = np.concatenate([g.y.ravel() for g in groups])
    scale = float(np.sqrt(np.mean(resid * resid)))
    steps = np.concatenate([np.diff(g.rel_s, axis=1).ravel() for g in groups])
    steps = steps[steps > 0.0]
    span = float(max(g.rel_s[:, -1].max() for g in groups))
    if not (scale > 0.0 and steps.size > 0 and span > 0.0):
        raise InputError("learn_gp_params needs positions that vary over distinct times")
    dt = float(np.median(steps))

    bounds = [
        (math.log(scale * _SF_BOUNDS_REL[0]), math.log(scale * _SF_BOUNDS_REL[1])),
        (math.log(dt * _LAMBDA_BOUNDS_REL[0]), math.log(span * _LAMBDA_BOUNDS_REL[1])),
        (math.log(scale * _SN_BOUNDS_REL[0]), math.log(scale * _SN_BOUNDS_REL[1])),
    ]
    starts = [
        (scale, lam0, noise * scale) for lam0 in (span / 8.0, span / 2.0) for noise in (0.1, 0.5)
    ]
    if init is not None:
        starts.insert(0, (init.sigma_f_m, init.lengthscale_s, init.sigma_n_m))

    best_x: FloatArray | None = None
    best_f = math.inf
    for sf0, lam0, sn0 in starts:
        x0 = np.clip(np.log([sf0, lam0, sn0]), [b[0] for b in bounds], [b[1] for b in bounds])
        try:
            res = minimize(
                _neg_reml, x0, args=(groups, n_obs), jac=True, method="L-BFGS-B", bounds=bounds
            )
        except np.linalg.LinAlgError:
            continue  # this start wandered into a numerically singular corner; try the next
        if np.all(np.isfinite(res.x)) and math.isfinite(res.fun) and res.fun < best_f:
            best_f = float(res.fun)
            best_x = np.asarray(res.x, dtype=np.float64)
    if best_x is None:
        raise InputError("learn_gp_params: the marginal likelihood could not be optimised")
    sf, lam, sn = (float(v) for v in np.exp(best_x))
    return GpParams(sigma_f_m=sf, lengthscale_s=lam, sigma_n_m=sn, window=int(window))
