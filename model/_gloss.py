"""Specular gloss in gloss units (ISO 2813) of the staircase, from its 3-D reflectance
(docs/gloss.md) [conventions §1, §11, §13].

A glossmeter lights the surface with a nearly collimated beam at the angle `theta` from its
normal and collects what is reflected into a receptor window centred on the mirror direction.
Its reading is the luminous flux into the window relative to the flux the black glass standard
(`GLOSS_STANDARD_INDEX`) sends there, times 100. The source and the receptor are rectangles
in angle: (in the plane of incidence) x (perpendicular to it). Here the flux is

    Phi = sum over source directions w_i of  s(w_i) (w_i . z) * integral over the receptor of
          p(w_i, w_o) d omega_o,

with `s` the source's share of the beam (uniform per steradian over its rectangle) and `p`
the staircase's reflected power per steradian per unit incident power (`lab_density_gaussian`,
`lab_density_microfacet`, `lab_density_rounded`, plus the diffuse body `lab_body` /
`lab_body_rounded` weighted by `body`). The standard's `p` is Fresnel's mirror, so its
integral is `R(w_i . z)` whenever the mirror direction lies in the window.

Quadrature (`SOURCE_NODES`, `RECEPTOR_NODES`): Gauss-Legendre over the source rectangle; over
the receptor, one Gauss-Legendre product rule per *warp*, each in the variable `u = atan((x -
c) / w)` about one of the staircase's lobe directions `c` (tread, riser, two-bounce path) with
the facets' width `w`, and one nearly uniform warp, combined by the balance heuristic: the
receptor integral is `sum_k sum_n omega_kn f(x_kn) / sum_j q_j(x_kn)`, `q_j` the density of
warp `j`'s nodes. A lobe much narrower than the window is then integrated as exactly as a wide
one, so a mirror-smooth flat surface gives Fresnel's values (docs/gloss.md §2).

Radians inside; `iso2813_geometry` turns the standard's degrees into a `GlossGeometry`.
Extremes: the wedge angle is held inside `[BETA_MIN_RAD, pi/2 - BETA_MIN_RAD]`, the layer at or
above `LAYER_MIN_UM`, the width at or above `WIDTH_MIN`, and the edge radius within
`max_edge_radius`, so that a wedge of 0 or 90 deg, a layer -> 0 or a mirror-smooth facet give
finite values and finite gradients.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._fresnel import fresnel_unpolarised
from ._lab import (
    LAB_KERNELS,
    face_direction,
    lab_body,
    lab_density_gaussian,
    lab_density_microfacet,
    lab_lobes,
    projected_incidence,
)
from ._lab_rounded import lab_body_rounded, rounded_arcs, rounded_flats
from ._rounded import ROUNDED_RESOLUTION, max_edge_radius, rounded_geometry

GLOSS_STANDARD_INDEX = 1.567
"""The black glass standard's refractive index: ISO 2813 assigns 100 gloss units to a polished
glass of index 1.567 at 587.6 nm (`GLOSS_STANDARD_WAVELENGTH_NM`), whose reflectance is
Fresnel's (docs/gloss.md §1)."""

GLOSS_STANDARD_WAVELENGTH_NM = 587.6
"""The wavelength at which ISO 2813 gives the standard's index (the helium d line)."""


class GlossAperture(NamedTuple):
    """One ISO 2813 geometry as the standard states it, in degrees: the angle of incidence and
    the full angular sizes of the source image and of the receptor window, in the plane of
    incidence (`_in`) and perpendicular to it (`_perp`)."""

    angle_deg: float
    source_in_deg: float
    source_perp_deg: float
    receptor_in_deg: float
    receptor_perp_deg: float


ISO2813_APERTURES: tuple[GlossAperture, ...] = (
    GlossAperture(20.0, 0.75, 2.5, 1.80, 3.6),
    GlossAperture(60.0, 0.75, 2.5, 4.4, 11.7),
    GlossAperture(85.0, 0.75, 2.5, 4.0, 6.0),
)
"""The three geometries of ISO 2813:2014 (and ASTM D523-14), nominal sizes without their
tolerances: source image 0.75 x 2.5 deg for all three, receptor 1.80 x 3.6 deg (20 deg),
4.4 x 11.7 deg (60 deg), 4.0 x 6.0 deg (85 deg), each (in the plane of incidence) x
(perpendicular). Where these numbers come from, and how far they could be checked:
docs/gloss.md §1."""


class GlossGeometry(NamedTuple):
    """A glossmeter geometry in radians: the angle of incidence from the surface normal and the
    full angular sizes of the source and the receptor in (`_in`) and perpendicular to
    (`_perp`) the plane of incidence."""

    angle: Float[Array, ""]
    source_in: Float[Array, ""]
    source_perp: Float[Array, ""]
    receptor_in: Float[Array, ""]
    receptor_perp: Float[Array, ""]


def iso2813_geometry(angle_deg: float) -> GlossGeometry:
    """The ISO 2813 geometry at `angle_deg` (20, 60 or 85) in radians; a ValueError names the
    three angles for any other."""
    for ap in ISO2813_APERTURES:
        if ap.angle_deg == float(angle_deg):
            return GlossGeometry(*(jnp.asarray(np.deg2rad(v)) for v in ap))
    known = ", ".join(f"{a.angle_deg:g}" for a in ISO2813_APERTURES)
    raise ValueError(f"ISO 2813 has no {angle_deg:g} deg geometry; use one of {known}")


class GlossSurface(NamedTuple):
    """The staircase a glossmeter is put on [conventions §2, §11, §12].

    `beta2`: the surface's angle to the build plate (rad; 0 a top surface, pi/2 a wall);
    `layer_um`: the layer thickness; `n`: the refractive index at the glossmeter's wavelength
    (complex allowed); `width`: the facets' spread, Gaussian sigma (rad) or microfacet alpha;
    `edge_radius_um`: the rounded edges' radius (0 sharp; used with `rounded=True`);
    `body`: the diffuse body's weight, `albedo / pi` (the lab model's `floor / scale`): its
    reflected power per steradian is `body * lab_body`.
    """

    beta2: ArrayLike
    layer_um: ArrayLike
    n: ArrayLike
    width: ArrayLike
    edge_radius_um: ArrayLike = 0.0
    body: ArrayLike = 0.0


class Gloss(NamedTuple):
    """Gloss units of one geometry: `total = specular + body`, the staircase's reflection and
    its diffuse body's share of the receptor's flux, each relative to the standard's x 100."""

    total: Float[Array, "..."]
    specular: Float[Array, "..."]
    body: Float[Array, "..."]


SOURCE_NODES = 3
"""Gauss-Legendre nodes per axis over the source rectangle: the flux varies smoothly with the
source direction except where a lobe narrower than the source crosses the window's edge."""

RECEPTOR_NODES = 10
"""Gauss-Legendre nodes per axis of each receptor warp (four warps: three lobes, one nearly
uniform). Doubling them moves the gloss of the tests' staircases by less than 0.01 GU
(tests/test_gloss.py::test_gloss_quadrature_converges)."""

SMOOTH_NODES = 4
"""Gauss-Legendre nodes per axis of the plain product rule over the receptor on which the
broad parts are integrated: the diffuse body and the rounded edges' arcs, whose light spreads
over tens of degrees (the fit likewise takes the arcs once per face, docs/model.md §7.6)."""

BETA_MIN_RAD = 1e-6
"""The wedge angle is kept this far from 0 and from pi/2: there a facet's length is 0 or
infinite; the gloss there is the flat surface's, within 1e-4 GU."""

LAYER_MIN_UM = 1e-6
"""The smallest layer thickness used (only the rounded model has a length scale)."""

WIDTH_MIN = 1e-6
"""The smallest facet width (sigma in rad, or alpha): a narrower lobe is a mirror to within
far below a gloss unit, and the warps keep it resolved."""

CORE_WIDTHS = 3.0
"""The receptor's nodes resolve the nearest lobe's core, this many lobe widths on each side
of its centre, with a plain Gauss-Legendre rule, and the rest of the window with a
logarithmic one (`_warped_axis`)."""


def _gauss_legendre(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Legendre points in (-1, 1) and weights summing to 1."""
    x, w = np.polynomial.legendre.leggauss(n)
    return x, w / w.sum()


def _gauss_legendre01(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Legendre points in (0, 1) and weights summing to 1."""
    x, w = _gauss_legendre(n)
    return 0.5 * (x + 1.0), w


def _frame(azimuth: Array) -> Array:
    """Columns: the glossmeter's x (in the plane of incidence, towards the receptor), y, and the
    surface normal, in the face frame; `azimuth` turns its x from the face frame's x (across
    the layer lines, uphill) towards y (along them) [conventions §13]."""
    c, s = jnp.cos(azimuth), jnp.sin(azimuth)
    zero, one = jnp.zeros_like(c), jnp.ones_like(c)
    return jnp.stack(
        [jnp.stack([c, s, zero]), jnp.stack([-s, c, zero]), jnp.stack([zero, zero, one])], axis=-1
    )


def _meter_direction(theta: Array, a: Array, b: Array, sign: float) -> Array:
    """Unit vector (glossmeter frame) at in-plane angle `theta + a` from the normal and `b` out
    of the plane of incidence; `sign = -1` towards the source, `+1` towards the receptor."""
    cb = jnp.cos(b)
    return jnp.stack([sign * cb * jnp.sin(theta + a), jnp.sin(b), cb * jnp.cos(theta + a)], -1)


def _to_meter(w: Array, frame: Array) -> tuple[Array, Array]:
    """A face-frame direction's receptor coordinates `(a, b)` about the mirror direction of the
    glossmeter's axis (before subtracting its angle): in-plane angle and out-of-plane angle."""
    g = jnp.einsum("...j,jk->...k", w, frame)
    return jnp.arctan2(g[..., 0], g[..., 2]), jnp.arcsin(jnp.clip(g[..., 1], -1.0, 1.0))


def _warped_axis(centre: Array, width: Array, lo: Array, hi: Array, v: Array, w: Array
                 ) -> tuple[Array, Array]:  # fmt: skip
    """Nodes and weights (dx included) over `[lo, hi]` crowded at `centre` (inside it), for a
    lobe of about `width` there: on each side of the centre, Gauss-Legendre (points `v` in
    (0, 1), weights `w` summing to 1) over the core `CORE_WIDTHS * width`, and beyond it over
    `x = x_core +- width (exp(lam v) - 1)`, `lam` such that `v = 1` reaches the interval's end:
    the lobe's core, its tail and a smooth function across the whole window are all integrated
    to high accuracy (docs/gloss.md §2). Returns `(..., 4N)` nodes and weights."""
    parts_x, parts_w = [], []
    for side, reach in ((-1.0, centre - lo), (1.0, hi - centre)):
        core = jnp.minimum(CORE_WIDTHS * width, reach)[..., None]
        parts_x.append(centre[..., None] + side * core * v)
        parts_w.append(w * core)
        lam = jnp.log1p((reach[..., None] - core) / width[..., None])
        grow = jnp.exp(lam * v)
        parts_x.append(centre[..., None] + side * (core + width[..., None] * (grow - 1.0)))
        parts_w.append(w * width[..., None] * lam * grow)
    return jnp.concatenate(parts_x, axis=-1), jnp.concatenate(parts_w, axis=-1)


def _nearest_lobe(a: Array, b: Array, ratio: Array, half_a: Array, half_b: Array,
                  scale: Array) -> tuple[Array, Array]:  # fmt: skip
    """The receptor point nearest to the lobe (of non-zero ratio) nearest to the receptor, in
    units of the lobes' width: the centre of the receptor warps, per source node."""
    ca, cb = jnp.clip(a, -half_a, half_a), jnp.clip(b, -half_b, half_b)
    dist = jnp.hypot(a - ca, b - cb) / scale
    dist = jnp.where(ratio > 1e-12, dist, jnp.inf)
    k = jnp.argmin(dist, axis=-1)[..., None]
    return (jnp.take_along_axis(ca, k, axis=-1)[..., 0],
            jnp.take_along_axis(cb, k, axis=-1)[..., 0])  # fmt: skip


def _surface(surface: GlossSurface, rounded: bool) -> GlossSurface:
    """The surface held where the model is finite (see the module text)."""
    b2 = jnp.clip(jnp.asarray(surface.beta2, float), BETA_MIN_RAD, jnp.pi / 2 - BETA_MIN_RAD)
    l1 = jnp.maximum(jnp.asarray(surface.layer_um, b2.dtype), LAYER_MIN_UM)
    width = jnp.maximum(jnp.asarray(surface.width, b2.dtype), WIDTH_MIN)
    r = jnp.asarray(surface.edge_radius_um, b2.dtype)
    r = jnp.clip(r, 0.0, max_edge_radius(b2, l1)) if rounded else jnp.zeros_like(r)
    return GlossSurface(b2, l1, jnp.asarray(surface.n), width, r, jnp.asarray(surface.body))


def _lobe_widths(width: Array, kind: str, theta: Array) -> tuple[Array, Array]:
    """The angular widths of the staircase's lobes in and perpendicular to the plane of
    incidence, for the receptor's nodes: Gaussian facets spread by sigma both ways
    (conventions §11: in `theta'` and in `t`); a micro-normal tilted by `d` turns a reflection
    by `2 d` in the plane of incidence and by `2 d cos(theta)` across it."""
    if kind == "gaussian":
        return width, width
    return 2.0 * width, 2.0 * width * jnp.cos(theta)


def gloss(
    surface: GlossSurface,
    geometry: GlossGeometry,
    azimuth: ArrayLike = 0.0,
    kind: str = "gaussian",
    *,
    rounded: bool = False,
    source_nodes: int = SOURCE_NODES,
    receptor_nodes: int = RECEPTOR_NODES,
    resolution: int = ROUNDED_RESOLUTION,
) -> Gloss:
    """Gloss units of the staircase `surface` in one glossmeter `geometry` (docs/gloss.md).

    `azimuth` (rad): the plane of incidence's turn from across the layer lines: 0 across with
    the source on the downhill side (its light lands on the risers, conventions §1's positive
    `theta_i`), pi/2 along the layer lines, pi across from uphill [conventions §13]. `kind`:
    the facets, "gaussian" (`width` = sigma) or a microfacet distribution (`width` = alpha);
    `rounded`: the rounded-edge model with `surface.edge_radius_um`. Scalar parameters; vmap
    for many. Finite, with finite gradients, for any wedge angle in [0, pi/2], any layer >= 0
    and any width >= 0.
    """
    if kind not in LAB_KERNELS:
        raise ValueError(f"facets {kind!r}: use one of {', '.join(LAB_KERNELS)}")
    s = _surface(surface, rounded)
    frame = _frame(jnp.asarray(azimuth, s.beta2.dtype))
    theta = jnp.asarray(geometry.angle, s.beta2.dtype)

    # the source: Gauss-Legendre over its rectangle, uniform per steradian
    xs, ws = _gauss_legendre(source_nodes)
    a_s = 0.5 * geometry.source_in * jnp.asarray(np.repeat(xs, source_nodes))
    b_s = 0.5 * geometry.source_perp * jnp.asarray(np.tile(xs, source_nodes))
    w_s = jnp.asarray(np.outer(ws, ws).ravel()) * jnp.cos(b_s)  # (S,)
    w_i = jnp.einsum("sj,kj->sk", _meter_direction(theta, a_s, b_s, -1.0), frame)  # (S, 3)
    cos_i = w_i[:, 2]

    # the standard: Fresnel's mirror, whose image lies in the window when (a, -b) does
    inside = (jnp.abs(a_s) <= 0.5 * geometry.receptor_in) & (
        jnp.abs(b_s) <= 0.5 * geometry.receptor_perp
    )
    standard = jnp.sum(w_s * cos_i * fresnel_unpolarised(cos_i, GLOSS_STANDARD_INDEX) * inside)

    # the receptor: Gauss-Legendre in log-warped coordinates about the nearest lobe
    lobes = lab_lobes(w_i, s.beta2, s.n)
    dirs = face_direction(lobes.theta_o, lobes.t_o[:, None])  # (S, 3, 3)
    a_c, b_c = _to_meter(dirs, frame)
    half_a, half_b = 0.5 * geometry.receptor_in, 0.5 * geometry.receptor_perp
    width_a, width_b = _lobe_widths(s.width, kind, theta)
    c_a, c_b = _nearest_lobe(a_c - theta, b_c, lobes.ratio, half_a, half_b, width_a)
    v, w = (jnp.asarray(x) for x in _gauss_legendre01(receptor_nodes))
    a_r, wa = _warped_axis(c_a, width_a, -half_a, half_a, v, w)  # (S, 2N)
    b_r, wb = _warped_axis(c_b, width_b, -half_b, half_b, v, w)
    n2 = 4 * receptor_nodes
    a_r = jnp.broadcast_to(a_r[:, :, None], (a_r.shape[0], n2, n2)).reshape(-1, n2 * n2)
    b_r = jnp.broadcast_to(b_r[:, None, :], (b_r.shape[0], n2, n2)).reshape(-1, n2 * n2)
    weight = (wa[:, :, None] * wb[:, None, :]).reshape(-1, n2 * n2) * jnp.cos(b_r)
    w_o = jnp.einsum("smj,kj->smk", _meter_direction(theta, a_r, b_r, 1.0), frame)  # (S, M, 3)

    # the broad parts (the diffuse body, the rounded edges' arcs) on a plain product rule
    xg, wg = (jnp.asarray(x) for x in _gauss_legendre(SMOOTH_NODES))
    a_g = jnp.repeat(half_a * xg, SMOOTH_NODES)
    b_g = jnp.tile(half_b * xg, SMOOTH_NODES)
    weight_g = jnp.outer(wg, wg).ravel() * geometry.receptor_in * geometry.receptor_perp
    weight_g = weight_g * jnp.cos(b_g)
    w_g = jnp.einsum("mj,kj->mk", _meter_direction(theta, a_g, b_g, 1.0), frame)  # (G, 3)

    peaked, broad, body = _densities(s, w_i[:, None, :], w_o, w_g[None], kind, rounded,
                                     resolution)  # fmt: skip
    received = jnp.sum(weight * peaked, axis=1) + jnp.sum(weight_g * broad, axis=1)
    flux_spec = jnp.sum(w_s * cos_i * received)
    flux_body = jnp.sum(w_s * cos_i * jnp.sum(weight_g * body, axis=1)) * s.body
    specular = 100.0 * flux_spec / standard
    diffuse = 100.0 * flux_body / standard
    return Gloss(total=specular + diffuse, specular=specular, body=diffuse)


def _densities(
    s: GlossSurface, w_i: Array, w_o: Array, w_g: Array, kind: str, rounded: bool,
    resolution: int,
) -> tuple[Array, Array, Array]:  # fmt: skip
    """The staircase's reflected power per steradian in two parts, the lobes at the node pairs
    `(w_i, w_o)` and the rounded edges' arcs at `(w_i, w_g)` (0 without rounding), and its
    body per unit `body` at `(w_i, w_g)` (face frame) [conventions §11, §12]."""
    if rounded:
        geo = rounded_geometry(projected_incidence(w_i).theta, s.beta2, s.layer_um,
                               s.edge_radius_um, resolution=resolution)  # fmt: skip
        flats = rounded_flats(w_i, w_o, s.beta2, s.n, s.width, s.layer_um, s.edge_radius_um,
                              geo, kind)  # fmt: skip
        arcs = rounded_arcs(w_i, w_g, s.beta2, s.n, s.width, geo, kind)
        body = lab_body_rounded(w_i, w_g, s.beta2, s.n, s.layer_um, s.edge_radius_um)
        return flats, arcs, body
    if kind == "gaussian":
        spec = lab_density_gaussian(w_i, w_o, s.beta2, s.n, s.width)
    else:
        spec = lab_density_microfacet(w_i, w_o, s.beta2, s.n, s.width, kind)
    body = lab_body(w_i, w_g, s.beta2, s.n)
    return spec, jnp.zeros_like(body), body
