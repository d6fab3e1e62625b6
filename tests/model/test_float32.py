"""Where float32 is allowed, and the error bound that makes it allowed [conventions §10].

float32 is allowed for evaluating the forward model (plots, previews, the fast preset) when the
broadening is at least 0.5 deg. The error of a density is then dominated by the float32
rounding of angles (about 1.2e-7 rad near pi/2) amplified by 1 / sigma. Documented bound
(README, "Floating point"): max |rho32 - rho64| <= 5e-5 * max rho, and the diffuse integral
within 5e-5 of its maximum. Fitting always uses float64.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from stairfit import model

DEG = np.pi / 180
F32_BOUND = 5e-5
# One compiled program per dtype and shape (an eager call compiles each operation on its own);
# under jax.jit as eagerly, Python floats are weakly typed and keep float32 inputs in float32.
_BRDF = jax.jit(model.brdf)
_DIFFUSE = jax.jit(model.diffuse_broadened)
_BAND = partial(jax.jit, static_argnums=6)(model.band_density)


def _f32(*xs):
    return tuple(jnp.asarray(x, jnp.float32) for x in xs)


@pytest.mark.parametrize("sigma_deg", [0.5, 1.0, 5.0, 30.0])
@pytest.mark.parametrize("beta2_deg", [0.5, 10, 45, 60, 89.5])
def test_brdf_float32_within_documented_bound(sigma_deg, beta2_deg):
    ti, to = np.meshgrid(np.linspace(-90, 90, 181) * DEG, np.linspace(-90, 90, 721) * DEG)
    args = (ti, to, beta2_deg * DEG, 1.46, sigma_deg * DEG)
    r64 = np.asarray(_BRDF(*args))
    r32 = _BRDF(*_f32(*args))
    assert r32.dtype == jnp.float32  # stays in float32 all the way
    err = np.abs(np.asarray(r32, np.float64) - r64)
    assert err.max() <= F32_BOUND * r64.max()


@pytest.mark.parametrize("sigma_deg", [0.5, 5.0])
def test_diffuse_and_band_density_float32_within_bound(sigma_deg):
    to = np.linspace(-90, 90, 361) * DEG
    d64 = np.asarray(_DIFFUSE(to, 10 * DEG, 1.46, sigma_deg * DEG))
    d32 = _DIFFUSE(*_f32(to, 10 * DEG, 1.46, sigma_deg * DEG))
    assert d32.dtype == jnp.float32
    assert np.abs(np.asarray(d32, np.float64) - d64).max() <= F32_BOUND * d64.max()

    n_obs = 19
    ti, to = np.zeros(n_obs), np.linspace(-80, 80, n_obs) * DEG
    b2, n = np.full(n_obs, 30 * DEG), np.full((n_obs, 3), 1.46)
    w = np.full((n_obs, 3), 1 / 3)
    ap = model.Aperture(0.01, 0.02, 3)
    b64 = np.asarray(_BAND(ti, to, b2, n, w, sigma_deg * DEG, ap))
    b32 = _BAND(*_f32(ti, to, b2, n, w, sigma_deg * DEG), ap)
    assert b32.dtype == jnp.float32
    assert np.abs(np.asarray(b32, np.float64) - b64).max() <= F32_BOUND * b64.max()


def test_float32_is_not_allowed_for_tiny_broadening():
    # the reason for the 0.5 deg limit: at sigma = 0.01 deg float32 angle rounding is visible
    to = np.linspace(29.9, 30.1, 4001) * DEG
    args = (0.0, to, 15 * DEG, 1.46, 0.01 * DEG)
    r64 = np.asarray(_BRDF(*args))
    r32 = np.asarray(_BRDF(*_f32(*args)), np.float64)
    assert np.abs(r32 - r64).max() > F32_BOUND * r64.max()
