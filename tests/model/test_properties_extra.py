"""Property-based stability: what tests/model/test_properties.py leaves out of issue 7's list.

tests/model/test_properties.py covers `sharp_lobes`, `brdf` (real and complex n), the diffuse
integrals and the float32 bound of `brdf`. Added here, over the same domain (angles in [-90, 90]
deg with the ends drawn on purpose, sigma from 1e-6 rad, n from 1.0001 to 3 and complex n):

* wedge angles right at the open ends of (0, 90) deg (1e-9 rad from either end);
* complex n in the lobes (Fresnel factors in [0, 1], gradients in n' and k);
* the measurement model the fits use (`band_density` with a finite aperture, and `radiance`
  at grazing views): finite values and gradients, non-negative;
* energy: the broadened density integrates over theta_o to the sum of the lobes' ratios, <= 1
  [conventions §4, §5];
* continuity of the broadened density across the regime boundaries, with a bound scaled to
  the step (the density's Lipschitz constant in theta_i);
* the float32 bound of tests/model/test_float32.py for `band_density`;
* the rounded-edge model: edge radius from 0 to `max_edge_radius`, finite values and gradients
  (few examples through one compiled function; it is slow to compile).

Every function is compiled once with fixed shapes; examples only change values.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from checks import all_finite
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from stairfit import model

HALF = float(np.pi / 2)
DEG = float(np.pi / 180)
SETTINGS = settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.too_slow])

angles = st.one_of(
    st.sampled_from([-HALF, HALF, 0.0, -HALF + 1e-12, HALF - 1e-12]),
    st.floats(-HALF, HALF),
)
beta2_ends = st.one_of(
    st.sampled_from([1e-9, 1e-6, HALF - 1e-6, HALF - 1e-9]),
    st.floats(1e-9, HALF - 1e-9),
)
beta2s = st.floats(1e-4, HALF - 1e-4)
sigmas = st.floats(1e-6, 1.5)
real_n = st.floats(1.0001, 3.0)
APERTURE = model.Aperture(2.5 * DEG, 1.5 * DEG, 3)


@jax.jit
def _lobes_and_brdf(ti, to, b2, n, s):
    def total(ti, to, b2, n, s):
        return jnp.sum(model.sharp_lobes(ti, b2, n).ratio) + model.brdf(ti, to, b2, n, s)

    return (
        model.sharp_lobes(ti, b2, n),
        model.brdf(ti, to, b2, n, s),
        jax.grad(total, argnums=(0, 1, 2, 3, 4))(ti, to, b2, n, s),
    )


@SETTINGS
@given(ti=angles, to=angles, b2=beta2_ends, n=real_n, s=sigmas)
def test_wedge_angles_at_the_open_ends(ti, to, b2, n, s):
    lobes, rho, grads = _lobes_and_brdf(ti, to, b2, n, s)
    assert all_finite(lobes) and all_finite(rho) and all_finite(grads)
    w = np.asarray(lobes.weight)
    assert np.all(w >= 0) and abs(w.sum() - 1) < 1e-12
    assert 0 <= float(np.sum(lobes.ratio)) <= 1 + 1e-12
    assert float(rho) >= 0


@jax.jit
def _complex_lobes(ti, b2, nr, k):
    def total(nr, k):
        return jnp.sum(model.sharp_lobes(ti, b2, nr + 1j * k).ratio)

    return model.sharp_lobes(ti, b2, nr + 1j * k), jax.grad(total, argnums=(0, 1))(nr, k)


@SETTINGS
@given(ti=angles, b2=beta2s, nr=real_n, k=st.floats(0.0, 5.0))
def test_lobes_with_complex_index(ti, b2, nr, k):
    lobes, grads = _complex_lobes(ti, b2, nr, k)
    assert all_finite(lobes) and all_finite(grads)
    f = np.asarray(lobes.fresnel)
    assert np.all(f >= 0) and np.all(f <= 1 + 1e-12)
    assert float(np.sum(lobes.ratio)) <= 1 + 1e-12


@jax.jit
def _measurement(ti, to, b2, n, s):
    n3 = n + jnp.array([[0.0, 0.01, 0.02]])  # three wavelengths of one channel
    w3 = jnp.array([[0.2, 0.5, 0.3]])

    def value(ti, to, b2, n3, s):
        dens = model.band_density(ti[None], to[None], b2[None], n3, w3, s, APERTURE)
        return jnp.sum(model.radiance(dens, ti[None], to[None], 2.0, 0.01))

    dens = model.band_density(ti[None], to[None], b2[None], n3, w3, s, APERTURE)
    return (
        dens,
        value(ti, to, b2, n3, s),
        jax.grad(value, argnums=(0, 1, 2, 3, 4))(ti, to, b2, n3, s),
    )


@SETTINGS
@given(ti=angles, to=angles, b2=beta2s, n=real_n, s=sigmas)
def test_measurement_model_finite_nonnegative_and_differentiable(ti, to, b2, n, s):
    # band_density with a finite aperture (nodes clipped at +-90 deg) and the radiance of
    # conventions §9, whose cos(theta_o) is floored at grazing views
    dens, val, grads = _measurement(ti, to, b2, n, s)
    assert all_finite(dens) and all_finite(val) and all_finite(grads)
    assert float(dens[0]) >= 0 and float(val) >= 0


_GRID = np.linspace(-HALF, HALF, 40_001)  # theta_o nodes for the energy integral


@jax.jit
def _integrated(ti, b2, n, s):
    rho = model.brdf(ti, jnp.asarray(_GRID), b2, n, s)
    h = _GRID[1] - _GRID[0]
    integral = h * (jnp.sum(rho) - 0.5 * (rho[0] + rho[-1]))  # trapezoid
    return integral, jnp.sum(model.sharp_lobes(ti, b2, n).ratio)


@settings(max_examples=60, deadline=None)
@given(ti=angles, b2=beta2s, nr=real_n, k=st.floats(0.0, 1.0), s=st.floats(0.5 * DEG, 1.5))
def test_broadened_density_conserves_energy(ti, b2, nr, k, s):
    # the integral of rho over theta_o is the total reflectance (sum of ratios) <= 1
    # [conventions §4, §5]. rho is smooth on [-90, 90] deg (the truncation is at the ends), so
    # the trapezoid error is about h^2 / 12 |rho'(b) - rho'(a)| (Euler-Maclaurin) with
    # h = 7.9e-5 rad and |rho'| <= 3 x peak / sigma <= 3 x 92 / 0.0087 per rad^2 at sigma =
    # 0.5 deg: at most 3.3e-5, hence the tolerance 5e-5
    integral, total = _integrated(ti, b2, nr + 1j * k, s)
    assert abs(float(integral) - float(total)) <= 5e-5
    assert float(total) <= 1 + 1e-12


@st.composite
def boundary(draw: st.DrawFn, beta2: float) -> float:
    # the regime boundaries -beta2, beta1 - beta2, beta1 [conventions §3]
    return draw(st.sampled_from([-beta2, HALF - 2 * beta2, HALF - beta2]))


@jax.jit
def _brdf_pair(edge, h, to, b2, n, s):
    lo = model.brdf(jnp.clip(edge - h, -HALF, HALF), to, b2, n, s)
    hi = model.brdf(jnp.clip(edge + h, -HALF, HALF), to, b2, n, s)
    return lo, hi


@settings(max_examples=100, deadline=None)
@given(
    data=st.data(),
    b2=st.floats(0.01, HALF - 0.01),
    n=real_n,
    to=angles,
    s=st.floats(1e-3, 1.5),
    h=st.sampled_from([1e-9, 1e-7, 1e-5]),
)
def test_broadened_density_continuous_across_regime_boundaries(data, b2, n, to, s, h):
    edge = data.draw(boundary(b2))
    lo, hi = (float(x) for x in _brdf_pair(edge, h, to, b2, n, s))
    # |d rho / d theta_i| <= sum over lobes of |d ratio| K + ratio |dK / d centre| + the
    # renormalisation's change; with K <= K_max = 2 / (sqrt(2 pi) s), |d ratio / d theta_i| <=
    # 4 / min(sin, cos)(beta2) (tests/model/test_properties.py) and |dK / dc| <= (1 / s + 2 / s)
    # K_max (Gaussian slope, and the truncation mass's own slope), each of 3 lobes:
    k_max = 2 / (np.sqrt(2 * np.pi) * s)
    lipschitz = 3 * k_max * (4 / min(np.sin(b2), np.cos(b2)) + 3 / s)
    assert abs(hi - lo) <= 2 * h * lipschitz + 1e-12


@jax.jit
def _band(ti, to, b2, n, s):
    nn = jnp.full((1, 3), n)
    w = jnp.full((1, 3), 1 / 3, ti.dtype)
    return model.band_density(ti[None], to[None], b2[None], nn, w, s, APERTURE)[0]


@SETTINGS
@given(ti=angles, to=angles, b2=beta2s, n=real_n, s=st.floats(0.5 * DEG, 1.5))
def test_band_density_float32_within_documented_bound(ti, to, b2, n, s):
    # tests/model/test_float32.py: |rho32 - rho64| <= 5e-5 x max rho for sigma >= 0.5 deg; as in
    # tests/model/test_properties.py, max rho <= 3 lobes x 2 / (sqrt(2 pi) sigma)
    f64 = float(_band(*(jnp.float64(x) for x in (ti, to, b2, n, s))))
    f32 = _band(*(jnp.float32(x) for x in (ti, to, b2, n, s)))
    assert f32.dtype == jnp.float32
    peak = 3 * 2 / (np.sqrt(2 * np.pi) * s)
    assert abs(float(f32) - f64) <= 5e-5 * peak


# --------------------------------------------------------------------------------------------
# The rounded-edge model
# --------------------------------------------------------------------------------------------

_TO = jnp.array([-HALF, -0.6, 0.0, 0.7, HALF])  # fixed shape: five views, both grazing ends
_LAYER_UM = 150.0


@jax.jit
def _rounded(p, b2):
    """Values and forward-mode Jacobian in (theta_i, sigma, n, r) for r = frac x r_max."""

    def f(p):
        ti, s, n, r_frac = p
        r = r_frac * model.max_edge_radius(b2, _LAYER_UM)
        return model.brdf_rounded(ti, _TO, b2, n, s, _LAYER_UM, r, resolution=2)

    return f(p), jax.jacfwd(f)(p)


@pytest.mark.slow  # compiling the rounded model's Jacobian takes 20-60 s
@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    ti=angles,
    b2=st.floats(0.02, HALF - 0.02),
    n=real_n,
    s=sigmas,
    frac=st.one_of(st.sampled_from([0.0, 1.0, 1e-6, 1 - 1e-9]), st.floats(0.0, 1.0)),
)
def test_rounded_model_finite_over_the_radius_range(ti, b2, n, s, frac):
    val, jac = _rounded(jnp.array([ti, s, n, frac]), b2)
    assert all_finite(val) and np.all(np.asarray(val) >= 0)
    assert all_finite(jac)
