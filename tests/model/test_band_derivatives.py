"""Derivatives of the band density and of the Fresnel factors: autodiff (through the Fresnel
factors' hand-arranged derivative rule) against central finite differences and an independent
formula, and finite at the extremes of conventions §10 (grazing angles, regime boundaries, tiny
sigma, n -> 1, complex n) [conventions §4, §5, §6, §8].
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from stairfit import model

DEG = np.pi / 180


def _case(n_lambda: int = 5, extreme: bool = False) -> dict[str, np.ndarray]:
    """Observations over wedges, viewing angles and two angles of incidence."""
    if extreme:
        ti = np.array([90, -90, 90 - 1e-7, -30, 60, 0.0]) * DEG
        to = np.array([-90, 90, 89.9999999, 30, -60, 0.0]) * DEG
        b2 = np.array([0.5, 89.5, 45, 30, 30, 30]) * DEG
    else:
        b2g, tog, tig = np.meshgrid(
            [10, 30, 60], np.linspace(-85, 85, 35), [20, -40], indexing="ij"
        )
        ti, to, b2 = tig.ravel() * DEG, tog.ravel() * DEG, b2g.ravel() * DEG
    lam = np.linspace(420, 680, n_lambda)
    n_base = np.asarray(model.materials.PLA_BODUROV_2016(lam))
    w = np.linspace(1.0, 2.0, n_lambda)
    return {
        "theta_i": ti,
        "theta_o": to,
        "beta2": b2,
        "n_base": np.broadcast_to(n_base, (ti.size, n_lambda)).copy(),
        "weight": np.broadcast_to(w / w.sum(), (ti.size, n_lambda)).copy(),
    }


def _density(x: jax.Array, c: dict, aperture: model.Aperture | None, n_base=None) -> jax.Array:
    """band_density as a function of x = (sigma, delta_n)."""
    nb = c["n_base"] if n_base is None else n_base
    return model.band_density(
        c["theta_i"], c["theta_o"], c["beta2"], nb + x[1], c["weight"], x[0], aperture
    )


# One compiled program per shape and dtype (an eager call compiles each operation on its own).
_DENSITY = jax.jit(_density, static_argnums=2)
_JACOBIAN = jax.jit(jax.jacfwd(_density), static_argnums=2)


def test_agrees_with_central_finite_differences():
    c = _case(n_lambda=3)
    x = np.array([3.0 * DEG, 0.01])
    jac = np.asarray(_JACOBIAN(jnp.asarray(x), c, None))
    for k in range(2):
        h = 1e-6
        up, dn = x.copy(), x.copy()
        up[k] += h
        dn[k] -= h
        fd = (np.asarray(_DENSITY(up, c, None)) - np.asarray(_DENSITY(dn, c, None))) / (2 * h)
        js = np.abs(fd).max()
        assert js > 0
        np.testing.assert_allclose(jac[:, k], fd, rtol=1e-5, atol=1e-6 * js)


@pytest.mark.parametrize(
    ("sigma", "n_const"),
    [(1e-6, None), (0.3, None), (0.05, 1.0001), (0.05, 1.5 + 0.02j)],
    ids=["tiny-sigma", "wide-sigma", "n-near-1", "complex-n"],
)
def test_finite_at_the_extremes(sigma, n_const):
    c = _case(n_lambda=3, extreme=True)
    n = c["n_base"] if n_const is None else np.full(c["n_base"].shape, n_const)
    x = jnp.array([sigma, 0.0])
    value = _DENSITY(x, c, None, n)
    jac = _JACOBIAN(x, c, None, n)
    assert np.all(np.isfinite(np.asarray(value))) and np.all(np.isfinite(np.asarray(jac)))


def _plain_fresnel(c: jax.Array, n: jax.Array) -> jax.Array:
    """Textbook Fresnel power reflectances via the angle of refraction (Snell's law), stacked
    (s, p): an independent formula for plain autodiff to differentiate."""
    sin_t = jnp.sqrt(1.0 - c**2) / n
    cos_t = jnp.sqrt(1.0 - sin_t**2)
    r_s = (c - n * cos_t) / (c + n * cos_t)
    r_p = (n * c - cos_t) / (n * c + cos_t)
    return jnp.stack([jnp.abs(r_s) ** 2, jnp.abs(r_p) ** 2])


@jax.jit
def _fresnel_rule_and_plain(c: jax.Array, n: jax.Array) -> tuple:
    """Values, jvps (in the cosine, in the index, in both) and gradients in the cosine of
    `model.fresnel_sp` (hand-arranged derivative rule) and of the independent formula."""

    def ours(cc: jax.Array, dn: jax.Array) -> jax.Array:
        r = model.fresnel_sp(cc, n + dn)
        return jnp.stack([r.s, r.p])

    def plain(cc: jax.Array, dn: jax.Array) -> jax.Array:
        return _plain_fresnel(cc, n + dn)

    values = (ours(c, 0.0), plain(c, 0.0))
    jvps = [
        (jax.jvp(ours, (c, 0.0), tangents)[1], jax.jvp(plain, (c, 0.0), tangents)[1])
        for tangents in [(jnp.ones_like(c), 0.0), (jnp.zeros_like(c), 1.0), (c, 0.3)]
    ]
    # reverse mode goes through the transposed rule
    grads = (
        jax.grad(lambda cc: ours(cc, 0.0).sum())(c),
        jax.grad(lambda cc: plain(cc, 0.0).sum())(c),
    )
    return values, jvps, grads


@pytest.mark.parametrize(
    "n", [1.46, 1.0001, 2.4, 1.5 + 0.05j], ids=["pla", "n-near-1", "high", "absorbing"]
)
def test_fresnel_derivative_rule_matches_plain_autodiff(n):
    """`model.fresnel_sp` has a hand-arranged derivative rule (model/_fresnel.py); its jvp in
    the cosine and in the index must equal autodiff of an independent formula."""
    c = jnp.array(
        [0.05, 0.2, 0.5, 0.8, 0.99]
    )  # away from c = 0, 1 where the plain form has sqrt(0)
    (v_ours, v_plain), jvps, (g_ours, g_plain) = _fresnel_rule_and_plain(c, jnp.asarray(n))
    np.testing.assert_allclose(v_ours, v_plain, rtol=1e-12, atol=1e-15)
    for d_ours, d_plain in jvps:
        assert np.abs(d_plain).max() > 1e-3
        np.testing.assert_allclose(d_ours, d_plain, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(g_ours, g_plain, rtol=1e-9, atol=1e-12)


@jax.jit
def _fresnel_derivatives(c: jax.Array, n: jax.Array) -> tuple[jax.Array, jax.Array]:
    """d(s, p) / d cos at every cosine, and d(sum of s and p) / d n."""
    g = jax.jacfwd(lambda cc: jnp.stack(model.fresnel_sp(cc, n)))(c)
    gn = jax.grad(lambda dn: sum(model.fresnel_sp(c, n + dn)).sum())(0.0)
    return g, gn


def test_fresnel_derivatives_finite_at_normal_and_grazing_incidence():
    c = jnp.array([0.0, 1e-9, 1.0 - 1e-12, 1.0])
    for n in (1.0001, 1.46, 1.5 + 0.05j):
        g, gn = _fresnel_derivatives(c, jnp.asarray(n))
        assert np.all(np.isfinite(np.asarray(g))) and np.isfinite(float(gn))
