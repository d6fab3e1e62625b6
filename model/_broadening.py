"""Gaussian angular broadening, truncated to the upper hemisphere [conventions §5]."""

from __future__ import annotations

import jax.numpy as jnp
from jax.scipy.special import erf
from jaxtyping import Array, ArrayLike, Float

from ._shapes import same_rank

HALF_PI = jnp.pi / 2


def hemisphere_gaussian(
    theta_o: ArrayLike, centre: ArrayLike, sigma: ArrayLike
) -> Float[Array, "..."]:
    """Density (1/rad) of a Gaussian of width `sigma` centred on `centre`, truncated to
    `[-pi/2, pi/2]` and renormalised there, evaluated at `theta_o` [conventions §5].

    Zero outside the hemisphere. Centres are clipped to the hemisphere: a lobe with non-zero
    weight never leaves it (docs/model.md), but the nominal direction of a zero-weight lobe can,
    and must not produce 0/0. The normaliser is then at least 1/2, so no division is near zero;
    `sigma` must be > 0 (1e-6 rad is fine in float64 and float32).
    """
    theta_o, centre, sigma = same_rank(theta_o, centre, sigma)
    centre = jnp.clip(centre, -HALF_PI, HALF_PI)
    z = (theta_o - centre) / sigma
    density = jnp.exp(-0.5 * z * z) / (
        jnp.sqrt(2.0 * jnp.pi) * sigma * hemisphere_mass(centre, sigma)
    )
    inside = jnp.abs(theta_o) <= HALF_PI
    return jnp.where(inside, density, 0.0)


def hemisphere_mass(centre: ArrayLike, sigma: ArrayLike) -> Float[Array, "..."]:
    """Mass of a Gaussian (centre, sigma) inside `[-pi/2, pi/2]`: the truncation normaliser.

    The centre is clipped to the hemisphere (see `hemisphere_gaussian`), so the mass is at
    least 1/2 [conventions §5].
    """
    centre, sigma = same_rank(centre, sigma)
    centre = jnp.clip(centre, -HALF_PI, HALF_PI)
    root2s = jnp.sqrt(2.0) * sigma
    mass = 0.5 * (erf((HALF_PI - centre) / root2s) - erf((-HALF_PI - centre) / root2s))
    return mass
