"""The sharp staircase: three delta lobes per angle of incidence (paper Eqs. 2-8).

The derivation that this module implements, and its check of the paper, is in docs/model.md.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from ._cell import facet_projections
from ._fresnel import fresnel_sp
from ._shapes import same_rank

LOBE_NAMES: tuple[str, str, str] = ("tread", "riser", "retro")
"""Lobe order used by every array with a trailing lobe axis [conventions §3]."""


class Lobes(NamedTuple):
    """Sharp lobes for each angle of incidence; the last axis is the lobe [conventions §3].

    `theta_o` (radians) is where each lobe goes, `weight` the fraction of the rays hitting one
    cell that leave by it (the three sum to 1), `fresnel` the unpolarised Fresnel factor of its
    reflection(s) [conventions §6]. `weight * fresnel` is the lobe's reflectance ratio, the
    paper's BRDF value [conventions §4].
    """

    theta_o: Float[Array, "... 3"]
    weight: Float[Array, "... 3"]
    fresnel: Float[Array, "... 3"]

    @property
    def ratio(self) -> Float[Array, "... 3"]:
        """Reflectance ratio of each lobe: weight x Fresnel factor, dimensionless."""
        return self.weight * self.fresnel


def lobe_weights(theta_i: ArrayLike, beta2: ArrayLike) -> Float[Array, "... 3"]:
    """Geometric weights (tread, riser, retro) of the sharp staircase [conventions §3].

    In regime B both facets are lit with projections `p_riser`, `p_tread` (paper Eqs. 2-3, here
    per unit period) whose sum is `cos(theta_i)`. A 90-degree corner maps a ray entering at
    offset `s` from the corner's projection to the offset `-s`, so the retroreflected width is
    `2 min(p_riser, p_tread)` and the larger facet reflects the difference directly (paper
    Eqs. 7-8). In regimes A and C only one facet is lit and everything it receives is direct.
    All fractions are normalised by `l cos(theta_i)` (paper Sec. 2). Finite values and
    gradients everywhere, including `theta_i = +-pi/2` and the regime boundaries.
    """
    theta_i, beta2 = same_rank(theta_i, beta2)
    proj = facet_projections(theta_i, beta2)
    both_lit = (proj.riser > 0.0) & (proj.tread > 0.0)
    total = proj.riser + proj.tread  # == cos(theta_i) > 0 whenever both facets are lit
    total_safe = jnp.where(both_lit, total, 1.0)  # safe-where: no 0/0 on the untaken branch
    common = jnp.minimum(proj.riser, proj.tread)
    retro = jnp.where(both_lit, 2.0 * common / total_safe, 0.0)
    # Outside regime B exactly one facet is lit: the tread in A (beta2 + theta_i < 0), the
    # riser in C. Decided from the angle, not from projections that round to 0 at grazing.
    regime_a = (beta2 + theta_i) < jnp.pi / 4
    tread = jnp.where(both_lit, (proj.tread - common) / total_safe, jnp.where(regime_a, 1.0, 0.0))
    riser = jnp.where(both_lit, (proj.riser - common) / total_safe, jnp.where(regime_a, 0.0, 1.0))
    return jnp.stack([tread, riser, retro], axis=-1)


def lobe_weight_kinks(beta2: ArrayLike) -> Float[Array, "... 3"]:
    """Angles of incidence where the lobe weights (and the lobes' Fresnel factors) have a kink in
    `theta_i`: `-beta2` and `90 deg - beta2` (regimes A|B and B|C, where a facet's local angle
    passes 90 deg) and `90 deg - 2 beta2` (tread and riser lit equally, the retroreflected share
    at its peak) [conventions §3]. Radians."""
    beta2 = jnp.asarray(beta2)
    return jnp.stack([-beta2, jnp.pi / 2 - 2 * beta2, jnp.pi / 2 - beta2], axis=-1)


def lobe_directions(theta_i: ArrayLike, beta2: ArrayLike) -> Float[Array, "... 3"]:
    """Paper Eqs. 4-6: `theta_i + 2 beta2`, `theta_i - 2 beta1`, `-theta_i` [conventions §3]."""
    theta_i, beta2 = jnp.broadcast_arrays(jnp.asarray(theta_i), jnp.asarray(beta2))
    beta1 = jnp.pi / 2 - beta2
    return jnp.stack([theta_i + 2 * beta2, theta_i - 2 * beta1, -theta_i], axis=-1)


def lobe_fresnel(theta_i: ArrayLike, beta2: ArrayLike, n: ArrayLike) -> Float[Array, "... 3"]:
    """Unpolarised Fresnel factor of each lobe at each facet's local angle [conventions §6].

    The tread's local angle is `|theta_i + beta2|`, the riser's `|theta_i + beta2 - pi/2|`; in
    the retroreflection the ray meets both (the angles sum to 90 deg) in one plane of incidence,
    so the product is taken per polarisation before averaging. Where a facet is unlit its cosine
    is clamped to 0 (its weight is 0 there).
    """
    theta_i, beta2, n = same_rank(theta_i, beta2, n)
    u = beta2 + theta_i
    tread = fresnel_sp(jnp.cos(u), n)
    riser = fresnel_sp(jnp.sin(u), n)
    retro = 0.5 * (tread.s * riser.s + tread.p * riser.p)
    return jnp.stack([0.5 * (tread.s + tread.p), 0.5 * (riser.s + riser.p), retro], axis=-1)


def sharp_lobes(theta_i: ArrayLike, beta2: ArrayLike, n: ArrayLike) -> Lobes:
    """All three sharp lobes for angles of incidence `theta_i` (radians) [conventions §1-§6].

    Arguments broadcast against each other; `n` is the (complex) refractive index at the
    wavelength of interest, `delta_n` already added.
    """
    theta_i, beta2, n = jnp.broadcast_arrays(
        jnp.asarray(theta_i), jnp.asarray(beta2), jnp.asarray(n)
    )
    return Lobes(
        theta_o=lobe_directions(theta_i, beta2),
        weight=lobe_weights(theta_i, beta2),
        fresnel=lobe_fresnel(theta_i, beta2, n),
    )
