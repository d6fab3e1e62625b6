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

from ._broadening import hemisphere_gaussian
from ._lab import (
    _Band,
    _band,
    _broadcast,
    _lobe_fresnel_band,
    line_gaussian,
    microfacet_parts,
    projected_incidence,
    projected_view,
)
from ._lobes import lobe_directions, lobe_weights
from ._rounded import (
    ROUNDED_RESOLUTION,
    RoundedGeometry,
    brdf_rounded_from_geometry,
    rounded_geometry,
)
from ._shapes import same_rank

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
    microfacet facets (`kind` "ggx"/"beckmann", `width` = alpha) [conventions §11, §12]: the
    flat facets' lobes (`rounded_flats`) plus the arcs' (`rounded_arcs`).

    `geometry`: `rounded_geometry` at (an angle near) each node's projected angle of incidence,
    broadcasting with the nodes; computed here at the nodes' own angles when None. At
    `edge_radius_um = 0` this is `lab_density_gaussian` resp. `lab_density_microfacet`.
    """
    w_i, w_o, (beta2, width) = _broadcast(w_i, w_o, beta2, width)
    if geometry is None:
        geometry = rounded_geometry(projected_incidence(w_i).theta, beta2, layer_um,
                                    edge_radius_um, resolution=resolution)  # fmt: skip
    flats = rounded_flats(w_i, w_o, beta2, n, width, layer_um, edge_radius_um, geometry, kind,
                          spectral_weight)  # fmt: skip
    arcs = rounded_arcs(w_i, w_o, beta2, n, width, geometry, kind, spectral_weight)
    return flats + arcs


def rounded_flats(
    w_i: ArrayLike,
    w_o: ArrayLike,
    beta2: ArrayLike,
    n: ArrayLike,
    width: ArrayLike,
    layer_um: ArrayLike,
    edge_radius_um: ArrayLike,
    geometry: RoundedGeometry,
    kind: str = "gaussian",
    spectral_weight: ArrayLike | None = None,
) -> Float[Array, "..."]:
    """The flat facets' part of `lab_density_rounded` (1/sr): Gaussian facets, the three delta
    lobes with the rounded weights (`geometry.delta_weight`), 3-D Fresnel factors and the
    kernels of `lab_density_gaussian`; microfacet facets, `lab_density_microfacet`'s single
    reflections scaled by each facet's flat share `(L_k - r) / L_k` and its two-bounce path by
    the rounded corner reflector's weight over the sharp one [conventions §11, §12]. Cheap:
    no arc is evaluated, so it can be taken at every node."""
    w_i, w_o, (beta2, width) = _broadcast(w_i, w_o, beta2, width)
    band = _band(n, spectral_weight)
    inc, view = projected_incidence(w_i), projected_view(w_o)
    up = (w_i[..., 2] > 0.0) & (w_o[..., 2] > 0.0)
    delta_w = geometry.delta_weight  # (..., 3)
    if kind == "gaussian":
        fresnel = _lobe_fresnel_band(inc.theta, inc.t, beta2, band)  # (..., 3)
        ratio = delta_w * fresnel
        theta_o = lobe_directions(inc.theta, beta2)
        to, s, ratio, theta_o = same_rank(view.theta[..., None], width[..., None], ratio, theta_o)
        k_in = hemisphere_gaussian(to, theta_o, s)
        out = jnp.sum(ratio * k_in, axis=-1) * line_gaussian(view.t, -inc.t, width)
        return jnp.where(up, out, 0.0)
    single, retro = microfacet_parts(w_i, w_o, beta2, band, width, kind)
    l1, r = (jnp.broadcast_to(jnp.asarray(a, beta2.dtype), beta2.shape)
             for a in (layer_um, edge_radius_um))  # fmt: skip
    l2 = l1 * jnp.cos(beta2) / jnp.sin(beta2)
    flat = jnp.stack(
        [jnp.clip((l2 - r) / jnp.maximum(l2, _TINY), 0.0, 1.0),
         jnp.clip((l1 - r) / jnp.maximum(l1, _TINY), 0.0, 1.0)], axis=-1,
    )  # fmt: skip
    sharp_retro = lobe_weights(inc.theta, beta2)[..., 2]
    has = sharp_retro > 1e-9
    scale_retro = jnp.where(
        has, delta_w[..., 2] / jnp.where(has, sharp_retro, 1.0), jnp.min(flat, axis=-1)
    )
    single, flat = same_rank(single, flat)
    facets = jnp.sum(single * flat, axis=-1)
    return jnp.where(up, facets + retro * scale_retro, 0.0)


def rounded_arcs(
    w_i: ArrayLike,
    w_o: ArrayLike,
    beta2: ArrayLike,
    n: ArrayLike,
    width: ArrayLike,
    geometry: RoundedGeometry,
    kind: str = "gaussian",
    spectral_weight: ArrayLike | None = None,
) -> Float[Array, "..."]:
    """The arcs' part of `lab_density_rounded` (1/sr): the rounded model's continuous lobes at
    the projected angles (3-D Fresnel factors), spread by a Gaussian of width sigma
    (Gaussian facets) or `ARC_SIGMA_PER_ALPHA * alpha` (microfacet facets) in `theta'` and, by
    `line_gaussian`, in `t` [conventions §11, §12]. The arcs' own spread of directions is far
    wider than the nodes of one face (a few degrees), so a fit may take it once per face
    (`fitting/_lab.py`)."""
    w_i, w_o, (beta2, width) = _broadcast(w_i, w_o, beta2, width)
    band = _band(n, spectral_weight)
    inc, view = projected_incidence(w_i), projected_view(w_o)
    up = (w_i[..., 2] > 0.0) & (w_o[..., 2] > 0.0)
    sigma = width if kind == "gaussian" else ARC_SIGMA_PER_ALPHA * width
    arcs_only = geometry._replace(delta_weight=jnp.zeros_like(geometry.delta_weight))
    rho = _rounded_band(arcs_only, inc.theta, view.theta, beta2, band, sigma, inc.t)
    return jnp.where(up, rho * line_gaussian(view.t, -inc.t, sigma), 0.0)
