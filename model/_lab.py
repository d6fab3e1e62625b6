"""The staircase for any pair of 3-D directions: out of the plane of incidence, with Gaussian or
microfacet facets (the "lab" model; docs/model.md §7) [conventions §1-§6, §11, §12].

The profile is extruded along the layer lines (y), so every facet normal lies in the (x, z)
plane. A ray's path over the profile is therefore the in-plane path of its projection onto
(x, z): lit widths, shadowing, masking and which facets a ray meets follow from the projected
angles alone, and each reflection keeps the ray's component along y (a mirror whose normal has
no y component). What changes out of the plane is (1) each reflection's local angle, whose
cosine is the in-plane one times the projection's length `c = sqrt(1 - t^2)` (`t` the y
component), (2) the s and p axes of a two-bounce path, which rotate between its two reflections,
and (3) where the reflected light goes: its direction is `(c sin theta', -t_i, c cos theta')`
for the in-plane lobe direction `theta'`. On the unit sphere `d omega = d theta' d t` exactly
(Archimedes), so an in-plane density in 1/rad times a density in `t` is a density per steradian.

Units: every density here is the reflected power per steradian per unit incident power,
`p(w_i, w_o) = f(w_i, w_o) cos(theta_o)` with `f` the BRDF (1/sr) [conventions §11].
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
from jax.scipy.special import erf, erfc
from jaxtyping import Array, ArrayLike, Float

from ._broadening import hemisphere_gaussian
from ._cell import facet_projections
from ._fresnel import SP, fresnel_sp, fresnel_unpolarised
from ._lobes import lobe_directions, lobe_weights
from ._microfacet import DISTRIBUTIONS, ndf, slope_cdf, smith_g1
from ._shapes import same_rank, with_rank

LAB_KERNELS: tuple[str, ...] = ("gaussian", *DISTRIBUTIONS)
"""How the facets spread their reflections: "gaussian" (the paper's broadening, lifted to 3-D)
or a microfacet distribution ("ggx", "beckmann") [conventions §12]."""

_TINY = 1e-12


class _Band(NamedTuple):
    """The refractive index at a channel's wavelength samples, `n` `(..., L)`, and their
    weights `(..., L)` (rows sum to 1) [conventions §8]: every Fresnel factor is evaluated at
    each sample and band-averaged at once, so that no geometry is repeated per wavelength."""

    n: Array
    weight: Array


def _band(n: ArrayLike, spectral_weight: ArrayLike | None) -> _Band:
    """`_Band` of an index without wavelength axis (`spectral_weight` None: one sample of
    weight 1) or with one (`n` and `spectral_weight` of shape `(..., L)`)."""
    n = jnp.asarray(n)
    if spectral_weight is None:
        return _Band(n[..., None], jnp.ones((1,), jnp.result_type(n.real.dtype, float)))
    return _Band(n, jnp.asarray(spectral_weight))


def _fresnel_u(cos: Array, band: _Band) -> Array:
    """Band-averaged unpolarised Fresnel reflectance at local cosine `cos`."""
    c, n, w = same_rank(cos[..., None], band.n, band.weight)
    return jnp.sum(fresnel_unpolarised(c, n) * w, axis=-1)


# --------------------------------------------------------------------------------------------
# Directions
# --------------------------------------------------------------------------------------------


class InPlane(NamedTuple):
    """A 3-D direction split into its projected angle (rad) and its component along the layer
    lines [conventions §11]: `w = (c sin a, t, c cos a)` with `c = sqrt(1 - t^2)` (for a light
    direction `a = -theta`, see `projected_incidence`)."""

    theta: Float[Array, "..."]
    t: Float[Array, "..."]
    c: Float[Array, "..."]


def _unit(w: ArrayLike) -> Array:
    w = jnp.asarray(w)
    norm2 = jnp.sum(w * w, axis=-1, keepdims=True)
    ok = norm2 > _TINY
    return jnp.where(ok, w / jnp.sqrt(jnp.where(ok, norm2, 1.0)), jnp.asarray([0.0, 0.0, 1.0]))


def _split(w: ArrayLike, sign: float) -> InPlane:
    """`theta = atan2(sign * w_x, w_z)` clipped to the hemisphere, `t = w_y`, `c = sqrt(1-t^2)`,
    with finite gradients where the projection vanishes (a direction along the layer lines)."""
    w = _unit(w)
    x, t, z = w[..., 0], w[..., 1], w[..., 2]
    has = x * x + z * z > _TINY
    x_s, z_s = jnp.where(has, x, 0.0), jnp.where(has, z, 1.0)
    theta = jnp.clip(jnp.arctan2(sign * x_s, z_s), -jnp.pi / 2, jnp.pi / 2)
    c2 = 1.0 - t * t
    c = jnp.where(c2 > _TINY, jnp.sqrt(jnp.where(c2 > _TINY, c2, 1.0)), 0.0)
    return InPlane(theta=theta, t=t, c=c)


def _length(t: Array) -> Array:
    """`c = sqrt(1 - t^2)`, the projection's length, with finite derivatives at `t = +-1`
    (double where: the square root's infinite slope at 0 would otherwise turn every zero
    tangent into NaN there)."""
    c2 = jnp.clip(1.0 - t * t, 0.0, 1.0)
    pos = c2 > 0.0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, c2, 1.0)), 0.0)


def projected_incidence(w_i: ArrayLike) -> InPlane:
    """The direction towards the light as (`theta_i'`, `t_i`, `c_i`): `theta_i'` the in-plane
    angle of incidence of its projection, signed as [conventions §1] (`w_i = (-c sin theta_i',
    t_i, c cos theta_i')`) [conventions §11]."""
    return _split(w_i, -1.0)


def projected_view(w_o: ArrayLike) -> InPlane:
    """The direction towards the viewer as (`theta_o'`, `t_o`, `c_o`), `w_o = (c sin theta_o',
    t_o, c cos theta_o')` [conventions §1, §11]."""
    return _split(w_o, 1.0)


def face_direction(theta: ArrayLike, t: ArrayLike, sign: float = 1.0) -> Float[Array, "... 3"]:
    """The unit vector `(sign c sin theta, t, c cos theta)`, `c = sqrt(1 - t^2)`: the inverse of
    `projected_view` (`sign = 1`) and `projected_incidence` (`sign = -1`) [conventions §11]."""
    theta, t = same_rank(theta, t)
    theta, t = jnp.broadcast_arrays(theta, t)
    c = _length(t)
    return jnp.stack([sign * c * jnp.sin(theta), t, c * jnp.cos(theta)], axis=-1)


# --------------------------------------------------------------------------------------------
# Sharp lobes in 3-D
# --------------------------------------------------------------------------------------------


def lobe_fresnel_3d(
    theta_i: ArrayLike, t_i: ArrayLike, beta2: ArrayLike, n: ArrayLike
) -> Float[Array, "... 3"]:
    """Unpolarised Fresnel factor of each sharp lobe for light out of the plane
    [conventions §6, §11].

    `theta_i` is the projected angle of incidence and `t_i` the direction's component along the
    layer lines. A facet's local cosine is the in-plane one times `c = sqrt(1 - t_i^2)`:
    `a = c cos(beta2 + theta_i)` (tread), `b = c sin(beta2 + theta_i)` (riser). In the
    retroreflection the s axis turns between the two reflections by `phi` with
    `sin^2 phi = t^2 / ((a^2 + t^2)(b^2 + t^2))` (docs/model.md §7.2), so a share `sin^2 phi`
    of the light reflected as s at the first facet meets the second as p:
    `((R_s R_s' + R_p R_p') cos^2 phi + (R_s R_p' + R_p R_s') sin^2 phi) / 2`. At `t_i = 0` this
    is `lobe_fresnel` exactly.
    """
    theta_i, t_i, beta2, n = same_rank(theta_i, t_i, beta2, n)
    u = beta2 + theta_i
    c = _length(t_i)
    a, b = c * jnp.cos(u), c * jnp.sin(u)
    tread, riser = fresnel_sp(a, n), fresnel_sp(b, n)
    retro = _two_bounce(tread, riser, a, b, t_i)
    return jnp.stack([0.5 * (tread.s + tread.p), 0.5 * (riser.s + riser.p), retro], axis=-1)


def _two_bounce(first: SP, second: SP, a: Array, b: Array, t: Array) -> Array:
    """Unpolarised factor of two reflections in perpendicular facets at local cosines `a`, `b`
    (their s, p reflectances `first`, `second`) of a ray with component `t` along the layer
    lines: `((R_s R_s' + R_p R_p') cos^2 phi + (R_s R_p' + R_p R_s') sin^2 phi) / 2`,
    `sin^2 phi = t^2 / ((a^2 + t^2)(b^2 + t^2))` (docs/model.md §7.2)."""
    same = 0.5 * (first.s * second.s + first.p * second.p)
    crossed = 0.5 * (first.s * second.p + first.p * second.s)
    t2 = t * t
    den = (a * a + t2) * (b * b + t2)
    ok = (den > _TINY) & (t2 > 0.0)
    sin2 = jnp.clip(jnp.where(ok, t2 / jnp.where(ok, den, 1.0), 0.0), 0.0, 1.0)
    return same + sin2 * (crossed - same)


def _lobe_fresnel_band(theta_i: Array, t_i: Array, beta2: Array, band: _Band) -> Array:
    """`lobe_fresnel_3d` band-averaged: `(..., 3)`."""
    f = lobe_fresnel_3d(theta_i[..., None], t_i[..., None], beta2[..., None], band.n)
    f, w = same_rank(f, band.weight[..., None])
    return jnp.sum(f * w, axis=-2)


class Lobes3D(NamedTuple):
    """The sharp staircase's three lobes for one direction of incidence [conventions §3, §11]:
    in-plane directions `theta_o` (rad), the shared component along the layer lines `t_o`
    (`= -t_i`: each reflection keeps the ray's y component), weights (the in-plane weights at
    the projected angle) and Fresnel factors (`lobe_fresnel_3d`)."""

    theta_o: Float[Array, "... 3"]
    t_o: Float[Array, "..."]
    weight: Float[Array, "... 3"]
    fresnel: Float[Array, "... 3"]

    @property
    def ratio(self) -> Float[Array, "... 3"]:
        """Reflectance ratio of each lobe (weight x Fresnel), dimensionless."""
        return self.weight * self.fresnel


def lab_lobes(
    w_i: ArrayLike, beta2: ArrayLike, n: ArrayLike, spectral_weight: ArrayLike | None = None
) -> Lobes3D:
    """The sharp lobes for light from the 3-D direction `w_i` (face frame) [conventions §11].

    `n` is the index; with `spectral_weight`, `n` and it have a last axis of wavelength
    samples and the Fresnel factors are band-averaged over it [conventions §8]."""
    inc = projected_incidence(w_i)
    ti, t, b = same_rank(inc.theta, inc.t, beta2)
    fresnel = _lobe_fresnel_band(ti, t, b, _band(n, spectral_weight))
    lead = fresnel.shape[:-1]
    ti, t, b = (jnp.broadcast_to(a, lead) for a in (ti, t, b))
    return Lobes3D(
        theta_o=lobe_directions(ti, b), t_o=-t, weight=lobe_weights(ti, b), fresnel=fresnel
    )


# --------------------------------------------------------------------------------------------
# Gaussian facets
# --------------------------------------------------------------------------------------------


def line_gaussian(t: ArrayLike, centre: ArrayLike, sigma: ArrayLike) -> Float[Array, "..."]:
    """Density in `t` (the component along the layer lines) of a Gaussian of width `sigma`
    centred on `centre`, truncated to `[-1, 1]` and renormalised there [conventions §11]: the
    out-of-plane factor of the Gaussian lab model."""
    t, centre, sigma = same_rank(t, centre, sigma)
    centre = jnp.clip(centre, -1.0, 1.0)
    root2s = jnp.sqrt(2.0) * sigma
    mass = 0.5 * (erf((1.0 - centre) / root2s) - erf((-1.0 - centre) / root2s))
    z = (t - centre) / sigma
    density = jnp.exp(-0.5 * z * z) / (jnp.sqrt(2.0 * jnp.pi) * sigma * mass)
    return jnp.where(jnp.abs(t) <= 1.0, density, 0.0)


def lab_density_gaussian(
    w_i: ArrayLike,
    w_o: ArrayLike,
    beta2: ArrayLike,
    n: ArrayLike,
    sigma: ArrayLike,
    sigma_perp: ArrayLike | None = None,
    spectral_weight: ArrayLike | None = None,
) -> Float[Array, "..."]:
    """Reflected power per steradian (per unit incident power) of the sharp staircase with the
    paper's Gaussian broadening, for 3-D directions (face frame) [conventions §5, §11].
    `spectral_weight`: band-average over the last axis of `n` (`lab_lobes`).

    Each lobe's delta becomes the in-plane hemisphere Gaussian of `brdf` (width `sigma`, rad) in
    the projected viewing angle times `line_gaussian` (width `sigma_perp`, default `sigma`) in
    the viewing direction's y component about the lobe's `-t_i`. Every lobe keeps its ratio.
    In the plane (`t_i = t_o = 0`) this is `brdf(theta_i, theta_o) * line_gaussian(0, 0,
    sigma_perp)`.
    """
    sigma_perp = sigma if sigma_perp is None else sigma_perp
    lobes = lab_lobes(w_i, beta2, n, spectral_weight)
    view = projected_view(w_o)
    to, t_o, s, sp, tc = same_rank(view.theta, view.t, sigma, sigma_perp, lobes.t_o)
    k_in = hemisphere_gaussian(to[..., None], lobes.theta_o, s[..., None])
    in_plane = jnp.sum(lobes.ratio * k_in, axis=-1)
    up = (jnp.asarray(w_o)[..., 2] > 0.0) & (jnp.asarray(w_i)[..., 2] > 0.0)
    return jnp.where(up, in_plane * line_gaussian(t_o, tc, sp), 0.0)


# --------------------------------------------------------------------------------------------
# Microfacet facets
# --------------------------------------------------------------------------------------------


def _ratio01(num: Array, den: Array) -> Array:
    """`num / den` clipped to [0, 1], 0 where `den <= 0` (double where)."""
    ok = den > _TINY
    return jnp.where(ok, jnp.clip(num / jnp.where(ok, den, 1.0), 0.0, 1.0), 0.0)


def lit_fractions(theta: ArrayLike, beta2: ArrayLike) -> Float[Array, "... 2"]:
    """Fractions (tread, riser) of each facet's length lit by light at the projected angle
    `theta` [conventions §2, §11]: 1 where nothing shadows it, less where the neighbouring tip
    does (regime A for the tread, C for the riser), 0 where it faces away. The shadow always
    starts at the concave corner, so the same function of `-theta_o` is the visible fraction,
    and a facet's part both lit and seen is the smaller of the two."""
    theta, beta2 = same_rank(theta, beta2)
    proj = facet_projections(theta, beta2)
    u = beta2 + theta
    tread = _ratio01(proj.tread, jnp.cos(beta2) * jnp.cos(u))
    riser = _ratio01(proj.riser, jnp.sin(beta2) * jnp.sin(u))
    return jnp.stack([tread, riser], axis=-1)


def facet_normals(beta2: ArrayLike) -> Float[Array, "... 2 3"]:
    """Outward unit normals (tread, riser) in the face frame: `(sin b2, 0, cos b2)` and
    `(-cos b2, 0, sin b2)` [conventions §2]."""
    b = jnp.asarray(beta2)
    sb, cb, zero = jnp.sin(b), jnp.cos(b), jnp.zeros_like(b)
    tread = jnp.stack([sb, zero, cb], axis=-1)
    riser = jnp.stack([-cb, zero, sb], axis=-1)
    return jnp.stack([tread, riser], axis=-2)


def microfacet_lobe(
    w_i: Array, w_o: Array, normal: Array, band: _Band, alpha: Array, kind: str
) -> Array:
    """`D(h) F(w_i . h) G1(w_i) G1(w_o) / 4` of a rough facet with outward `normal` (the
    microfacet reflection without its `1 / (w_i . n)(w_o . n)`), `h` the half vector; unit
    vectors on the last axis [conventions §12]."""
    s = w_i + w_o
    h = _unit(s)
    cos_h = jnp.sum(h * normal, axis=-1)
    cos_ih = jnp.sum(w_i * h, axis=-1)
    cos_i = jnp.sum(w_i * normal, axis=-1)
    cos_o = jnp.sum(w_o * normal, axis=-1)
    g = smith_g1(cos_i, cos_ih, alpha, kind) * smith_g1(cos_o, cos_ih, alpha, kind)
    f = _fresnel_u(jnp.clip(cos_ih, 0.0, 1.0), band)
    return ndf(cos_h, alpha, kind) * f * g / 4.0


RETRO_NODES = 16
"""Nodes of the rule over a rough facet's in-plane deflection in the two-bounce path."""


def _deflection_rule(kind: str) -> tuple[np.ndarray, np.ndarray]:
    """In-plane deflections (in units of `alpha`) and weights (sum 1) of one rough reflection:
    twice a micro-normal's in-plane slope, whose marginal is normal (Beckmann, standard
    deviation `alpha / sqrt 2`) or Student's t with 2 degrees of freedom (GGX, scale
    `alpha / sqrt 2`). Beckmann: Gauss-Hermite; GGX: Gauss-Legendre in the cumulative
    probability `u`, at the closed-form quantiles `y sqrt(2 / (1 - y^2))`, `y = 2u - 1`, whose
    nodes crowd towards both ends and so resolve the heavy tails [conventions §12]."""
    if kind == "beckmann":
        x, w = np.polynomial.hermite_e.hermegauss(RETRO_NODES)
        return np.sqrt(2.0) * x, w / w.sum()
    y, w = np.polynomial.legendre.leggauss(RETRO_NODES)
    return np.sqrt(2.0) * y * np.sqrt(2.0 / (1.0 - y * y)), w / w.sum()


def _ggx_deflection_quantile(u: np.ndarray) -> np.ndarray:
    """The deflection (units of `alpha`) below which the share `u` of one GGX reflection's
    deflections lies (the quantiles `_deflection_rule` takes its nodes at)."""
    y = 2.0 * u - 1.0
    return np.sqrt(2.0) * y * np.sqrt(2.0 / (1.0 - y * y))


def _deflection_spread(kind: str) -> np.ndarray:
    """The standard deviation (units of `alpha`) of the deflections each node of
    `_deflection_rule` stands for: its weight is the probability of a cell (consecutive cells,
    in the order of the nodes), taken as uniform in the deflection between the cell's edges;
    an outermost cell, unbounded, as reaching as far beyond its node as its inner edge lies
    before it. The two-bounce path spreads each node's light by it (`_retro_one_way`): a
    node far in GGX's tail stands for deflections tens of degrees apart, and drawn as one
    narrow lobe it made a spurious peak (six to thirteen times the 3-D tracer's density on a
    30-deg wedge 50 deg from the retroreflection). Beckmann's nodes lie closer than the
    second reflection's own width (`2 alpha`) out to where their weights vanish: 0 there."""
    x, w = _deflection_rule(kind)
    if kind == "beckmann":
        return np.zeros_like(x)
    cum = np.concatenate([[0.0], np.cumsum(w)])
    inner = np.clip(cum[1:-1], 1e-15, 1.0 - 1e-15)
    edges = np.concatenate([[np.nan], _ggx_deflection_quantile(inner), [np.nan]])
    edges[0] = 2.0 * x[0] - edges[1]
    edges[-1] = 2.0 * x[-1] - edges[-2]
    return np.diff(edges) / np.sqrt(12.0)


class RoughRetro(NamedTuple):
    """The rough two-bounce path for one direction of incidence, per first facet (tread,
    riser) and deflection node (last two axes): `mass`, the share of the rays hitting a period
    that take it (their first reflection deflected by `shift` in the plane and not seen from
    outside), `shift` (rad), by how much that turns the path's outgoing in-plane direction
    (`-deflection`: the second mirror reverses it), and `cos_second`, the in-plane local cosine
    at which the deflected ray meets the other facet (`|sin(u + delta)|` on the riser after the
    tread, `|cos(u + delta)|` on the tread after the riser, `u = beta2 + theta_i`)
    [conventions §3, §12]."""

    mass: Float[Array, "... 2 N"]
    shift: Float[Array, "... 2 N"]
    cos_second: Float[Array, "... 2 N"]
    spread: Float[Array, "... 2 N"]

    @property
    def weight(self) -> Float[Array, "..."]:
        """The path's share of the rays: its geometric weight."""
        return jnp.sum(self.mass, axis=(-2, -1))


def rough_retro(
    theta_i: ArrayLike, beta2: ArrayLike, alpha: ArrayLike, kind: str = "ggx"
) -> RoughRetro:
    """Which rays of a rough staircase reflect twice, by first facet and in-plane deflection.

    Of each facet's lit rays (the share `p_k / cos theta_i` of a period) a reflection deflected
    by `delta` (`_deflection_rule`) is seen from outside for the share
    `min(1, visible(mirror + delta) / lit)` (`lit_fractions`); the rest meets the other facet.
    As `alpha -> 0` the total is the sharp retro weight `2 min(p_r, p_t) / cos theta_i`.
    """
    theta_i, beta2, alpha = same_rank(theta_i, beta2, alpha)
    x, w = (with_rank(jnp.asarray(a, jnp.result_type(theta_i, float)), theta_i.ndim + 2)
            for a in _deflection_rule(kind))  # (..., 1, N) each  # fmt: skip
    lit = lit_fractions(theta_i, beta2)  # (..., 2)
    mirror = lobe_directions(theta_i, beta2)[..., :2]  # tread, riser lobe directions
    delta = alpha[..., None, None] * x  # (..., 1, N)
    out = jnp.clip(mirror[..., None] + delta, -jnp.pi / 2, jnp.pi / 2)  # (..., 2, N)
    b = beta2[..., None]
    seen = jnp.stack([lit_fractions(-out[..., k, :], b)[..., k] for k in range(2)], axis=-2)
    trapped = 1.0 - jnp.minimum(1.0, seen / jnp.where(lit > 0, lit, 1.0)[..., None])
    proj = facet_projections(theta_i, beta2)
    cos_i = proj.riser + proj.tread
    share = (
        jnp.stack([proj.tread, proj.riser], axis=-1)
        / jnp.where(cos_i > _TINY, cos_i, 1.0)[..., None]
    )
    share = jnp.where((cos_i > _TINY)[..., None] & (lit > 0), share, 0.0)
    mass = share[..., None] * trapped * w
    u = (beta2 + theta_i)[..., None] + delta[..., 0, :]  # (..., N)
    second = jnp.stack([jnp.abs(jnp.sin(u)), jnp.abs(jnp.cos(u))], axis=-2)
    spread = alpha[..., None, None] * with_rank(
        jnp.asarray(_deflection_spread(kind), mass.dtype), theta_i.ndim + 2
    )
    return RoughRetro(mass=mass, shift=jnp.broadcast_to(-delta, mass.shape),
                      cos_second=jnp.broadcast_to(second, mass.shape),
                      spread=jnp.broadcast_to(spread, mass.shape))  # fmt: skip


def retro_weight_rough(
    theta_i: ArrayLike, beta2: ArrayLike, alpha: ArrayLike, kind: str = "ggx"
) -> Float[Array, "..."]:
    """Share of the rays hitting a period that reflect twice when the facets are rough
    (`rough_retro`'s total) [conventions §3, §12]."""
    return rough_retro(theta_i, beta2, alpha, kind).weight


def _broadcast(
    w_i: ArrayLike, w_o: ArrayLike, *scalars: ArrayLike
) -> tuple[Array, Array, tuple[Array, ...]]:
    """Unit `w_i`, `w_o` (last axis 3) and scalars broadcast to one leading shape."""
    w_i, w_o = _unit(w_i), _unit(w_o)
    xs = [jnp.asarray(x) for x in scalars]
    lead = jnp.broadcast_shapes(w_i.shape[:-1], w_o.shape[:-1], *(x.shape for x in xs))
    w_i = jnp.broadcast_to(w_i, (*lead, 3))
    w_o = jnp.broadcast_to(w_o, (*lead, 3))
    return w_i, w_o, tuple(jnp.broadcast_to(x, lead) for x in xs)


GGX_SCALE_POWER = 1.5
"""Two independent deflections with GGX's slope distribution (Student's t, 2 degrees of
freedom) of scales `a` and `b` add to about that distribution with the scale
`(a^p + b^p)^(1/p)`, `p = GGX_SCALE_POWER`: between the Cauchy's sum of scales (`p = 1`) and
the normal's quadrature (`p = 2`, exact for Beckmann); checked against the 3-D ray tracer
(tests/validation/test_lab_vs_raytrace.py)."""


def _combined_scale(a: Array, b: Array, kind: str) -> Array:
    """`(a^p + b^p)^(1/p)` with `p = 2` (Beckmann) or `GGX_SCALE_POWER` (GGX), finite
    gradients at `a = b = 0`."""
    p = 2.0 if kind == "beckmann" else GGX_SCALE_POWER
    total = (a + _TINY) ** p + (b + _TINY) ** p
    return total ** (1.0 / p)


def _retro_one_way(
    w_i: Array, w_o: Array, beta2: Array, band: _Band, alpha: Array, kind: str
) -> Array:
    """The rough two-bounce path's reflected power per steradian for light from `w_i`, seen
    from `w_o` (unit vectors, face frame; broadcast) [conventions §11, §12].

    Per first facet and deflection node of `rough_retro`, the path leaves in the plane at
    `-theta_i' + shift` and along the layer lines at `-t_i`; the second reflection spreads it by
    a microfacet lobe in the deflection `(d theta', d t)` (`d omega = d theta' d t`) with scales
    `s1 = 2 alpha` (one reflection's in-plane turn) and `s2 = 2 alpha |(a, b)|` (both
    reflections' turn along the layer lines, `a`, `b` the facets' local cosines, their scales
    combined by `_combined_scale`): GGX
    `1 / (pi s1 s2 (1 + x^2 + y^2)^2)`, Beckmann `exp(-x^2 - y^2) / (pi s1 s2)`, `x = (d theta' -
    shift) / s1`, `y = d t / s2` (docs/model.md §7.4). The power is the mass times the 3-D
    Fresnel factor and each reflection's micro-shadowing `G1(a)^2 G1(b)^2` (a narrow lobe's
    albedo). Deflections beyond the horizon are lost.
    """
    inc, view = projected_incidence(w_i), projected_view(w_o)
    paths = rough_retro(inc.theta, beta2, alpha, kind)
    u = beta2 + inc.theta
    c = inc.c[..., None, None]
    first = c * jnp.stack([jnp.cos(u), jnp.sin(u)], axis=-1)[..., None]  # (..., 2, 1)
    second = c * paths.cos_second  # (..., 2, N): the deflected ray's cosine at the other facet
    first = jnp.broadcast_to(first, second.shape)
    a = jnp.stack([first[..., 0, :], second[..., 1, :]], axis=-2)  # tread's cosine per path
    b = jnp.stack([second[..., 0, :], first[..., 1, :]], axis=-2)  # riser's cosine
    t = inc.t[..., None, None]
    factor = _two_bounce_band(a, b, t, band)  # (..., 2, N)
    al = alpha[..., None, None]
    shadow = (smith_g1(a, a, al, kind) * smith_g1(b, b, al, kind)) ** 2
    s1 = jnp.sqrt(4.0 * al * al + 2.0 * paths.spread**2)
    s2 = 2.0 * al * jnp.maximum(_combined_scale(jnp.abs(a), jnp.abs(b), kind), 1e-3)
    x = ((view.theta + inc.theta)[..., None, None] - paths.shift) / s1
    y = (view.t + inc.t)[..., None, None] / s2
    r2 = x * x + y * y
    if kind == "ggx":
        kern = 1.0 / (jnp.pi * s1 * s2 * (1.0 + r2) ** 2)
    else:
        kern = jnp.exp(-r2) / (jnp.pi * s1 * s2)
    return jnp.sum(factor * shadow * paths.mass * kern, axis=(-2, -1))


def _two_bounce_band(a: Array, b: Array, t: Array, band: _Band) -> Array:
    """`_two_bounce` at the facets' local cosines `a` (tread) and `b` (riser), band-averaged over
    `band`'s samples: `a`, `b`, `t` of shape `(..., 2, N)` (paths, nodes), the samples on a
    last axis after them."""
    n = band.n[..., None, None, :]  # (..., 1, 1, L)
    a_, b_, t_, n = same_rank(a[..., None], b[..., None], t[..., None], n)
    f = _two_bounce(fresnel_sp(a_, n), fresnel_sp(b_, n), a_, b_, t_)
    f, w = same_rank(f, band.weight[..., None, None, :])
    return jnp.sum(f * w, axis=-1)


def lab_density_microfacet(
    w_i: ArrayLike,
    w_o: ArrayLike,
    beta2: ArrayLike,
    n: ArrayLike,
    alpha: ArrayLike,
    kind: str = "ggx",
    spectral_weight: ArrayLike | None = None,
) -> Float[Array, "..."]:
    """Reflected power per steradian (per unit incident power) of the sharp staircase whose
    facets are microfacet-rough (roughness `alpha`, distribution `kind`), for 3-D directions
    (face frame) [conventions §11, §12].

    Single reflections: for each facet `k` of length `L_k` (`l2` tread, `l1` riser, per period
    `l`), `(L_k / l) V_k D F G / (4 w_i . z)` with `V_k` the share of the facet both lit and seen
    (`lit_fractions` at `theta_i'` and `-theta_o'`): the microfacet BRDF of each facet, weighted
    by its visible lit area, exact for single scattering and reciprocal (docs/model.md §7.3).
    The two-bounce retroreflection follows `_retro_one_way`, the path from the light (not
    reciprocal in its far tails; averaging it with its reverse was further from the tracer and
    let the reflected power exceed 1 near grazing: `RETRO_RECIPROCAL`, docs/model.md §7.4).
    """
    w_i, w_o, (beta2, alpha) = _broadcast(w_i, w_o, beta2, alpha)
    single, retro = microfacet_parts(w_i, w_o, beta2, _band(n, spectral_weight), alpha, kind)
    return jnp.sum(single, axis=-1) + retro


RETRO_RECIPROCAL = False


def microfacet_parts(
    w_i: Array, w_o: Array, beta2: Array, band: _Band, alpha: Array, kind: str
) -> tuple[Array, Array]:
    """The terms of `lab_density_microfacet` (unit `w_i`, `w_o` and the scalars broadcast to one
    leading shape, `_broadcast`): the single reflections per facet `(..., 2)` (tread, riser) and
    the two-bounce path `(...)`, 0 below the horizon [conventions §11, §12]."""
    inc, view = projected_incidence(w_i), projected_view(w_o)
    cos_i, cos_o = w_i[..., 2], w_o[..., 2]
    up = (cos_i > 0.0) & (cos_o > 0.0)
    visible = jnp.minimum(lit_fractions(inc.theta, beta2), lit_fractions(-view.theta, beta2))
    normals = facet_normals(beta2)
    length = jnp.stack([jnp.cos(beta2), jnp.sin(beta2)], axis=-1)  # L_k / l
    lobes = jnp.stack(
        [microfacet_lobe(w_i, w_o, normals[..., k, :], band, alpha, kind) for k in range(2)], -1
    )
    cos_i_safe = jnp.where(up, cos_i, 1.0)
    single = length * visible * lobes / cos_i_safe[..., None]
    # the two-bounce path from the light; with RETRO_RECIPROCAL, the mean of it and the
    # reversed path from the viewer (p(w_o -> w_i) cos_o / cos_i)
    retro = _retro_one_way(w_i, w_o, beta2, band, alpha, kind)
    if RETRO_RECIPROCAL:
        backward = _retro_one_way(w_o, w_i, beta2, band, alpha, kind)
        retro = 0.5 * (retro + backward * jnp.where(up, cos_o, 0.0) / cos_i_safe)
    return jnp.where(up[..., None], single, 0.0), jnp.where(up, retro, 0.0)


# --------------------------------------------------------------------------------------------
# The diffuse body and the radiance
# --------------------------------------------------------------------------------------------


def lab_body(
    w_i: ArrayLike,
    w_o: ArrayLike,
    beta2: ArrayLike,
    n: ArrayLike,
    spectral_weight: ArrayLike | None = None,
) -> Float[Array, "..."]:
    """The diffuse body of the staircase's material, per unit albedo (1/sr x pi): light that
    enters a facet (transmittance `1 - F`), is scattered inside and leaves through a facet
    (`1 - F` again), Lambertian, each facet weighted by its visible lit share:
    `sum_k (L_k / l) V_k (w_i . n_k)(w_o . n_k) T_i T_o / (w_i . z)`, plus each facet's body
    seen in the other facet's mirror and lit through it (`body_mirrored`) [conventions §11].
    For a flat surface it is `cos(theta_o) T_i T_o`, so `floor * lab_body / cos(theta_o)` is a
    Lambertian radiance per unit irradiance (`floor cos(theta_i)` when `n -> 1`)."""
    w_i, w_o, (beta2,) = _broadcast(w_i, w_o, beta2)
    band = _band(n, spectral_weight)
    inc, view = projected_incidence(w_i), projected_view(w_o)
    lit, seen = lit_fractions(inc.theta, beta2), lit_fractions(-view.theta, beta2)
    visible = jnp.minimum(lit, seen)
    length = jnp.stack([jnp.cos(beta2), jnp.sin(beta2)], axis=-1)
    normals = facet_normals(beta2)
    terms = body_terms(w_i, w_o, normals, band)  # (..., 2)
    mirrored = body_mirrored(w_i, w_o, normals, length, length, lit, seen, band)
    return body_per_incidence(w_i, w_o, jnp.sum(length * visible * terms, axis=-1) + mirrored)


def _facet_cosines(w: Array, normals: Array) -> Array:
    """A direction's cosine with each normal, clipped to [0, 1]: `(..., K)` for `(..., K, 3)`."""
    return jnp.clip(jnp.einsum("...j,...kj->...k", w, normals), 0.0, 1.0)


def body_terms(w_i: Array, w_o: Array, normals: Array, band: _Band) -> Array:
    """Each surface normal's diffuse term `(w_i . m)(w_o . m) T_i T_o` (both cosines clipped to
    [0, 1], `T = 1 - F` band-averaged over `band`'s samples), `(..., K)` for normals
    `(..., K, 3)` [conventions §11]."""
    cos_i, cos_o = _facet_cosines(w_i, normals), _facet_cosines(w_o, normals)
    ci, co, bn, bw = same_rank(  # (..., K, L): the normal axis before the samples
        cos_i[..., None], cos_o[..., None], band.n[..., None, :], band.weight[..., None, :]
    )
    trans = (1.0 - fresnel_unpolarised(ci, bn)) * (1.0 - fresnel_unpolarised(co, bn))
    return cos_i * cos_o * jnp.sum(trans * bw, axis=-1)


def body_mirrored(
    w_i: Array,
    w_o: Array,
    normals: Array,
    length: Array,
    flat: Array,
    lit: Array,
    seen: Array,
    band: _Band,
) -> Array:
    """The body seen in the other facet's mirror, and lit through it, per unit period length
    `(...)` (summed over the two facets; add it to the body's summed terms) [conventions §11;
    docs/model.md §7.8].

    Tread and riser are the arms of a right-angled groove, so a view ray that one facet `j`
    reflects meets the other facet `k` from the concave corner up to `min(flat_k, flat_j
    cos_oj / cos_ok)`, where `k` glows with its body (lit from `length_k (1 - lit_k)` on: the
    shadow starts at the corner). That part of `k` appears in `j` with `j`'s Fresnel factor at
    the view's local cosine; the mirror keeps `k`'s local angle. The reverse path, the lamp
    seen in `j` lighting `k` where the view sees it, is the same with the directions swapped,
    so the sum is reciprocal. `normals` `(..., 2, 3)`, `length` the facets' lengths per period
    and `flat` their flat reach from the corner (the length less a rounded tip), `lit` and
    `seen` the lit and visible fractions (`lit_fractions`), all `(..., 2)`."""
    cos_i, cos_o = _facet_cosines(w_i, normals), _facet_cosines(w_o, normals)
    facets = _Band(band.n[..., None, :], band.weight[..., None, :])  # the facet axis before L
    trans_i, trans_o = 1.0 - _fresnel_u(cos_i, facets), 1.0 - _fresnel_u(cos_o, facets)
    other = jnp.flip  # facet j of body facet k, along the last axis

    def through(cos_a: Array, cos_b: Array, reached: Array) -> Array:
        """Body facets' span reached through the other facet's mirror from direction `a`, part
        of it lit (or seen) from `b`, times `cos_a`, times the mirror's Fresnel factor."""
        reach = jnp.minimum(flat * cos_a, other(flat * cos_a, -1))
        span = jnp.maximum(reach - length * (1.0 - reached) * cos_a, 0.0)
        return span * other(_fresnel_u(cos_a, facets), -1) * cos_b

    seen_in_mirror = through(cos_o, cos_i, lit)  # the view reflected, facet k lit by the lamp
    lit_in_mirror = through(cos_i, cos_o, seen)  # the lamp reflected, facet k seen
    return jnp.sum((seen_in_mirror + lit_in_mirror) * trans_i * trans_o, axis=-1)


def body_per_incidence(w_i: Array, w_o: Array, summed: Array) -> Array:
    """A body's summed terms (per unit period length) over `w_i . z`, 0 below the horizon."""
    lead = jnp.broadcast_shapes(summed.shape, w_i.shape[:-1], w_o.shape[:-1])
    up = jnp.broadcast_to((w_i[..., 2] > 0.0) & (w_o[..., 2] > 0.0), lead)
    cos_z = jnp.where(up, jnp.broadcast_to(w_i[..., 2], lead), 1.0)
    return jnp.where(up, summed / cos_z, 0.0)


# --------------------------------------------------------------------------------------------
# The plate's light
# --------------------------------------------------------------------------------------------

PLATE_WIDTH_FLOOR_RAD = 1e-4
"""The smallest lobe width `plate_reflectance` uses at the horizon: a sharp lobe crossing it
then switches within 0.01 deg, with finite derivatives."""


def plate_reflectance(
    w_o: ArrayLike,
    beta2: ArrayLike,
    n: ArrayLike,
    width: ArrayLike,
    kernel: str = "gaussian",
    spectral_weight: ArrayLike | None = None,
) -> Float[Array, "..."]:
    """The share of the base plate's radiance that the staircase reflects towards the viewer
    `w_o` (face frame), dimensionless [conventions §11, §12; docs/model.md §7.7].

    A wedge stands on a plate that the lamp lights; the risers reflect the plate in front of
    the wedge into a view from downhill. By reciprocity the share is that of the reversed view
    ray: the sharp lobes of light arriving from `w_o` (`lab_lobes`), each its ratio (weight x
    Fresnel) times the part of it that leaves below the plate's horizon, whose in-plane angle
    is `beta2 - 90 deg` (the tread's normal is the plate's). A uniform plate radiance makes the
    out-of-plane spread irrelevant (a direction's elevation sign depends on its projected angle
    only), so that part is the in-plane spread's: a Gaussian of `width` (rad) in the reflected
    angle for `kernel` "gaussian"; for a microfacet kernel (`alpha = tan(width)`) the share of
    micro-slopes that turn the reflection past the horizon, a reflection turning by twice the
    slope's angle (`slope_cdf`)."""
    lobes = lab_lobes(w_o, beta2, n, spectral_weight)
    beta2_, width_ = same_rank(jnp.asarray(beta2), jnp.asarray(width))
    width_ = jnp.maximum(width_, PLATE_WIDTH_FLOOR_RAD)[..., None]
    past = (beta2_ - jnp.pi / 2)[..., None] - lobes.theta_o  # > 0: the lobe is below it
    if kernel == "gaussian":
        below = 0.5 * erfc(-past / (jnp.sqrt(2.0) * width_))
    else:
        half = jnp.clip(0.5 * past, -0.5 * jnp.pi + 1e-6, 0.5 * jnp.pi - 1e-6)
        below = slope_cdf(jnp.tan(half), jnp.tan(width_), kernel)
    up = jnp.asarray(w_o)[..., 2] > 0.0
    return jnp.where(up, jnp.sum(lobes.ratio * below, axis=-1), 0.0)
