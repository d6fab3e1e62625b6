"""The rounded staircase: every convex layer edge is a circular arc of radius `r`.

The derivation that this module implements is in docs/rounded.md; conventions §1-§6 apply
unchanged [conventions §1-§6]. In short, in the frame of the wedge face (x uphill, z the face
normal) one period is: the tip arc (outward normals sweeping `alpha` in `[beta2 - pi/2, beta2]`),
the flat tread (`l2 - r`, normal `beta2`), the concave 90-degree corner, the flat riser
(`l1 - r`, normal `beta2 - pi/2`). Every ray leaves after at most two reflections, so the
reflected light consists of

* three **delta lobes** from flat facets only, in the sharp model's directions and with its
  Fresnel factors, but with smaller weights: tread -> escape, riser -> escape, and the
  retroreflection tread <-> riser (the corner reflector with shortened arms);
* seven **continuous lobes**, each one reflection off an arc (possibly preceded or followed by
  a flat reflection or another arc): tip -> {tread, left tip, escape, right tip, riser},
  tread -> tip and riser -> tip.

Every visibility boundary (shadow of a neighbouring tip, the corner reflector's arm ends, rays
grazing a neighbouring tip or passing a facet end) is computed exactly: in closed form where the
beam is parallel (first hits and flat-first paths, by unfolding the flat reflection), and by
bisection followed by one differentiable Newton step for the fan of rays leaving an arc. The
quadrature nodes lie between the boundaries, so every result is a smooth function of `r`.

A continuous lobe is represented by `resolution` panels per sub-interval, each carrying a
quadratic interpolant (in `theta_o`) of the lobe's density through three Gauss-Legendre nodes.
Broadening convolves each panel with the Gaussian analytically (erf), with the hemisphere
truncation of [conventions §5] applied per ray, so the result stays exact as `sigma -> 0`.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.special import erf
from jaxtyping import Array, ArrayLike, Float

from ._broadening import hemisphere_gaussian, hemisphere_mass
from ._fresnel import SP, fresnel_sp, fresnel_unpolarised
from ._lab import lobe_fresnel_3d
from ._lobes import Lobes, lobe_directions, lobe_fresnel
from ._shapes import same_rank, with_rank

HALF_PI = np.pi / 2

ROUNDED_RESOLUTION = 4
"""Default number of panels per continuous sub-interval (see docs/rounded.md, error vs time)."""

ARC_LOBE_NAMES: tuple[str, ...] = (
    "tip>tread",
    "tip>tip_left",
    "tip",
    "tip>tip_right",
    "tip>riser",
    "tread>tip",
    "riser>tip",
)
"""Order of the continuous lobes on every array with a lobe axis (docs/rounded.md §3)."""

_N_ARC_FIRST = 5  # the first five continuous lobes start on the arc
_ESC_SLOT = 2  # tip -> escape: a single reflection
_GL_X, _GL_W = (np.asarray(a) for a in np.polynomial.legendre.leggauss(3))
_BISECT_STEPS = 12
_NEWTON_STEPS = 3
_HORIZON_CUTS = np.array([0.0, 1.5, 3.5, 6.5])
"""Distances (in sigma) from the horizon cutting the window where the truncation matters."""
_HORIZON_NODES = 4
_NARROW = 0.05
"""Panels narrower than `_NARROW * sigma` use the Gaussian at the nodes instead of erf moments."""


# --------------------------------------------------------------------------------------------
# Validity
# --------------------------------------------------------------------------------------------


def max_edge_radius(beta2: ArrayLike, layer_um: ArrayLike) -> Float[Array, "..."]:
    """Largest edge radius (micrometres) that fits the cell: `min(l1, l2)`, `l2 = l1 cot beta2`.

    The arc is tangent to both facets of a 90-degree tip and shortens each by `r`, so each
    facet keeps a non-negative flat length exactly when `r <= min(l1, l2)` [conventions §2].
    """
    beta2 = jnp.asarray(beta2)
    l1 = jnp.asarray(layer_um, dtype=beta2.dtype)
    return jnp.minimum(l1, l1 * jnp.cos(beta2) / jnp.sin(beta2))


def _room_np(b: np.ndarray, l1: np.ndarray) -> np.ndarray:
    """`max_edge_radius` for concrete float64 arrays (the range checks: no float32 rounding
    at the bound when x64 is off)."""
    return np.minimum(l1, l1 * np.cos(b) / np.sin(b))


def check_edge_radius(beta2: ArrayLike, layer_um: ArrayLike, edge_radius_um: ArrayLike) -> None:
    """Raise ValueError if a concrete `edge_radius_um` is negative or exceeds `max_edge_radius`.

    Traced values (inside `jax.jit`) cannot be checked here; a fit keeps `r` in range through
    its parameter transform (docs/rounded.md §7).
    """
    arrays = (beta2, layer_um, edge_radius_um)
    if any(isinstance(a, jax.core.Tracer) for a in arrays):
        return
    b, l1, r = np.broadcast_arrays(*(np.asarray(a, dtype=float) for a in arrays))
    r_max = _room_np(b, l1)
    if np.any(r < 0):
        raise ValueError(
            f"edge_radius_um = {r.min():g} um is negative: the edge radius must be >= 0 "
            "(0 is the sharp staircase)"
        )
    bad = r > r_max * (1 + 1e-12)
    if np.any(bad):
        i = np.flatnonzero(bad.ravel())[0]
        raise ValueError(
            f"edge_radius_um = {r.ravel()[i]:g} um does not fit the cell of beta2 = "
            f"{np.rad2deg(b.ravel()[i]):g} deg, layer_um = {l1.ravel()[i]:g}: the arc must leave "
            f"both facets a non-negative flat length, r <= max_edge_radius(beta2, layer_um) = "
            f"{r_max.ravel()[i]:g} um; reduce edge_radius_um"
        )


# --------------------------------------------------------------------------------------------
# Small helpers
# --------------------------------------------------------------------------------------------


def _safe_arcsin(x: Array) -> Array:
    """arcsin of `x` clipped to [-1, 1], with a finite (zero) gradient at +-1."""
    x = jnp.clip(x, -1.0, 1.0)
    inside = jnp.abs(x) < 1.0
    x_safe = jnp.where(inside, x, 0.0)
    return jnp.where(inside, jnp.arcsin(x_safe), jnp.sign(x) * HALF_PI)


def _contract(a: Array, b: Array, n_axes: int) -> Array:
    """`sum(a * b)` over the last `n_axes` axes, the leading axes broadcast against each other.

    Written as one `dot_general` (leading axes of equal size are batch axes, an axis of size 1
    in one operand is a free axis of the other): XLA's CPU reduction of a broadcast product
    is several times slower, and would also recompute the operands' producers.
    """
    lead = jnp.broadcast_shapes(a.shape[:-n_axes], b.shape[:-n_axes])
    nd = len(lead)
    a = a.reshape((1,) * (nd - a.ndim + n_axes) + a.shape[: a.ndim - n_axes] + (-1,))
    b = b.reshape((1,) * (nd - b.ndim + n_axes) + b.shape[: b.ndim - n_axes] + (-1,))
    batch = [i for i in range(nd) if a.shape[i] == b.shape[i]]
    a_free = [i for i in range(nd) if a.shape[i] != b.shape[i] and b.shape[i] == 1]
    b_free = [i for i in range(nd) if a.shape[i] != b.shape[i] and a.shape[i] == 1]
    a2 = jnp.squeeze(a, axis=tuple(b_free)) if b_free else a
    b2 = jnp.squeeze(b, axis=tuple(a_free)) if a_free else b
    a_pos = [i for i in range(nd) if i not in b_free]  # axis order of a2 (without contraction)
    b_pos = [i for i in range(nd) if i not in a_free]
    dims = (
        ((a2.ndim - 1,), (b2.ndim - 1,)),
        (tuple(a_pos.index(i) for i in batch), tuple(b_pos.index(i) for i in batch)),
    )
    out = jax.lax.dot_general(a2, b2, dims)  # axes: batch, a_free, b_free
    order = batch + a_free + b_free
    return jnp.transpose(out, np.argsort(order)) if order != list(range(nd)) else out


def _wrap(angle: Array) -> Array:
    """Angle wrapped to (-pi, pi]; the shift is piecewise constant, so gradients pass."""
    return angle - 2 * np.pi * jnp.round(angle / (2 * np.pi))


def _cross(ax: Array, az: Array, bx: Array, bz: Array) -> Array:
    """z-component-free 2-D cross product `a_x b_z - a_z b_x` in the (x, z) plane."""
    return ax * bz - az * bx


# --------------------------------------------------------------------------------------------
# Geometry of one angle of incidence
# --------------------------------------------------------------------------------------------


class _Cell(NamedTuple):
    """Cell constants at one angle of incidence (all broadcast to one shape)."""

    ti: Array  # angle of incidence, clamped inside (-pi/2, pi/2)
    b: Array  # beta2
    l1: Array
    l2: Array
    L: Array  # period
    Lc: Array  # L cos(theta_i): the width of one period on the ray front
    c: Array  # cos(beta2 + theta_i)
    s: Array  # sin(beta2 + theta_i)


def _cell(theta_i: Array, beta2: Array, layer_um: Array) -> _Cell:
    eps = max(1e-7, 1e3 * float(np.finfo(np.dtype(theta_i.dtype)).eps))  # 1e-7 / 1.2e-4 rad
    ti = jnp.clip(theta_i, -HALF_PI + eps, HALF_PI - eps)
    sb, cb = jnp.sin(beta2), jnp.cos(beta2)
    L = layer_um / sb
    u = beta2 + ti
    return _Cell(
        ti=ti,
        b=beta2,
        l1=layer_um,
        l2=layer_um * cb / sb,
        L=L,
        Lc=L * jnp.cos(ti),
        c=jnp.cos(u),
        s=jnp.sin(u),
    )


class _Split(NamedTuple):
    """How the ray front of one period divides among the paths (docs/rounded.md §2-§3).

    Widths are lengths on the ray front (micrometres); angle ranges are in radians.
    """

    tread_escape: Array
    tread_retro: Array
    riser_escape: Array
    riser_retro: Array
    arc_lo: Array  # lit arc: alpha in [arc_lo, arc_hi]
    arc_hi: Array
    tread_tip_lo: Array  # tread -> tip: angle alpha* on the mirror image of the tip
    tread_tip_hi: Array
    riser_tip_lo: Array  # riser -> tip: angle alpha^dagger on the mirror image of the tip
    riser_tip_hi: Array


def _lit_arc(k: _Cell, r: Array) -> tuple[Array, Array]:
    """The lit part of the arc, `alpha in [lo, hi]` (right-hand tip for theta_i >= 0,
    left-hand tip otherwise; both are copies): front-facing, and not in the shadow of the
    neighbouring tip (docs/rounded.md §2). With `k` at `-theta_o` it is the part seen from
    `theta_o`."""
    ti, b, c, s, Lc = k.ti, k.b, k.c, k.s, k.Lc
    pos = ti >= 0
    m_plus = jnp.where(b + ti >= HALF_PI, 1.0, s)
    m_minus = jnp.where(ti <= -b, -1.0, -c)
    a_lo = jnp.maximum(b - HALF_PI, -HALF_PI - ti)
    a_hi = jnp.minimum(b, HALF_PI - ti)
    x_lo = jnp.where(pos, m_plus - Lc / r, -1.0)
    x_hi = jnp.where(pos, 1.0, m_minus + Lc / r)
    a_lo = jnp.maximum(a_lo, _safe_arcsin(x_lo) - ti)
    a_hi = jnp.maximum(jnp.minimum(a_hi, _safe_arcsin(x_hi) - ti), a_lo)
    return a_lo, a_hi


def _split(k: _Cell, r: Array) -> _Split:
    """First hits and flat-first paths in closed form, for edge radius `r` (> 0 where angles
    are used). Ray-front coordinate `u = x cos(theta_i) + z sin(theta_i)`, origin at the centre
    of the tip arc left of the groove (docs/rounded.md §2)."""
    ti, b, c, s, Lc = k.ti, k.b, k.c, k.s, k.Lc
    big = 4.0 * k.L
    pos = ti >= 0
    # Shadow thresholds: for theta_i >= 0 a point is lit iff u >= max of u over the tip to its
    # left; for theta_i < 0 iff u <= min of u over the tip to its right.
    m_plus = jnp.where(b + ti >= HALF_PI, 1.0, s)
    m_minus = jnp.where(ti <= -b, -1.0, -c)
    thr_lo = jnp.where(pos, r * m_plus, -big)
    thr_hi = jnp.where(pos, big, Lc + r * m_minus)
    u_t0 = r * s  # tread starts (tangent point with the arc)
    u_corner = k.l2 * c + r * (s - c)
    u_r1 = Lc - r * c  # riser ends (tangent point with the next arc)
    t_lo, t_hi = jnp.maximum(u_t0, thr_lo), jnp.minimum(u_corner, thr_hi)
    r_lo, r_hi = jnp.maximum(u_corner, thr_lo), jnp.minimum(u_r1, thr_hi)

    # Tread -> ... : unfold the tread reflection; the image of the right tip has centre
    # u = uc_t and its front-facing part alpha* in [max(b - pi, -pi/2 - ti), b - pi/2].
    uc_t = Lc - 2.0 * (k.l1 - r) * s
    ta_max = b - HALF_PI
    ta_min = jnp.minimum(jnp.maximum(b - np.pi, -HALF_PI - ti), ta_max)
    ua_hi = 2.0 * u_corner - u_r1  # == uc_t + r sin(ta_max + ti): the corner reflector's edge
    ua_lo = ua_hi - r * (jnp.sin(ta_max + ti) - jnp.sin(ta_min + ti))
    tread_escape = jnp.maximum(jnp.minimum(t_hi, ua_lo) - t_lo, 0.0)
    tread_retro = jnp.maximum(t_hi - jnp.maximum(t_lo, ua_hi), 0.0)
    ta_u_lo = jnp.clip(jnp.maximum(t_lo, ua_lo), ua_lo, ua_hi)
    ta_u_hi = jnp.clip(jnp.minimum(t_hi, ua_hi), ta_u_lo, ua_hi)

    # Riser -> ... : the image of the left tip (centre uc_r), alpha^dagger in
    # [b, min(b + pi/2, pi/2 - ti)].
    uc_r = 2.0 * (k.l2 - r) * c
    ra_min = b
    ra_max = jnp.maximum(jnp.minimum(b + HALF_PI, HALF_PI - ti), ra_min)
    ub_lo = 2.0 * u_corner - u_t0  # == uc_r + r sin(b + ti)
    ub_hi = ub_lo + r * (jnp.sin(ra_max + ti) - s)
    riser_retro = jnp.maximum(jnp.minimum(r_hi, ub_lo) - r_lo, 0.0)
    riser_escape = jnp.maximum(r_hi - jnp.maximum(r_lo, ub_hi), 0.0)
    ra_u_lo = jnp.clip(jnp.maximum(r_lo, ub_lo), ub_lo, ub_hi)
    ra_u_hi = jnp.clip(jnp.minimum(r_hi, ub_hi), ra_u_lo, ub_hi)

    a_lo, a_hi = _lit_arc(k, r)

    def to_angle(u: Array, centre: Array) -> Array:
        return _safe_arcsin((u - centre) / r) - ti

    return _Split(
        tread_escape=tread_escape,
        tread_retro=tread_retro,
        riser_escape=riser_escape,
        riser_retro=riser_retro,
        arc_lo=a_lo,
        arc_hi=a_hi,
        tread_tip_lo=to_angle(ta_u_lo, uc_t),
        tread_tip_hi=to_angle(ta_u_hi, uc_t),
        riser_tip_lo=to_angle(ra_u_lo, uc_r),
        riser_tip_hi=to_angle(ra_u_hi, uc_r),
    )


# --------------------------------------------------------------------------------------------
# The fan of rays leaving the arc
# --------------------------------------------------------------------------------------------

# Classes of a ray leaving the arc, in the order in which they occur as alpha increases
# (reflected rays of a convex mirror do not cross): left tread, left tip, escape, right tip,
# right riser.
_T0, _A0, _ESC, _A2, _R1 = range(5)


class _ArcGeom(NamedTuple):
    """Neighbours of the lit arc (centre at the origin), for radius `rg`."""

    ti: Array
    b: Array
    rg: Array
    L: Array
    t0x: Array  # left tread: start point and full vector
    t0z: Array
    tex: Array
    tez: Array
    r1x: Array  # right riser: start point (the corner) and full vector
    r1z: Array
    rex: Array
    rez: Array


def _arc_geom(k: _Cell, rg: Array) -> _ArcGeom:
    sb, cb = jnp.sin(k.b), jnp.cos(k.b)
    # left tread from C0 + rg n_T along t_T, length l2 - rg; C0 = (-L, 0)
    t0x, t0z = -k.L + rg * sb, rg * cb
    tlen = k.l2 - rg
    tex, tez = tlen * cb, -tlen * sb
    # right riser from the corner K1 = left tread end + (L, 0), along t_R, length l1 - rg
    r1x, r1z = t0x + tex + k.L, t0z + tez
    rlen = k.l1 - rg
    rex, rez = rlen * sb, rlen * cb
    return _ArcGeom(k.ti, k.b, rg, k.L, t0x, t0z, tex, tez, r1x, r1z, rex, rez)


def _ray(g: _ArcGeom, alpha: Array) -> tuple[Array, Array, Array, Array, Array]:
    """Start point and direction of the ray reflected at arc angle `alpha`."""
    phi = g.ti + 2.0 * alpha
    return g.rg * jnp.sin(alpha), g.rg * jnp.cos(alpha), jnp.sin(phi), jnp.cos(phi), phi


def _hit_segment(px, pz, dx, dz, ax, az, ex, ez) -> Array:  # noqa: ANN001
    """Distance along the ray to the segment `a + s e` (s in [0, 1]), or inf."""
    den = _cross(dx, dz, ex, ez)
    den_safe = jnp.where(den == 0, 1.0, den)
    wx, wz = ax - px, az - pz
    t = _cross(wx, wz, ex, ez) / den_safe
    sp = _cross(wx, wz, dx, dz) / den_safe
    # (a hair of tolerance: at r = r_max a facet ends exactly where the arc ends)
    ok = (den != 0) & (sp >= -1e-9) & (sp <= 1 + 1e-9) & (t > 0)
    return jnp.where(ok, t, jnp.inf)


def _circle(g: _ArcGeom, px, pz, dx, dz, cx) -> tuple[Array, Array, Array, Array]:  # noqa: ANN001
    """Entering intersection of the ray with the circle of the tip centred at `(cx, 0)`.

    Returns `(t, hx, hz, root)`: distance along the ray, hit point relative to the centre and
    `sqrt(rg^2 - d^2)` (`d` the distance of the centre from the line; 0 if it misses), which
    is `rg` times the cosine of the local angle of incidence.
    """
    wx, wz = px - cx, pz
    bq = dx * wx + dz * wz
    dist = _cross(wx, wz, dx, dz)
    disc = (g.rg - dist) * (g.rg + dist)  # rg^2 - dist^2 without cancellation
    hit = disc > 0
    root = jnp.where(hit, jnp.sqrt(jnp.where(hit, disc, 1.0)), 0.0)
    t = -bq - root
    return t, wx + t * dx, wz + t * dz, root


def _arc_class(g: _ArcGeom, alpha: Array) -> Array:
    """Which class (`_T0` .. `_R1`) the ray reflected at arc angle `alpha` belongs to."""
    px, pz, dx, dz, _ = _ray(g, alpha)
    sb, cb = jnp.sin(g.b), jnp.cos(g.b)
    t_t = _hit_segment(px, pz, dx, dz, g.t0x, g.t0z, g.tex, g.tez)
    t_r = _hit_segment(px, pz, dx, dz, g.r1x, g.r1z, g.rex, g.rez)
    hits = []
    for cx in (-g.L, g.L):
        t, hx, hz, root = _circle(g, px, pz, dx, dz, cx)
        on_arc = (hx * sb + hz * cb >= 0) & (hz * sb - hx * cb >= 0)  # b - pi/2 <= alpha2 <= b
        # t > -tiny: at r = r_max the arcs meet in a cusp and a ray leaving the end of one arc
        # starts on the next circle (it hits the corner at once)
        hits.append(jnp.where((root > 0) & (t > -1e-12 * g.L) & on_arc, t, jnp.inf))
    ts = jnp.stack([t_t, hits[0], jnp.full_like(t_t, jnp.inf), hits[1], t_r], axis=-1)
    return jnp.where(jnp.isfinite(jnp.min(ts, axis=-1)), jnp.argmin(ts, axis=-1), _ESC)


def _events(g: _ArcGeom, alpha: Array) -> tuple[Array, Array]:
    """The four boundary functions and their derivatives, shape `(..., 4)`.

    Boundary k is where the ray from the arc passes through the left tread's upper end (1), is
    tangent to the left tip from above (2) or to the right tip (3), or passes through the right
    riser's upper end (4). Each is `cross(Q - P, d) + c = Qx cos(phi) - Qz sin(phi) +
    rg sin(theta_i + alpha) + c` with `P` the point on the arc, `d` the ray's direction at
    angle `phi = theta_i + 2 alpha` and `Q`, `c` the point and offset of the boundary.
    """
    sb, cb = jnp.sin(g.b), jnp.cos(g.b)
    z = jnp.zeros_like(g.L)
    qx = jnp.stack([g.t0x, -g.L, g.L, g.L - g.rg * cb], axis=-1)
    qz = jnp.stack([g.t0z, z, z, g.rg * sb], axis=-1)
    off = jnp.stack([z, g.rg, -g.rg, z], axis=-1)
    phi = g.ti[..., None] + 2.0 * alpha
    u = g.ti[..., None] + alpha
    rg = g.rg[..., None]
    sp, cp = jnp.sin(phi), jnp.cos(phi)
    f = qx * cp - qz * sp + rg * jnp.sin(u) + off
    df = -2.0 * (qx * sp + qz * cp) + rg * jnp.cos(u)
    return f, df


def _arc_boundaries(g: _ArcGeom, lo: Array, hi: Array) -> Array:
    """The four class boundaries in `[lo, hi]`, shape `(..., 4)`, non-decreasing.

    Without gradient: bisection on the class (robust), then safeguarded Newton steps on the
    boundary's smooth function. With gradient: one final Newton step, whose derivative is the
    exact implicit derivative of the boundary (docs/rounded.md §4).
    """
    ks = with_rank(jnp.arange(1, 5), lo.ndim + 1)
    gs = jax.tree_util.tree_map(jax.lax.stop_gradient, g)
    gs4 = jax.tree_util.tree_map(lambda a: a[..., None], gs)
    # The ends are classified a hair inside: exactly at an end the ray may graze the arc or
    # run along a facet, which the ray cast cannot classify reliably.
    nudge = 1e-7 * (hi - lo)
    lo_s = jnp.broadcast_to(jax.lax.stop_gradient(lo + nudge)[..., None], (*lo.shape, 4))
    hi_s = jnp.broadcast_to(jax.lax.stop_gradient(hi - nudge)[..., None], (*hi.shape, 4))
    below_lo = _arc_class(gs4, lo_s) < ks
    below_hi = _arc_class(gs4, hi_s) < ks

    def bisect(_: int, bracket: tuple[Array, Array]) -> tuple[Array, Array]:
        a, z = bracket
        mid = 0.5 * (a + z)
        below = _arc_class(gs4, mid) < ks
        return jnp.where(below, mid, a), jnp.where(below, z, mid)

    a, z = jax.lax.fori_loop(0, _BISECT_STEPS, bisect, (lo_s, hi_s))

    def newton(_: int, x: Array) -> Array:
        f, df = _events(gs, x)
        step = f / jnp.where(df == 0, 1.0, df)
        return jnp.clip(x - jnp.where(df == 0, 0.0, step), a, z)

    x0 = jax.lax.stop_gradient(jax.lax.fori_loop(0, _NEWTON_STEPS, newton, 0.5 * (a + z)))
    f, df = _events(g, x0)
    converged = jnp.abs(jax.lax.stop_gradient(f)) <= 1e-9 * g.L[..., None]
    df_safe = jnp.where(converged & (df != 0), df, 1.0)
    root = x0 - jnp.where(converged & (df != 0), f / df_safe, 0.0)
    interior = below_lo & ~below_hi
    bound = jnp.where(interior, root, jnp.where(below_hi, hi[..., None], lo[..., None]))
    bound = jnp.clip(bound, lo[..., None], hi[..., None])
    return jax.lax.cummax(bound, axis=bound.ndim - 1)


class _Nodes(NamedTuple):
    """Outgoing direction and optics at parameter values `t` of the continuous lobes."""

    theta_o: Array
    density: Array  # geometric power per radian of theta_o (per unit incident power)
    cos1: Array  # local incidence cosine of the first reflection
    cos2: Array  # ... of the second reflection (1 for the single-reflection lobe, unused)


def _tip_to_tip(g: _ArcGeom, alpha: Array, cx: Array) -> tuple[Array, Array]:
    """Outgoing direction and second-bounce cosine of a ray reflected at `alpha` off the arc
    and then off the tip centred at `(cx, 0)`."""
    px, pz, dx, dz, phi = _ray(g, alpha)
    _, hx, hz, root = _circle(g, px, pz, dx, dz, cx)
    alpha2 = jnp.arctan2(hx, hz)
    return _wrap(2.0 * alpha2 + np.pi - phi), root / g.rg


def _slot_eval(k: _Cell, g: _ArcGeom, r: Array, t: Array) -> _Nodes:
    """Evaluate the seven continuous lobes at parameters `t` of shape `(..., 7, m)`.

    Lobe j's parameter is the angle of the outward normal where the incident beam meets the
    arc (for tread/riser -> tip: the mirror image of the arc), so its geometric power per unit
    parameter is `r cos(theta_i + t) / (L cos theta_i)` for all seven (docs/rounded.md §3).
    """
    ex = jax.tree_util.tree_map(lambda a: a[..., None], g)
    ti, b = ex.ti, ex.b
    phi = ti[..., None] + 2.0 * t[..., :5, :]  # arc-first lobes: direction after the arc
    theta = [
        _wrap(2 * b + np.pi - phi[..., 0, :]),  # tip > tread: mirror in the tread
        None,
        phi[..., 2, :],  # tip: escapes
        None,
        _wrap(2 * b - phi[..., 4, :]),  # tip > riser
        _wrap(2 * b + np.pi - ti - 2.0 * t[..., 5, :]),  # tread > tip (unfolded)
        _wrap(2 * b - ti - 2.0 * t[..., 6, :]),  # riser > tip (unfolded)
    ]
    slope = [2.0, None, 2.0, None, 2.0, 2.0, 2.0]
    cos2 = [-jnp.cos(phi[..., 0, :] - b), None, jnp.ones_like(phi[..., 2, :]), None]
    cos2 += [jnp.sin(phi[..., 4, :] - b), jnp.cos(ti + t[..., 5, :]), jnp.cos(ti + t[..., 6, :])]
    for j, cx in ((1, -ex.L), (3, ex.L)):
        tj = t[..., j, :]
        (theta[j], cos2[j]), (slope[j], _) = jax.jvp(
            lambda a, cx=cx: _tip_to_tip(ex, a, cx), (tj,), (jnp.ones_like(tj),)
        )
        slope[j] = jnp.abs(slope[j])
    cos_hit = jnp.cos(ti[..., None] + t)
    weight = r[..., None, None] * cos_hit / k.Lc[..., None, None]
    slope_all = jnp.stack([jnp.broadcast_to(sl, t.shape[:-2] + t.shape[-1:]) for sl in slope], -2)
    good = slope_all > 0
    density = jnp.where(good, weight / jnp.where(good, slope_all, 1.0), 0.0)
    cos1 = jnp.concatenate(
        [
            cos_hit[..., :5, :],
            jnp.broadcast_to(k.c[..., None, None], cos_hit[..., 5:6, :].shape),
            jnp.broadcast_to(k.s[..., None, None], cos_hit[..., 6:7, :].shape),
        ],
        axis=-2,
    )
    return _Nodes(
        theta_o=jnp.stack(theta, axis=-2),
        density=density,
        cos1=cos1,
        cos2=jnp.stack(cos2, axis=-2),
    )


# --------------------------------------------------------------------------------------------
# The sigma = 0 structure
# --------------------------------------------------------------------------------------------


class RoundedStructure(NamedTuple):
    """The unbroadened rounded staircase at one angle of incidence [conventions §3, §4].

    `lobes`: the three delta lobes (tread, riser, retro; sharp directions and Fresnel factors,
    weights reduced by the arcs). Continuous lobes (axis -3 follows `ARC_LOBE_NAMES`, then
    `resolution` panels, then 3 nodes): panel `j` covers `theta_o` in
    `[panel_lo, panel_hi]` (radians) and its power density (1/rad, Fresnel included) is the
    quadratic through `(node_theta_o, node_density)`. `node_weight` is the geometric density
    (no Fresnel). All densities are per unit incident power.
    """

    lobes: Lobes
    panel_lo: Float[Array, "... 7 P"]
    panel_hi: Float[Array, "... 7 P"]
    node_theta_o: Float[Array, "... 7 P 3"]
    node_density: Float[Array, "... 7 P 3"]
    node_weight: Float[Array, "... 7 P 3"]


def _panel_fractions(resolution: int) -> tuple[np.ndarray, np.ndarray]:
    """Panel edges `(7, P + 1)` and Gauss-Legendre nodes `(7, P, 3)` as fractions of each
    lobe's parameter interval.

    Uniform in a variable `tau` in [0, 1]. For the two tip -> tip lobes the parameter is
    `tau^2` measured from the end where the ray grazes the second tip: there the outgoing
    direction moves like the square root of the arc angle, and in `tau` it moves linearly, so
    the panels are evenly spread in `theta_o` (docs/rounded.md §5).
    """
    tau_e = np.linspace(0.0, 1.0, resolution + 1)
    mid, half = 0.5 * (tau_e[1:] + tau_e[:-1]), 0.5 * (tau_e[1:] - tau_e[:-1])
    tau_n = mid[:, None] + half[:, None] * _GL_X

    def stretch(tau: np.ndarray) -> np.ndarray:
        out = np.broadcast_to(tau, (7, *tau.shape)).copy()
        out[1] = 1.0 - (1.0 - tau) ** 2  # left tip: grazing at the upper end
        out[3] = tau**2  # right tip: grazing at the lower end
        return out

    return stretch(tau_e), stretch(tau_n)


class RoundedGeometry(NamedTuple):
    """What `rounded_geometry` returns (see there); arrays in radians and 1/rad."""

    delta_weight: Array  # (..., 3)
    slot_lo: Array  # (..., 7): parameter interval of each continuous lobe (arc angle)
    slot_hi: Array
    panel_lo: Array  # (..., 7, P)
    panel_hi: Array
    nodes: _Nodes  # (..., 7, P, 3)


def _arc_radius(k: _Cell, r: Array) -> Array:
    """The radius at which arc angles are evaluated: `r`, but at least `sqrt(eps)` periods
    (the `r -> 0+` limit; the arcs' powers keep the factor `r` itself)."""
    r_tiny = k.L * float(np.sqrt(np.finfo(np.dtype(k.L.dtype)).eps))
    return jnp.where(r > r_tiny, r, r_tiny)


def _geometry(
    theta_i: Array, beta2: Array, layer_um: Array, r: Array, resolution: int
) -> RoundedGeometry:
    k = _cell(theta_i, beta2, layer_um)
    rg = _arc_radius(k, r)
    flats = _split(k, r)
    ang = _split(k, rg)
    g = _arc_geom(k, rg)
    bounds = _arc_boundaries(g, ang.arc_lo, ang.arc_hi)
    edges = jnp.concatenate([ang.arc_lo[..., None], bounds, ang.arc_hi[..., None]], axis=-1)
    lo = jnp.concatenate(
        [edges[..., :-1], ang.tread_tip_lo[..., None], ang.riser_tip_lo[..., None]], axis=-1
    )
    hi = jnp.concatenate(
        [edges[..., 1:], ang.tread_tip_hi[..., None], ang.riser_tip_hi[..., None]], axis=-1
    )
    frac_e, frac_n = (jnp.asarray(a, lo.dtype) for a in _panel_fractions(resolution))
    frac_e, frac_n = with_rank(frac_e, lo.ndim + 1), with_rank(frac_n, lo.ndim + 2)
    t_edges = lo[..., None] + (hi - lo)[..., None] * frac_e  # (..., 7, P + 1)
    t_nodes = lo[..., None, None] + (hi - lo)[..., None, None] * frac_n  # (..., 7, P, 3)
    shape = t_nodes.shape
    both = jnp.concatenate([t_edges, t_nodes.reshape(*shape[:-2], -1)], axis=-1)
    ev = _slot_eval(k, g, r, both)
    n_e = resolution + 1
    th_edges = ev.theta_o[..., :n_e]
    nodes = jax.tree_util.tree_map(lambda a: a[..., n_e:].reshape(shape), ev)
    lo_th = jnp.minimum(th_edges[..., 1:], th_edges[..., :-1])
    hi_th = jnp.maximum(th_edges[..., 1:], th_edges[..., :-1])
    return RoundedGeometry(_delta_weight(k, flats), lo, hi, lo_th, hi_th, nodes)


def _delta_weight(k: _Cell, flats: _Split) -> Array:
    """The three delta lobes' weights (tread, riser, retro), fractions of the incident power."""
    w = [flats.tread_escape, flats.riser_escape, flats.tread_retro + flats.riser_retro]
    return jnp.stack(w, axis=-1) / k.Lc[..., None]


def rounded_delta_weight(
    theta_i: ArrayLike, beta2: ArrayLike, layer_um: ArrayLike, edge_radius_um: ArrayLike
) -> Float[Array, "... 3"]:
    """The rounded staircase's delta-lobe weights `(tread, riser, retro)` (fractions of the
    incident power, closed form, docs/rounded.md §3), `rounded_geometry`'s `delta_weight`
    without the arcs: cheap enough for every node of a fit, where the weights change fast with
    the angle of incidence (near a facet's grazing mirror direction) [conventions §1, §2]."""
    ti, b, l1, r = _geom_args(theta_i, beta2, layer_um, edge_radius_um)
    k = _cell(ti, b, l1)
    return _delta_weight(k, _split(k, r))


def _fresnel_product(nodes: _Nodes, n: Array, c: Array | None = None) -> Array:
    """Unpolarised Fresnel factor of each node's path [conventions §6].

    Both reflections of a two-bounce path lie in one plane of incidence, so the product is
    taken per polarisation and then averaged. Evaluated only where needed: the first bounce of
    tread/riser -> tip is one flat facet (one value), tip -> escape has no second bounce.
    `c` (broadcasting with `n`): a ray out of the plane, whose projection onto it has the
    length `c`, meets every surface at the local cosine `c` times the in-plane one
    [conventions §11]; the turn of the s and p axes between two reflections is left out here
    (docs/model.md §7.5).
    """
    n_b = n[..., None, None, None]
    cos1, cos2 = nodes.cos1, nodes.cos2
    if c is not None:
        c_b = jnp.asarray(c)[..., None, None, None]
        cos1, cos2 = cos1 * c_b, cos2 * c_b
    arc1: SP = fresnel_sp(cos1[..., :_N_ARC_FIRST, :, :], n_b)
    flat: SP = fresnel_sp(cos1[..., _N_ARC_FIRST:, :1, :1], n_b)
    second = [j for j in range(7) if j != _ESC_SLOT]
    bounce2: SP = fresnel_sp(cos2[..., second, :, :], n_b)

    def first(a: Array, b: Array) -> Array:
        shape = jnp.broadcast_shapes(a.shape[:-3], b.shape[:-3]) + a.shape[-2:]
        a = jnp.broadcast_to(a, (*shape[:-2], _N_ARC_FIRST, *shape[-2:]))
        b = jnp.broadcast_to(b, (*shape[:-2], 7 - _N_ARC_FIRST, *shape[-2:]))
        return jnp.concatenate([a, b], axis=-3)

    def with_one(a: Array) -> Array:  # insert the escape slot's "second bounce" of 1
        one = jnp.ones_like(a[..., :1, :, :])
        return jnp.concatenate([a[..., :_ESC_SLOT, :, :], one, a[..., _ESC_SLOT:, :, :]], -3)

    f1s, f1p = first(arc1.s, flat.s), first(arc1.p, flat.p)
    return 0.5 * (f1s * with_one(bounce2.s) + f1p * with_one(bounce2.p))


def rounded_structure(
    theta_i: ArrayLike,
    beta2: ArrayLike,
    n: ArrayLike,
    layer_um: ArrayLike,
    edge_radius_um: ArrayLike,
    *,
    resolution: int = ROUNDED_RESOLUTION,
) -> RoundedStructure:
    """The unbroadened rounded model: delta lobes plus panels of continuous lobes.

    Angles in radians [conventions §1]; `layer_um` and `edge_radius_um` in micrometres;
    `n` complex allowed [conventions §6]. Arguments broadcast.
    """
    check_edge_radius(beta2, layer_um, edge_radius_um)
    theta_i, beta2, layer_um, r = _geom_args(theta_i, beta2, layer_um, edge_radius_um)
    n = jnp.asarray(n)
    geo = _geometry(theta_i, beta2, layer_um, r, resolution)
    lobes_shape = jnp.broadcast_shapes(theta_i.shape, n.shape)
    ti_b = jnp.broadcast_to(theta_i, lobes_shape)
    b_b = jnp.broadcast_to(beta2, lobes_shape)
    lobes = Lobes(
        theta_o=lobe_directions(ti_b, b_b),
        weight=jnp.broadcast_to(geo.delta_weight, (*lobes_shape, 3)),
        fresnel=lobe_fresnel(ti_b, b_b, n),
    )
    fres = _fresnel_product(geo.nodes, n)
    return RoundedStructure(
        lobes=lobes,
        panel_lo=geo.panel_lo,
        panel_hi=geo.panel_hi,
        node_theta_o=geo.nodes.theta_o,
        node_density=geo.nodes.density * fres,
        node_weight=geo.nodes.density,
    )


def _geom_args(
    theta_i: ArrayLike, beta2: ArrayLike, layer_um: ArrayLike, r: ArrayLike
) -> tuple[Array, Array, Array, Array]:
    """Broadcast the geometric arguments to one shape and their common float dtype (Python
    scalars are weakly typed, so float32 angles stay float32) [conventions §10]."""
    dtype = jnp.result_type(theta_i, beta2, layer_um, r)
    if not jnp.issubdtype(dtype, jnp.floating):
        dtype = jnp.result_type(float)
    arrays = [jnp.asarray(a, dtype) for a in (theta_i, beta2, layer_um, r)]
    ti, b, l1, rr = jnp.broadcast_arrays(*arrays)
    return ti, b, l1, rr


# --------------------------------------------------------------------------------------------
# Panels: interpolation, integrals, broadening
# --------------------------------------------------------------------------------------------


def _lagrange(lo: Array, hi: Array, zeta: Array) -> tuple[Array, Array, Array, Array]:
    """Monomial coefficients (in xi = (theta - m) / h) of the three Lagrange basis polynomials.

    Returns `(m, h, coef)` with `coef[..., i, k]` the coefficient of `xi^k` in basis `i`, and
    the standard Gauss-Legendre positions where the panel is too narrow to place nodes.
    """
    m = 0.5 * (lo + hi)
    h = 0.5 * (hi - lo)
    wide = h > 0
    h_safe = jnp.where(wide, h, 1.0)
    gl_x = jnp.asarray(_GL_X, zeta.dtype)
    xi = jnp.where(wide[..., None], (zeta - m[..., None]) / h_safe[..., None], gl_x)
    xi = jnp.clip(xi, -1.0, 1.0)
    x0, x1, x2 = xi[..., 0], xi[..., 1], xi[..., 2]
    # Nodes closer than this (a panel whose direction map is numerically degenerate, e.g. a
    # sub-interval of width ~1e-8 rad) get the constant through the nodes' mean instead.
    spread = jnp.minimum(jnp.minimum(jnp.abs(x1 - x0), jnp.abs(x2 - x1)), jnp.abs(x2 - x0))
    good = spread > 0.05
    pairs = ((x1, x2, x0), (x0, x2, x1), (x0, x1, x2))
    coefs = []
    for xj, xk, xi_ in pairs:
        den = (xi_ - xj) * (xi_ - xk)
        inv = 1.0 / jnp.where(good, den, 1.0)
        lagrange = jnp.stack([xj * xk * inv, -(xj + xk) * inv, inv], axis=-1)
        constant = jnp.stack([jnp.full_like(inv, 1 / 3), 0 * inv, 0 * inv], axis=-1)
        coefs.append(jnp.where(good[..., None], lagrange, constant))
    return m, h, jnp.stack(coefs, axis=-2), xi


def _poly_integral(coef: Array, h: Array, x_lo: Array, x_hi: Array) -> Array:
    """Integral over theta of each basis polynomial between xi = x_lo and x_hi: `h int dxi`."""
    powers = jnp.stack(
        [x_hi - x_lo, (x_hi**2 - x_lo**2) / 2, (x_hi**3 - x_lo**3) / 3], axis=-1
    )  # (..., 3 powers)
    return h[..., None] * jnp.sum(coef * powers[..., None, :], axis=-1)


_INV_SQRT_2PI = float(1 / np.sqrt(2 * np.pi))
_INV_SQRT_2 = float(1 / np.sqrt(2.0))


def _basis(coef: Array, xi: Array) -> Array:
    """Values of the basis polynomials `coef[..., i, :]` at `xi` (broadcast against `i`)."""
    return coef[..., 0] + xi * (coef[..., 1] + xi * coef[..., 2])


def _std_pdf(z: Array) -> Array:
    return jnp.exp(-0.5 * z * z) * _INV_SQRT_2PI


def _std_cdf(z: Array) -> Array:
    return 0.5 * (1.0 + erf(z * _INV_SQRT_2))


def _kernel_moments(
    theta_o: Array, sigma: Array, lo: Array, hi: Array, m: Array, h: Array
) -> Array:
    """`M[..., k] = int_panel xi^k K(theta_o; theta', sigma) dtheta'` (k = 0, 1, 2), with
    `xi = (theta' - m) / h` and `K` the hemisphere-truncated, per-ray renormalised Gaussian
    [conventions §5]. A panel's polynomial `sum_k c_k xi^k` then contributes `sum_k c_k M_k`.

    Plain Gaussian part: exact moments (erf) for panels wider than `_NARROW * sigma`, Gauss-
    Legendre with the kernel at the nodes otherwise (where the exact moments would cancel
    catastrophically). Truncation part, `K (1/mass - 1)`, which only matters within a few sigma
    of +-pi/2: Gauss-Legendre on the panel's overlap with window pieces cut at `_HORIZON_CUTS`
    sigma from each horizon. Zero for `|theta_o| > pi/2`.
    """
    th = theta_o[..., None, None]
    sg = sigma[..., None, None]
    # exact moments of xi^k against the Gaussian
    za, zb = (lo - th) / sg, (hi - th) / sg
    pa, pb = _std_pdf(za), _std_pdf(zb)
    j0 = _std_cdf(zb) - _std_cdf(za)
    j1 = sg * (pa - pb)
    j2 = sg * sg * (j0 + za * pa - zb * pb)
    delta = m - th
    wide = h > _NARROW * sg
    h_safe = jnp.where(wide, h, 1.0)
    m1 = (j1 - delta * j0) / h_safe
    m2 = (j2 - 2 * delta * j1 + delta * delta * j0) / (h_safe * h_safe)
    # narrow panels: Gauss-Legendre with the kernel at the standard nodes
    gl_x, gl_w = (with_rank(jnp.asarray(a, lo.dtype), m.ndim + 1) for a in (_GL_X, _GL_W))
    xq = m[..., None] + h[..., None] * gl_x
    fq = h[..., None] * gl_w * _std_pdf((xq - th[..., None]) / sg[..., None]) / sg[..., None]
    narrow = [jnp.sum(fq, -1), jnp.sum(fq * gl_x, -1), jnp.sum(fq * gl_x * gl_x, -1)]
    plain = [jnp.where(wide, a, b) for a, b in zip([j0, m1, m2], narrow, strict=True)]
    # truncation correction near the horizons: window pieces between distances cuts[j] and
    # cuts[j+1] sigma from +pi/2 and from -pi/2, never crossing 0 (so the sides never overlap)
    xh, wh = (
        with_rank(jnp.asarray(a, lo.dtype), lo.ndim + 2)
        for a in np.polynomial.legendre.leggauss(_HORIZON_NODES)
    )
    near = with_rank(jnp.asarray(np.tile(_HORIZON_CUTS[:-1], 2), lo.dtype), lo.ndim + 1)
    far = with_rank(jnp.asarray(np.tile(_HORIZON_CUTS[1:], 2), lo.dtype), lo.ndim + 1)
    upper = with_rank(np.repeat([True, False], len(_HORIZON_CUTS) - 1), lo.ndim + 1)
    s6 = sg[..., None]
    piece_lo = jnp.where(upper, jnp.maximum(HALF_PI - far * s6, 0.0), -HALF_PI + near * s6)
    piece_hi = jnp.where(upper, HALF_PI - near * s6, jnp.minimum(-HALF_PI + far * s6, 0.0))
    a_ = jnp.maximum(lo[..., None], piece_lo)  # (..., P, 6)
    b_ = jnp.maximum(jnp.minimum(hi[..., None], piece_hi), a_)
    hw = 0.5 * (b_ - a_)
    x = (0.5 * (a_ + b_))[..., None] + hw[..., None] * xh  # (..., P, 6, q)
    s_x = sg[..., None, None]
    mass = hemisphere_mass(x, s_x)
    kern = _std_pdf((x - th[..., None, None]) / s_x) / s_x
    f = kern * (1.0 / mass - 1.0) * hw[..., None] * wh
    xi = (x - m[..., None, None]) / jnp.where(h > 0, h, 1.0)[..., None, None]
    corr = [jnp.sum(f, (-2, -1)), jnp.sum(f * xi, (-2, -1)), jnp.sum(f * xi * xi, (-2, -1))]
    moments = jnp.stack([p + c for p, c in zip(plain, corr, strict=True)], axis=-1)
    inside = jnp.abs(theta_o) <= HALF_PI
    return jnp.where(inside[..., None, None, None], moments, 0.0)


# --------------------------------------------------------------------------------------------
# Public functions
# --------------------------------------------------------------------------------------------


def brdf_rounded(
    theta_i: ArrayLike,
    theta_o: ArrayLike,
    beta2: ArrayLike,
    n: ArrayLike,
    sigma: ArrayLike,
    layer_um: ArrayLike,
    edge_radius_um: ArrayLike,
    *,
    resolution: int = ROUNDED_RESOLUTION,
) -> Float[Array, "..."]:
    """In-plane reflectance density `rho(theta_i, theta_o)` (1/rad) of the rounded staircase.

    The rounded counterpart of `brdf` [conventions §4, §5]: the three delta lobes (with their
    weights reduced by the arcs) and the seven continuous arc lobes, each ray's Gaussian of
    width `sigma` (radians, > 0) truncated to the hemisphere and renormalised. Equal to `brdf`
    at `edge_radius_um = 0`. `layer_um` is `l1` and `edge_radius_um` the tip radius `r`, both in
    micrometres, `0 <= r <= max_edge_radius(beta2, layer_um)`. `resolution` (static) is the
    number of panels per continuous sub-interval (error versus time: docs/rounded.md §6). All
    arguments broadcast; geometry is computed once per distinct (theta_i, beta2, layer_um, r)
    element and the Fresnel factors once per element of the broadcast with `n`, so pass
    wavelengths on their own axis [conventions §1, §6].
    """
    check_edge_radius(beta2, layer_um, edge_radius_um)
    ti, b, l1, r = _geom_args(theta_i, beta2, layer_um, edge_radius_um)
    # The barrier keeps XLA from fusing (and so repeating) the geometry into every wavelength
    # and every viewing angle.
    geo = jax.lax.optimization_barrier(_geometry(ti, b, l1, r, resolution))
    return brdf_rounded_from_geometry(geo, ti, theta_o, b, n, sigma)


def rounded_geometry(
    theta_i: ArrayLike,
    beta2: ArrayLike,
    layer_um: ArrayLike,
    edge_radius_um: ArrayLike,
    *,
    resolution: int = ROUNDED_RESOLUTION,
) -> RoundedGeometry:
    """The part of `brdf_rounded` that depends on the geometry only (not on `theta_o`, `n`,
    `sigma`): delta-lobe weights, panels and node densities, one set per broadcast element of
    the arguments [conventions §1, §2].

    For callers that evaluate many viewing angles, wavelengths or widths at few distinct
    (theta_i, beta2, layer_um) (a fit): compute it once per distinct geometry, gather it to the
    rows (`jax.tree_util.tree_map(lambda a: a[idx], geo)`) and finish with
    `brdf_rounded_from_geometry`. Traced radii are not range-checked (see `check_edge_radius`).
    """
    check_edge_radius(beta2, layer_um, edge_radius_um)
    ti, b, l1, r = _geom_args(theta_i, beta2, layer_um, edge_radius_um)
    return _geometry(ti, b, l1, r, resolution)


def _with_lead_rank(geo: RoundedGeometry, ndim: int) -> RoundedGeometry:
    """`geo` with unit axes prepended to every leaf so that its leading axes number `ndim`."""
    extra = ndim - (geo.delta_weight.ndim - 1)
    return jax.tree_util.tree_map(lambda a: a.reshape((1,) * extra + a.shape), geo)


def brdf_rounded_from_geometry(
    geo: RoundedGeometry,
    theta_i: ArrayLike,
    theta_o: ArrayLike,
    beta2: ArrayLike,
    n: ArrayLike,
    sigma: ArrayLike,
    t_i: ArrayLike | None = None,
) -> Float[Array, "..."]:
    """`brdf_rounded` from a precomputed `rounded_geometry` (1/rad) [conventions §4, §5, §6].

    `geo`'s leading axes must broadcast with `theta_i` and `beta2` (the angles it was computed
    at, radians) and those with `theta_o`, `n` and `sigma`, as in `brdf_rounded`. `t_i`: the
    light's component along the layer lines (the lab model; `theta_i` is then the projected
    angle, conventions §11): every Fresnel factor at the 3-D local angle, the delta lobes'
    retroreflection with the turn of its s and p axes (`lobe_fresnel_3d`).
    """
    dtype = geo.panel_lo.dtype
    lead = geo.delta_weight.ndim - 1  # the leading (broadcast) axes of the geometry
    t_in = jnp.zeros((), dtype) if t_i is None else jnp.asarray(t_i, dtype)
    ti, b, theta_o, sigma, n, t_in = same_rank(
        jnp.asarray(theta_i, dtype), jnp.asarray(beta2, dtype), jnp.asarray(theta_o, dtype),
        jnp.asarray(sigma, dtype), n, t_in, jnp.zeros((1,) * lead, dtype),
    )[:6]  # fmt: skip
    geo = _with_lead_rank(geo, ti.ndim)
    # delta lobes, exactly as the sharp model broadens them
    kernel = hemisphere_gaussian(theta_o[..., None], lobe_directions(ti, b), sigma[..., None])
    fresnel = lobe_fresnel(ti, b, n) if t_i is None else lobe_fresnel_3d(ti, t_in, b, n)
    ratio = geo.delta_weight * fresnel
    delta = jnp.sum(ratio * kernel, axis=-1)
    # continuous lobes
    m, h, coef, _ = _lagrange(geo.panel_lo, geo.panel_hi, geo.nodes.theta_o)
    moments = _kernel_moments(theta_o, sigma, geo.panel_lo, geo.panel_hi, m, h)
    w = jnp.sum(coef * moments[..., None, :], axis=-1)  # weight of each node value
    c = None if t_i is None else jnp.sqrt(jnp.clip(1.0 - t_in * t_in, 0.0, 1.0))
    g = geo.nodes.density * _fresnel_product(geo.nodes, n, c)
    # The quadratic interpolants can undershoot a little where the Fresnel factor varies on a
    # sub-panel scale (n -> 1 near grazing, where it jumps from ~0 to 1 within a degree).
    # (`where`, not `maximum`: at exactly 0, e.g. r = 0 in a far tail, keep the derivative)
    rho = delta + _contract(g, w, 3)
    return jnp.where(rho >= 0, rho, 0.0)


ARC_SEEN_NODES = 12
"""Gauss-Legendre nodes of `arc_single_seen` over the lit and seen arc within `ARC_SEEN_REACH`
kernel widths of the arc angle whose mirror direction is the view: a Gaussian cut anywhere
in that window integrates to 1e-5 (its tails beyond it hold 7e-6)."""
ARC_SEEN_REACH = 4.5


def arc_single_seen(
    theta_i: ArrayLike,
    theta_o: ArrayLike,
    beta2: ArrayLike,
    n: ArrayLike,
    sigma: ArrayLike,
    layer_um: ArrayLike,
    edge_radius_um: ArrayLike,
    c: ArrayLike = 1.0,
) -> Float[Array, "..."]:
    """In-plane density (1/rad) of the light reflected once by the rounded tips into
    `theta_o` when each arc point spreads its mirror direction `phi = theta_i + 2 alpha` by a
    Gaussian of width `sigma` (per ray truncated to the hemisphere and renormalised), counted
    where the point is lit and **seen from `theta_o`** (docs/model.md §7.6): a rough arc point
    whose mirror ray would hit the next step still sends light to a camera that sees it, and a
    point hidden from the camera sends none. At `sigma -> 0` it is the `tip` lobe of
    `brdf_rounded`, whose visibility is the mirror ray's. `c`: the 3-D factor of the local
    cosines [conventions §11]. Angles in radians; arguments broadcast."""
    ti, b, l1, r = _geom_args(theta_i, beta2, layer_um, edge_radius_um)
    th, sg, c = (jnp.asarray(a, ti.dtype) for a in (theta_o, sigma, c))
    ti, b, l1, r, th, sg, n, c = same_rank(ti, b, l1, r, th, sg, n, c)
    k = _cell(ti, b, l1)
    rg = _arc_radius(k, r)
    lit_lo, lit_hi = _lit_arc(k, rg)
    seen_lo, seen_hi = _lit_arc(_cell(-th, b, l1), rg)
    centre = 0.5 * (th - k.ti)  # the arc angle whose mirror direction is theta_o
    reach = 0.5 * ARC_SEEN_REACH * sg  # the kernel's sd in alpha is sigma / 2
    lo = jnp.maximum(jnp.maximum(lit_lo, seen_lo), centre - reach)
    hi = jnp.maximum(jnp.minimum(jnp.minimum(lit_hi, seen_hi), centre + reach), lo)
    x, w = (with_rank(jnp.asarray(a, lo.dtype), lo.ndim + 1)
            for a in np.polynomial.legendre.leggauss(ARC_SEEN_NODES))  # fmt: skip
    half = 0.5 * (hi - lo)
    a = (0.5 * (lo + hi))[..., None] + half[..., None] * x
    cos_hit = jnp.cos(k.ti[..., None] + a)
    phi = k.ti[..., None] + 2.0 * a
    s_n = sg[..., None]
    # each point's Gaussian renormalised on its own hemisphere, alpha +- pi/2 (not the face's)
    mass = hemisphere_mass(phi - a, s_n)
    kern = _std_pdf((th[..., None] - phi) / s_n) / s_n / mass
    fres = fresnel_unpolarised(cos_hit * c[..., None], n[..., None])
    power = r[..., None] * cos_hit / k.Lc[..., None]  # incident power per unit alpha (§2)
    out = half * jnp.sum(w * power * fres * kern, axis=-1)
    return jnp.where(jnp.abs(th) <= HALF_PI, out, 0.0)


def rounded_binned(
    theta_i: ArrayLike,
    bin_edges: ArrayLike,
    beta2: ArrayLike,
    n: ArrayLike,
    layer_um: ArrayLike,
    edge_radius_um: ArrayLike,
    *,
    resolution: int = ROUNDED_RESOLUTION,
) -> Float[Array, "... n_bins"]:
    """Reflected power per `theta_o` bin without broadening (sigma = 0), per unit incident power.

    `bin_edges` (radians, increasing, 1-D) follow `numpy.histogram`: bins are half-open
    `[e_k, e_k+1)` except the last, which is closed; a delta lobe on an edge counts in the bin
    above it. Divide by the bin widths for the density of [conventions §4]. The trailing axis
    is the bin; the others broadcast from the arguments.
    """
    s = rounded_structure(theta_i, beta2, n, layer_um, edge_radius_um, resolution=resolution)
    e = jnp.asarray(bin_edges, s.panel_lo.dtype)
    # delta lobes
    d = s.lobes.theta_o[..., None]  # (..., 3, 1)
    e_d = with_rank(e, d.ndim)
    inside = (d >= e_d[..., :-1]) & (d < e_d[..., 1:])
    inside = inside.at[..., -1].set(inside[..., -1] | (d[..., 0] == e[-1]))
    delta = jnp.sum(s.lobes.ratio[..., None] * inside, axis=-2)
    # panels: exact integral of the interpolant over each bin
    m, h, coef, _ = _lagrange(s.panel_lo, s.panel_hi, s.node_theta_o)
    h_safe = jnp.where(h > 0, h, 1.0)
    xe = (with_rank(e, m.ndim + 1) - m[..., None]) / h_safe[..., None]
    xe = jnp.clip(xe, -1.0, 1.0)  # (..., 7, P, n_e)
    powers = jnp.stack([xe, xe**2 / 2, xe**3 / 3], axis=-1)  # (..., 7, P, n_e, 3)
    anti = jnp.einsum("...ik,...ek->...ei", coef, powers)  # (..., 7, P, n_e, 3 basis)
    per_bin = (anti[..., 1:, :] - anti[..., :-1, :]) * h[..., None, None]
    cont = jnp.einsum("...spi,...spbi->...b", s.node_density, per_bin)
    return delta + cont


class RoundedPaths(NamedTuple):
    """Geometric weight and reflectance ratio of every path [conventions §3, §4].

    The last axis has 10 entries: the delta lobes `tread`, `riser`, `retro`, then the
    continuous lobes in `ARC_LOBE_NAMES` order. `weight` is the exact fraction of the rays
    hitting one period that take the path (closed form; the ten sum to 1), `ratio` the
    reflected power (Fresnel included; panels integrated for the continuous lobes).
    """

    weight: Float[Array, "... 10"]
    ratio: Float[Array, "... 10"]


PATH_NAMES: tuple[str, ...] = ("tread", "riser", "retro", *ARC_LOBE_NAMES)
"""Order of `RoundedPaths` entries."""


def rounded_paths(
    theta_i: ArrayLike,
    beta2: ArrayLike,
    n: ArrayLike,
    layer_um: ArrayLike,
    edge_radius_um: ArrayLike,
    *,
    resolution: int = ROUNDED_RESOLUTION,
) -> RoundedPaths:
    """Weight and reflectance ratio of each of the ten paths (see `RoundedPaths`)."""
    check_edge_radius(beta2, layer_um, edge_radius_um)
    ti, b, l1, r = _geom_args(theta_i, beta2, layer_um, edge_radius_um)
    n = jnp.asarray(n)
    geo = _geometry(ti, b, l1, r, resolution)
    k = _cell(ti, b, l1)
    tic = k.ti[..., None]
    arc_w = (
        r[..., None] * (jnp.sin(tic + geo.slot_hi) - jnp.sin(tic + geo.slot_lo)) / k.Lc[..., None]
    )
    weight = jnp.concatenate([geo.delta_weight, arc_w], axis=-1)
    _, h, coef, _ = _lagrange(geo.panel_lo, geo.panel_hi, geo.nodes.theta_o)
    full = _poly_integral(coef, h, -jnp.ones_like(h), jnp.ones_like(h))  # (..., 7, P, 3)
    g = geo.nodes.density * _fresnel_product(geo.nodes, n)
    arc_ratio = jnp.sum(g * full, axis=(-2, -1))
    delta_ratio = geo.delta_weight * lobe_fresnel(ti, b, n)
    weight = jnp.broadcast_to(weight, (*arc_ratio.shape[:-1], 10))
    return RoundedPaths(weight=weight, ratio=jnp.concatenate([delta_ratio, arc_ratio], axis=-1))


def rounded_total(
    theta_i: ArrayLike,
    beta2: ArrayLike,
    n: ArrayLike,
    layer_um: ArrayLike,
    edge_radius_um: ArrayLike,
    *,
    resolution: int = ROUNDED_RESOLUTION,
) -> Float[Array, "..."]:
    """Total reflectance (reflected / incident power, dimensionless) [conventions §4]."""
    p = rounded_paths(theta_i, beta2, n, layer_um, edge_radius_um, resolution=resolution)
    return jnp.sum(p.ratio, axis=-1)
