"""Rounded edges in the lab model: the rounded staircase (docs/rounded.md) for 3-D directions,
with Gaussian or microfacet facets (docs/model.md §7.6) [conventions §11, §12].

The rounded profile is extruded like the sharp one, so a 3-D ray follows its projection's
in-plane path (docs/model.md §7.1): the rounded model is evaluated at the projected angles,
every Fresnel factor at the 3-D local angle, and its light leaves with `t_o = -t_i`.

* Gaussian facets: `brdf_rounded` at `(theta_i', theta_o')` times `line_gaussian` in `t_o`.
* Microfacet facets: the flat parts reflect as the sharp microfacet staircase's facets
  (`lab_density_microfacet`'s single reflections, each facet scaled by its flat share
  `(L_k - r) / L_k`), the two-bounce path scaled by the rounded corner reflector's weight over
  the sharp one, and the arcs' continuous lobes spread by a Gaussian of width
  `ARC_SIGMA_PER_ALPHA * alpha` in the plane and along the layer lines.

The rounded geometry (which depends on the projected angle of incidence) may be passed in,
computed once at a nearby angle for many nodes (the fit computes it once per photo and face);
the delta lobes' directions, weights' Fresnel factors and every kernel are always evaluated at
each node's own angles.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from ._lab import (
    _Band,
    _band,
    _broadcast,
    line_gaussian,
    microfacet_parts,
    projected_incidence,
    projected_view,
)
from ._lobes import lobe_weights
from ._rounded import (
    ROUNDED_RESOLUTION,
    RoundedGeometry,
    brdf_rounded_from_geometry,
    rounded_geometry,
)

ARC_SIGMA_PER_ALPHA = 2.0**0.5
"""With microfacet facets, the arcs of rounded edges spread their light by a Gaussian of width
`ARC_SIGMA_PER_ALPHA * alpha` (rad): a reflection doubles a micro-normal's tilt, and
Beckmann's slopes along one axis have the standard deviation `alpha / sqrt(2)`; the arcs'
own spread of directions is far wider, so the kernel's shape matters little there
(docs/model.md §7.6)."""

_TINY = 1e-12


def _rounded_band(
    geo: RoundedGeometry, theta_i: Array, theta_o: Array, beta2: Array, band: _Band,
    sigma: Array, t_i: Array,
) -> Array:  # fmt: skip
    """`brdf_rounded_from_geometry` (with the 3-D Fresnel factors of `t_i`) band-averaged over
    `band`'s samples, which get an axis of their own after the leading ones."""
    lead = geo.delta_weight.ndim - 1
    geo_l = jax.tree_util.tree_map(lambda a: jnp.expand_dims(a, lead), geo)
    args = [jnp.asarray(a)[..., None] for a in (theta_i, theta_o, beta2, sigma, t_i)]
    rho = brdf_rounded_from_geometry(geo_l, args[0], args[1], args[2], band.n, args[3], args[4])
    w = band.weight
    rho, w = jnp.broadcast_arrays(rho, w.reshape((1,) * (rho.ndim - w.ndim) + w.shape))
    return jnp.sum(rho * w, axis=-1)


def lab_density_rounded(
    w_i: ArrayLike,
    w_o: ArrayLike,
    beta2: ArrayLike,
    n: ArrayLike,
    width: ArrayLike,
    layer_um: ArrayLike,
    edge_radius_um: ArrayLike,
    kind: str = "gaussian",
    spectral_weight: ArrayLike | None = None,
    geometry: RoundedGeometry | None = None,
    *,
    resolution: int = ROUNDED_RESOLUTION,
) -> Float[Array, "..."]:
    """Reflected power per steradian (per unit incident power) of the rounded staircase (tip
    radius `edge_radius_um`, layer `layer_um`, micrometres) for 3-D directions, with Gaussian
    facets (`kind` "gaussian", `width` = sigma in rad, the same along the layer lines) or
    microfacet facets (`kind` "ggx"/"beckmann", `width` = alpha) [conventions §11, §12].

    `geometry`: `rounded_geometry` at (an angle near) each node's projected angle of incidence,
    broadcasting with the nodes; computed here at the nodes' own angles when None. At
    `edge_radius_um = 0` this is `lab_density_gaussian` resp. `lab_density_microfacet`.
    """
    w_i, w_o, (beta2, width) = _broadcast(w_i, w_o, beta2, width)
    band = _band(n, spectral_weight)
    inc, view = projected_incidence(w_i), projected_view(w_o)
    if geometry is None:
        geometry = rounded_geometry(inc.theta, beta2, layer_um, edge_radius_um,
                                    resolution=resolution)  # fmt: skip
    up = (w_i[..., 2] > 0.0) & (w_o[..., 2] > 0.0)
    if kind == "gaussian":
        rho = _rounded_band(geometry, inc.theta, view.theta, beta2, band, width, inc.t)
        out = rho * line_gaussian(view.t, -inc.t, width)
        return jnp.where(up, out, 0.0)
    sigma = ARC_SIGMA_PER_ALPHA * width
    arcs_only = geometry._replace(delta_weight=jnp.zeros_like(geometry.delta_weight))
    arcs = _rounded_band(arcs_only, inc.theta, view.theta, beta2, band, sigma, inc.t)
    arcs = arcs * line_gaussian(view.t, -inc.t, sigma)
    single, retro = microfacet_parts(w_i, w_o, beta2, band, width, kind)
    l1, r = (jnp.broadcast_to(jnp.asarray(a, beta2.dtype), beta2.shape)
             for a in (layer_um, edge_radius_um))  # fmt: skip
    l2 = l1 * jnp.cos(beta2) / jnp.sin(beta2)
    flat = jnp.stack(
        [jnp.clip((l2 - r) / jnp.maximum(l2, _TINY), 0.0, 1.0),
         jnp.clip((l1 - r) / jnp.maximum(l1, _TINY), 0.0, 1.0)], axis=-1,
    )  # fmt: skip
    sharp_retro = lobe_weights(inc.theta, beta2)[..., 2]
    rounded_retro = geometry.delta_weight[..., 2]
    has = sharp_retro > 1e-9
    scale_retro = jnp.where(
        has, rounded_retro / jnp.where(has, sharp_retro, 1.0), jnp.min(flat, axis=-1)
    )
    facets = jnp.sum(single * flat, axis=-1)
    return jnp.where(up, facets + retro * scale_retro + arcs, 0.0)
