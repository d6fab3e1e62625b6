"""Rounded edges in the lab model: the rounded staircase (docs/rounded.md) for 3-D directions,
with Gaussian or microfacet facets (docs/model.md §7.6) [conventions §11, §12].

The rounded profile is extruded like the sharp one, so a 3-D ray follows its projection's
in-plane path (docs/model.md §7.1): the rounded model is evaluated at the projected angles,
every Fresnel factor at the 3-D local angle, and its light leaves with `t_o = -t_i`.

* Gaussian facets: `brdf_rounded` at `(theta_i', theta_o')` times `line_gaussian` in `t_o`.
* Microfacet facets: the flat parts reflect as the sharp microfacet staircase's facets
  (`lab_density_microfacet`'s single reflections, each facet scaled by the share of its lit
  and seen part that stays flat), the two-bounce path scaled by the rounded corner reflector's
  weight over the sharp one, and the arcs' continuous lobes spread by a Gaussian of width
  `ARC_SIGMA_PER_ALPHA * alpha` in the plane (the single reflection counted where the camera
  sees the arc, `arc_single_seen`) and by the slope distribution along the layer lines
  (`arc_deflection`).
* The body: the flats' Lambertian body on their lit and seen flat length and the tips' quarter
  circles (`lab_body_rounded`).

The rounded geometry (which depends on the projected angle of incidence) may be passed in,
computed once at a nearby angle for many nodes (the fit computes it once per photo and face);
the delta lobes' directions, weights' Fresnel factors and every kernel are always evaluated at
each node's own angles.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._broadening import hemisphere_gaussian
from ._lab import (
    _Band,
    _band,
    _broadcast,
    _lobe_fresnel_band,
    body_mirrored,
    body_per_incidence,
    body_terms,
    facet_normals,
    line_gaussian,
    lit_fractions,
    microfacet_parts,
    projected_incidence,
    projected_view,
)
from ._lobes import lobe_directions, lobe_weights
from ._microfacet import slope_marginal
from ._rounded import (
    _ESC_SLOT,
    ROUNDED_RESOLUTION,
    RoundedGeometry,
    arc_single_seen,
    brdf_rounded_from_geometry,
    rounded_delta_weight,
    rounded_geometry,
)
from ._shapes import same_rank, with_rank

ARC_SIGMA_PER_ALPHA = 2.0**0.5
"""With microfacet facets, the arcs of rounded edges spread their light in the plane by a
Gaussian of width `ARC_SIGMA_PER_ALPHA * alpha` (rad): a reflection doubles a micro-normal's
tilt, and Beckmann's slopes along one axis have the standard deviation `alpha / sqrt(2)`; the
arcs' own spread of directions in the plane is far wider, so the kernel's shape matters little
there (along the layer lines it does: `arc_deflection`; docs/model.md §7.6)."""

_TINY = 1e-12
_HORIZON = 0.5 * np.pi - 1e-6


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
    flats = rounded_flats(w_i, w_o, beta2, n, width, layer_um, edge_radius_um, kind,
                          spectral_weight)  # fmt: skip
    arcs = rounded_arcs(w_i, w_o, beta2, n, width, layer_um, edge_radius_um, geometry, kind,
                        spectral_weight)  # fmt: skip
    return flats + arcs


def rounded_flats(
    w_i: ArrayLike,
    w_o: ArrayLike,
    beta2: ArrayLike,
    n: ArrayLike,
    width: ArrayLike,
    layer_um: ArrayLike,
    edge_radius_um: ArrayLike,
    kind: str = "gaussian",
    spectral_weight: ArrayLike | None = None,
) -> Float[Array, "..."]:
    """The flat facets' part of `lab_density_rounded` (1/sr): Gaussian facets, the three delta
    lobes with the rounded weights (`rounded_delta_weight` at each node's own projected angle
    of incidence, as they change fast near a facet's grazing mirror direction; docs/model.md
    §7.6), 3-D Fresnel factors and the
    kernels of `lab_density_gaussian`; microfacet facets, `lab_density_microfacet`'s single
    reflections scaled by the share of each facet's lit and seen part that stays flat: its
    rounded delta weight over its sharp lobe weight (exact at its mirror direction) times how
    `flat_lit_seen`'s share at the view differs from its share at the mirror direction
    (`flat_lit_seen` alone where the sharp weight is 0); its two-bounce path by the rounded
    corner reflector's weight over the sharp one [conventions §11, §12]. Cheap: no arc is
    evaluated, so it can be taken at every node. Uniform shares `(L_k - r) / L_k` made a
    grazing view of a 60-deg wedge's treads 1.7 times too bright against the 3-D tracer; the
    share at the mirror direction alone, a view 10 deg from it 17% too dark against Mitsuba."""
    w_i, w_o, (beta2, width) = _broadcast(w_i, w_o, beta2, width)
    band = _band(n, spectral_weight)
    inc, view = projected_incidence(w_i), projected_view(w_o)
    up = (w_i[..., 2] > 0.0) & (w_o[..., 2] > 0.0)
    l1, r = (jnp.broadcast_to(jnp.asarray(a, beta2.dtype), beta2.shape)
             for a in (layer_um, edge_radius_um))  # fmt: skip
    delta_w = rounded_delta_weight(inc.theta, beta2, l1, r)  # (..., 3)
    if kind == "gaussian":
        fresnel = _lobe_fresnel_band(inc.theta, inc.t, beta2, band)  # (..., 3)
        ratio = delta_w * fresnel
        theta_o = lobe_directions(inc.theta, beta2)
        to, s, ratio, theta_o = same_rank(view.theta[..., None], width[..., None], ratio, theta_o)
        k_in = hemisphere_gaussian(to, theta_o, s)
        out = jnp.sum(ratio * k_in, axis=-1) * line_gaussian(view.t, -inc.t, width)
        return jnp.where(up, out, 0.0)
    single, retro = microfacet_parts(w_i, w_o, beta2, band, width, kind)
    l2 = l1 * jnp.cos(beta2) / jnp.sin(beta2)
    flat = jnp.stack(
        [jnp.clip((l2 - r) / jnp.maximum(l2, _TINY), 0.0, 1.0),
         jnp.clip((l1 - r) / jnp.maximum(l1, _TINY), 0.0, 1.0)], axis=-1,
    )  # fmt: skip
    sharp_w = lobe_weights(inc.theta, beta2)
    has_w = sharp_w[..., :2] > 1e-9
    at_view = _flat_share(*flat_lit_seen(inc.theta, view.theta, beta2, l1, l2, r))
    mirror = jnp.clip(lobe_directions(inc.theta, beta2), -_HORIZON, _HORIZON)
    at_mirror = jnp.stack(
        [_flat_share(*flat_lit_seen(inc.theta, mirror[..., k], beta2, l1, l2, r))[..., k]
         for k in range(2)], axis=-1,
    )  # fmt: skip
    exact = delta_w[..., :2] / jnp.where(has_w, sharp_w[..., :2], 1.0)
    # the exact share at the mirror direction corrects `flat_lit_seen`'s share at the view;
    # where the mirror direction sees no flat part (an arc hides it) the view may still see
    # one, and that share is the limit of the correction (exact and at_mirror vanish together)
    has_m = has_w & (at_mirror > _TINY)
    seen = jnp.where(has_m, exact * at_view / jnp.where(has_m, at_mirror, 1.0), at_view)
    sharp_retro = sharp_w[..., 2]
    has = sharp_retro > 1e-9
    scale_retro = jnp.where(
        has, delta_w[..., 2] / jnp.where(has, sharp_retro, 1.0), jnp.min(flat, axis=-1)
    )
    single, seen = same_rank(single, seen)
    facets = jnp.sum(single * seen, axis=-1)
    return jnp.where(up, facets + retro * scale_retro, 0.0)


def _flat_share(flat_len: Array, sharp_len: Array) -> Array:
    """The flat share of each facet's lit and seen length (0 where the sharp one is 0)."""
    ok = sharp_len > _TINY
    return jnp.where(ok, flat_len / jnp.where(ok, sharp_len, 1.0), 0.0)


def flat_lit_seen(
    theta_i: Array, theta_o: Array, beta2: Array, l1: Array, l2: Array, r: Array
) -> tuple[Array, Array]:
    """Each facet's (tread, riser) flat length that is both lit and seen when its convex tips
    are rounded with radius `r` (um), and the sharp staircase's lit and seen length, both
    `(..., 2)`, for projected angles `theta_i'`, `theta_o'` [docs/model.md §7.6].

    Shadows and masking fall into the concave corners, so the lit (seen) part of a facet runs
    from its tip; the arc takes the tip's first `r` (its tangent length on a right-angled
    corner). A rounded tip casts a lower edge: the line along a direction `d` that grazes the
    arc lies `delta = r (|(n_t + n_r) . d_perp| - 1)` (when positive) inside the one through the
    sharp tip, which moves the shadow's (mask's) end on facet `k` by `delta / (d . n_k)`.
    Without that shift a grazing view of a 40-deg wedge lost half its body radiance."""
    b = beta2
    n_t = (jnp.sin(b), jnp.cos(b))
    n_r = (-jnp.cos(b), jnp.sin(b))
    bis = (n_t[0] + n_r[0], n_t[1] + n_r[1])
    length = jnp.stack([l2, l1], axis=-1)

    def reach(sharp_frac: Array, dx: Array, dz: Array) -> Array:
        delta = r * jnp.maximum(jnp.abs(bis[0] * dz - bis[1] * dx) - 1.0, 0.0)
        facing = jnp.stack([dx * n_t[0] + dz * n_t[1], dx * n_r[0] + dz * n_r[1]], axis=-1)
        shift = delta[..., None] / jnp.maximum(facing, _TINY)
        return jnp.where(facing > 0.0, jnp.minimum(sharp_frac * length + shift, length), 0.0)

    lit = reach(lit_fractions(theta_i, beta2), -jnp.sin(theta_i), jnp.cos(theta_i))
    seen = reach(lit_fractions(-theta_o, beta2), jnp.sin(theta_o), jnp.cos(theta_o))
    flat = jnp.clip(jnp.minimum(lit, seen) - r[..., None], 0.0, None)
    sharp = jnp.minimum(lit_fractions(theta_i, beta2), lit_fractions(-theta_o, beta2)) * length
    return flat, sharp


ARC_BODY_NODES = 8
"""Gauss-Legendre nodes across a rounded tip's quarter circle for its diffuse body
(`lab_body_rounded`): the integrand is a product of two clipped cosines, smooth but for one
kink, so 8 nodes keep it well under a per cent of the arc's body."""


def lab_body_rounded(
    w_i: ArrayLike,
    w_o: ArrayLike,
    beta2: ArrayLike,
    n: ArrayLike,
    layer_um: ArrayLike,
    edge_radius_um: ArrayLike,
    spectral_weight: ArrayLike | None = None,
) -> Float[Array, "..."]:
    """`lab_body` of the rounded staircase: the flat parts' Lambertian body on their lit and
    seen flat length (`flat_lit_seen`) plus each tip's quarter circle (length `pi r / 2`, its
    normal turning from the tread's to the riser's), unshadowed (shadows fall into the concave
    corners), and the flats' bodies in each other's mirror (`body_mirrored`, each flat's
    reach from the corner ending at its tip's arc) [conventions §11]. At `edge_radius_um = 0`
    it is `lab_body`. A sharp body on a 60-deg wedge with 25-um tips gave a third of Mitsuba's
    body radiance at a grazing view."""
    w_i, w_o, (beta2,) = _broadcast(w_i, w_o, beta2)
    band = _band(n, spectral_weight)
    inc, view = projected_incidence(w_i), projected_view(w_o)
    l1 = jnp.broadcast_to(jnp.asarray(layer_um, beta2.dtype), beta2.shape)
    r = jnp.broadcast_to(jnp.asarray(edge_radius_um, beta2.dtype), beta2.shape)
    l2 = l1 * jnp.cos(beta2) / jnp.sin(beta2)
    period = l1 / jnp.sin(beta2)
    normals = facet_normals(beta2)  # (..., 2, 3)
    flat_len, _ = flat_lit_seen(inc.theta, view.theta, beta2, l1, l2, r)
    flats = jnp.sum(flat_len * body_terms(w_i, w_o, normals, band), axis=-1) / period
    length = jnp.stack([l2, l1], axis=-1) / period[..., None]  # (tread, riser) per period
    reach = jnp.maximum(length - (r / period)[..., None], 0.0)  # each flat ends at its tip's arc
    lit, seen = lit_fractions(inc.theta, beta2), lit_fractions(-view.theta, beta2)
    flats = flats + body_mirrored(w_i, w_o, normals, length, reach, lit, seen, band)
    x, w = np.polynomial.legendre.leggauss(ARC_BODY_NODES)
    rank = normals.ndim  # (..., 2, 3): the nodes take the facet axis' place
    phi = with_rank(jnp.asarray(0.25 * np.pi * (x + 1.0), beta2.dtype)[:, None], rank)
    arc_n = jnp.cos(phi) * normals[..., :1, :] + jnp.sin(phi) * normals[..., 1:, :]  # (..., N, 3)
    weight = with_rank(jnp.asarray(0.25 * np.pi * w, beta2.dtype), rank - 1)  # (..., N)
    arcs = jnp.sum(weight * body_terms(w_i, w_o, arc_n, band), axis=-1) * r / period
    return body_per_incidence(w_i, w_o, flats + arcs)


def rounded_arcs(
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
    """The arcs' part of `lab_density_rounded` (1/sr): `arc_panels` plus, with microfacet
    facets, `arc_single` [conventions §11, §12]."""
    panels = arc_panels(w_i, w_o, beta2, n, width, geometry, kind, spectral_weight)
    if kind == "gaussian":
        return panels
    return panels + arc_single(w_i, w_o, beta2, n, width, layer_um, edge_radius_um, kind,
                               spectral_weight)  # fmt: skip


def _along(w_i: Array, w_o: Array, width: Array, kind: str) -> Array:
    """The arcs' density in `t_o`: `line_gaussian` (Gaussian facets) or `arc_deflection`."""
    if kind == "gaussian":
        return line_gaussian(projected_view(w_o).t, -projected_incidence(w_i).t, width)
    return arc_deflection(w_i, w_o, width, kind)


def arc_panels(
    w_i: ArrayLike,
    w_o: ArrayLike,
    beta2: ArrayLike,
    n: ArrayLike,
    width: ArrayLike,
    geometry: RoundedGeometry,
    kind: str = "gaussian",
    spectral_weight: ArrayLike | None = None,
) -> Float[Array, "..."]:
    """The rounded model's continuous lobes (`geometry`'s panels) at the projected angles (3-D
    Fresnel factors), spread by a Gaussian of width sigma (Gaussian facets) or
    `ARC_SIGMA_PER_ALPHA * alpha` (microfacet facets) in `theta'` and along the layer lines by
    `line_gaussian` resp. `arc_deflection` (1/sr) [conventions §11, §12]. With microfacet
    facets without the arcs' single reflection (`arc_single`). Their spread of directions is
    far wider than the nodes of one face (a few degrees), so a fit takes them once per face
    (`fitting/_lab.py`)."""
    w_i, w_o, (beta2, width) = _broadcast(w_i, w_o, beta2, width)
    band = _band(n, spectral_weight)
    inc, view = projected_incidence(w_i), projected_view(w_o)
    up = (w_i[..., 2] > 0.0) & (w_o[..., 2] > 0.0)
    sigma = width if kind == "gaussian" else ARC_SIGMA_PER_ALPHA * width
    arcs_only = geometry._replace(delta_weight=jnp.zeros_like(geometry.delta_weight))
    if kind != "gaussian":  # `arc_single` has the single reflection
        density = geometry.nodes.density.at[..., _ESC_SLOT, :, :].set(0.0)
        arcs_only = arcs_only._replace(nodes=geometry.nodes._replace(density=density))
    rho = _rounded_band(arcs_only, inc.theta, view.theta, beta2, band, sigma, inc.t)
    return jnp.where(up, rho * _along(w_i, w_o, width, kind), 0.0)


def arc_single(
    w_i: ArrayLike,
    w_o: ArrayLike,
    beta2: ArrayLike,
    n: ArrayLike,
    width: ArrayLike,
    layer_um: ArrayLike,
    edge_radius_um: ArrayLike,
    kind: str,
    spectral_weight: ArrayLike | None = None,
) -> Float[Array, "..."]:
    """The arcs' single reflection with microfacet facets (`kind` "ggx"/"beckmann", `width` =
    alpha), 1/sr: `arc_single_seen` (an arc point counts where the camera sees it) at the
    projected angles with the 3-D local cosines, band-averaged, times `arc_deflection` along
    the layer lines [conventions §11, §12]. It changes fast with the angles where the next step
    hides the arcs, so a fit takes it at every node (docs/model.md §7.6)."""
    w_i, w_o, (beta2, width) = _broadcast(w_i, w_o, beta2, width)
    band = _band(n, spectral_weight)
    inc, view = projected_incidence(w_i), projected_view(w_o)
    up = (w_i[..., 2] > 0.0) & (w_o[..., 2] > 0.0)
    c = jnp.sqrt(jnp.clip(1.0 - inc.t * inc.t, 0.0, 1.0))
    args = [jnp.asarray(a)[..., None] for a in (inc.theta, view.theta, beta2,
                                                ARC_SIGMA_PER_ALPHA * width, layer_um,
                                                edge_radius_um, c)]  # fmt: skip
    seen = arc_single_seen(*args[:3], band.n, *args[3:])
    seen, w = same_rank(seen, band.weight)
    rho = jnp.sum(seen * w, axis=-1)
    return jnp.where(up, rho * arc_deflection(w_i, w_o, width, kind), 0.0)


def arc_deflection(w_i: Array, w_o: Array, alpha: Array, kind: str) -> Array:
    """Density in `t_o` of an arc's reflection with microfacet facets: a micro-normal's slope
    `s` along the layer lines turns the reflection's `t` by `2 s cos_h` (`cos_h` the local
    cosine, that of half the angle between `w_i` and `w_o`), so the density is the slope's
    (`slope_marginal`, GGX's heavy tails kept) at `(t_o + t_i) / (2 cos_h)` over `2 cos_h`
    [conventions §12]. A Gaussian of the slopes' width gave half the traced density 0.2 in `t`
    from the mirror direction (GGX, alpha 0.06; docs/model.md §7.6)."""
    w_i, w_o = same_rank(w_i, w_o)
    cos_h = jnp.sqrt(jnp.maximum(0.5 * (1.0 + jnp.sum(w_i * w_o, axis=-1)), _TINY))
    dt = w_o[..., 1] + w_i[..., 1]
    return slope_marginal(dt / (2.0 * cos_h), alpha, kind) / (2.0 * cos_h)
