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
`lab_density_microfacet`, or the rounded model's `rounded_flats` and `rounded_arcs`, plus the
diffuse body `lab_body` / `lab_body_rounded` weighted by `body`), averaged over the
glossmeter's luminous response (`luminous_rule`). The standard's `p` is Fresnel's mirror, so
its integral is `R(w_i . z)` whenever the mirror direction lies in the window.

Quadrature (`SOURCE_NODES`, `RECEPTOR_NODES`, `SMOOTH_NODES`; docs/gloss.md §2): a
Gauss-Legendre product rule over the source rectangle. Over the receptor, per source
direction, a rule about each of the `LOBE_RULES` lobes nearest to the window (lobes of non-zero
ratio, in units of their width; centres clipped into the window), shared out by a smooth
partition of unity (`_shares`). A rule works in its lobe's own coordinates `(p, q) = L (a -
a_c, b - b_c)` (`_lobe_frame`: the Gaussian kernel's `(theta', t)` per sigma, which a grazing
view along the layer lines shears, or a microfacet lobe's `2 alpha` widths), in which the window
is a parallelogram: `p` runs over its extent and `q` over each exact slice, each with a plain
Gauss-Legendre rule over the lobe's core (`CORE_WIDTHS` widths either side) and a logarithmic
one beyond (`_warped_axis`). A lobe far narrower than the window is then integrated as exactly
as a wide one, so that a mirror-smooth flat surface gives Fresnel's gloss, and so is a smooth
function across the window. The broad parts (the diffuse body, the rounded edges' arcs) take a
plain product rule over the window. Not resolved: a lobe narrower than the source that leaves
the window for part of it (`SOURCE_NODES`).

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
from jax.scipy.special import logsumexp
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
from ._shapes import with_rank

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
    `layer_um`: the layer thickness; `n`: the refractive index (complex allowed), one value or
    one per wavelength sample on a last axis with `spectral_weight` (the glossmeter's luminous
    response, `luminous_rule`) [conventions §8]; `width`: the facets' spread, Gaussian sigma
    (rad) or microfacet alpha; `edge_radius_um`: the rounded edges' radius (0 sharp; used
    with `rounded=True`); `body`: the diffuse body's weight, `albedo / pi` (the lab model's
    `floor / scale`): its reflected power per steradian is `body * lab_body`.
    """

    beta2: ArrayLike
    layer_um: ArrayLike
    n: ArrayLike
    width: ArrayLike
    edge_radius_um: ArrayLike = 0.0
    body: ArrayLike = 0.0
    spectral_weight: ArrayLike | None = None


GLOSS_ILLUMINANT = "C"
"""ISO 2813's source and receptor together respond as CIE illuminant C times the luminous
efficiency V(lambda) (the CIE 1931 y-bar): the gloss is a ratio of luminous fluxes."""

LUMINOUS_NODES = 3
"""Wavelengths of `luminous_rule`: the 3-point Gauss rule of the illuminant C x y-bar weight
reproduces its 81-sample average of a flat surface's Fresnel reflectance within 0.001 GU, for
the strongly dispersive `pla-bodurov2016` too (one wavelength, 557 nm, is 0.4 GU off;
587.6 nm alone is 2 GU off at 20 deg)."""


def luminous_rule(nodes: int = LUMINOUS_NODES) -> tuple[np.ndarray, np.ndarray]:
    """Wavelengths (nm) and weights (sum 1) of the Gauss rule of the glossmeter's luminous
    response (`GLOSS_ILLUMINANT` x y-bar on `spectral.VISIBLE_NM`): `sum_k w_k f(lambda_k)` is
    the luminous average of a smooth `f`, exact for polynomials of degree `2 nodes - 1`
    (Golub-Welsch from the Stieltjes recurrence of the discrete measure) [conventions §8]."""
    from . import spectral

    lam = spectral.VISIBLE_NM
    w = spectral.xyz_weights(GLOSS_ILLUMINANT, lam)[1]
    w = w / w.sum()
    mid, half = 0.5 * (lam.max() + lam.min()), 0.5 * (lam.max() - lam.min())
    u = (lam - mid) / half
    alpha, beta = np.zeros(nodes), np.zeros(nodes)
    p_prev, p, norm_prev = np.zeros_like(u), np.ones_like(u), 1.0
    for j in range(nodes):
        norm = np.sum(w * p * p)
        alpha[j] = np.sum(w * u * p * p) / norm
        beta[j] = norm / norm_prev if j else 0.0
        p_prev, p, norm_prev = p, (u - alpha[j]) * p - beta[j] * p_prev, norm
    off = np.sqrt(beta[1:])
    x, vectors = np.linalg.eigh(np.diag(alpha) + np.diag(off, 1) + np.diag(off, -1))
    return mid + half * x, vectors[0] ** 2


class Gloss(NamedTuple):
    """Gloss units of one geometry: `total = specular + body`, the staircase's reflection and
    its diffuse body's share of the receptor's flux, each relative to the standard's x 100."""

    total: Float[Array, "..."]
    specular: Float[Array, "..."]
    body: Float[Array, "..."]


_TINY = 1e-12
_BIG = 1e30

SOURCE_NODES: tuple[int, int] = (2, 5)
"""Gauss-Legendre nodes over the source rectangle, (in the plane of incidence, across it). Its
0.75 deg in the plane barely change a lobe wider than it; across, its 2.5 deg turn the
projected angle of incidence by up to 14 deg at 85 deg along the layer lines, through the lobe
weights' kinks: 3 x 3 nodes were 0.6 GU (2.5%) off there with 1-deg facets, 2 x 5 within
0.15 GU of 9 x 9. Not resolved: a lobe narrower than the source that leaves the window for
part of it (mirror-smooth facets a few tenths of a degree from flat), where the reading is a
step in the source direction."""

RECEPTOR_NODES = 8
"""Gauss-Legendre nodes of each of the four pieces (core and tail on either side of the lobe)
of each receptor axis: 32 x 32 nodes per source direction. With facets of 1 deg and wider
(alpha 0.02 and above) doubling them moves the gloss by at most 0.15 GU, by 0.02 GU in nine
cases of ten (docs/gloss.md §2; tests/model/test_gloss.py::test_gloss_quadrature_converges)."""

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

LOBE_RULES = 2
"""Receptor rules per source direction, one about each of the lobes nearest to the window:
along the layer lines a few degrees from flat the two-bounce path's lobe lies at the mirror
direction beside the tread's, both narrow across the plane of incidence at grazing angles (a
single rule about the nearest missed the other by up to 0.8 GU at 85 deg with 1-deg facets)."""

CORE_WIDTHS = 5.0
"""The receptor's nodes resolve the nearest lobe's core, this many lobe widths on each side
of its centre, with a plain Gauss-Legendre rule, and the rest of the window with a
logarithmic one (`_warped_axis`). Three widths left the Gaussian's 0.3% beyond them to the
logarithmic rule, which gave a mirror-smooth flat surface 0.03 GU too much at 60 deg."""


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
    v, w = with_rank(v, centre.ndim + 1), with_rank(w, centre.ndim + 1)
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


def _nearest_lobes(a: Array, b: Array, ratio: Array, half: Array, scale: Array
                   ) -> tuple[Array, Array, Array]:  # fmt: skip
    """The `LOBE_RULES` lobes (of non-zero ratio) nearest to the window, in units of the lobes'
    width, per source node: their centres `(S, K, 2)`, the window's points nearest to them
    (the rules' centres) and whether each is a lobe at all (`(S, K)`; False where fewer lobes
    have light)."""
    ca, cb = jnp.clip(a, -half[0], half[0]), jnp.clip(b, -half[1], half[1])
    dist = jnp.hypot(a - ca, b - cb) / scale
    has = ratio > 1e-12
    order = jnp.argsort(jnp.where(has, dist, jnp.inf), axis=-1)[:, :LOBE_RULES]

    def pick(x: Array) -> Array:
        return jnp.take_along_axis(x, order, axis=-1)

    centre = jnp.stack([pick(a), pick(b)], -1)
    return centre, jnp.stack([pick(ca), pick(cb)], -1), pick(has)


def _shares(a: Array, b: Array, centre: Array, lobe: Array, valid: Array) -> Array:
    """Each rule's share of its nodes `(S, K, M)`: a partition of unity over the window,
    `g_k / sum_j g_j` with `g_j = |det L_j| / (1 + |L_j (x - c_j)|^2)^2` about lobe `j`'s own
    centre (0 for no lobe). Near a lobe its own rule takes (nearly) all, so each lobe is
    integrated by the rule crowded about it; the shares are smooth, so the rules see smooth
    integrands."""
    x = jnp.stack([a, b], -1)  # (S, K, M, 2): the nodes of rule k
    d = x[:, :, None, :, :] - centre[:, None, :, None, :]  # (S, K, J, M, 2)
    r2 = jnp.sum(jnp.einsum("sjpq,skjmq->skjmp", lobe, d) ** 2, axis=-1)  # (S, K, J, M)
    log_det = jnp.log(jnp.abs(jnp.linalg.det(lobe)))[:, None, :, None]  # (S, 1, J, 1)
    log_g = jnp.where(valid[:, None, :, None], log_det - 2.0 * jnp.log1p(r2), -jnp.inf)
    own = jnp.take_along_axis(log_g, jnp.arange(log_g.shape[1])[None, :, None, None], axis=2)
    share = jnp.exp(own[:, :, 0, :] - logsumexp(log_g, axis=2))
    return jnp.where(valid[:, :, None], share, 0.0)


def _surface(surface: GlossSurface, rounded: bool) -> GlossSurface:
    """The surface held where the model is finite (see the module text)."""
    b2 = jnp.clip(jnp.asarray(surface.beta2, float), BETA_MIN_RAD, jnp.pi / 2 - BETA_MIN_RAD)
    l1 = jnp.maximum(jnp.asarray(surface.layer_um, b2.dtype), LAYER_MIN_UM)
    width = jnp.maximum(jnp.asarray(surface.width, b2.dtype), WIDTH_MIN)
    r = jnp.asarray(surface.edge_radius_um, b2.dtype)
    r = jnp.clip(r, 0.0, max_edge_radius(b2, l1)) if rounded else jnp.zeros_like(r)
    sw = None if surface.spectral_weight is None else jnp.asarray(surface.spectral_weight)
    return GlossSurface(b2, l1, jnp.asarray(surface.n), width, r, jnp.asarray(surface.body), sw)


def _lobe_frame(width: Array, kind: str, theta: Array, a: Array, b: Array, frame: Array
                ) -> Array:  # fmt: skip
    """`L` `(..., 2, 2)`: receptor offsets `(da, db)` at `(a, b)` to the lobe's own coordinates
    `L (da, db)`, in which the lobe is about one wide either way [conventions §11, §12].

    Gaussian facets spread by sigma in `theta'` and in `t`, so `L = J / sigma` with `J` the
    derivative of `(theta', t)` by `(a, b)`: sheared, not only scaled, where `theta'` is the
    projection of a direction close to the layer lines (grazing incidence along them, a source
    node out of the plane of incidence). A micro-normal tilted by `d` turns a reflection by
    `2 d` in the plane of incidence and by `2 d cos(theta)` across it:
    `L = diag(1 / 2 alpha, 1 / (2 alpha cos(theta)))`."""
    one, zero = jnp.ones_like(a), jnp.zeros_like(a)
    if kind != "gaussian":
        inv = 0.5 / width
        return jnp.stack([jnp.stack([inv * one, zero], -1),
                          jnp.stack([zero, inv / jnp.cos(theta) * one], -1)], -2)  # fmt: skip
    ca, sa, cb, sb = jnp.cos(theta + a), jnp.sin(theta + a), jnp.cos(b), jnp.sin(b)
    w = jnp.einsum("sj,kj->sk", jnp.stack([cb * sa, sb, cb * ca], -1), frame)
    d_a = jnp.einsum("sj,kj->sk", jnp.stack([cb * ca, zero, -cb * sa], -1), frame)
    d_b = jnp.einsum("sj,kj->sk", jnp.stack([-sb * sa, cb, -sb * ca], -1), frame)
    c2 = jnp.maximum(w[:, 0] ** 2 + w[:, 2] ** 2, _TINY)

    def column(d: Array) -> Array:  # d(theta', t) along one receptor axis
        return jnp.stack([(w[:, 2] * d[:, 0] - w[:, 0] * d[:, 2]) / c2, d[:, 1]], -1)

    return jnp.stack([column(d_a), column(d_b)], -1) / width


def _interval(m: Array, c: Array, lo: Array, hi: Array) -> tuple[Array, Array]:
    """The `q` with `lo <= m q + c <= hi`: an interval, or all `q` (as +-`_BIG`) where `m` is 0
    (then the outer variable's range has already enforced it)."""
    has = jnp.abs(m) > _TINY
    m_s = jnp.where(has, m, 1.0)
    q1, q2 = (lo - c) / m_s, (hi - c) / m_s
    return jnp.where(has, jnp.minimum(q1, q2), -_BIG), jnp.where(has, jnp.maximum(q1, q2), _BIG)


def _receptor_nodes(centre: Array, lobe: Array, half: Array, v: Array, w: Array
                    ) -> tuple[Array, Array, Array]:  # fmt: skip
    """Receptor nodes `(a, b)` `(S, M)` and weights (da db included) for lobes at `centre`
    `(S, 2)` with lobe frames `lobe` `(S, 2, 2)` (`_lobe_frame`), over the window
    `|a| <= half[0]`, `|b| <= half[1]`: in the lobe's coordinates `(p, q) = L (a, b) - L c`,
    in which the window is a parallelogram, the outer variable `p` over its extent and for each
    `p` the inner `q` over the exact slice, both `_warped_axis` about the lobe (or the window's
    point nearest to it)."""
    inv = jnp.linalg.inv(lobe)  # (S, 2, 2): (p, q) -> (da, db)
    corners = jnp.asarray([[-1.0, -1.0], [-1.0, 1.0], [1.0, -1.0], [1.0, 1.0]]) * half[None, :]
    pq = jnp.einsum("sij,skj->ski", lobe, corners[None] - centre[:, None, :])  # (S, 4, 2)
    p_lo, p_hi = jnp.min(pq[..., 0], axis=1), jnp.max(pq[..., 0], axis=1)
    p, wp = _warped_axis(jnp.clip(0.0, p_lo, p_hi), jnp.ones_like(p_lo), p_lo, p_hi, v, w)
    bounds = [  # each window edge pair as a condition on q for the node's p
        _interval(inv[:, k, 1, None], centre[:, k, None] + inv[:, k, 0, None] * p, -half[k],
                  half[k])
        for k in range(2)
    ]  # fmt: skip
    q_lo = jnp.maximum(bounds[0][0], bounds[1][0])
    q_hi = jnp.maximum(jnp.minimum(bounds[0][1], bounds[1][1]), q_lo)  # empty slices: 0 long
    q, wq = _warped_axis(jnp.clip(0.0, q_lo, q_hi), jnp.ones_like(q_lo), q_lo, q_hi, v, w)
    n = p.shape[1]
    p = jnp.broadcast_to(p[:, :, None], q.shape)  # (S, P, Q)
    a = centre[:, 0, None, None] + inv[:, 0, 0, None, None] * p + inv[:, 0, 1, None, None] * q
    b = centre[:, 1, None, None] + inv[:, 1, 0, None, None] * p + inv[:, 1, 1, None, None] * q
    weight = wp[:, :, None] * wq * jnp.abs(jnp.linalg.det(inv))[:, None, None]
    flat = (a.shape[0], n * q.shape[-1])
    return a.reshape(flat), b.reshape(flat), weight.reshape(flat)


def gloss(
    surface: GlossSurface,
    geometry: GlossGeometry,
    azimuth: ArrayLike = 0.0,
    kind: str = "gaussian",
    *,
    rounded: bool = False,
    source_nodes: tuple[int, int] = SOURCE_NODES,
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
    (xa, wa), (xb, wb) = (_gauss_legendre(n) for n in source_nodes)
    a_s = 0.5 * geometry.source_in * jnp.asarray(np.repeat(xa, xb.size))
    b_s = 0.5 * geometry.source_perp * jnp.asarray(np.tile(xb, xa.size))
    w_s = jnp.asarray(np.outer(wa, wb).ravel()) * jnp.cos(b_s)  # (S,)
    w_i = jnp.einsum("sj,kj->sk", _meter_direction(theta, a_s, b_s, -1.0), frame)  # (S, 3)
    cos_i = w_i[:, 2]

    # the standard: Fresnel's mirror, whose image lies in the window when (a, -b) does
    inside = (jnp.abs(a_s) <= 0.5 * geometry.receptor_in) & (
        jnp.abs(b_s) <= 0.5 * geometry.receptor_perp
    )
    standard = jnp.sum(w_s * cos_i * fresnel_unpolarised(cos_i, GLOSS_STANDARD_INDEX) * inside)

    # the receptor: a rule about each of the two lobes nearest to the window, shared out
    lobes = lab_lobes(w_i, s.beta2, s.n, s.spectral_weight)
    dirs = face_direction(lobes.theta_o, lobes.t_o[:, None])  # (S, 3, 3)
    a_c, b_c = _to_meter(dirs, frame)
    half = jnp.stack([0.5 * geometry.receptor_in, 0.5 * geometry.receptor_perp])
    scale = s.width if kind == "gaussian" else 2.0 * s.width
    centre, clipped, valid = _nearest_lobes(a_c - theta, b_c, lobes.ratio, half, scale)
    n_s, k = centre.shape[:2]
    lobe = _lobe_frame(s.width, kind, theta, clipped[..., 0].ravel(), clipped[..., 1].ravel(),
                       frame).reshape(n_s, k, 2, 2)  # fmt: skip
    v, w = (jnp.asarray(x) for x in _gauss_legendre01(receptor_nodes))
    a_r, b_r, weight = _receptor_nodes(clipped.reshape(-1, 2), lobe.reshape(-1, 2, 2), half,
                                       v, w)  # fmt: skip
    a_r, b_r, weight = (x.reshape(n_s, k, -1) for x in (a_r, b_r, weight))
    weight = weight * _shares(a_r, b_r, centre, lobe, valid)  # (S, K, M)
    a_r, b_r, weight = (x.reshape(n_s, -1) for x in (a_r, b_r, weight))
    weight = weight * jnp.cos(b_r)  # d omega = cos b da db
    w_o = jnp.einsum("smj,kj->smk", _meter_direction(theta, a_r, b_r, 1.0), frame)  # (S, M, 3)

    # the broad parts (the diffuse body, the rounded edges' arcs) on a plain product rule
    xg, wg = (jnp.asarray(x) for x in _gauss_legendre(SMOOTH_NODES))
    a_g = jnp.repeat(half[0] * xg, SMOOTH_NODES)
    b_g = jnp.tile(half[1] * xg, SMOOTH_NODES)
    weight_g = jnp.outer(wg, wg).ravel() * geometry.receptor_in * geometry.receptor_perp
    weight_g = weight_g * jnp.cos(b_g)
    w_g = jnp.einsum("mj,kj->mk", _meter_direction(theta, a_g, b_g, 1.0), frame)  # (G, 3)

    peaked, broad, body = _densities(s, w_i[:, None, :], w_o, w_g[None], kind, rounded,
                                     resolution)  # fmt: skip
    received = jnp.sum(weight * peaked, axis=1) + jnp.sum(weight_g[None] * broad, axis=1)
    flux_spec = jnp.sum(w_s * cos_i * received)
    flux_body = jnp.sum(w_s * cos_i * jnp.sum(weight_g[None] * body, axis=1)) * s.body
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
                              kind, s.spectral_weight)  # fmt: skip
        arcs = rounded_arcs(w_i, w_g, s.beta2, s.n, s.width, s.layer_um, s.edge_radius_um, geo,
                            kind, s.spectral_weight)  # fmt: skip
        body = lab_body_rounded(w_i, w_g, s.beta2, s.n, s.layer_um, s.edge_radius_um,
                                s.spectral_weight)  # fmt: skip
        return flats, arcs, body
    if kind == "gaussian":
        spec = lab_density_gaussian(w_i, w_o, s.beta2, s.n, s.width,
                                    spectral_weight=s.spectral_weight)  # fmt: skip
    else:
        spec = lab_density_microfacet(w_i, w_o, s.beta2, s.n, s.width, kind, s.spectral_weight)
    body = lab_body(w_i, w_g, s.beta2, s.n, s.spectral_weight)
    return spec, jnp.zeros_like(body), body
