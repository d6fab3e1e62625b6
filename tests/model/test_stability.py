"""Finite values and finite, correct gradients of the sharp model at the extremes (issue 2)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from checks import all_finite

from stairfit import model

DEG = np.pi / 180
HALF = np.pi / 2


def _extreme_angles(beta2: float) -> list[float]:
    b1 = HALF - beta2
    exact = [-HALF, HALF, -beta2, b1 - beta2, b1, 0.0]
    near = [-HALF + 1e-9, HALF - 1e-9, -beta2 + 1e-9, -beta2 - 1e-9, b1 + 1e-9, b1 - 1e-9]
    return exact + near


BETAS = [0.5 * DEG, 10 * DEG, 45 * DEG, 60 * DEG, 89.5 * DEG]
INDICES = [1.46, 1.0001, 3.0]
# One compiled program per shape (an eager call compiles each operation on its own).
_BRDF = jax.jit(model.brdf)
_LOBES = jax.jit(model.sharp_lobes)
_DIFFUSE_SHARP = jax.jit(model.diffuse_sharp, static_argnames="cosine_weighted")
_DIFFUSE = jax.jit(model.diffuse_broadened, static_argnames=("cosine_weighted", "n_nodes"))


@jax.jit
def _lobes_and_grads(ti, b, nn):
    def total(ti, b, nn):
        return jnp.sum(model.sharp_lobes(ti, b, nn).ratio)

    grads = jax.vmap(jax.grad(total, argnums=(0, 1, 2)), in_axes=(0, None, None))(ti, b, nn)
    return model.sharp_lobes(ti, b, nn), grads


@pytest.mark.parametrize("beta2", BETAS)
@pytest.mark.parametrize("n", INDICES)
def test_lobes_finite_values_and_gradients_at_extremes(beta2, n):
    angles = jnp.array(_extreme_angles(beta2))
    lobes, grads = _lobes_and_grads(angles, beta2, n)
    assert all_finite(lobes)
    np.testing.assert_allclose(jnp.sum(lobes.weight, axis=-1), 1.0, atol=1e-12)
    assert all_finite(grads)


@jax.jit
def _brdf_and_grads(ti, to, b, n, s):
    val = model.brdf(ti, to, b, n, s)
    g = jax.vmap(jax.grad(model.brdf, argnums=(0, 1, 2, 3, 4)), in_axes=(0, 0, None, None, None))(
        jnp.ravel(ti), jnp.ravel(to), b, n, s
    )
    return val, g


@pytest.mark.parametrize("beta2", BETAS)
@pytest.mark.parametrize("sigma", [1e-6, 1e-3, 5 * DEG, 1.0])
def test_brdf_finite_values_and_gradients_at_extremes(beta2, sigma):
    angles = _extreme_angles(beta2)
    ti, to = np.meshgrid(angles, [*angles, HALF - 2 * beta2], indexing="ij")
    val, grads = _brdf_and_grads(jnp.asarray(ti), jnp.asarray(to), beta2, 1.46, sigma)
    assert all_finite(val) and bool(jnp.all(val >= 0))
    assert all_finite(grads)


@jax.jit
def _complex_brdf_and_grads(ti, to, nr, k, s):
    def f(ti, to, nr, k, s):
        return model.brdf(ti, to, 30 * DEG, nr + 1j * k, s)

    g = jax.vmap(jax.grad(f, argnums=(0, 1, 2, 3, 4)), in_axes=(0, 0, None, None, None))
    return f(ti, to, nr, k, s), g(ti, to, nr, k, s)


def test_complex_index_values_and_gradients():
    ti, to = np.meshgrid(_extreme_angles(30 * DEG), [-HALF, 0.1, HALF], indexing="ij")
    v, g = _complex_brdf_and_grads(jnp.ravel(ti), jnp.ravel(to), 1.5, 0.3, 0.05)
    assert all_finite(v) and all_finite(g)
    # an absorbing index reflects more at normal incidence: |(n-1)/(n+1)|^2
    r = float(model.flat_reflectance(0.0, 1.5 + 0.3j))
    assert r == pytest.approx(abs((0.5 + 0.3j) / (2.5 + 0.3j)) ** 2, rel=1e-12)


@pytest.mark.parametrize(
    "point",
    [
        # (theta_i, theta_o, beta2, n, sigma): one per regime, near grazing, small sigma
        (-1.2, -0.9, 0.3, 1.46, 0.08),
        (0.1, 0.5, 0.6, 1.5, 0.1),
        (1.3, -0.3, 0.5, 1.46, 0.12),
        (HALF - 1e-3, -0.2, 45 * DEG, 1.46, 0.05),
        (0.2, -0.2 + 2e-6, 30 * DEG, 1.46, 1e-5),
        (0.3, 0.35, 10 * DEG, 1.0001, 0.05),
    ],
)
def test_brdf_jvp_matches_central_finite_differences(point):
    x0 = np.array(point, dtype=np.float64)
    for k in range(5):
        v = np.zeros(5)
        v[k] = 1.0
        tangent = _brdf_jvp(jnp.asarray(x0), jnp.asarray(v))
        h = 1e-6 * max(1.0, abs(x0[k])) if x0[4] > 1e-3 else 1e-9
        fd = (float(_brdf_at(x0 + h * v)) - float(_brdf_at(x0 - h * v))) / (2 * h)
        assert float(tangent) == pytest.approx(fd, rel=2e-5, abs=1e-7 * max(1.0, abs(fd))), k


@jax.jit
def _brdf_at(x: jax.Array) -> jax.Array:
    return model.brdf(x[0], x[1], x[2], x[3], x[4])


@jax.jit
def _brdf_jvp(x: jax.Array, v: jax.Array) -> jax.Array:
    return jax.jvp(_brdf_at, (x,), (v,))[1]


@jax.jit
def _diffuse_and_grads(theta_o, b, n, s):
    out = []
    for cw in (False, True):

        def f(b, n, s, cw=cw):
            return jnp.sum(model.diffuse_broadened(theta_o, b, n, s, cosine_weighted=cw))

        out.append(
            (
                model.diffuse_sharp(theta_o, b, n, cosine_weighted=cw),
                model.diffuse_broadened(theta_o, b, n, s, cosine_weighted=cw),
                jax.grad(f, argnums=(0, 1, 2))(b, n, s),
            )
        )
    return out


@pytest.mark.parametrize("sigma", [1e-6, 5 * DEG])
def test_diffuse_finite_values_and_gradients(sigma):
    theta_o = jnp.array([-HALF, -HALF + 1e-9, -70 * DEG, 0.0, HALF - 1e-9, HALF])
    for beta2 in BETAS:
        assert all_finite(_diffuse_and_grads(theta_o, beta2, 1.46, sigma))


def test_broadening_conserves_each_lobes_energy():
    # conventions §5: the truncated, renormalised Gaussian keeps the reflectance ratio exactly
    theta_o = np.linspace(-HALF, HALF, 200001)
    for ti in (-1.5, -0.3, 0.0, 0.7, 1.55):
        for sigma in (0.01, 0.1, 0.5):
            rho = np.asarray(_BRDF(ti, theta_o, 20 * DEG, 1.46, sigma))
            total = np.trapezoid(rho, theta_o)
            expected = float(jnp.sum(_LOBES(ti, 20 * DEG, 1.46).ratio))
            assert total == pytest.approx(expected, rel=1e-6)


def test_small_sigma_density_tends_to_the_sharp_lobes():
    # integrating the density over a window around each lobe recovers that lobe's ratio
    ti, b2 = -0.1, 30 * DEG
    lobes = _LOBES(ti, b2, 1.46)
    for k in range(3):
        if float(lobes.weight[k]) == 0:
            continue
        mu = float(lobes.theta_o[k])
        grid = np.linspace(mu - 1e-4, mu + 1e-4, 20001)
        rho = np.asarray(_BRDF(ti, grid, b2, 1.46, 1e-6))
        assert np.trapezoid(rho, grid) == pytest.approx(float(lobes.ratio[k]), rel=1e-6)


@pytest.mark.parametrize("beta2_deg", [10, 45, 60])
def test_continuity_across_regime_boundaries(beta2_deg):
    b2 = beta2_deg * DEG
    b1 = HALF - b2
    for edge in (-b2, b1 - b2, b1):
        for eps in (1e-6, 1e-9):
            lo = _LOBES(edge - eps, b2, 1.46)
            hi = _LOBES(edge + eps, b2, 1.46)
            # weights are Lipschitz in theta_i with a constant below 1 / cos(theta_i) <= 60 here
            np.testing.assert_allclose(lo.ratio, hi.ratio, atol=200 * eps)


@pytest.mark.parametrize("sigma", [1e-3, 1 * DEG, 5 * DEG, 0.5])
def test_diffuse_broadened_quadrature_converges_to_dense_reference(sigma):
    theta_o = np.array([-71, -69, -30, 0, 30, 89.9]) * DEG
    theta_i = np.linspace(-HALF, HALF, 200001)
    ref = np.array(
        [
            np.trapezoid(np.asarray(_BRDF(theta_i, t, 10 * DEG, 1.46, sigma)), theta_i)
            for t in theta_o
        ]
    )
    got = np.asarray(_DIFFUSE(theta_o, 10 * DEG, 1.46, sigma, n_nodes=8))
    # the dense trapezoid reference is itself good to ~1e-7 relative (kinks at the regime
    # boundaries); 2e-6 leaves room for that, the quadrature's own error is below 1e-8
    np.testing.assert_allclose(got, ref, rtol=2e-6)


def test_diffuse_broadened_tends_to_sharp_as_sigma_vanishes():
    grid = np.linspace(-85, 85, 35) * DEG
    for beta2 in (10 * DEG, 45 * DEG, 60 * DEG):
        away = np.abs(grid - (2 * beta2 - HALF)) > 1e-3  # away from the Fig. 5 jump
        for cw in (False, True):
            sharp = np.asarray(_DIFFUSE_SHARP(grid, beta2, 1.46, cosine_weighted=cw))
            small = np.asarray(_DIFFUSE(grid, beta2, 1.46, 1e-7, cosine_weighted=cw))
            np.testing.assert_allclose(small[away], sharp[away], rtol=1e-5, atol=1e-9)
