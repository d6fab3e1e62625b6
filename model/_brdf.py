"""The broadened in-plane BRDF of the sharp staircase [conventions §4, §5]."""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from ._broadening import hemisphere_gaussian
from ._fresnel import fresnel_unpolarised
from ._lobes import sharp_lobes
from ._shapes import same_rank


def brdf(
    theta_i: ArrayLike, theta_o: ArrayLike, beta2: ArrayLike, n: ArrayLike, sigma: ArrayLike
) -> Float[Array, "..."]:
    """In-plane reflectance density `rho(theta_i, theta_o)` in 1/rad [conventions §4].

    The sum over the three lobes of (weight x Fresnel) x a hemisphere-truncated Gaussian of
    width `sigma` (radians, > 0) centred on the lobe direction [conventions §3, §5]. All
    arguments broadcast; angles in radians [conventions §1]; `n` may be complex [conventions §6].
    """
    theta_i, theta_o, beta2, n, sigma = same_rank(theta_i, theta_o, beta2, n, sigma)
    lobes = sharp_lobes(theta_i, beta2, n)
    kernel = hemisphere_gaussian(theta_o[..., None], lobes.theta_o, sigma[..., None])
    return jnp.sum(lobes.ratio * kernel, axis=-1)


def flat_reflectance(theta: ArrayLike, n: ArrayLike) -> Float[Array, "..."]:
    """Unpolarised Fresnel reflectance of the flat material at incidence `theta` (radians).

    The paper's "material" curve in Fig. 5: for a flat surface `rho` is a single delta at
    `theta_o = theta_i` and the diffuse integral is `R(theta_o)` [conventions §4].
    """
    return fresnel_unpolarised(jnp.cos(jnp.asarray(theta)), n)
