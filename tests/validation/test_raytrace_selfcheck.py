"""Checks of the independent ray tracer (tests/raytrace.py) against facts that need no model.

Geometry and optics only: energy conservation for a perfect mirror, the flat-surface Fresnel
limit, the law of reflection and the 90-degree corner reflector, symmetry of the 45-degree
wedge, projected areas at normal incidence, and the rounded profile's arcs checked two ways
(true circles against polylines, and r -> 0 against the sharp profile). Conventions:
[conventions §1-§3, §6].
"""

from __future__ import annotations

import numpy as np
import pytest
from raytrace import (
    ESCAPED,
    PRIMITIVE_NAMES,
    TRAPPED,
    Staircase,
    fresnel_sp,
    histogram,
    lobes,
    paths,
    total_reflectance,
    trace,
)

L1 = 150.0
EDGES_2DEG = np.arange(-90.0, 90.0 + 1e-9, 2.0)
# Symmetric odd edges (-91, -89, ..., 91): mirror images of bins are bins, and the sharp lobes
# of the non-integer angles below never fall on an edge.
EDGES_ODD = np.arange(-91.0, 91.0 + 1e-9, 2.0)


def fresnel_sine_tangent_laws(theta_rad: np.ndarray, n: float) -> tuple[np.ndarray, np.ndarray]:
    """Fresnel's sine and tangent laws (real n > 1, 0 < theta < 90 deg): a second, independent
    textbook form, R_s = sin^2(i - t) / sin^2(i + t), R_p = tan^2(i - t) / tan^2(i + t)."""
    t = np.arcsin(np.sin(theta_rad) / n)
    return (
        np.sin(theta_rad - t) ** 2 / np.sin(theta_rad + t) ** 2,
        np.tan(theta_rad - t) ** 2 / np.tan(theta_rad + t) ** 2,
    )


# ------------------------------------------------------------------------------ geometry, Fresnel


@pytest.mark.parametrize("beta2_deg", [0.5, 10, 30, 45, 60, 89.5])
def test_period_is_the_distance_between_tips(beta2_deg):
    st = Staircase(beta2_deg, L1)
    assert st.period_um == pytest.approx(np.hypot(st.l1_um, st.l2_um), rel=1e-12)
    assert st.l2_um == pytest.approx(L1 / np.tan(np.deg2rad(beta2_deg)), rel=1e-12)


def test_fresnel_normal_incidence_and_brewster():
    R_s, R_p = fresnel_sp(np.array([1.0]), 1.46)
    assert R_s[0] == pytest.approx(((1.46 - 1) / 2.46) ** 2, rel=1e-12)
    assert R_p[0] == pytest.approx(R_s[0], rel=1e-12)
    assert round(float(R_s[0]), 4) == 0.0350
    brewster = np.arctan(1.46)
    R_s, R_p = fresnel_sp(np.array([np.cos(brewster)]), 1.46)
    assert R_p[0] < 1e-25 and R_s[0] > 0.05
    R_s, R_p = fresnel_sp(np.array([0.0]), 1.46)  # grazing
    assert R_s[0] == pytest.approx(1.0) and R_p[0] == pytest.approx(1.0)


@pytest.mark.parametrize("n", [1.0001, 1.46, 2.4])
def test_fresnel_matches_the_sine_and_tangent_laws(n):
    theta = np.deg2rad(np.linspace(0.5, 89.5, 179))
    R_s, R_p = fresnel_sp(np.cos(theta), n)
    ref_s, ref_p = fresnel_sine_tangent_laws(theta, n)
    np.testing.assert_allclose(R_s, ref_s, rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(R_p, ref_p, rtol=1e-7, atol=1e-15)  # R_p ~ 0 near Brewster


@pytest.mark.parametrize("n", [1.5 + 0.3j, 0.2 + 3.0j, 1.46 + 1e-6j])
def test_fresnel_complex_index_is_physical(n):
    R_s, R_p = fresnel_sp(np.array([1.0]), n)
    assert R_s[0] == pytest.approx(abs((n - 1) / (n + 1)) ** 2, rel=1e-12)
    cos = np.cos(np.deg2rad(np.linspace(0, 90, 901)))
    R_s, R_p = fresnel_sp(cos, n)
    # the wrong branch of the complex square root would give R > 1 (a growing wave)
    assert np.all((R_s >= 0) & (R_s <= 1 + 1e-12)) and np.all((R_p >= 0) & (R_p <= 1 + 1e-12))
    assert np.all(R_s >= R_p - 1e-12)  # s never below p for an isotropic medium


def test_perfect_mirror_flag():
    R_s, R_p = fresnel_sp(np.linspace(0, 1, 5), None)
    assert np.all(R_s == 1) and np.all(R_p == 1)


def test_invalid_geometry_and_angles_are_refused():
    with pytest.raises(ValueError, match=r"min\(l1, l2\)"):
        Staircase(60, L1, tip_radius_um=60, fillet_radius_um=40)  # l2 = 86.6 um
    with pytest.raises(ValueError, match="tip_radius_um"):
        Staircase(30, L1, tip_radius_um=-1)
    with pytest.raises(ValueError, match="beta2_deg"):
        Staircase(90, L1)
    with pytest.raises(ValueError, match="arc_segments"):
        Staircase(30, L1, tip_radius_um=10, arc_segments=0)
    with pytest.raises(ValueError, match="grazing"):
        trace(Staircase(30, L1), 90.0, 1.46, n_rays=10)
    Staircase(45, L1, tip_radius_um=L1)  # exactly at the limit: both facets vanish, allowed


# ------------------------------------------------------------------------------ energy, counting

MIRROR_CASES = [
    (10, 0.0, 0.0),
    (45, 0.0, 0.0),
    (60, 0.0, 0.0),
    (30, 0.2 * L1, 0.1 * L1),
    (10, 0.05 * L1, 0.05 * L1),
    (60, 0.4 * L1, 0.0),
    (45, L1, 0.0),  # arcs only: every facet is used up
    (30, 0.0, 0.5 * L1),  # fillets only
]


@pytest.mark.parametrize(("beta2_deg", "r", "rf"), MIRROR_CASES)
def test_perfect_mirror_conserves_energy(beta2_deg, r, rf):
    st = Staircase(beta2_deg, L1, r, rf)
    for theta in (-89.9, -50.0, -beta2_deg, 0.0, 90 - 2 * beta2_deg, 37.0, 89.9):
        res = trace(st, theta, None, n_rays=20_000)
        assert np.all(res.status == ESCAPED), (theta, res.n_trapped, res.n_lost)
        assert total_reflectance(res) == pytest.approx(1.0, abs=1e-12)
        assert np.all((res.theta_o_deg > -90) & (res.theta_o_deg < 90))


@pytest.mark.parametrize("beta2_deg", [10, 30, 45, 60])
def test_every_sharp_ray_is_accounted_for(beta2_deg):
    st = Staircase(beta2_deg, L1)
    allowed = {("tread",), ("riser",), ("tread", "riser"), ("riser", "tread")}
    for theta in np.arange(-89.5, 90, 7.0):
        res = trace(st, theta, 1.46, n_rays=20_000)
        assert res.n_lost == 0 and res.n_trapped == 0
        assert np.all((res.n_bounces >= 1) & (res.n_bounces <= 2))
        p = paths(res)
        assert set(p) <= allowed, set(p) - allowed
        assert sum(s.weight for s in p.values()) == pytest.approx(1.0, abs=1e-12)
        assert sum(lo.weight for lo in lobes(res)) == pytest.approx(1.0, abs=1e-12)
        assert len(lobes(res)) <= 3
        # reflected power never exceeds what one reflection at the most grazing facet allows
        assert np.all(res.power <= 1.0)


def test_rays_still_bouncing_after_max_bounces_are_reported():
    # The 45-degree groove at normal incidence retroreflects everything in two bounces.
    res = trace(Staircase(45, L1), 0.0, 1.46, n_rays=10_000, max_bounces=1)
    assert res.n_trapped == 10_000 and res.n_lost == 0
    assert np.all(res.status == TRAPPED) and total_reflectance(res) == 0.0
    assert np.all(np.isnan(res.theta_o_deg))


# ------------------------------------------------------------------------------ optics facts


@pytest.mark.parametrize("theta_deg", [-70.0, -30.0, 0.0, 20.0, 55.0])
def test_flat_limit_is_the_fresnel_reflectance_of_a_flat_surface(theta_deg):
    # beta2 = 1e-4 deg: the tread is the whole face up to ~ sin(beta2) ~ 2e-6 of the rays.
    res = trace(Staircase(1e-4, L1), theta_deg, 1.46, n_rays=20_000)
    if theta_deg == 0:
        ref_s = ref_p = ((1.46 - 1) / 2.46) ** 2
    else:
        ref_s, ref_p = fresnel_sine_tangent_laws(np.deg2rad(abs(theta_deg)), 1.46)
    esc = res.escaped
    assert np.sum(res.power_s[esc]) / res.n_rays == pytest.approx(ref_s, abs=1e-5)
    assert np.sum(res.power_p[esc]) / res.n_rays == pytest.approx(ref_p, abs=1e-5)
    main = max(lobes(res, tol_deg=1e-3), key=lambda lo: lo.weight)
    assert main.weight > 0.9999
    assert main.theta_o_deg == pytest.approx(theta_deg, abs=1e-3)  # mirror direction


@pytest.mark.parametrize("beta2_deg", [10, 30, 45, 60])
def test_law_of_reflection_and_retroreflection_of_the_sharp_groove(beta2_deg):
    beta1 = 90 - beta2_deg
    st = Staircase(beta2_deg, L1)
    for theta in np.arange(-88.3, 90, 3.7):
        p = paths(trace(st, theta, 1.46, n_rays=20_000))
        # a facet with normal at alpha sends theta_i to theta_i + 2 alpha [conventions §2]
        expected = {
            ("tread",): theta + 2 * beta2_deg,
            ("riser",): theta - 2 * beta1,
            ("tread", "riser"): -theta,  # two mirrors at 90 degrees reverse the ray
            ("riser", "tread"): -theta,
        }
        for key, s in p.items():
            assert s.theta_o_min_deg == pytest.approx(expected[key], abs=1e-9), (theta, key)
            assert s.theta_o_max_deg == pytest.approx(expected[key], abs=1e-9), (theta, key)
        two_bounce = sum(s.weight for k, s in p.items() if len(k) == 2)
        if theta < -beta2_deg or theta > beta1:
            assert two_bounce == 0  # only one facet faces the light
    # seen along the groove's bisector the 2-D corner reflector returns every ray
    res = trace(st, beta1 - beta2_deg, 1.46, n_rays=20_000)
    assert np.all(res.n_bounces == 2)
    assert np.allclose(res.theta_o_deg, -(beta1 - beta2_deg), atol=1e-9)


@pytest.mark.parametrize(("r", "rf"), [(0.0, 0.0), (0.2 * L1, 0.1 * L1), (0.35 * L1, 0.0)])
@pytest.mark.parametrize("beta2_deg", [10, 30, 60])
def test_first_hits_at_normal_incidence_are_the_horizontal_extents(beta2_deg, r, rf):
    # Light straight down the face normal sees every point of the profile (a graph z = f(x)),
    # so each primitive receives its x extent divided by the period.
    st = Staircase(beta2_deg, L1, r, rf)
    b2 = np.deg2rad(beta2_deg)
    arc = np.sin(b2) + np.cos(b2)  # x extent of a 90-degree arc with normals in [b2-90, b2]
    extent = {
        "tip": r * arc,
        "tread": (st.l2_um - r - rf) * np.cos(b2),
        "fillet": rf * arc,
        "riser": (L1 - r - rf) * np.sin(b2),
    }
    n_rays = 40_000
    res = trace(st, 0.0, 1.46, n_rays=n_rays)
    for k, name in enumerate(PRIMITIVE_NAMES):
        frac = np.mean(res.first_hit == k)
        # midpoint stratification: at most one ray per boundary of each (<= 3) interval
        assert frac == pytest.approx(extent[name] / st.period_um, abs=3.0 / n_rays), name


@pytest.mark.parametrize(("r", "rf"), [(0.0, 0.0), (0.2 * L1, 0.1 * L1), (0.4 * L1, 0.0)])
@pytest.mark.parametrize("theta_deg", [-63.7, -20.3, 7.9, 41.1])
def test_45_deg_wedge_is_mirror_symmetric(theta_deg, r, rf):
    # The 45-degree cell is symmetric about its groove: theta_i -> -theta_i mirrors theta_o.
    n_rays = 40_000
    st = Staircase(45, L1, r, rf)
    a = trace(st, theta_deg, 1.5 + 0.3j, n_rays=n_rays)
    b = trace(st, -theta_deg, 1.5 + 0.3j, n_rays=n_rays)
    assert total_reflectance(a) == pytest.approx(total_reflectance(b), rel=1e-12)
    # the mirrored ray grid is the same grid, so bins can differ only by rays that land
    # within rounding of an edge: allow two rays' power per bin
    np.testing.assert_allclose(
        histogram(a, EDGES_ODD), histogram(b, EDGES_ODD)[::-1], rtol=0, atol=2.0 / n_rays
    )


# ------------------------------------------------------------------------------ arcs


@pytest.mark.parametrize(
    ("beta2_deg", "r", "rf", "theta_deg"),
    [(30, 0.2 * L1, 0.1 * L1, 17.0), (30, 0.2 * L1, 0.1 * L1, -89.9), (60, 0.4 * L1, 0.0, -40.0)],
)
def test_polyline_arcs_converge_to_true_circles(beta2_deg, r, rf, theta_deg):
    # Chords of 90/M degrees quantise the arcs' normals, so the polyline's distribution of
    # theta_o differs from the circle's at first order in 1/M. Measured by the Wasserstein-1
    # distance (degrees; the area between the two normalised cumulative distributions, which
    # unlike 2-degree bins does not depend on how the quantised directions meet the bin edges),
    # quadrupling M must cut it by about 4 (measured 3.4-5.5; asserted > 3), and at M = 1024 it
    # is below 0.1 deg (measured 0.015-0.05). The 2-degree histograms then agree within 1% of
    # the total per bin (measured 0.1%, but 0.64% at theta_i = -89.9 deg, where nearly all light
    # hits the tip arcs near their tops and the chords' discrete directions bunch at the scale
    # of a bin), and the total reflectance within 1e-4 relative.
    n_rays = 20_000
    exact = trace(Staircase(beta2_deg, L1, r, rf), theta_deg, 1.46, n_rays=n_rays)
    fine = np.arange(-90.0, 90.0 + 1e-9, 0.01)
    cdf_exact = np.cumsum(histogram(exact, fine)) / total_reflectance(exact)
    w1 = {}
    for m in (64, 256, 1024):
        poly = trace(
            Staircase(beta2_deg, L1, r, rf, arc_segments=m), theta_deg, 1.46, n_rays=n_rays
        )
        assert poly.n_lost == 0 and poly.n_trapped == 0
        cdf = np.cumsum(histogram(poly, fine)) / total_reflectance(exact)
        w1[m] = np.abs(cdf - cdf_exact).sum() * 0.01
    assert w1[64] > 3 * w1[256] > 9 * w1[1024], w1
    assert w1[1024] < 0.1, w1
    h_exact, h = histogram(exact, EDGES_2DEG), histogram(poly, EDGES_2DEG)
    assert np.abs(h - h_exact).max() < 0.01 * h_exact.sum()
    assert total_reflectance(poly) == pytest.approx(total_reflectance(exact), rel=1e-4)


@pytest.mark.parametrize("beta2_deg", [30, 60])
@pytest.mark.parametrize("theta_deg", [-50.3, 10.1, 70.7])
def test_arcs_shrinking_to_zero_recover_the_sharp_profile(beta2_deg, theta_deg):
    # Rays that touch an arc of radius r are a fraction O(r / period) of all rays; the
    # histogram's L1 distance to the sharp one must shrink with r, linearly.
    n_rays = 40_000
    sharp = histogram(trace(Staircase(beta2_deg, L1), theta_deg, 1.46, n_rays=n_rays), EDGES_ODD)
    dist = {}
    for r in (1.0, 0.1, 0.01):  # um, against l1 = 150 um
        st = Staircase(beta2_deg, L1, tip_radius_um=r, fillet_radius_um=r)
        dist[r] = np.abs(histogram(trace(st, theta_deg, 1.46, n_rays=n_rays), EDGES_ODD) - sharp)
        dist[r] = dist[r].sum()
    assert dist[1.0] > 5 * dist[0.1] > 0, dist
    assert dist[0.01] < 1e-4 * sharp.sum() * 10, dist  # r / period ~ 1e-4: ~4 rays of 40_000
