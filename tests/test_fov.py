"""p(F) and E[x | x in F] of disks and convex polygons: double integral, exact cases, symmetry."""

from __future__ import annotations

import math
from itertools import pairwise

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.typing import NDArray
from scipy.integrate import dblquad
from scipy.special import ndtr
from scipy.stats import norm

from companion.errors import InputError
from companion.sat.fov import ConvexPolygon, Disk, Region, prob_in_region, region_moments

FloatArray = NDArray[np.float64]

CAMERA_TRAPEZOID = np.array([[-20.0, -12.0], [20.0, -12.0], [28.0, 14.0], [-28.0, 14.0]])


# ---------------------------------------------------------------------------------------------
# Reference: scipy dblquad in whitened coordinates z = L^-1 (x - m), where the integrand is the
# standard normal and a thin Gaussian is no harder than a round one; z clipped to |z_i| <= 9.


_Z = 9.0


def _reference(mean: FloatArray, cov: FloatArray, region: Region) -> tuple[float, FloatArray]:
    """(p(F), E[x 1_F]) of N(mean, cov) by dblquad (epsabs 1e-11), outer z1, inner z2."""
    l11 = math.sqrt(cov[0, 0])
    l21 = cov[0, 1] / l11
    l22 = math.sqrt(cov[1, 1] - l21 * l21)
    m0, m1 = float(mean[0]), float(mean[1])

    if isinstance(region, Disk):
        c0, c1 = (float(v) for v in region.center_xy)
        r = region.radius_m

        def chord(z1: float) -> tuple[float, float]:
            w = r * r - (m0 + l11 * z1 - c0) ** 2
            if w <= 0.0:
                return 0.0, 0.0
            mid, half = (c1 - m1 - l21 * z1) / l22, math.sqrt(w) / l22
            lo, hi = max(mid - half, -_Z), min(mid + half, _Z)
            return lo, max(lo, hi)

        cuts = [max((c0 - m0 - r) / l11, -_Z), min((c0 - m0 + r) / l11, _Z)]
    else:
        verts = region.vertices_xy
        edges = np.roll(verts, -1, axis=0) - verts

        def chord(z1: float) -> tuple[float, float]:
            lo, hi = -_Z, _Z
            x0 = m0 + l11 * z1
            for (vx, vy), (ex, ey) in zip(verts, edges, strict=True):
                # inside: ex (x1 - vy) - ey (x0 - vx) >= 0 with x1 = m1 + l21 z1 + l22 z2
                const = ex * (m1 + l21 * z1 - vy) - ey * (x0 - vx)
                coef = ex * l22
                if coef > 0.0:
                    lo = max(lo, -const / coef)
                elif coef < 0.0:
                    hi = min(hi, -const / coef)
                elif const < 0.0:
                    return 0.0, 0.0
            return lo, max(lo, hi)

        zv = (verts[:, 0] - m0) / l11
        a, b = max(float(zv.min()), -_Z), min(float(zv.max()), _Z)
        cuts = [a, *sorted(float(z) for z in zv if a < z < b), b]  # kinks at the vertices

    moments = np.zeros(3)  # int phi, int z1 phi, int z2 phi over F
    for k, weight in enumerate(
        (lambda z2, z1: 1.0, lambda z2, z1: z1, lambda z2, z1: z2)
    ):
        for a, b in pairwise(cuts):
            if b <= a:
                continue
            moments[k] += dblquad(
                lambda z2, z1, w=weight: w(z2, z1) * math.exp(-0.5 * (z1 * z1 + z2 * z2)),
                a, b, lambda z1: chord(z1)[0], lambda z1: chord(z1)[1],
                epsabs=1e-11, epsrel=1e-11,
            )[0] / (2.0 * math.pi)
    first = np.array([m0 * moments[0] + l11 * moments[1],
                      m1 * moments[0] + l21 * moments[1] + l22 * moments[2]])
    return float(moments[0]), first


def _rotation(angle: float) -> FloatArray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s], [s, c]])


def _cov(sig1: float, sig2: float, angle: float) -> FloatArray:
    rot = _rotation(angle)
    cov: FloatArray = rot @ np.diag([sig1 * sig1, sig2 * sig2]) @ rot.T
    return cov


def _random_cov(rng: np.random.Generator) -> FloatArray:
    """sigmas 0.05 .. 20 m log-uniform, ratio at most 100, random orientation."""
    sig1 = math.exp(rng.uniform(math.log(0.05), math.log(20.0)))
    sig2 = sig1 / math.exp(rng.uniform(0.0, math.log(100.0)))
    return _cov(sig1, max(sig2, 0.05), rng.uniform(0.0, math.pi))


def _convex_hull(points: FloatArray) -> FloatArray:
    """Counter-clockwise hull (monotone chain), written out so the test does not lean on scipy."""
    pts = sorted(map(tuple, points))

    def half(seq: list[tuple[float, float]]) -> list[tuple[float, float]]:
        out: list[tuple[float, float]] = []
        for p in seq:
            while len(out) >= 2 and (
                (out[-1][0] - out[-2][0]) * (p[1] - out[-2][1])
                - (out[-1][1] - out[-2][1]) * (p[0] - out[-2][0])
            ) <= 0.0:
                out.pop()
            out.append(p)
        return out

    lower, upper = half(pts), half(pts[::-1])
    return np.array(lower[:-1] + upper[:-1])


def _check_against_reference(mean: FloatArray, cov: FloatArray, region: Region) -> None:
    p_ref, first_ref = _reference(mean, cov, region)
    mass, mean_in = region_moments(mean[None], cov[None], region)
    assert abs(mass[0] - p_ref) <= 1e-6
    assert prob_in_region(mean[None], cov[None], region)[0] == mass[0]
    np.testing.assert_allclose(
        mass[0] * mean_in[0], first_ref, rtol=0.0, atol=1e-6 * (1.0 + float(np.abs(mean).max()))
    )


# ---------------------------------------------------------------------------------------------
# Against the double integral


def _disk_cases() -> list[tuple[FloatArray, FloatArray, Disk]]:
    rng = np.random.default_rng(20240611)
    cases = []
    for i in range(14):
        cov = _random_cov(rng)
        radius = rng.uniform(1.0, 30.0)
        center = rng.normal(0.0, 50.0, 2)
        direction = _rotation(rng.uniform(0.0, 2.0 * math.pi))[:, 0]
        spread = math.sqrt(float(direction @ cov @ direction))
        offset = (0.0, -1.0, 1.5, -3.0, 0.3, 4.0, -0.5)[i % 7]  # radial sigmas from the edge
        mean = center + (radius + offset * spread) * direction
        cases.append((mean, cov, Disk(center, radius)))
    paper = np.diag([50.0, 50.0])  # the paper's initial belief, near and far from the FOV
    cases.append((np.array([30.0, 5.0]), paper, Disk(np.zeros(2), 25.0)))
    cases.append((np.array([3.0, -2.0]), paper, Disk(np.array([1.0, 1.0]), 7.5)))
    thin = _cov(20.0, 0.2, 0.3)  # sigma ratio 100 across a small disk, and along a big one
    cases.append((np.array([1.0, 0.5]), thin, Disk(np.zeros(2), 1.0)))
    cases.append((np.array([30.0, 0.0]), _cov(9.5, 0.095, 1.2), Disk(np.zeros(2), 30.0)))
    cases.append((np.array([0.0, 30.0]), _cov(0.05, 0.05, 0.0), Disk(np.zeros(2), 30.0)))
    # Where only one choice of outer axis converges: a small round Gaussian on a big circle (the
    # boundary is flat: integrate along it) and a needle across it (integrate along the needle).
    rim = 30.0 * _rotation(math.radians(80.0))[:, 0]
    cases.append((rim, _cov(0.05, 0.05, 0.0), Disk(np.zeros(2), 30.0)))
    cases.append((rim, _cov(0.106, 0.1, 0.0), Disk(np.zeros(2), 30.0)))
    rim = 30.0 * _rotation(math.radians(60.0))[:, 0]
    cases.append((rim, _cov(2.11, 0.0705, 0.0), Disk(np.zeros(2), 30.0)))
    return cases


@pytest.mark.parametrize("case", _disk_cases())
def test_disk_matches_double_integral(case: tuple[FloatArray, FloatArray, Disk]) -> None:
    _check_against_reference(*case)


def _polygon_cases() -> list[tuple[FloatArray, FloatArray, ConvexPolygon]]:
    rng = np.random.default_rng(7)
    cases = []
    for i in range(10):
        k = 3 + i  # 3 .. 12 vertices
        cloud = rng.normal(0.0, rng.uniform(2.0, 25.0), (60, 2))
        hull = _convex_hull(cloud)
        if hull.shape[0] > k:
            hull = hull[np.sort(rng.choice(hull.shape[0], k, replace=False))]
        poly = ConvexPolygon(hull + rng.normal(0.0, 30.0, 2))
        cov = _random_cov(rng)
        anchor = poly.vertices_xy[rng.integers(hull.shape[0])]
        mean = anchor + rng.normal(0.0, 1.0, 2) * np.sqrt(np.diag(cov))
        cases.append((mean, cov, poly))
    sliver = ConvexPolygon(np.array([[0.0, 0.0], [50.0, 0.05], [50.0, 0.1], [0.0, 0.08]]))
    cases.append((np.array([25.0, 0.0]), _cov(3.0, 0.04, 0.01), sliver))
    cases.append((np.array([10.0, 1.0]), np.diag([4.0, 1.0]), sliver))
    camera = ConvexPolygon(CAMERA_TRAPEZOID)
    cases.append((np.array([27.0, 13.0]), _cov(6.0, 2.0, 0.7), camera))
    cases.append((np.array([0.0, -12.0]), np.diag([50.0, 50.0]), camera))
    triangle = ConvexPolygon(np.array([[0.0, 0.0], [5.0, 1.0], [1.0, 4.0]]))
    cases.append((np.array([1.0, 1.0]), np.array([[2.0, 1.9], [1.9, 2.0]]), triangle))
    return cases


@pytest.mark.parametrize("case", _polygon_cases())
def test_polygon_matches_double_integral(
    case: tuple[FloatArray, FloatArray, ConvexPolygon],
) -> None:
    _check_against_reference(*case)


def test_many_components_in_one_call_match_one_at_a_time() -> None:
    rng = np.random.default_rng(3)
    n = 200
    covs = np.array([_random_cov(rng) for _ in range(n)])
    means = rng.normal(0.0, 15.0, (n, 2))
    for region in (Disk(np.array([2.0, -1.0]), 12.0), ConvexPolygon(CAMERA_TRAPEZOID)):
        mass, mean_in = region_moments(means, covs, region)
        for i in rng.choice(n, 15, replace=False):
            p1, m1 = region_moments(means[i : i + 1], covs[i : i + 1], region)
            assert p1[0] == pytest.approx(mass[i], abs=1e-15)
            np.testing.assert_allclose(m1[0], mean_in[i], rtol=1e-12, atol=1e-12)


# ---------------------------------------------------------------------------------------------
# Exact special cases


@pytest.mark.parametrize(("radius", "sigma"), [(1.0, 0.05), (1.0, 20.0), (7.5, 7.07), (25.0, 3.0)])
def test_isotropic_gaussian_centred_on_disk(radius: float, sigma: float) -> None:
    centre = np.array([3.0, -4.0])
    mass, mean_in = region_moments(centre[None], (sigma**2 * np.eye(2))[None], Disk(centre, radius))
    assert mass[0] == pytest.approx(-math.expm1(-(radius**2) / (2.0 * sigma**2)), abs=1e-9)
    np.testing.assert_allclose(mean_in[0], centre, atol=1e-9)


def test_rectangle_with_diagonal_covariance_is_a_product_of_phi_differences() -> None:
    rect = ConvexPolygon(np.array([[-1.0, 2.0], [4.0, 2.0], [4.0, 5.0], [-1.0, 5.0]]))
    means = np.array([[0.0, 0.0], [1.5, 3.5], [-3.0, 6.0], [4.0, 2.0]])
    sig = np.array([[1.0, 2.0], [0.3, 5.0], [2.0, 0.5], [1.0, 1.0]])
    covs = np.einsum("ni,ij->nij", sig**2, np.eye(2))
    mass, mean_in = region_moments(means, covs, rect)
    lo = (np.array([-1.0, 2.0]) - means) / sig
    hi = (np.array([4.0, 5.0]) - means) / sig
    axis_mass = ndtr(hi) - ndtr(lo)
    axis_mean = means + sig * (norm.pdf(lo) - norm.pdf(hi)) / axis_mass  # truncated normal
    np.testing.assert_allclose(mass, axis_mass.prod(axis=1), rtol=0.0, atol=1e-14)
    np.testing.assert_allclose(mean_in, axis_mean, rtol=1e-10, atol=1e-12)


def test_huge_polygon_is_a_half_plane() -> None:
    big = 1e7
    half_plane = ConvexPolygon(np.array([[0.0, -big], [big, -big], [big, big], [0.0, big]]))
    cov = np.array([[4.0, 3.0], [3.0, 9.0]])
    means = np.array([[-3.0, 1.0], [0.0, 0.0], [1.0, -40.0], [7.0, 3.0]])
    mass = prob_in_region(means, np.broadcast_to(cov, (4, 2, 2)), half_plane)
    np.testing.assert_allclose(mass, ndtr(means[:, 0] / 2.0), rtol=0.0, atol=1e-14)


def test_gaussian_at_a_corner_or_on_an_edge_of_a_square() -> None:
    square = ConvexPolygon(np.array([[0.0, 0.0], [1e4, 0.0], [1e4, 1e4], [0.0, 1e4]]))
    means = np.array([[0.0, 0.0], [5e3, 0.0], [1e4, 1e4]])
    mass = prob_in_region(means, np.tile(np.eye(2), (3, 1, 1)), square)
    np.testing.assert_allclose(mass, [0.25, 0.5, 0.25], atol=1e-14)
    disk = Disk(np.zeros(2), 1e4)  # a straight edge at the scale of the Gaussian
    assert prob_in_region(np.array([[1e4, 0.0]]), np.eye(2)[None], disk)[0] == pytest.approx(
        0.5, abs=1e-4
    )


@pytest.mark.parametrize("region", [Disk(np.zeros(2), 5.0), ConvexPolygon(CAMERA_TRAPEZOID)])
def test_far_away_is_zero_and_deep_inside_is_one(region: Region) -> None:
    means = np.array([[500.0, 0.0], [0.0, -300.0], [0.0, 0.0], [0.1, -0.2]])
    covs = np.array([np.eye(2), np.eye(2) * 4.0, np.eye(2) * 1e-4, _cov(0.2, 0.05, 1.0)])
    mass, mean_in = region_moments(means, covs, region)
    assert mass.tolist() == [0.0, 0.0, 1.0, 1.0]
    np.testing.assert_array_equal(mean_in[:2], means[:2])  # no mass: its own mean
    np.testing.assert_allclose(mean_in[2:], means[2:], atol=1e-9)


def test_decided_components_join_the_computed_ones_continuously() -> None:
    radius = 20.0
    disk = Disk(np.zeros(2), radius)
    covs = np.tile(_cov(2.0, 0.5, 0.4), (3, 1, 1))
    gaps = np.array([-1e-9, 0.0, 1e-9]) + 6.5 * 2.0  # at the K sigma_max threshold
    zeros = np.zeros(3)
    inside = prob_in_region(np.column_stack([radius - gaps, zeros]), covs, disk)
    outside = prob_in_region(np.column_stack([radius + gaps, zeros]), covs, disk)
    np.testing.assert_allclose(inside, 1.0, rtol=0.0, atol=1e-9)
    np.testing.assert_allclose(outside, 0.0, rtol=0.0, atol=1e-9)
    assert inside[0] < 1.0  # computed just inside the threshold, decided beyond it
    assert inside[2] == 1.0


def test_no_components_gives_empty_arrays() -> None:
    for region in (Disk(np.zeros(2), 1.0), ConvexPolygon(CAMERA_TRAPEZOID)):
        mass, mean_in = region_moments(np.zeros((0, 2)), np.zeros((0, 2, 2)), region)
        assert mass.shape == (0,)
        assert mean_in.shape == (0, 2)
        assert prob_in_region(np.zeros((0, 2)), np.zeros((0, 2, 2)), region).shape == (0,)


# ---------------------------------------------------------------------------------------------
# Invariances


def _moved(region: Region, rot: FloatArray, shift: FloatArray) -> Region:
    if isinstance(region, Disk):
        return Disk(rot @ region.center_xy + shift, region.radius_m)
    return ConvexPolygon(region.vertices_xy @ rot.T + shift)


@pytest.mark.parametrize("region", [Disk(np.array([3.0, 1.0]), 8.0),
                                    ConvexPolygon(CAMERA_TRAPEZOID)])
def test_rotating_and_translating_everything_changes_nothing(region: Region) -> None:
    rng = np.random.default_rng(11)
    n = 40
    covs = np.array([_random_cov(rng) for _ in range(n)])
    means = rng.normal(0.0, 20.0, (n, 2))
    mass, mean_in = region_moments(means, covs, region)
    assert 0.05 < mass.mean() < 0.95  # the cases straddle the boundary
    for angle in (0.3, 2.0, -1.1):
        rot, shift = _rotation(angle), np.array([1e3, -2e3])
        mass2, mean_in2 = region_moments(
            means @ rot.T + shift, rot @ covs @ rot.T, _moved(region, rot, shift)
        )
        np.testing.assert_allclose(mass2, mass, rtol=0.0, atol=1e-8)
        scale = 1.0 + np.abs(means).max()
        np.testing.assert_allclose(
            mass2[:, None] * mean_in2, mass[:, None] * (mean_in @ rot.T + shift),
            rtol=0.0, atol=1e-8 * 3e3 * scale,
        )


def test_vertex_order_and_start_do_not_matter() -> None:
    rng = np.random.default_rng(5)
    verts = _convex_hull(rng.normal(0.0, 10.0, (30, 2)))
    n = 25
    covs = np.array([_random_cov(rng) for _ in range(n)])
    means = rng.normal(0.0, 10.0, (n, 2))
    base, base_mean = region_moments(means, covs, ConvexPolygon(verts))
    for order in (verts[::-1], np.roll(verts, 3, axis=0), np.roll(verts[::-1], 2, axis=0)):
        poly = ConvexPolygon(order)
        assert np.array_equal(
            np.roll(poly.vertices_xy, -int(np.argmin(poly.vertices_xy[:, 0])), axis=0),
            np.roll(verts, -int(np.argmin(verts[:, 0])), axis=0),
        )  # stored counter-clockwise whatever was given
        mass, mean_in = region_moments(means, covs, poly)
        np.testing.assert_allclose(mass, base, rtol=0.0, atol=1e-13)
        np.testing.assert_allclose(mean_in, base_mean, rtol=0.0, atol=1e-9)


def test_disk_agrees_with_a_2000_gon() -> None:
    rng = np.random.default_rng(9)
    n_sides = 2000
    radius = 10.0
    angles = np.arange(n_sides) * (2.0 * math.pi / n_sides)
    # Same area as the disk, so that the sides cut off as much as they add.
    scale = radius * math.sqrt(2.0 * math.pi / (n_sides * math.sin(2.0 * math.pi / n_sides)))
    gon = ConvexPolygon(scale * np.column_stack([np.cos(angles), np.sin(angles)]))
    n = 30
    covs = np.array([_cov(rng.uniform(1.0, 5.0), rng.uniform(1.0, 5.0), rng.uniform(0, 3.2))
                     for _ in range(n)])
    along = radius * rng.uniform(0.0, 1.5, (n, 1))
    means = rng.normal(0.0, 1.0, (n, 2)) + along * _rotation(1.0)[:, 0]
    mass_disk, mean_disk = region_moments(means, covs, Disk(np.zeros(2), radius))
    mass_gon, mean_gon = region_moments(means, covs, gon)
    np.testing.assert_allclose(mass_gon, mass_disk, rtol=0.0, atol=1e-5)
    np.testing.assert_allclose(
        mass_gon[:, None] * mean_gon, mass_disk[:, None] * mean_disk, rtol=0.0, atol=1e-4
    )


def test_inputs_are_not_mutated_and_views_are_accepted() -> None:
    states = np.array([[1.0, 2.0, 0.5, 0.1], [9.0, -1.0, 0.0, 0.0]])  # x, y, vx, vy
    covs4 = np.tile(np.diag([4.0, 2.0, 1.0, 1.0]), (2, 1, 1))
    covs4[0, 0, 1] = covs4[0, 1, 0] = 1.0
    frozen_states, frozen_covs = states.copy(), covs4.copy()
    states.flags.writeable = False
    covs4.flags.writeable = False
    region = Disk(np.zeros(2), 6.0)
    mass, mean_in = region_moments(states[:, :2], covs4[:, :2, :2], region)
    expected, _ = region_moments(frozen_states[:, :2].copy(), frozen_covs[:, :2, :2].copy(), region)
    np.testing.assert_array_equal(mass, expected)
    np.testing.assert_array_equal(states, frozen_states)
    np.testing.assert_array_equal(covs4, frozen_covs)
    mean_in[:] = 0.0  # the result is the caller's own
    np.testing.assert_array_equal(states, frozen_states)


# ---------------------------------------------------------------------------------------------
# The regions themselves


def test_disk_geometry_and_sampling() -> None:
    disk = Disk(np.array([2.0, -3.0]), 4.0)
    assert disk.area_m2 == pytest.approx(16.0 * math.pi)
    np.testing.assert_array_equal(disk.centroid_xy, [2.0, -3.0])
    assert disk.contains(np.array([[6.0, -3.0], [6.01, -3.0], [2.0, 0.9]])).tolist() == [
        True, False, True,
    ]
    pts = disk.sample_uniform(np.random.default_rng(0), 20000)
    assert pts.shape == (20000, 2)
    assert disk.contains(pts).all()
    radial = np.hypot(*(pts - disk.center_xy).T)
    assert np.mean(radial < 2.0) == pytest.approx(0.25, abs=0.015)  # area-uniform, not radius
    np.testing.assert_allclose(pts.mean(axis=0), disk.centroid_xy, atol=0.06)
    assert disk.sample_uniform(np.random.default_rng(0), 0).shape == (0, 2)


def test_polygon_geometry_and_sampling() -> None:
    poly = ConvexPolygon(CAMERA_TRAPEZOID[::-1])  # clockwise in
    assert poly.area_m2 == pytest.approx(0.5 * (40.0 + 56.0) * 26.0)
    centroid_y = -12.0 + 26.0 * (40.0 + 2.0 * 56.0) / (3.0 * (40.0 + 56.0))
    np.testing.assert_allclose(poly.centroid_xy, [0.0, centroid_y], atol=1e-12)
    probes = np.array([[0.0, 0.0], [27.9, 13.9], [28.1, 13.9], [0.0, -12.0]])
    assert poly.contains(probes).tolist() == [True, True, False, True]
    pts = poly.sample_uniform(np.random.default_rng(1), 20000)
    assert poly.contains(pts).all()
    np.testing.assert_allclose(pts.mean(axis=0), poly.centroid_xy, atol=0.3)
    assert np.mean(pts[:, 1] > 1.0) == pytest.approx(
        (14.0 - 1.0) * (48.0 + 56.0) / 2.0 / poly.area_m2, abs=0.015
    )


def test_regions_are_frozen_and_keep_their_own_copy() -> None:
    centre = np.array([1.0, 2.0])
    verts = CAMERA_TRAPEZOID.copy()
    disk, poly = Disk(centre, 3.0), ConvexPolygon(verts)
    centre[0] = 99.0
    verts[0, 0] = 99.0
    assert disk.center_xy[0] == 1.0
    assert poly.vertices_xy[0, 0] == -20.0
    with pytest.raises(ValueError, match="read-only"):
        disk.center_xy[0] = 5.0
    with pytest.raises(AttributeError):
        disk.radius_m = 4.0  # type: ignore[misc]
    assert disk == Disk(np.array([1.0, 2.0]), 3.0)
    assert hash(poly) == hash(ConvexPolygon(CAMERA_TRAPEZOID))
    assert poly != ConvexPolygon(CAMERA_TRAPEZOID + 1.0)


# ---------------------------------------------------------------------------------------------
# Bad input


def _one(mean: object, cov: object) -> None:
    region = Disk(np.zeros(2), 1.0)
    prob_in_region(np.asarray(mean, dtype=float), np.asarray(cov, dtype=float), region)


@pytest.mark.parametrize(
    ("mean", "cov", "message"),
    [
        ([[np.nan, 0.0]], [np.eye(2)], "means_xy contains NaN"),
        ([[0.0, 0.0]], [[[1.0, 0.0], [0.0, np.inf]]], "covs_xy contains NaN or infinite"),
        ([[0.0, 0.0]], [[[1.0, 2.0], [2.0, 1.0]]], "not positive definite"),
        ([[0.0, 0.0]], [[[-1.0, 0.0], [0.0, -1.0]]], "not positive definite"),
        ([[0.0, 0.0]], [[[1.0, 1.0], [1.0, 1.0]]], "not positive definite"),
        ([[0.0, 0.0]], [[[1.0, 0.5], [0.0, 1.0]]], "not symmetric"),
        ([[0.0, 0.0, 0.0]], [np.eye(2)], r"means_xy must have shape \(n, 2\)"),
        ([0.0, 0.0], [np.eye(2)], r"means_xy must have shape \(n, 2\)"),
        ([[0.0, 0.0]], [np.eye(3)], r"covs_xy must have shape \(1, 2, 2\)"),
        ([[0.0, 0.0], [1.0, 1.0]], [np.eye(2)], r"covs_xy must have shape \(2, 2, 2\)"),
    ],
)
def test_bad_gaussians_are_refused(mean: object, cov: object, message: str) -> None:
    with pytest.raises(InputError, match=message):
        _one(mean, cov)


@pytest.mark.parametrize(
    ("vertices", "message"),
    [
        ([[0.0, 0.0], [1.0, 0.0]], "at least 3 vertices"),
        ([[0.0, 0.0], [1.0, 0.0], [np.nan, 1.0]], "NaN"),
        ([[0.0, 0.0], [2.0, 0.0], [1.0, 0.5], [2.0, 2.0], [0.0, 2.0]], "not convex"),
        ([[0.0, 0.0], [1.0, 1.0], [2.0, 2.0]], "degenerate"),
        ([[0.0, 0.0], [1.0, 0.0], [1.0, 0.0], [0.0, 1.0]], "zero length"),
        ([[1.0, 1.0], [1.0, 1.0], [1.0, 1.0]], "zero length"),
        (np.array([[math.cos(a), math.sin(a)] for a in np.arange(5) * 4 * math.pi / 5]),
         "not simple"),  # a pentagram turns left at every vertex
        ([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], r"shape \(k, 2\)"),
    ],
)
def test_bad_polygons_are_refused(vertices: object, message: str) -> None:
    with pytest.raises(InputError, match=message):
        ConvexPolygon(np.asarray(vertices, dtype=float))


@pytest.mark.parametrize("radius", [0.0, -1.0, math.nan, math.inf])
def test_bad_disks_are_refused(radius: float) -> None:
    with pytest.raises(InputError, match="radius_m must be finite and > 0"):
        Disk(np.zeros(2), radius)
    with pytest.raises(InputError, match="center_xy"):
        Disk(np.array([0.0, np.nan]), 1.0)


def test_other_bad_arguments_are_refused() -> None:
    with pytest.raises(InputError, match="region must be a Disk or a ConvexPolygon"):
        prob_in_region(np.zeros((1, 2)), np.eye(2)[None], "disk")  # type: ignore[arg-type]
    with pytest.raises(InputError, match="sample count"):
        Disk(np.zeros(2), 1.0).sample_uniform(np.random.default_rng(0), -1)
    with pytest.raises(InputError, match=r"points_xy must have shape \(n, 2\)"):
        ConvexPolygon(CAMERA_TRAPEZOID).contains(np.zeros(2))


# ---------------------------------------------------------------------------------------------
# Properties

_sigma = st.floats(0.05, 20.0)
_coord = st.floats(-60.0, 60.0)


@st.composite
def _gaussian(draw: st.DrawFn) -> tuple[FloatArray, FloatArray]:
    sig1, sig2 = draw(_sigma), draw(_sigma)
    sig2 = min(max(sig2, sig1 / 100.0), sig1 * 100.0)
    cov = _cov(sig1, sig2, draw(st.floats(0.0, math.pi)))
    return np.array([draw(_coord), draw(_coord)]), cov


@st.composite
def _region(draw: st.DrawFn) -> Region:
    centre = np.array([draw(st.floats(-20.0, 20.0)), draw(st.floats(-20.0, 20.0))])
    if draw(st.booleans()):
        return Disk(centre, draw(st.floats(1.0, 30.0)))
    k = draw(st.integers(3, 12))
    angles = np.sort(np.array(draw(st.lists(st.floats(0.0, 2 * math.pi), min_size=k,
                                            max_size=k, unique=True))))
    axes = np.array([draw(st.floats(1.0, 30.0)), draw(st.floats(0.05, 30.0))])
    tilt = _rotation(draw(st.floats(0.0, math.pi)))
    verts = (np.column_stack([np.cos(angles), np.sin(angles)]) * axes) @ tilt.T + centre
    try:
        return ConvexPolygon(verts)
    except InputError:  # nearly coincident angles; fall back to a disk
        return Disk(centre, float(axes[0]))


@settings(deadline=None, max_examples=80)
@given(gaussians=st.lists(_gaussian(), min_size=1, max_size=6), region=_region())
def test_masses_are_probabilities_and_conditional_means_lie_in_the_region(
    gaussians: list[tuple[FloatArray, FloatArray]], region: Region
) -> None:
    means = np.array([g[0] for g in gaussians])
    covs = np.array([g[1] for g in gaussians])
    mass, mean_in = region_moments(means, covs, region)
    assert np.all(np.isfinite(mass))
    assert np.all((mass >= 0.0) & (mass <= 1.0))
    assert np.all(np.isfinite(mean_in))
    sure = mass > 1e-3
    if isinstance(region, Disk):
        dist = np.hypot(*(mean_in[sure] - region.center_xy).T)
        assert np.all(dist <= region.radius_m * (1.0 + 1e-6))
    else:
        v = region.vertices_xy
        edge = np.roll(v, -1, axis=0) - v
        rel = mean_in[sure][:, None, :] - v[None]
        cross = (edge[None, :, 0] * rel[..., 1] - edge[None, :, 1] * rel[..., 0]) / np.hypot(
            *edge.T
        )
        assert np.all(cross >= -1e-6)
