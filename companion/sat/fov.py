"""Sensing regions on the ground and the Gaussian mass inside them (Eq. prob_of_detection_given_f).

p(F) is the probability that a component's position x ~ N(m, P) lies in the field of view F. Every
call handles all components at once with a fixed number of numpy calls, no per-component loop.

ConvexPolygon, exact. Whitened, z = L^-1 (x - m) with P = L L^T, the polygon stays convex and its
standard-normal mass is a sum over edges of signed triangles (origin, v_i, v_i+1). For a triangle
with apex at the origin and far edge on a line at distance h, in polar coordinates,
    mass = int (1 - exp(-h^2 / (2 cos^2 phi))) dphi / 2 pi
         = dtheta / 2 pi - [T(h, t_b) - T(h, t_a)],
T being Owen's T function and t the coordinate along the edge from the foot point over h. The
angle terms add up to the winding number (1 inside, 0 outside). The first moment follows from the
divergence theorem, int_F z phi(z) dz = -sum_e n_e int_e phi ds, closed form along each edge.

Disk, one-dimensional quadrature. In the Gaussian's principal frame, whitened
(z_i = v_i . (x - m) / sigma_i), the disk is an axis-aligned ellipse with centre z_c and semi-axes
H_i = r / sigma_i. Integrating over one axis j with the other axis k in closed form, and walking
the ellipse by its angle (z_j = z_cj + H_j sin th, chord z_k in z_ck +- H_k cos th), gives the
smooth integrand of Green's theorem
    p(F) = int H_j cos th phi(z_j) [Phi(z_ck + H_k cos th) - Phi(z_ck - H_k cos th)] dth,
taken by Gauss-Legendre over the window of th where |z_j| <= K. Of the two axes, j is the one over
whose window the half-chord H_k cos th varies least: that is the boundary's tangent where the
boundary is flat on the scale of one sigma, and its normal where it is sharply curved, so the
integrand never has a feature much narrower than its window and one fixed node count serves every
anisotropy. (Rays from the disk centre with the radial integral in closed form were tried first;
at sigma ratio 100 the rays graze the whitened boundary and 20000 nodes over the circle still
left errors of 2e-3.)
The first moment uses the same nodes: one more power of z_j outside, phi differences inside.

Components whose mean is farther than K sigma_max from the region boundary are decided without
quadrature (mass 0 or 1; the tail neglected is below exp(-K^2 / 2) = 7e-10).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TypeAlias

import numpy as np
from numpy.typing import NDArray
from scipy.special import ndtr, owens_t

from companion.errors import InputError
from companion.kernel_cache import kernel
from companion.sat.linalg import spd_2x2_faults

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
CovEntries: TypeAlias = tuple[FloatArray, FloatArray, FloatArray]  # P00, P01, P11, each (n,)

__all__ = [
    "ConvexPolygon",
    "Disk",
    "Region",
    "prob_in_region",
    "region_moments",
    "truncation_moments",
]

_K_SIGMA = 6.5
"""Mahalanobis radius beyond which mass is neglected: tail exp(-K^2 / 2) = 6.7e-10 in 2-D and
2 Phi(-K) = 8e-11 along one axis, far below the 1e-6 asked of p(F)."""

_N_NODES = 36
"""Gauss-Legendre nodes of the disk quadrature. Worst error over 60000 random cases (sigma 0.05 to
20 m, sigma ratio up to 100, r 1 to 30 m, means within 6 sigma of the boundary or inside):
32 nodes 1.5e-7 in p(F) and 2.5e-7 (1 + |m|) in p(F) E[x | F]; 36 nodes 5e-9 and 8e-9; 40 nodes
reach the 2e-10 floor set by _K_SIGMA. Each node costs about 35 ns per component."""

_EDGE_CUT = 8.0
"""A polygon edge farther than this from the whitened mean skips its Owen's T terms: they are
bounded by the mass beyond the edge, exp(-8^2 / 2) = 1.3e-14."""

_S_TINY = 1e-12
"""An edge whose line passes closer than this (whitened) to the mean bounds a triangle of mass
below 4e-13; it is dropped instead of dividing by its distance."""

_MASS_FLOOR = 1e-300
"""Below this mass, E[x | x in F] is reported as the component's own mean."""

_CONVEX_TOL = 1e-12
"""Sine of a vertex's turning angle still counted as straight (collinear vertices are allowed)."""

_MAX_VERTEX_M = 1e150
"""Largest polygon coordinate accepted: products of coordinates stay far below overflow."""

_MIN_AREA_M2, _MAX_AREA_M2 = 1e-200, 1e200
"""Areas a region may have. The filter divides by the area (clutter and birth intensities per
square metre): an area that underflows to 0 or overflows (a disk radius below ~1e-162 m or above
~1e154 m) would make them infinite or NaN; this range leaves a wide margin."""

_TWO_PI = 2.0 * math.pi
_INV_SQRT_2PI = 1.0 / math.sqrt(_TWO_PI)
_INV_SQRT_2 = 1.0 / math.sqrt(2.0)
_GL_X, _GL_W = np.polynomial.legendre.leggauss(_N_NODES)


def _readonly(a: FloatArray) -> FloatArray:
    """A private read-only float64 copy."""
    out = np.array(a, dtype=np.float64, copy=True)
    out.flags.writeable = False
    return out


def _points(points_xy: FloatArray, name: str) -> FloatArray:
    """points_xy as a float (n, 2) array of finite values, or InputError."""
    pts = np.asarray(points_xy, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise InputError(f"{name} must have shape (n, 2), got {pts.shape}")
    if not np.isfinite(pts).all():
        raise InputError(f"{name} contains NaN or infinite values")
    return pts


def _check_area(area_m2: float, what: str) -> None:
    """InputError unless the area lies in [_MIN_AREA_M2, _MAX_AREA_M2]."""
    if not _MIN_AREA_M2 <= area_m2 <= _MAX_AREA_M2:  # NaN fails too
        raise InputError(f"{what} area {area_m2!r} m^2 must lie in "
                         f"[{_MIN_AREA_M2:.0e}, {_MAX_AREA_M2:.0e}] m^2")


def _count(n: int) -> int:
    """n as a sample count >= 0, or InputError."""
    if isinstance(n, bool) or not isinstance(n, int | np.integer) or n < 0:
        raise InputError(f"sample count must be an integer >= 0, got {n!r}")
    return int(n)


@dataclass(frozen=True, slots=True, eq=False)
class Disk:
    """The paper's circular FOV: the ground points within radius_m of center_xy (metres).

    Its area must lie in [1e-200, 1e200] m^2 (InputError otherwise).
    """

    center_xy: FloatArray  # (2,) easting, northing, metres
    radius_m: float

    def __post_init__(self) -> None:
        try:
            center = np.asarray(self.center_xy, dtype=np.float64)
            radius = float(self.radius_m)
        except (TypeError, ValueError) as exc:
            raise InputError(
                f"disk needs numbers, got {self.center_xy!r}, {self.radius_m!r}"
            ) from exc
        if center.shape != (2,) or not np.isfinite(center).all():
            raise InputError(f"disk center_xy must be 2 finite numbers, got {self.center_xy!r}")
        if not (math.isfinite(radius) and radius > 0.0):
            raise InputError(f"disk radius_m must be finite and > 0, got {self.radius_m!r}")
        _check_area(math.pi * radius * radius, "disk")
        object.__setattr__(self, "center_xy", _readonly(center))
        object.__setattr__(self, "radius_m", radius)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Disk):
            return NotImplemented
        return self.radius_m == other.radius_m and bool(np.all(self.center_xy == other.center_xy))

    def __hash__(self) -> int:
        return hash((self.center_xy.tobytes(), self.radius_m))

    @property
    def area_m2(self) -> float:
        """Area, square metres."""
        return math.pi * self.radius_m**2

    @property
    def centroid_xy(self) -> FloatArray:
        """Area centroid (the centre), metres."""
        return self.center_xy.copy()

    def contains(self, points_xy: FloatArray) -> BoolArray:
        """Whether each point of points_xy (n, 2) lies in the closed disk."""
        d = _points(points_xy, "points_xy") - self.center_xy
        inside: BoolArray = np.einsum("ni,ni->n", d, d) <= self.radius_m**2
        return inside

    def sample_uniform(self, rng: np.random.Generator, n: int) -> FloatArray:
        """n points (n, 2) drawn uniformly in the disk."""
        count = _count(n)
        radius = self.radius_m * np.sqrt(rng.random(count))  # area-uniform: P(rho < s) = s^2
        angle = rng.uniform(0.0, _TWO_PI, count)
        unit = np.stack([np.cos(angle), np.sin(angle)], axis=1)
        points: FloatArray = self.center_xy + radius[:, None] * unit
        return points


@dataclass(frozen=True, slots=True, eq=False)
class ConvexPolygon:
    """A convex FOV, e.g. a camera footprint on the ground; vertices_xy stored counter-clockwise.

    Any orientation and starting vertex may be given; collinear vertices are allowed, repeated
    ones, reflex turns, self-intersection and zero area are not (InputError), nor coordinates
    beyond 1e150 m or an area outside [1e-200, 1e200] m^2.
    """

    vertices_xy: FloatArray  # (k, 2), metres, k >= 3

    def __post_init__(self) -> None:
        try:
            verts = np.asarray(self.vertices_xy, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise InputError(f"polygon vertices_xy must be numbers: {exc}") from exc
        if verts.ndim != 2 or verts.shape[1] != 2:
            raise InputError(f"polygon vertices_xy must have shape (k, 2), got {verts.shape}")
        if verts.shape[0] < 3:
            raise InputError(f"polygon needs at least 3 vertices, got {verts.shape[0]}")
        if not np.isfinite(verts).all():
            raise InputError("polygon vertices_xy contains NaN or infinite values")
        if np.abs(verts).max() > _MAX_VERTEX_M:
            raise InputError(f"polygon vertices_xy must lie within {_MAX_VERTEX_M:.0e} m")
        # The shape checks run on the vertices centred and scaled into [-1, 1], so that no
        # product overflows or underflows whatever the polygon's size.
        scale = float(np.max(np.abs(verts - verts.mean(axis=0))))
        if scale == 0.0:
            raise InputError("polygon has repeated consecutive vertices (an edge of zero length)")
        q = (verts - verts.mean(axis=0)) / scale
        twice_area = float(np.sum(q[:, 0] * np.roll(q[:, 1], -1)
                                  - np.roll(q[:, 0], -1) * q[:, 1]))  # shoelace
        if twice_area < 0.0:
            verts, q = verts[::-1].copy(), q[::-1]  # clockwise given: store counter-clockwise
        edges = np.roll(q, -1, axis=0) - q
        lengths = np.hypot(edges[:, 0], edges[:, 1])
        if np.any(lengths <= 1e-12):
            raise InputError("polygon has repeated consecutive vertices (an edge of zero length)")
        nxt = np.roll(edges, -1, axis=0)
        norm = lengths * np.roll(lengths, -1)
        turn_sin = (edges[:, 0] * nxt[:, 1] - edges[:, 1] * nxt[:, 0]) / norm
        if np.any(turn_sin < -_CONVEX_TOL):
            raise InputError("polygon is not convex (it turns both left and right)")
        turning = np.arctan2(turn_sin, np.einsum("ki,ki->k", edges, nxt) / norm)
        if abs(float(turning.sum()) - _TWO_PI) > 1e-6:
            raise InputError("polygon is not simple (its boundary winds around more than once)")
        if abs(twice_area) <= 1e-12 * float(lengths.sum()) ** 2:
            raise InputError("polygon is degenerate: its area is zero (collinear vertices)")
        object.__setattr__(self, "vertices_xy", _readonly(verts))
        _check_area(self.area_m2, "polygon")

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, ConvexPolygon):
            return NotImplemented
        return self.vertices_xy.shape == other.vertices_xy.shape and bool(
            np.all(self.vertices_xy == other.vertices_xy)
        )

    def __hash__(self) -> int:
        return hash(self.vertices_xy.tobytes())

    def _fan_twice_areas(self) -> FloatArray:
        """Twice the areas of the fan triangles (v0, v_i, v_i+1), i = 1 .. k-2."""
        rel = self.vertices_xy[1:] - self.vertices_xy[0]
        cross: FloatArray = rel[:-1, 0] * rel[1:, 1] - rel[:-1, 1] * rel[1:, 0]
        return np.maximum(cross, 0.0)  # collinear vertices: zero, never negative by round-off

    @property
    def area_m2(self) -> float:
        """Area, square metres."""
        return 0.5 * float(self._fan_twice_areas().sum())

    @property
    def centroid_xy(self) -> FloatArray:
        """Area centroid, metres."""
        tri = self._fan_twice_areas()
        v = self.vertices_xy
        centres = (v[0] + v[1:-1] + v[2:]) / 3.0
        centroid: FloatArray = (tri[:, None] * centres).sum(axis=0) / tri.sum()
        return centroid

    def contains(self, points_xy: FloatArray) -> BoolArray:
        """Whether each point of points_xy (n, 2) lies in the closed polygon."""
        pts = _points(points_xy, "points_xy")
        v = self.vertices_xy
        edge = np.roll(v, -1, axis=0) - v  # (k, 2)
        rel = pts[:, None, :] - v[None, :, :]  # (n, k, 2)
        cross = edge[None, :, 0] * rel[..., 1] - edge[None, :, 1] * rel[..., 0]
        inside: BoolArray = np.all(cross >= 0.0, axis=1)  # left of every edge
        return inside

    def sample_uniform(self, rng: np.random.Generator, n: int) -> FloatArray:
        """n points (n, 2) drawn uniformly in the polygon (a fan triangle by area, then a point)."""
        count = _count(n)
        tri = self._fan_twice_areas()
        v = self.vertices_xy
        pick = rng.choice(tri.shape[0], size=count, p=tri / tri.sum())
        u = rng.random((count, 2))
        fold = u.sum(axis=1) > 1.0  # fold the unit square onto the unit triangle
        u[fold] = 1.0 - u[fold]
        points: FloatArray = v[0] + u[:, :1] * (v[1:-1][pick] - v[0]) + u[:, 1:] * (
            v[2:][pick] - v[0]
        )
        return points


Region: TypeAlias = Disk | ConvexPolygon


def _gaussians(means_xy: FloatArray, covs_xy: FloatArray) -> tuple[FloatArray, CovEntries]:
    """Validated (n, 2) means and the covariances' P00, P01 (symmetrised), P11, or InputError."""
    means = np.asarray(means_xy, dtype=np.float64)
    covs = np.asarray(covs_xy, dtype=np.float64)
    if means.ndim != 2 or means.shape[1] != 2:
        raise InputError(f"means_xy must have shape (n, 2), got {means.shape}")
    if covs.shape != (means.shape[0], 2, 2):
        raise InputError(f"covs_xy must have shape ({means.shape[0]}, 2, 2), got {covs.shape}")
    if not np.isfinite(means).all():
        raise InputError("means_xy contains NaN or infinite values")
    if not np.isfinite(covs).all():
        raise InputError("covs_xy contains NaN or infinite values")
    asymmetric, indefinite = spd_2x2_faults(covs)
    if asymmetric.any():
        raise InputError("covs_xy is not symmetric")
    if indefinite.any():
        raise InputError("covs_xy is not positive definite")
    p00, p01, p10, p11 = covs.reshape(-1, 4).T
    if (p01 != p10).any():
        p01 = 0.5 * (p01 + p10)
    return means, (p00, p01, p11)


def _disk(
    means: FloatArray, cov: CovEntries, disk: Disk, order: int
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Mass in the disk (n,) and, up to `order`, the moments E[(x - m) 1_F] (n, 2) and
    E[(x - m)(x - m)^T 1_F] (n, 2, 2) (zeros when not asked)."""
    n = means.shape[0]
    mass = np.empty(n)
    moment = np.zeros((n, 2))
    second = np.zeros((n, 2, 2))
    a, b, d = cov
    disk_kernel(means, a, b, d, disk.center_xy, disk.radius_m, order, mass, moment, second)
    return mass, moment, second


@kernel
def _ndtr(x: float) -> float:  # pragma: no cover - compiled
    """Phi(x), the standard normal CDF."""
    return 0.5 * math.erfc(-x * _INV_SQRT_2)


@kernel
def disk_kernel(  # pragma: no cover - compiled; tested through _disk
    means: FloatArray,
    a: FloatArray,
    b: FloatArray,
    d: FloatArray,
    center: FloatArray,
    radius: float,
    order: int,
    mass: FloatArray,
    moment: FloatArray,
    second: FloatArray,
) -> None:
    """Fill mass, moment and second (see _disk) component by component, for the components'
    position means (n, >= 2) and covariance entries a = P00, b = P01, d = P11 (n,)."""
    gl_x, gl_w = _GL_X, _GL_W
    for i in range(means.shape[0]):
        ex = center[0] - means[i, 0]  # c - m
        ey = center[1] - means[i, 1]
        dist = math.hypot(ex, ey)
        hd = 0.5 * (a[i] - d[i])
        lam1 = 0.5 * (a[i] + d[i]) + math.hypot(hd, b[i])  # larger eigenvalue of P
        if abs(dist - radius) > _K_SIGMA * math.sqrt(lam1):  # decided: boundary beyond K sigma
            inside = 1.0 if dist < radius else 0.0
            mass[i] = inside
            if order >= 2:
                second[i, 0, 0] = inside * a[i]
                second[i, 0, 1] = second[i, 1, 0] = inside * b[i]
                second[i, 1, 1] = inside * d[i]
            continue
        # Principal frame: v1 = (c, s), v2 = (-s, c); sigma_1 >= sigma_2.
        sig1 = math.sqrt(lam1)
        sig2 = math.sqrt((a[i] * d[i] - b[i] * b[i]) / lam1)  # lam2 = det P / lam1
        ang = 0.5 * math.atan2(b[i], hd)
        c, s = math.cos(ang), math.sin(ang)
        # Per principal axis: ellipse centre z_c = v . (c - m) / sigma, semi-axis H = r / sigma,
        # the window [lo, hi] of sin th where |z_c + H sin th| <= K, and the point of that
        # window nearest to sin th = 0.
        zc1 = (c * ex + s * ey) / sig1
        zc2 = (c * ey - s * ex) / sig2
        h1, h2 = radius / sig1, radius / sig2
        lo1 = min(max((-_K_SIGMA - zc1) / h1, -1.0), 1.0)
        hi1 = min(max((_K_SIGMA - zc1) / h1, -1.0), 1.0)
        lo2 = min(max((-_K_SIGMA - zc2) / h2, -1.0), 1.0)
        hi2 = min(max((_K_SIGMA - zc2) / h2, -1.0), 1.0)
        near1 = max(lo1, min(hi1, 0.0))
        near2 = max(lo2, min(hi2, 0.0))
        # Variation of cos th over each window (cos is largest at the nearest point); the outer
        # axis j is the one where the inner half-chord H_k cos th varies least.
        swing1 = 2.0 * math.sqrt(1.0 - near1 * near1) - math.sqrt(1.0 - lo1 * lo1) - math.sqrt(
            1.0 - hi1 * hi1
        )
        swing2 = 2.0 * math.sqrt(1.0 - near2 * near2) - math.sqrt(1.0 - lo2 * lo2) - math.sqrt(
            1.0 - hi2 * hi2
        )
        outer2 = swing2 * h1 < swing1 * h2
        if outer2:
            zj, hj, lo, hi, zk, hk = zc2, h2, lo2, hi2, zc1, h1
        else:
            zj, hj, lo, hi, zk, hk = zc1, h1, lo1, hi1, zc2, h2
        th_lo, th_hi = math.asin(lo), math.asin(hi)
        half = 0.5 * (th_hi - th_lo)
        mid = th_lo + half
        za = -abs(zk)  # Phi(z + h) - Phi(z - h) = Phi(-|z| + h) - Phi(-|z| - h): no cancellation
        m0 = mj = mk = mjj = mjk = mkk = 0.0
        for q in range(gl_x.shape[0]):  # Gauss-Legendre nodes over th
            sin_th = math.sin(mid + half * gl_x[q])
            cos_th = math.sqrt(max(1.0 - sin_th * sin_th, 0.0))
            zj_th = zj + hj * sin_th
            # Green's theorem on the ellipse: dz_j = H_j cos th dth, phi(z_j) times the chord.
            outer = gl_w[q] * cos_th * math.exp(-0.5 * zj_th * zj_th)
            chord = hk * cos_th
            w_mass = outer * (_ndtr(za + chord) - _ndtr(za - chord))
            m0 += w_mass
            if order >= 1:
                lo_k, hi_k = zk - chord, zk + chord
                phi_lo, phi_hi = math.exp(-0.5 * lo_k * lo_k), math.exp(-0.5 * hi_k * hi_k)
                w_first = outer * (phi_lo - phi_hi)  # int_lo^hi z phi = phi(lo) - phi(hi)
                mj += w_mass * zj_th
                mk += w_first
                mjj += w_mass * zj_th * zj_th
                mjk += w_first * zj_th
                # int_lo^hi z^2 phi(z) dz = Phi(hi) - Phi(lo) - (hi phi(hi) - lo phi(lo)):
                mkk += w_mass - outer * (hi_k * phi_hi - lo_k * phi_lo) * _INV_SQRT_2PI
        scale = _INV_SQRT_2PI * half * hj  # dth = half dx; phi(z) = exp(-z^2 / 2) / sqrt(2 pi)
        # Eq. prob_of_detection_given_f:
        mass[i] = min(max(m0 * scale, 0.0), 1.0)
        if order < 1:
            continue
        fj, fk = mj * scale, mk * _INV_SQRT_2PI * scale  # int_F z phi(z) dz along (j, k)
        f1, f2 = (fk, fj) if outer2 else (fj, fk)
        f1 *= sig1
        f2 *= sig2
        moment[i, 0] = c * f1 - s * f2  # x - m = [v1 v2] diag(sigma) z
        moment[i, 1] = s * f1 + c * f2
        if order < 2:
            continue
        sjj, sjk, skk = mjj * scale, mjk * _INV_SQRT_2PI * scale, mkk * scale
        s11, s12, s22 = (skk, sjk, sjj) if outer2 else (sjj, sjk, skk)
        # E[(x - m)(x - m)^T 1_F] = A S A^T with A = [v1 v2] diag(sigma).
        a11, a12, a21, a22 = c * sig1, -s * sig2, s * sig1, c * sig2
        t11 = a11 * s11 + a12 * s12
        t12 = a11 * s12 + a12 * s22
        t21 = a21 * s11 + a22 * s12
        t22 = a21 * s12 + a22 * s22
        second[i, 0, 0] = t11 * a11 + t12 * a12
        second[i, 0, 1] = second[i, 1, 0] = t11 * a21 + t12 * a22
        second[i, 1, 1] = t21 * a21 + t22 * a22


def _polygon(
    means: FloatArray, cov: CovEntries, poly: ConvexPolygon, order: int
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Mass in the polygon (n,) and, up to `order`, E[(x - m) 1_F] (n, 2) and
    E[(x - m)(x - m)^T 1_F] (n, 2, 2) (zeros when not asked)."""
    a, b, d = cov
    l11 = np.sqrt(a)[:, None]  # Cholesky P = L L^T, closed form
    l21 = b[:, None] / l11
    l22 = np.sqrt((a * d - b * b) / a)[:, None]
    rel = poly.vertices_xy[None, :, :] - means[:, None, :]  # (n, k, 2)
    ax = rel[..., 0] / l11  # whitened vertices z = L^-1 (v - m)
    ay = (rel[..., 1] - l21 * ax) / l22
    dx, dy = np.roll(ax, -1, axis=1) - ax, np.roll(ay, -1, axis=1) - ay
    length = np.hypot(dx, dy)
    # An edge shorter than one ulp of v - m (a mean ~1e16 edge lengths away) whitens to zero
    # length: give it no direction (sd = 0, dropped below as `tiny`) instead of 0 / 0 = NaN.
    # Such a mean is far outside, where another edge decides the (zero) mass.
    length_safe = np.where(length > 0.0, length, 1.0)
    ux, uy = dx / length_safe, dy / length_safe  # edge direction
    sd = ax * uy - ay * ux  # signed distance of the edge line, > 0 with the mean on its left
    ta = ax * ux + ay * uy  # edge start and end along the edge, from the foot point
    tb = ta + length
    tiny = np.abs(sd) < _S_TINY
    sd_safe = np.where(tiny, 1.0, sd)
    ra, rb = ta / sd_safe, tb / sd_safe  # tan of the ends' angles from the foot point, signed
    gap = np.maximum(ta, 0.0) - np.minimum(tb, 0.0)
    near = ~tiny & (sd * sd + gap * gap < _EDGE_CUT**2)  # segment within reach of the mass
    h = np.abs(sd[near])
    owen = np.zeros_like(sd)
    owen[near] = owens_t(h, rb[near]) - owens_t(h, ra[near])
    # Signed triangles (0, v_i, v_i+1): dtheta / 2 pi - [T(h, t_b) - T(h, t_a)], summed. The
    # angles sum to the winding number: 1 with the mean left of every edge, 0 if right of one.
    winding = np.all(sd > _S_TINY, axis=1).astype(np.float64)
    on_edge = ~(sd < -_S_TINY).any(axis=1) & (winding == 0.0)
    if on_edge.any():  # mean on the boundary: the interior angle there over 2 pi
        angle = np.where(tiny[on_edge], 0.0, np.arctan(rb[on_edge]) - np.arctan(ra[on_edge]))
        winding[on_edge] = angle.sum(axis=1) / _TWO_PI
    # Eq. prob_of_detection_given_f:
    mass = np.minimum(np.maximum(winding - owen.sum(axis=1), 0.0), 1.0)
    moment = np.zeros_like(means)
    second = np.zeros((means.shape[0], 2, 2))
    if order >= 1:
        # int_F z phi(z) dz = -sum_e n_e phi(h_e) [Phi(t_b) - Phi(t_a)], outer normal (u_y, -u_x).
        sg = np.where(ta > 0.0, -1.0, 1.0)  # Phi(t_b) - Phi(t_a) = Phi(-t_a) - Phi(-t_b)
        edge_phi = np.exp(-0.5 * sd * sd) * _INV_SQRT_2PI
        line = edge_phi * sg * (ndtr(sg * tb) - ndtr(sg * ta))
        mz1 = -(uy * line).sum(axis=1)
        mz2 = (ux * line).sum(axis=1)
        moment[:, 0] = l11[:, 0] * mz1  # x - m = L z
        moment[:, 1] = l21[:, 0] * mz1 + l22[:, 0] * mz2
    if order >= 2:
        # int_F z_i z_j phi dz = delta_ij p(F) - sum_e n_j int_e z_i phi ds (divergence theorem);
        # along an edge z = f + t u (foot point f): int z phi ds = f line + u phi(h) [phi(t)]_b^a.
        fx, fy = ax - ta * ux, ay - ta * uy
        tip = edge_phi * _INV_SQRT_2PI * (np.exp(-0.5 * ta * ta) - np.exp(-0.5 * tb * tb))
        along = (fx * line + ux * tip, fy * line + uy * tip)  # int_e z_i phi ds, i = x, y
        normal = (uy, -ux)
        mzz = np.empty((means.shape[0], 2, 2))
        for i in range(2):
            for j in range(2):
                mzz[:, i, j] = (i == j) * mass - (normal[j] * along[i]).sum(axis=1)
        mzz = 0.5 * (mzz + mzz.transpose(0, 2, 1))
        chol = np.zeros((means.shape[0], 2, 2))
        chol[:, 0, 0], chol[:, 1, 0], chol[:, 1, 1] = l11[:, 0], l21[:, 0], l22[:, 0]
        second = chol @ mzz @ chol.transpose(0, 2, 1)  # x - m = L z
    return mass, moment, second


def _raw_moments(
    means_xy: FloatArray, covs_xy: FloatArray, region: Region, order: int, check: bool = True
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Validated means, p(F) (n,), E[(x - m) 1_F] (n, 2), E[(x - m)(x - m)^T 1_F] (n, 2, 2).

    check=False trusts the caller's arrays (float64, symmetric positive definite): the filter
    hands in its own components, which it keeps valid.
    """
    if check:
        means, cov = _gaussians(means_xy, covs_xy)
    else:
        means = means_xy
        cov = (covs_xy[:, 0, 0], covs_xy[:, 0, 1], covs_xy[:, 1, 1])
    if not isinstance(region, Disk | ConvexPolygon):
        raise InputError(f"region must be a Disk or a ConvexPolygon, got {type(region)}")
    if means.shape[0] == 0:
        return means, np.zeros(0), np.zeros((0, 2)), np.zeros((0, 2, 2))
    if isinstance(region, Disk):
        mass, moment, second = _disk(means, cov, region, order)
    else:
        mass, moment, second = _polygon(means, cov, region, order)
    return means, mass, moment, second


def prob_in_region(
    means_xy: FloatArray, covs_xy: FloatArray, region: Region, check: bool = True
) -> FloatArray:
    """p(F) (n,): mass of each N(means_xy[i], covs_xy[i]) (metres) in region, to 1e-6 absolute.

    Eq. prob_of_detection_given_f with the full covariance, correlation included; n may be 0.
    """
    return _raw_moments(means_xy, covs_xy, region, 0, check)[1]


def region_moments(
    means_xy: FloatArray, covs_xy: FloatArray, region: Region
) -> tuple[FloatArray, FloatArray]:
    """(p(F) (n,), E[x | x in F] (n, 2)) per Gaussian; its own mean where p(F) <= 1e-300.

    p(F) E[x | x in F] is accurate to 1e-6 (1 + |m|); E[x | x in F] alone has few correct digits
    where p(F) is below about 1e-9 (the neglected tails are then comparable to the mass).
    """
    means, mass, moment, _ = _raw_moments(means_xy, covs_xy, region, order=1)
    ok = mass > _MASS_FLOOR
    mean_in = means.copy()
    mean_in[ok] += moment[ok] / mass[ok, None]  # E[x | F] = m + E[(x - m) 1_F] / p(F)
    return mass, mean_in


def truncation_moments(
    means_xy: FloatArray, covs_xy: FloatArray, region: Region, check: bool = True
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """p(F) (n,), E[(x - m) 1_F] (n, 2) and E[(x - m)(x - m)^T 1_F] (n, 2, 2) per Gaussian.

    The raw moments of each component's mass inside the region, about its own mean: what the
    no-detection update needs to moment-match (1 - c 1_F(x)) N(x; m, P).
    """
    _, mass, moment, second = _raw_moments(means_xy, covs_xy, region, 2, check)
    return mass, moment, second
