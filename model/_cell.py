"""The staircase unit cell (paper Eq. 1) and the facet projections (paper Eqs. 2-3).

All angles in radians; lengths in micrometres where they appear [conventions §1, §2].
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from ._shapes import same_rank


class UnitCell(NamedTuple):
    """Lengths of one staircase period [conventions §2], in micrometres."""

    l1_um: Float[Array, "..."]  # riser: the layer thickness
    l2_um: Float[Array, "..."]  # tread: l1 cot(beta2)
    l_um: Float[Array, "..."]  # period along the wedge face: sqrt(l1^2 + l2^2)
    beta1_rad: Float[Array, "..."]  # 90 deg - beta2


def unit_cell(beta2: ArrayLike, layer_um: ArrayLike) -> UnitCell:
    """Paper Eq. 1: `l2 = l1 cot(beta2)`, `beta1 = pi/2 - beta2`, `l = sqrt(l1^2 + l2^2)`.

    `l` is computed as `l1 / sin(beta2)`, which equals the square root exactly and is finite
    for every `beta2` in `(0, pi/2]` [conventions §2].
    """
    beta2, l1 = same_rank(beta2, layer_um)
    l1 = l1.astype(beta2.dtype)
    sin_b, cos_b = jnp.sin(beta2), jnp.cos(beta2)
    return UnitCell(
        l1_um=l1, l2_um=l1 * cos_b / sin_b, l_um=l1 / sin_b, beta1_rad=jnp.pi / 2 - beta2
    )


class Projections(NamedTuple):
    """Projections of the lit part of each facet onto the ray front, in units of the period `l`.

    `riser` is the paper's `r1 / l`, `tread` its `r2 / l` [conventions §2, §3]. In every regime
    `riser + tread == cos(theta_i)`: the whole period is accounted for.
    """

    riser: Float[Array, "..."]
    tread: Float[Array, "..."]


def facet_projections(theta_i: ArrayLike, beta2: ArrayLike) -> Projections:
    """Paper Eqs. 2-3 divided by `l` (`l1 = l sin beta2`, `l2 = l cos beta2`).

    `r1 = l1 max(sin(beta2 + theta_i), 0) + l2 min(cos(beta2 + theta_i), 0)` and
    `r2 = l2 max(cos(beta2 + theta_i), 0) + l1 min(sin(beta2 + theta_i), 0)`: a facet turned away
    from the light gets nothing and its neighbour loses what the step in front shadows
    [conventions §1-§3]. Only `max`/`min` are involved, so gradients are finite everywhere.
    """
    theta_i, beta2 = same_rank(theta_i, beta2)
    u = beta2 + theta_i
    sin_u, cos_u = jnp.sin(u), jnp.cos(u)
    sin_b, cos_b = jnp.sin(beta2), jnp.cos(beta2)
    riser = sin_b * jnp.maximum(sin_u, 0.0) + cos_b * jnp.minimum(cos_u, 0.0)
    tread = cos_b * jnp.maximum(cos_u, 0.0) + sin_b * jnp.minimum(sin_u, 0.0)
    return Projections(riser=riser, tread=tread)
