"""Dispersion models, camera channels and colour [conventions §7, §8]."""

from __future__ import annotations

from functools import partial

import colour
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from stairfit import model
from stairfit.model import materials, spectral

DEG = np.pi / 180


def test_bodurov_pla_index_at_550nm_is_1_4672():
    # the refractiveindex.info "formula 1" worked by hand: n^2 = 1 + 0.9809 / (1 - (C/0.55)^2)
    expected = np.sqrt(1 + 0.9809 / (1 - (0.2123719 / 0.55) ** 2))
    n = float(materials.PLA_BODUROV_2016(550.0))
    assert n == pytest.approx(expected, rel=1e-12)
    assert round(n, 4) == 1.4672
    # its dispersion is strong (the caveat in the README): n(450) - n(650) > 0.05
    assert float(materials.PLA_BODUROV_2016(450.0) - materials.PLA_BODUROV_2016(650.0)) > 0.05


def test_default_pla_is_the_papers_constant_and_delta_n_shifts_it():
    pla = model.get_material("PLA")
    lam = np.array([400.0, 550.0, 700.0])
    np.testing.assert_allclose(pla(lam), 1.46)
    np.testing.assert_allclose(model.refractive_index(pla, lam, 0.02), 1.48)


def test_unknown_material_names_the_known_ones():
    with pytest.raises(ValueError, match="pla-bodurov2016"):
        model.get_material("unobtainium")


def test_cauchy_tabulated_and_absorbing_models():
    c = materials.Cauchy(a=1.45, b_um2=0.004)
    assert float(c(500.0)) == pytest.approx(1.45 + 0.004 / 0.25)
    t = materials.Tabulated(wavelength_nm=(400.0, 600.0), n=(1.5, 1.4), k=(0.0, 0.02))
    assert complex(t(500.0)) == pytest.approx(1.45 + 0.01j)
    assert complex(t(300.0)) == pytest.approx(1.5 + 0.0j)  # held at the ends
    k = materials.ConstantIndex(n=1.5, k=0.1)
    assert jnp.iscomplexobj(k(np.array([500.0])))
    assert not jnp.iscomplexobj(materials.ConstantIndex(n=1.5)(np.array([500.0])))


@pytest.mark.parametrize("camera", spectral.CAMERAS)
def test_channel_weights_are_normalised_and_ordered(camera):
    cw = model.channel_weights(camera, "D65")
    np.testing.assert_allclose(cw.weights.sum(axis=1), 1.0)
    assert np.all(cw.weights >= 0)
    eff = cw.effective_nm
    assert eff[0] > eff[1] > eff[2]  # R, G, B
    if camera != "Sigma SDMerill (NPL)":  # a Foveon sensor: broad, overlapping layers
        assert 560 < eff[0] < 660 and 480 < eff[1] < 580 and 420 < eff[2] < 500
    col = cw.collapsed()
    np.testing.assert_allclose(col.weights, np.eye(3))
    np.testing.assert_allclose(col.wavelength_nm, eff)


def test_unknown_camera_and_illuminant_are_clear_errors():
    with pytest.raises(ValueError, match="known cameras"):
        spectral.camera_sensitivities("Brownie")
    with pytest.raises(ValueError, match="D65"):
        spectral.illuminant_spd("XYZ")


@pytest.mark.filterwarnings("ignore::colour.utilities.ColourRuntimeWarning")
@pytest.mark.parametrize("illuminant", ["D65", "A"])
def test_xyz_of_a_grey_reflector_matches_colour_science(illuminant):
    # independent path: colour.sd_to_XYZ (ASTM E308 integration) of a constant 5% reflector
    w = spectral.xyz_weights(illuminant)
    ours = w @ np.full(w.shape[1], 0.05)
    sd = colour.SpectralDistribution(dict.fromkeys(range(360, 831), 0.05), name="grey")
    ref = (
        colour.sd_to_XYZ(
            sd,
            colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"],
            colour.SDS_ILLUMINANTS[illuminant],
        )
        / 100.0
    )
    np.testing.assert_allclose(ours, ref, rtol=5e-3)
    assert ours[1] == pytest.approx(0.05, rel=1e-12)  # Y of a 5% reflector is 0.05 by design


def test_reflected_colour_is_warmer_under_a_and_differentiable():
    theta_o = jnp.array([0.0])
    lam = spectral.VISIBLE_NM

    @partial(jax.jit, static_argnums=1)  # one program (eager: one per operation)
    def xyz(delta_n, illuminant):
        n = model.refractive_index(materials.PLA_BODUROV_2016, lam, delta_n)
        d = model.diffuse_broadened(theta_o[:, None], 20 * DEG, n[None, :], 5 * DEG)
        return jnp.asarray(spectral.xyz_weights(illuminant)) @ d[0]

    xyz65, xyz_a = np.asarray(xyz(0.0, "D65")), np.asarray(xyz(0.0, "A"))
    x65, xa = xyz65[0] / xyz65.sum(), xyz_a[0] / xyz_a.sum()
    assert xa > x65 + 0.1  # incandescent light is much redder
    g = jax.grad(lambda dn: xyz(dn, "D65")[1])(0.0)
    assert np.isfinite(float(g)) and float(g) > 0  # higher index, more Fresnel reflection
