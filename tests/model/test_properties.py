"""Property-based stability over the whole parameter domain, edges included (issue 7).

hypothesis draws angles in [-90, 90] deg (the ends and the regime boundaries drawn on
purpose), wedge angles in (0, 90) deg, broadening from 1e-6 rad, n from 1.0001 to 3 and complex
n. Every model function must give finite values and finite gradients there, respect the energy
bounds, and be continuous across the regime boundaries. Examples are few enough for CI (each
property runs about 150 examples through one compiled function).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from checks import all_finite
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from stairfit import model

HALF = float(np.pi / 2)
SETTINGS = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])

beta2s = st.floats(1e-4, HALF - 1e-4)
sigmas = st.floats(1e-6, 1.5)
real_n = st.floats(1.0001, 3.0)
angles = st.one_of(
    st.sampled_from([-HALF, HALF, 0.0, -HALF + 1e-12, HALF - 1e-12]),
    st.floats(-HALF, HALF),
)


@st.composite
def angle_near_boundary(draw: st.DrawFn, beta2: float) -> float:
    edge = draw(st.sampled_from([-beta2, HALF - 2 * beta2, HALF - beta2]))
    offset = draw(st.sampled_from([0.0, 1e-12, -1e-12, 1e-7, -1e-7]))
    return float(np.clip(edge + offset, -HALF, HALF))


@jax.jit
def _lobes_grads(ti, b2, n):
    def total(ti, b2, n):
        return jnp.sum(model.sharp_lobes(ti, b2, n).ratio)

    return model.sharp_lobes(ti, b2, n), jax.grad(total, argnums=(0, 1, 2))(ti, b2, n)


@jax.jit
def _brdf_grads(ti, to, b2, n, s):
    return model.brdf(ti, to, b2, n, s), jax.grad(model.brdf, argnums=(0, 1, 2, 3, 4))(
        ti, to, b2, n, s
    )


@jax.jit
def _brdf_complex_grads(ti, to, b2, nr, k, s):
    def f(ti, to, b2, nr, k, s):
        return model.brdf(ti, to, b2, nr + 1j * k, s)

    return f(ti, to, b2, nr, k, s), jax.grad(f, argnums=(0, 1, 2, 3, 4, 5))(ti, to, b2, nr, k, s)


@SETTINGS
@given(ti=angles, b2=beta2s, n=real_n)
def test_lobes_finite_bounded_and_differentiable(ti, b2, n):
    lobes, grads = _lobes_grads(ti, b2, n)
    assert all_finite(lobes) and all_finite(grads)
    w, r = np.asarray(lobes.weight), np.asarray(lobes.ratio)
    assert np.all(w >= 0) and abs(w.sum() - 1) < 1e-12
    assert np.all(r >= 0) and r.sum() <= 1.0 + 1e-12
    # energy bound: never more than the largest single-facet Fresnel factor allows
    assert r.sum() <= float(np.max(np.asarray(lobes.fresnel)[:2])) + 1e-12


@SETTINGS
@given(ti=angles, to=angles, b2=beta2s, n=real_n, s=sigmas)
def test_brdf_finite_nonnegative_and_differentiable(ti, to, b2, n, s):
    val, grads = _brdf_grads(ti, to, b2, n, s)
    assert all_finite(val) and float(val) >= 0
    assert all_finite(grads)


@SETTINGS
@given(ti=angles, to=angles, b2=beta2s, nr=real_n, k=st.floats(0.0, 2.0), s=sigmas)
def test_complex_index_finite_and_differentiable(ti, to, b2, nr, k, s):
    val, grads = _brdf_complex_grads(ti, to, b2, nr, k, s)
    assert all_finite(val) and float(val) >= 0
    assert all_finite(grads)


# one compiled program per dtype (an eager call compiles each operation on its own)
_SHARP_LOBES = jax.jit(model.sharp_lobes)
_BRDF = jax.jit(model.brdf)


@SETTINGS
@given(data=st.data(), b2=beta2s, n=real_n)
def test_continuity_across_regime_boundaries(data, b2, n):
    edge = data.draw(angle_near_boundary(b2))
    step = 1e-7
    lo = np.asarray(_SHARP_LOBES(max(edge - step, -HALF), b2, n).ratio)
    hi = np.asarray(_SHARP_LOBES(min(edge + step, HALF), b2, n).ratio)
    # weights change at most at rate 2 / cos(theta_i) (and Fresnel slower); cos(theta_i) is at
    # least sin(beta2) or cos(beta2) inside regime B, so the jump is bounded by the step times
    # 4 / min(sin, cos)(beta2) (with room for the Fresnel factor's own slope)
    bound = 2 * step * 4.0 / min(np.sin(b2), np.cos(b2)) + 1e-12
    assert np.all(np.abs(hi - lo) <= bound)


@jax.jit
def _diffuse(to, b2, n, s):
    return (
        model.diffuse_sharp(to, b2, n),
        model.diffuse_broadened(to, b2, n, s),
        jax.grad(lambda b, nn, ss: model.diffuse_broadened(to, b, nn, ss), argnums=(0, 1, 2))(
            b2, n, s
        ),
    )


@settings(max_examples=60, deadline=None)
@given(to=angles, b2=beta2s, n=real_n, s=sigmas)
def test_diffuse_integrals_finite_bounded_and_differentiable(to, b2, n, s):
    sharp, broad, grads = _diffuse(to, b2, n, s)
    assert all_finite(sharp) and all_finite(broad) and all_finite(grads)
    # a reflectance under diffuse light: between 0 and the sum of three Fresnel maxima (<= 3)
    assert 0 <= float(sharp) <= 3 and 0 <= float(broad) <= 3


@SETTINGS
@given(ti=angles, to=angles, b2=beta2s, n=real_n, s=st.floats(np.deg2rad(0.5), 1.5))
def test_float32_within_documented_bound(ti, to, b2, n, s):
    # tests/model/test_float32.py: |rho32 - rho64| <= 5e-5 x max rho for sigma >= 0.5 deg; the peak
    # density of one lobe is at most 1 / (sqrt(2 pi) sigma mass) with mass >= 1/2
    f64 = float(_BRDF(ti, to, b2, n, s))
    f32 = float(_BRDF(*(jnp.float32(x) for x in (ti, to, b2, n, s))))
    peak = 3 * 2 / (np.sqrt(2 * np.pi) * s)
    assert abs(f32 - f64) <= 5e-5 * peak
