"""The paper's own facts about the sharp staircase (Pranovich et al. 2020, Secs. 2-3)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from stairfit import model

DEG = np.pi / 180
PAPER_WEDGES_DEG = (10, 20, 30, 40, 45, 60)
# One compiled program per shape (an eager call compiles each operation on its own).
_LOBE_WEIGHTS = jax.jit(model.lobe_weights)
_SHARP_LOBES = jax.jit(model.sharp_lobes)
_BRDF = jax.jit(model.brdf)
_DIFFUSE_SHARP = jax.jit(model.diffuse_sharp, static_argnames="cosine_weighted")


def test_flat_surface_normal_incidence_is_0_0350():
    # Paper Fig. 5 "material": ((n - 1) / (n + 1))^2 at n = 1.46 = 0.0350 (to 4 decimals).
    r = float(model.flat_reflectance(0.0, 1.46))
    assert r == pytest.approx(((1.46 - 1) / (1.46 + 1)) ** 2, rel=1e-12)
    assert round(r, 4) == 0.0350


def test_table1_step_lengths_from_150um_layers():
    # Table 1: l1 = 150 um; l2 = l1 cot(beta2). Independent arithmetic here, not model code.
    for b in PAPER_WEDGES_DEG:
        cell = model.unit_cell(b * DEG, 150.0)
        assert float(cell.l2_um) == pytest.approx(150.0 / np.tan(b * DEG), rel=1e-12)
        assert float(cell.l_um) == pytest.approx(np.hypot(150.0, 150.0 / np.tan(b * DEG)))
        assert float(cell.beta1_rad) == pytest.approx((90 - b) * DEG)


def test_30_deg_cell_is_about_1_7_times_the_60_deg_cell():
    # Sec. 3.3: "The unit cell of the 30 deg wedge is approximately 1.7 times bigger".
    ratio = float(model.unit_cell(30 * DEG, 150).l_um / model.unit_cell(60 * DEG, 150).l_um)
    assert ratio == pytest.approx(np.sqrt(3), rel=1e-12)
    assert 1.65 < ratio < 1.8


@pytest.mark.parametrize("beta2_deg", PAPER_WEDGES_DEG)
def test_weights_are_fractions_that_sum_to_one(beta2_deg):
    theta_i = np.linspace(-90, 90, 3601) * DEG
    w = np.asarray(_LOBE_WEIGHTS(theta_i, beta2_deg * DEG))
    assert np.all(w >= 0) and np.all(w <= 1)
    np.testing.assert_allclose(w.sum(-1), 1.0, atol=1e-12)
    lobes = _SHARP_LOBES(theta_i, beta2_deg * DEG, 1.46)
    ratio = np.asarray(lobes.ratio)
    assert np.all(ratio >= 0) and np.all(ratio <= 1)


@pytest.mark.parametrize("beta2_deg", PAPER_WEDGES_DEG)
def test_retroreflection_only_between_minus_beta2_and_beta1(beta2_deg):
    b2 = beta2_deg * DEG
    b1 = np.pi / 2 - b2
    theta_i = np.linspace(-90, 90, 7201) * DEG
    retro = np.asarray(_LOBE_WEIGHTS(theta_i, b2))[:, 2]
    inside = (theta_i > -b2 + 1e-9) & (theta_i < b1 - 1e-9)
    assert np.all(retro[~inside] <= 1e-12)
    assert np.all(retro[inside] > 0)
    # maximal (everything retro) where the groove is seen symmetrically: theta_i = beta1 - beta2
    w = np.asarray(_LOBE_WEIGHTS(b1 - b2, b2))
    np.testing.assert_allclose(w, [0, 0, 1], atol=1e-12)


def test_45_deg_wedge_is_symmetric_about_theta_o_0():
    theta_i = np.linspace(-89, 89, 179) * DEG
    theta_o = np.linspace(-90, 90, 181) * DEG
    T, Th_o = np.meshgrid(theta_i, theta_o, indexing="ij")
    rho = np.asarray(_BRDF(T, Th_o, 45 * DEG, 1.46, 5 * DEG))
    np.testing.assert_allclose(rho, rho[::-1, ::-1], rtol=1e-10, atol=1e-14)
    d = np.asarray(_DIFFUSE_SHARP(theta_o, 45 * DEG, 1.46))
    np.testing.assert_allclose(d, d[::-1], rtol=1e-10, atol=1e-14)


def test_30_and_60_deg_wedges_are_mirror_images():
    theta_i = np.linspace(-89, 89, 179) * DEG
    theta_o = np.linspace(-90, 90, 181) * DEG
    T, Th_o = np.meshgrid(theta_i, theta_o, indexing="ij")
    rho30 = np.asarray(_BRDF(T, Th_o, 30 * DEG, 1.46, 5 * DEG))
    rho60 = np.asarray(_BRDF(T, Th_o, 60 * DEG, 1.46, 5 * DEG))
    np.testing.assert_allclose(rho30, rho60[::-1, ::-1], rtol=1e-10, atol=1e-14)
    assert not np.allclose(rho30, rho60, rtol=1e-3)  # but they are not identical


@pytest.mark.parametrize("beta2_deg", [10, 20, 30, 40])
def test_fig5_minimum_at_minus_90_plus_2_beta2(beta2_deg):
    # Fig. 5: the tread lobe reaches theta_o = -90 + 2 beta2 from theta_i = -90, where
    # "there is no contribution"; just below, its source would be below the horizon. The riser
    # lobe from theta_i -> +90 lands on the same theta_o (90 - 2 beta1 = -90 + 2 beta2) and
    # vanishes on the other side. Without a cosine weight the curve jumps there.
    edge = (-90 + 2 * beta2_deg) * DEG
    eps = 1e-7
    d = np.asarray(_DIFFUSE_SHARP(jnp.array([edge - eps, edge + eps]), beta2_deg * DEG, 1.46))

    def fresnel(gamma_deg):  # unpolarised, computed independently of the model
        c = np.cos(gamma_deg * DEG)
        s = np.sqrt(1.46**2 - 1 + c**2)
        return 0.5 * (((c - s) / (c + s)) ** 2 + ((1.46**2 * c - s) / (1.46**2 * c + s)) ** 2)

    # right: tread at local angle 90 - beta2 (weight 1, regime A); left: riser at local angle
    # beta2 (weight 1, regime C)
    assert d[1] - d[0] == pytest.approx(fresnel(90 - beta2_deg) - fresnel(beta2_deg), rel=1e-4)
    # The grid point where the curve changes fastest is the edge.
    grid = np.linspace(edge - 10 * DEG, edge + 10 * DEG, 2001)
    dg = np.asarray(_DIFFUSE_SHARP(grid, beta2_deg * DEG, 1.46))
    assert abs(grid[np.argmax(np.diff(dg)) + 1] - edge) < 0.011 * DEG
    # With the physical cos(theta_i) weight the contribution from theta_i -> -90 vanishes
    # continuously, and the edge is a true local minimum of the curve.
    dc = np.asarray(_DIFFUSE_SHARP(grid, beta2_deg * DEG, 1.46, cosine_weighted=True))
    assert abs(grid[np.argmin(dc)] - edge) < 0.011 * DEG
    assert dc.min() < 0.8 * dc[0] and dc.min() < 0.8 * dc[-1]


def test_retro_fresnel_is_per_polarisation_product_not_product_of_unpolarised():
    # Sec. 2: "half of each type of polarisation (also in the case of retroreflection...)"
    theta_i, b2, n = -0.2, 30 * DEG, 1.46
    f = np.asarray(model.lobe_fresnel(theta_i, b2, n))
    u = b2 + theta_i
    t, r = model.fresnel_sp(np.cos(u), n), model.fresnel_sp(np.sin(u), n)
    per_pol = 0.5 * (t.s * r.s + t.p * r.p)
    unpol = 0.25 * (t.s + t.p) * (r.s + r.p)
    assert f[2] == pytest.approx(float(per_pol), rel=1e-12)
    assert abs(float(per_pol) - float(unpol)) > 0.05 * float(per_pol)  # the choice matters here
