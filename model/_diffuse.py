"""Diffuse lighting: the BRDF integrated over all angles of incidence (paper Fig. 5).

`D(theta_o) = integral over theta_i in [-pi/2, pi/2] of rho(theta_i, theta_o) d theta_i`
[conventions §4], optionally with the physical `cos(theta_i)` weight.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._broadening import HALF_PI, hemisphere_gaussian
from ._lobes import sharp_lobes
from ._shapes import with_rank

# For lobe k the direction is theta_o = slope_k * theta_i + offset_k(beta2) [conventions §3].
_SLOPES = (1.0, 1.0, -1.0)


def _lobe_sources(theta_o: Array, beta2: Array) -> Array:
    """The `theta_i` that sends each lobe to `theta_o` (inverse of paper Eqs. 4-6)."""
    beta1 = HALF_PI - beta2
    return jnp.stack([theta_o - 2 * beta2, theta_o + 2 * beta1, -theta_o], axis=-1)


def diffuse_sharp(
    theta_o: ArrayLike, beta2: ArrayLike, n: ArrayLike, cosine_weighted: bool = False
) -> Float[Array, "..."]:
    """Exact diffuse-lighting integral of the sharp staircase (sigma = 0), dimensionless.

    Each lobe is a delta at `theta_o = +-theta_i + const` with slope of magnitude 1, so its
    contribution is its reflectance ratio at the one `theta_i` that reaches `theta_o`, if that
    `theta_i` lies strictly inside `(-pi/2, pi/2)` [conventions §3, §4]: a source at exactly
    +-90 deg is a beam of zero width and contributes nothing (paper Sec. 2). The jumps where a
    source reaches +-90 deg are the discontinuities of the paper's Fig. 5; exactly at a jump the
    value is the lower side's (the paper's "minimum").
    """
    theta_o, beta2 = jnp.broadcast_arrays(jnp.asarray(theta_o), jnp.asarray(beta2))
    src = _lobe_sources(theta_o, beta2)
    inside = jnp.abs(src) < HALF_PI  # "no contribution if theta_i = +-90 deg" (paper Sec. 2)
    src_safe = jnp.where(inside, src, 0.0)
    lobes = sharp_lobes(src_safe, beta2[..., None], jnp.asarray(n)[..., None])
    ratio = jnp.diagonal(lobes.ratio, axis1=-2, axis2=-1)  # lobe k evaluated at its own source
    if cosine_weighted:
        ratio = ratio * jnp.cos(src_safe)
    return jnp.sum(jnp.where(inside, ratio, 0.0), axis=-1)


WINDOW_SIGMAS = 8.0
"""Half-width of the integration window in units of sigma (Gaussian mass beyond it: 1e-15)."""

_SUBCUTS = np.array([-5.5, -3.5, -2.0, -1.0, 1.0, 2.0, 3.5, 5.5])
"""Cuts (in sigma around the lobe's source angle) that keep each piece at most 2.5 sigma wide."""


def diffuse_broadened(
    theta_o: ArrayLike,
    beta2: ArrayLike,
    n: ArrayLike,
    sigma: ArrayLike,
    cosine_weighted: bool = False,
    n_nodes: int = 6,
) -> Float[Array, "..."]:
    """Diffuse-lighting integral of the broadened BRDF, dimensionless [conventions §4, §5].

    Each lobe direction has slope +-1 in `theta_i`, so the lobe's Gaussian factor is, as a
    function of `theta_i`, the normal density of width `sigma` around the lobe's source angle
    `c` (the `theta_i` that sends the sharp lobe to `theta_o`). For each lobe the integral runs
    over `c +- 8 sigma` clipped to `[-pi/2, pi/2]`, cut at the regime boundaries `-beta2`,
    `beta1 - beta2`, `beta1` (kinks of the integrand) and at `c +- (1, 2, 3.5, 5.5) sigma`, with
    `n_nodes` Gauss-Legendre nodes on each of the 12 pieces. Every piece is then smooth and at
    most 2.5 sigma wide, so the error falls exponentially with `n_nodes` for every `sigma`
    (1e-6 rad to radians; measured in tests and the benchmark), and as `sigma -> 0` the result
    tends to `diffuse_sharp`. Differentiable in every argument.
    """
    theta_o, beta2, n, sigma = jnp.broadcast_arrays(
        jnp.asarray(theta_o), jnp.asarray(beta2), jnp.asarray(n), jnp.asarray(sigma)
    )
    dtype = theta_o.dtype
    c = _lobe_sources(theta_o, beta2)  # (..., 3): lobe k's source angle
    s3 = sigma[..., None]
    lo = jnp.clip(c - WINDOW_SIGMAS * s3, -HALF_PI, HALF_PI)
    hi = jnp.clip(c + WINDOW_SIGMAS * s3, -HALF_PI, HALF_PI)
    beta1 = HALF_PI - beta2
    kinks = jnp.stack([-beta2, beta1 - beta2, beta1], axis=-1)[..., None, :]  # (..., 1, 3)
    around = c[..., None] + s3[..., None] * with_rank(jnp.asarray(_SUBCUTS, dtype), c.ndim + 1)
    cuts = jnp.concatenate([jnp.broadcast_to(kinks, (*c.shape, 3)), around], axis=-1)
    cuts = jnp.sort(jnp.clip(cuts, lo[..., None], hi[..., None]), axis=-1)
    edges = jnp.concatenate([lo[..., None], cuts, hi[..., None]], axis=-1)  # (..., 3, 13)
    xi, wi = np.polynomial.legendre.leggauss(n_nodes)
    xi, wi = jnp.asarray(xi, dtype), jnp.asarray(wi, dtype)
    mid = 0.5 * (edges[..., 1:] + edges[..., :-1])
    half = 0.5 * (edges[..., 1:] - edges[..., :-1])
    xi, wi = with_rank(xi, mid.ndim + 1), with_rank(wi, mid.ndim + 1)
    nodes = (mid[..., None] + half[..., None] * xi).reshape(*c.shape, -1)  # (..., 3, 12N)
    weights = (half[..., None] * wi).reshape(nodes.shape)
    lobes = sharp_lobes(nodes, beta2[..., None, None], n[..., None, None])  # (..., 3, 12N, 3)
    pick = with_rank(jnp.eye(3, dtype=dtype)[:, None, :], nodes.ndim + 1)  # window k: lobe k
    ratio = jnp.sum(lobes.ratio * pick, axis=-1)
    centre = jnp.sum(lobes.theta_o * pick, axis=-1)
    # the lobe's truncated Gaussian at theta_o, centred on its direction from each node
    # [conventions §5]: as a function of theta_i, a normal density around the source angle c
    gauss = hemisphere_gaussian(theta_o[..., None, None], centre, sigma[..., None, None])
    integrand = ratio * gauss
    if cosine_weighted:
        integrand = integrand * jnp.cos(nodes)
    total = jnp.sum(integrand * weights, axis=(-2, -1))
    return jnp.where(jnp.abs(theta_o) <= HALF_PI, total, 0.0)
