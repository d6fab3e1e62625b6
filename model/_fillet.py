"""Concave fillets: the rounded staircase with every concave corner a circular arc of radius `r_f`.

The derivation is in docs/rounded.md §1 (geometry, range, number of reflections) and §11 (this
model); conventions §1-§6 apply unchanged [conventions §1-§6]. The filleted model is the
analytic rounded model plus a correction computed by a small differentiable ray tracer of one
period,

    filleted(r, r_f) = rounded(r) + [T(r, r_f) - T(r, 0)],

where `T` traces the same `rays` stratified rays across one period of the ray front (exact
ray/segment and ray/circle intersections, up to `bounces` reflections, Fresnel per
polarisation per bounce, shadowing and masking exact per ray). A ray that never meets the
fillet takes bit-identical steps in both terms, so it cancels exactly: the quadrature error is
confined to the rays that meet the fillet or the sharp corner it replaces, and `r_f = 0` is
the rounded model exactly, in value and in every derivative. The profile with `r, r_f > 0` is
tangent-continuous, so each ray's direction and power are continuous in the parameters and
derivatives through the per-ray geometry are consistent.
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._broadening import hemisphere_gaussian
from ._fresnel import fresnel_sp
from ._rounded import (
    ROUNDED_RESOLUTION,
    RoundedGeometry,
    _room_np,
    brdf_rounded,
    brdf_rounded_from_geometry,
    check_edge_radius,
    max_edge_radius,
    rounded_binned,
    rounded_geometry,
    rounded_total,
)
from ._shapes import same_rank, with_rank

HALF_PI = np.pi / 2

FILLET_RAYS = 2048
"""Default number of rays per period in the fillet correction (docs/rounded.md §11)."""

FILLET_BOUNCES = 16
"""Default number of reflections traced per ray (the bound of docs/rounded.md §1)."""

FILLET_SEARCH_FRACTION = 4
"""The fillet correction's search pass traces `rays // FILLET_SEARCH_FRACTION` stratified rays
to find where the two lanes differ; the `rays` rays are then spread over that footprint
(`_pair_rays`, docs/rounded.md §11)."""

FILLET_MAX_REFINE = 64
"""At most this many rays per search stratum of the footprint."""

FILLET_FD_STEP = 0.01
"""Steps of the correction's derivatives in the geometry, as a fraction of `min(l1, l2)` (the
radii), of `l1`, and of 15 deg (the angles) (docs/rounded.md §11)."""

_EPS = 1e-9  # smallest accepted ray parameter, in periods (rejects a ray's own start point)
_TIPS = (0, 1)  # the tip arcs bounding a ray's groove: at the groove's left and right end


# --------------------------------------------------------------------------------------------
# Validity and the number of reflections
# --------------------------------------------------------------------------------------------


def max_fillet_radius(
    beta2: ArrayLike, layer_um: ArrayLike, edge_radius_um: ArrayLike
) -> Float[Array, "..."]:
    """Largest fillet radius (micrometres) beside tip arcs of radius `edge_radius_um`:
    `min(l1, l2) - r`, `l2 = l1 cot beta2`.

    The tip arc and the fillet each take their radius off both facets (both corners are right
    angles), so the flat tread `[r, l2 - r_f]` and riser `[r_f, l1 - r]` keep a non-negative
    length exactly when `r + r_f <= min(l1, l2)` [conventions §2].
    """
    room = max_edge_radius(beta2, layer_um)
    return room - jnp.asarray(edge_radius_um, dtype=room.dtype)


def check_fillet_radius(
    beta2: ArrayLike, layer_um: ArrayLike, edge_radius_um: ArrayLike, fillet_radius_um: ArrayLike
) -> None:
    """Raise ValueError if a concrete fillet radius is negative or does not fit beside the tips.

    Also checks the tip radius (`check_edge_radius`). Traced values (inside `jax.jit`) are not
    checked, as for the tip radius (docs/rounded.md §7).
    """
    check_edge_radius(beta2, layer_um, edge_radius_um)
    arrays = (beta2, layer_um, edge_radius_um, fillet_radius_um)
    if any(isinstance(a, jax.core.Tracer) for a in arrays):
        return
    b, l1, r, rf = np.broadcast_arrays(*(np.asarray(a, dtype=float) for a in arrays))
    if np.any(rf < 0):
        raise ValueError(
            f"fillet_radius_um = {rf.min():g} um is negative: the fillet radius must be >= 0 "
            "(0 is a sharp concave corner)"
        )
    cap = _room_np(b, l1)
    bad = r + rf > cap * (1 + 1e-12)
    if np.any(bad):
        i = np.flatnonzero(bad.ravel())[0]
        raise ValueError(
            f"fillet_radius_um = {rf.ravel()[i]:g} um does not fit the cell of beta2 = "
            f"{np.rad2deg(b.ravel()[i]):g} deg, layer_um = {l1.ravel()[i]:g} beside "
            f"edge_radius_um = {r.ravel()[i]:g}: r + r_f must not exceed min(l1, l2) = "
            f"{cap.ravel()[i]:g} um, so r_f <= {cap.ravel()[i] - r.ravel()[i]:g} um; reduce "
            "fillet_radius_um or edge_radius_um"
        )


def fillet_bounce_bound(theta_i: ArrayLike, beta2: ArrayLike) -> np.ndarray:
    """Largest number of reflections of any ray on a filleted staircase (docs/rounded.md §1).

    `4 + pi / (4 delta)` with `delta` the angle (radians) between the incident direction and
    the nearer facet, `delta = min(|theta_i - beta1|, |theta_i + beta2|)`; unbounded (inf) at
    `delta = 0`, where rays parallel to a facet creep along the fillet. The mechanism is
    derived in §1; the bound itself is checked against the ray tracer over a grid, not proved.
    NumPy (concrete angles, radians); a planning helper, not part of the traced model.
    """
    ti, b = np.broadcast_arrays(np.asarray(theta_i, float), np.asarray(beta2, float))
    delta = np.minimum(np.abs(ti - (HALF_PI - b)), np.abs(ti + b))
    with np.errstate(divide="ignore"):
        return np.where(delta > 0, 4.0 + np.pi / (4.0 * delta), np.inf)


# --------------------------------------------------------------------------------------------
# The tracer of one period (scalar geometry; vectorised by the public functions)
# --------------------------------------------------------------------------------------------


class _Cell(NamedTuple):
    """The constants of one cell's primitives, per ray (arrays of the rays' shape) [conventions
    §2]: `sin`, `cos` of beta2, `l1`, `l2`, the `period`, the radii, the smallest accepted ray
    parameter `eps`, the tip arc's and the fillet's centres in cell 0 and the unit vector `mid`
    halfway between the facets' normals."""

    sb: Array
    cb: Array
    l1: Array
    l2: Array
    period: Array
    r: Array
    rf: Array
    eps: Array
    tip: tuple[Array, Array]
    fil: tuple[Array, Array]
    mid: tuple[Array, Array]


def _unit(angle: Array) -> tuple[Array, Array]:
    """`(x, z)` of the unit vector at `angle` from z towards +x [conventions §1]."""
    return jnp.sin(angle), jnp.cos(angle)


def _cell(b: Array, l1: Array, r: Array, rf: Array) -> _Cell:
    """`_Cell` of wedge `b`, layer `l1`, tip radius `r` and fillet radius `rf` (broadcast)."""
    sb, cb = jnp.sin(b), jnp.cos(b)
    l2, period = l1 * cb / sb, l1 / sb
    c_tip = (-r * (sb - cb), -r * (cb + sb))
    c_fil = (l2 * cb + rf * (sb - cb), -l2 * sb + rf * (cb + sb))
    return _Cell(sb, cb, l1, l2, period, r, rf, _EPS * period, c_tip, c_fil, _unit(b - np.pi / 4))


def _line_hit(ray: tuple, anchor: tuple, tangent: tuple, normal: tuple, lo, hi, eps) -> Array:  # noqa: ANN001
    """Ray parameter of the hit on the facet `anchor + s tangent`, `s in [lo, hi]`, seen from
    its front (air) side; inf for none. `t` does not depend on `lo`, `hi` (the radii), so rays
    away from the facets' ends take bit-identical steps for every fillet radius."""
    px, pz, dx, dz = ray
    nd = normal[0] * dx + normal[1] * dz
    front = nd < 0
    t = (normal[0] * (anchor[0] - px) + normal[1] * (anchor[1] - pz)) / jnp.where(front, nd, -1.0)
    s = tangent[0] * (px + t * dx - anchor[0]) + tangent[1] * (pz + t * dz - anchor[1])
    return jnp.where(front & (t > eps) & (s >= lo) & (s <= hi), t, jnp.inf)


def _circle_hit(ray: tuple, centre: tuple, radius, sign: float, mid: tuple, eps) -> tuple:  # noqa: ANN001
    """Hit on an arc of the circle (`centre`, `radius`) whose outward normals lie within 45 deg
    of `mid`: `(t, nx, nz)`, `t = inf` for none. `sign = +1`: convex (the ray meets it from
    outside, near root; normal `(q - c) / R`); `-1`: concave (from inside, far root; normal
    `(c - q) / R`). Double-where at the square root and the division (finite gradients)."""
    px, pz, dx, dz = ray
    wx, wz = px - centre[0], pz - centre[1]
    b = dx * wx + dz * wz
    disc = b * b - (wx * wx + wz * wz - radius * radius)
    real = (disc > 0) & (radius > 0)
    t = -b - sign * jnp.sqrt(jnp.where(real, disc, 1.0))
    r_safe = jnp.where(radius > 0, radius, 1.0)
    nx = sign * (wx + t * dx) / r_safe
    nz = sign * (wz + t * dz) / r_safe
    in_arc = nx * mid[0] + nz * mid[1] >= np.cos(np.pi / 4)
    return jnp.where(real & in_arc & (t > eps), t, jnp.inf), nx, nz


def _nearest(ray: tuple, c: _Cell) -> tuple[Array, Array, Array]:
    """The first hit of each ray in its groove [conventions §2]: the tread `[r, l2 - r_f]`
    from the tip at the origin, the riser `[r, l1 - r_f]` down from the tip at `(L, 0)`, the
    fillet (concave) between them and the two tip arcs (convex) at `x = 0` and `x = L`, normals
    in `[beta2 - 90 deg, beta2]`. Returns the ray parameter (inf = none) and the outward normal
    at the hit (the first of equal ones: an argmin over the stacked candidates, cheaper than a
    running minimum).

    Why five primitives suffice (docs/rounded.md §11, "the groove"): the profile is a graph
    `z = h(x)` (every normal has a positive `z`), highest at the tops of the tip arcs, `x =
    c.tip[0] + k L`, height `h_top`. A ray starts at `h_top` or on the surface, so `z <= h_top`
    there; between its start `x0` in the groove `[c.tip[0], c.tip[0] + L]` and the groove's end
    in its direction of travel, it either meets the surface or passes that tip's top above
    `h_top`, rising, and then stays above every later point of the profile: it escapes. So
    it hits, if at all, within its own groove, on the five primitives whose `x` range meets it
    (the tip arcs only with their inner halves). The other cells' primitives, which an earlier
    version also tested (13 in all), were never the nearest hit."""
    n_tr, n_ri = (c.sb, c.cb), (-c.cb, c.sb)
    hits = [
        (_line_hit(ray, (0.0, 0.0), (c.cb, -c.sb), n_tr, c.r, c.l2 - c.rf, c.eps), *n_tr),
        (_line_hit(ray, (c.period, 0.0), (-c.sb, -c.cb), n_ri, c.r, c.l1 - c.rf, c.eps), *n_ri),
        _circle_hit(ray, c.fil, c.rf, -1.0, c.mid, c.eps),
        *(_circle_hit(ray, (c.tip[0] + s * c.period, c.tip[1]), c.r, 1.0, c.mid, c.eps)
          for s in _TIPS),
    ]  # fmt: skip
    t = jnp.stack([h[0] for h in hits])
    j = jnp.argmin(t, axis=0)[None]
    pick = lambda a: jnp.take_along_axis(a, j, 0)[0]  # noqa: E731
    nx = jnp.stack([jnp.broadcast_to(h[1], t.shape[1:]) for h in hits])
    nz = jnp.stack([jnp.broadcast_to(h[2], t.shape[1:]) for h in hits])
    return pick(t), pick(nx), pick(nz)


class _Rays(NamedTuple):
    """The traced rays of each geometry and lane: per bounce (trailing axis) the cosine of the
    local angle of incidence and whether the ray reflected there; whether it escaped, and where
    to."""

    cos: Float[Array, "... n_rays bounces"]
    hit: Array
    escaped: Array
    theta_o: Float[Array, "... n_rays"]


def _step(k: Array, bounces: int, state: tuple, c: _Cell) -> tuple:
    """One reflection of every ray in `state = (px, pz, dx, dz, active)` at bounce `k`: the new
    state, whether each ray reflected (`hit`), whether it left upwards (`esc`) and the cosine
    of its local angle of incidence (1 where it did not reflect). Step `bounces` (after the
    last reflection) only checks for escape. Elementwise in each ray's state and cell."""
    px, pz, dx, dz, active = state
    t, nx, nz = _nearest((px, pz, dx, dz), c)
    meets = jnp.isfinite(t)
    esc = active & ~meets & (dz > 0)
    hit = active & meets & (k < bounces)
    t = jnp.where(hit, t, 0.0)
    dn = dx * nx + dz * nz
    x = px + t * dx  # in the groove; back into it should rounding put a tip-top hit outside
    x = x - c.period * ((x > c.tip[0] + c.period).astype(x.dtype) - (x < c.tip[0]).astype(x.dtype))
    new = (x, pz + t * dz, dx - 2 * dn * nx, dz - 2 * dn * nz)
    px, pz, dx, dz = (jnp.where(hit, a, o) for a, o in zip(new, (px, pz, dx, dz), strict=True))
    return (px, pz, dx, dz, hit), esc, jnp.where(hit, -dn, 1.0)


def _trace(
    ti: Array, b: Array, l1: Array, r: Array, rf: Array, rays: int, bounces: int,
    frac: Array | None = None,
) -> _Rays:  # fmt: skip
    """Trace `rays` rays per element of the (broadcast) geometry, stratified (midpoints) across
    one period of the ray front, or starting at the fractions `frac` of the period (`(...,
    rays)`), for up to `bounces` reflections [conventions §1, §2]. A ray still reflecting
    after that is dropped.

    All rays of all geometries are one flat batch, stepped together by one while loop until
    no ray is still reflecting (the steps skipped would change nothing, so the result is that
    of `bounces` steps of every ray to the bit). Every ray is stepped at every pass (a ray that
    left keeps its state): with the five primitives of the groove (`_nearest`) a step is cheap
    enough that gathering the few rays still reflecting cost more than it saved (docs/rounded.md
    §11). The rays are never differentiated through (derivatives in the geometry are
    differences, `_fd_correction`)."""
    ti, b, l1, r, rf = jnp.broadcast_arrays(ti, b, l1, r, rf)
    shape = ti.shape
    n_all = ti.size * rays
    flat = lambda a: jnp.broadcast_to(a[..., None], (*shape, rays)).reshape(n_all)  # noqa: E731
    cell = _cell(*(flat(a) for a in (b, l1, r, rf)))
    if frac is None:
        frac = (jnp.arange(rays, dtype=ti.dtype) + 0.5) / rays
    frac = jnp.broadcast_to(frac, (*shape, rays)).reshape(n_all)
    r_ = cell.r
    state = (
        -r_ * (cell.sb - cell.cb) + frac * cell.period,
        -r_ * (cell.cb + cell.sb) + r_,
        flat(jnp.sin(ti)),
        flat(-jnp.cos(ti)),
        jnp.ones(n_all, bool),
    )

    def body(carry: tuple) -> tuple:
        k, state, esc, cos, hits = carry
        state, out, cos_k = _step(k, bounces, state, cell)
        cos = jax.lax.dynamic_update_index_in_dim(cos, cos_k, k, 0)
        hits = jax.lax.dynamic_update_index_in_dim(hits, state[4], k, 0)
        return (k + 1, state, esc | out, cos, hits)

    def any_left(carry: tuple) -> Array:
        return (carry[0] <= bounces) & jnp.any(carry[1][4])

    # rows 0..bounces-1 the reflections, row `bounces` written by the escape-only step
    start = (
        jnp.asarray(0), state, jnp.zeros(n_all, bool),
        jnp.ones((bounces + 1, n_all), ti.dtype), jnp.zeros((bounces + 1, n_all), bool),
    )  # fmt: skip
    _, (_, _, dx, dz, _), esc, cos, hit = jax.lax.while_loop(any_left, body, start)
    unflat = lambda a: a.reshape(*a.shape[:-1], *shape, rays)  # noqa: E731
    return _Rays(
        cos=jnp.moveaxis(unflat(cos[:bounces]), 0, -1),
        hit=jnp.moveaxis(unflat(hit[:bounces]), 0, -1),
        escaped=unflat(esc),
        theta_o=unflat(jnp.arctan2(dx, dz)),
    )


# --------------------------------------------------------------------------------------------
# The traced ray pairs, once per geometry
# --------------------------------------------------------------------------------------------


class FilletRays(NamedTuple):
    """The rays of `T(r, r_f)` and of `T(r, 0)` for each broadcast element of the geometry
    (`fillet_rays`); the axis `2` is the lane (`r_f`, then 0). Angles in radians.

    `cos`: per bounce the cosine of the local angle of incidence (1 where the ray did not
    reflect); `hit`: whether it reflected at that bounce; `escaped`: whether it left the surface
    upwards within `bounces` reflections; `theta_o`: its final direction [conventions §1];
    `live`: whether the two lanes of the ray differ at all (a ray that meets neither the fillet
    nor the corner it replaces takes bit-identical steps in both and is left out of every sum;
    it would cancel exactly); `weight`: the share of the period's ray front the ray stands for
    (its stratum's width; 0 for an unused ray).
    """

    cos: Float[Array, "... 2 n_rays bounces"]
    hit: Array
    escaped: Array
    theta_o: Float[Array, "... 2 n_rays"]
    live: Array
    weight: Float[Array, "... n_rays"]


def _differ(rays: _Rays) -> Array:
    """Per ray, whether its two lanes (the axis before the rays) differ in any bit."""
    cos, hit, esc, th = rays
    return (
        jnp.any((cos[..., 0, :, :] != cos[..., 1, :, :]) | (hit[..., 0, :, :] != hit[..., 1, :, :]),
                axis=-1)
        | (esc[..., 0, :] != esc[..., 1, :])
        | (th[..., 0, :] != th[..., 1, :])
    )  # fmt: skip


def _pair_rays(
    ti: Array, b: Array, l1: Array, r: Array, rf: Array, rays: int, bounces: int,
    rf_other: Array | float = 0.0,
) -> FilletRays:  # fmt: skip
    """The rays for `r_f` and for `rf_other` (default 0) on a new axis before the ray axis:
    `(..., 2, rays[, K])`, placed where the two lanes differ (docs/rounded.md §11).

    A search pass traces `rays // FILLET_SEARCH_FRACTION` stratified rays; the strata whose
    ray differs between the lanes, and their neighbours, are the footprint, and `rays` rays
    are spread over it: `m = rays // (strata in it)` (at most `FILLET_MAX_REFINE`) at the
    midpoints of equal parts of each of its strata, each standing for `1 / (strata x m)` of the
    period. Every other stratum's rays are the same in both lanes and cancel. Both passes trace
    both lanes in one vectorised computation, so a ray that meets neither lane's fillet (nor
    the corner) gives the same bits in both (`live` is False for it)."""
    ti, b, l1, r, rf, rf_other = jnp.broadcast_arrays(ti, b, l1, r, rf, rf_other)
    pair = [jnp.stack([a, a], axis=-1) for a in (ti, b, l1, r)]
    pair.append(jnp.stack([rf, rf_other], axis=-1))
    n0 = max(rays // FILLET_SEARCH_FRACTION, 1)
    found = _differ(_Rays(*_trace(*pair, rays=n0, bounces=bounces)))
    near = found | jnp.roll(found, 1, axis=-1) | jnp.roll(found, -1, axis=-1)
    count = jnp.sum(near, axis=-1, keepdims=True)  # (..., 1)
    m = jnp.clip(rays // jnp.maximum(count, 1), 1, FILLET_MAX_REFINE)
    order = jnp.argsort(~near, axis=-1, stable=True)  # the footprint's strata first, in order
    j = jnp.arange(rays).reshape((1,) * (m.ndim - 1) + (rays,))
    k = j // m  # (..., rays): which of the footprint's strata
    stratum = jnp.take_along_axis(order, jnp.minimum(k, n0 - 1), axis=-1)
    frac = (stratum + ((j - k * m) + 0.5) / m) / n0
    weight = jnp.where(k < count, 1.0 / (n0 * m), 0.0).astype(ti.dtype)
    frac = jnp.stack([frac, frac], axis=-2).astype(ti.dtype)
    traced = _Rays(*_trace(*pair, rays=rays, bounces=bounces, frac=frac))
    return FilletRays(*traced, _differ(traced) & (weight > 0), weight)


def split_rays(rays: FilletRays, size: int) -> FilletRays:
    """`rays` in chunks of `size` consecutive rays on a new leading axis (`n_rays / size`
    chunks; `size` must divide `n_rays`), e.g. to sum a contraction over the rays chunk by
    chunk (`lax.scan`) where one pass would hold too large an array. The rays are not changed,
    only grouped."""
    n = rays.weight.shape[-1]
    if size <= 0 or n % size:
        raise ValueError(f"split_rays: {size} rays per chunk does not divide {n} rays")

    def split(a: Array, axis: int) -> Array:
        axis %= a.ndim
        a = a.reshape((*a.shape[:axis], n // size, size, *a.shape[axis + 1 :]))
        return jnp.moveaxis(a, axis, 0)

    return FilletRays(
        cos=split(rays.cos, -2), hit=split(rays.hit, -2), escaped=split(rays.escaped, -1),
        theta_o=split(rays.theta_o, -1), live=split(rays.live, -1),
        weight=split(rays.weight, -1),
    )  # fmt: skip


def fillet_ray_power(rays: FilletRays, n: ArrayLike) -> Float[Array, "... 2 n_rays"]:
    """Each ray's reflected unpolarised power per unit incident power per period, signed `+`
    for the filleted lane and `-` for the `r_f = 0` lane, 0 for rays whose lanes are identical
    or that did not escape (Fresnel per polarisation per bounce [conventions §6]).

    `n` (complex allowed) broadcasts with the leading axes of `rays`; pass the index samples on
    their own axis (e.g. `rays` with leading `(G, 1)`, `n` of shape `(K,)` gives
    `(G, K, 2, n_rays)`). The product over bounces is accumulated one bounce at a time, so no
    `(index x rays x bounces)` array is formed, and only over the bounces some ray reflected at
    (a loop of dynamic length: the later ones are factors 1)."""
    n_b = jnp.asarray(n)[..., None, None]
    bounces = rays.cos.shape[-1]
    reflected = jnp.any(rays.hit, axis=tuple(range(rays.hit.ndim - 1)))  # per bounce
    used = jnp.max(jnp.where(reflected, jnp.arange(1, bounces + 1), 0))

    def one(k: Array, acc: tuple) -> tuple:
        hit = jax.lax.dynamic_index_in_dim(rays.hit, k, axis=-1, keepdims=False)
        f = fresnel_sp(jax.lax.dynamic_index_in_dim(rays.cos, k, axis=-1, keepdims=False), n_b)
        return acc[0] * jnp.where(hit, f.s, 1.0), acc[1] * jnp.where(hit, f.p, 1.0)

    shape = jnp.broadcast_shapes(rays.cos.shape[:-1], n_b.shape)
    ones = jnp.ones(shape, rays.cos.dtype)  # fresnel_sp computes at the cosines' precision
    p_s, p_p = jax.lax.fori_loop(0, used, one, (ones, ones))
    keep = rays.escaped & rays.live[..., None, :]
    power = 0.5 * (p_s + p_p) * rays.weight[..., None, :]
    sign = with_rank(jnp.asarray([1.0, -1.0], power.dtype)[:, None], power.ndim)
    power = power * sign
    return jnp.where(keep, power, 0.0)


def _correction_from_rays(kind: str, rays: FilletRays, rest: tuple) -> Array:
    """`T(r, r_f) - T(r, 0)` for one output kind from traced rays; `rest` is `(n,)`,
    `(n, edges)` or `(n, theta_o, sigma)`, broadcasting with the rays' leading axes."""
    w = fillet_ray_power(rays, rest[0])
    if kind == "total":
        return jnp.sum(w, axis=(-2, -1))
    if kind == "brdf":
        to, sg = jnp.asarray(rest[1]), jnp.asarray(rest[2])
        kern = hemisphere_gaussian(to[..., None, None], rays.theta_o, sg[..., None, None])
        # a contraction, not a product and a sum: unit axes (e.g. the index of `kern`, the
        # viewing angle of `w`) stay unbroadcast
        return jnp.einsum("...pr,...pr->...", w, kern)
    e = rest[1]
    th = rays.theta_o[..., None]
    e_d = with_rank(e, th.ndim)
    inside = (th >= e_d[..., :-1]) & (th < e_d[..., 1:])
    inside = inside.at[..., -1].set(inside[..., -1] | (th[..., 0] == e[-1]))
    return jnp.sum(w[..., None] * inside, axis=(-3, -2))


def _args(*arrays: ArrayLike) -> tuple[Array, ...]:
    """The arguments at one rank and one float dtype (radians, micrometres) [conventions §10]."""
    dtype = jnp.result_type(*(a for a in arrays if not jnp.iscomplexobj(a)))
    if not jnp.issubdtype(dtype, jnp.floating):
        dtype = jnp.result_type(float)
    return same_rank(*(a if jnp.iscomplexobj(a) else jnp.asarray(a, dtype) for a in arrays))


def _geom_args(*arrays: ArrayLike) -> tuple[Array, ...]:
    """The geometric arguments broadcast to one shape and float dtype [conventions §10]."""
    return tuple(jnp.broadcast_arrays(*_args(*arrays)))


def fillet_rays(
    theta_i: ArrayLike,
    beta2: ArrayLike,
    layer_um: ArrayLike,
    edge_radius_um: ArrayLike,
    fillet_radius_um: ArrayLike,
    *,
    rays: int = FILLET_RAYS,
    bounces: int = FILLET_BOUNCES,
    other_fillet_um: ArrayLike = 0.0,
) -> FilletRays:
    """The traced ray pairs of the fillet correction, one set per broadcast element of the
    geometry (radians, micrometres) [conventions §1, §2]: what does not depend on `theta_o`,
    the index or the broadening, so a caller with many of those per geometry (a fit) traces
    once per distinct geometry and finishes with `fillet_ray_power` and the kernel.

    The second lane has fillet radius `other_fillet_um`: 0 (the default) for the correction
    `T(r, r_f) - T(r, 0)`; another radius gives `T(r, r_f) - T(r, other)` directly, which is
    the difference of the two corrections (a ray that differs in neither from `T(r, 0)` is
    the same in both), so a derivative in `r_f` needs one pair of traces, not two.

    Not differentiable in the geometry (a `stop_gradient`: the per-ray derivative is
    heavy-tailed, docs/rounded.md §11); derivatives in the geometry are differences between
    traces at `fillet_difference_points`, as `brdf_filleted` takes them. Traced radii are not
    range-checked (`check_fillet_radius`)."""
    check_fillet_radius(beta2, layer_um, edge_radius_um, fillet_radius_um)
    check_fillet_radius(beta2, layer_um, edge_radius_um, other_fillet_um)
    geom = jax.lax.stop_gradient(
        _geom_args(theta_i, beta2, layer_um, edge_radius_um, fillet_radius_um, other_fillet_um)
    )
    return _pair_rays(*geom[:5], rays, bounces, geom[5])


class FilletGeometry(NamedTuple):
    """What `fillet_geometry` returns: the angles it was computed at (radians), the rounded
    model's geometry (`rounded_geometry`) and the fillet correction's rays (`fillet_rays`)."""

    theta_i: Array
    beta2: Array
    rounded: RoundedGeometry
    rays: FilletRays


def fillet_geometry(
    theta_i: ArrayLike,
    beta2: ArrayLike,
    layer_um: ArrayLike,
    edge_radius_um: ArrayLike,
    fillet_radius_um: ArrayLike,
    *,
    resolution: int = ROUNDED_RESOLUTION,
    rays: int = FILLET_RAYS,
    bounces: int = FILLET_BOUNCES,
) -> FilletGeometry:
    """The part of `brdf_filleted` that depends on the geometry only (not on `theta_o`, `n`,
    `sigma`), one set per broadcast element: the rounded geometry and the traced ray pairs.
    Finish with `brdf_filleted_from_geometry` (or `filleted_*_from_geometry`). Derivatives in
    the geometry: see `fillet_rays` (the rounded part keeps its analytic ones)."""
    ti, b, l1, r, rf = _geom_args(theta_i, beta2, layer_um, edge_radius_um, fillet_radius_um)
    rounded = rounded_geometry(ti, b, l1, r, resolution=resolution)
    return FilletGeometry(ti, b, rounded, fillet_rays(ti, b, l1, r, rf, rays=rays, bounces=bounces))


def _with_lead_rank(tree: FilletRays, lead: int, ndim: int) -> FilletRays:
    """Unit axes prepended to every leaf so that the `lead` leading axes number `ndim`."""
    return jax.tree_util.tree_map(lambda a: a.reshape((1,) * (ndim - lead) + a.shape), tree)


def _rest_rank(geo: FilletGeometry, *arrays: ArrayLike) -> tuple[FilletRays, tuple[Array, ...]]:
    """The rays and `arrays` at one rank (the rays' leading axes against the arrays')."""
    lead = geo.theta_i.ndim
    out = same_rank(*arrays, jnp.zeros((1,) * lead, geo.theta_i.dtype))[:-1]
    return _with_lead_rank(geo.rays, lead, out[0].ndim), out


def brdf_filleted_from_geometry(
    geo: FilletGeometry, theta_o: ArrayLike, n: ArrayLike, sigma: ArrayLike
) -> Float[Array, "..."]:
    """`brdf_filleted` from a precomputed `fillet_geometry` (1/rad) [conventions §4, §5, §6]:
    `brdf_rounded_from_geometry` plus the correction, clipped at 0. `geo`'s leading axes must
    broadcast with `theta_o`, `n` and `sigma`."""
    base = brdf_rounded_from_geometry(geo.rounded, geo.theta_i, theta_o, geo.beta2, n, sigma)
    dtype = geo.theta_i.dtype
    rays, (n_, to, sg) = _rest_rank(
        geo, n if jnp.iscomplexobj(n) else jnp.asarray(n, dtype), jnp.asarray(theta_o, dtype),
        jnp.asarray(sigma, dtype),
    )  # fmt: skip
    rho = base + _correction_from_rays("brdf", rays, (n_, to, sg))
    return jnp.where(rho >= 0, rho, 0.0)


# --------------------------------------------------------------------------------------------
# Derivatives in the geometry: differences between traces
# --------------------------------------------------------------------------------------------


class _Static(NamedTuple):
    """The static knobs of a correction (hashable: a `custom_jvp` non-differentiable arg)."""

    kind: str  # "brdf", "binned" or "total"
    rays: int
    bounces: int


def _cap(b: Array, l1: Array) -> Array:
    """`min(l1, l2)`, the room for `r + r_f` [conventions §2]."""
    return max_edge_radius(b, l1)


def fillet_difference_points(
    theta_i: ArrayLike, beta2: ArrayLike, layer_um: ArrayLike, r: ArrayLike, rf: ArrayLike
) -> list[tuple[Array, Array]]:
    """For each geometric argument `(theta_i, beta2, layer_um, r, r_f)` (radians,
    micrometres), the two values the correction's derivative differences (docs/rounded.md
    §11): `+-` a step (`FILLET_FD_STEP` of 15 deg for the angles, of `l1` for the layer, of
    `min(l1, l2)` for the radii), one-sided where a side would leave the domain (grazing
    incidence, a wedge or layer on which `r + r_f` no longer fits, a radius below 0)."""
    ti, b, l1, r, rf = (jnp.asarray(a) for a in (theta_i, beta2, layer_um, r, rf))
    cap = _cap(b, l1)
    fits = lambda b_, l1_: r + rf <= _cap(b_, l1_) * (1 + 1e-12)  # noqa: E731
    h_angle, h_len = FILLET_FD_STEP * np.pi / 12, FILLET_FD_STEP * cap
    b_hi = jnp.where((b + h_angle < HALF_PI) & fits(b + h_angle, l1), b + h_angle, b)
    b_lo = jnp.where((b - h_angle > 0) & fits(b - h_angle, l1), b - h_angle, b)
    l1_lo = jnp.where(fits(b, 0.99 * l1), 0.99 * l1, l1)
    room = jnp.maximum(cap - r - rf, 0.0)
    return [
        (jnp.maximum(ti - h_angle, -HALF_PI), jnp.minimum(ti + h_angle, HALF_PI)),
        (b_lo, b_hi),
        (l1_lo, 1.01 * l1),
        (jnp.maximum(r - h_len, 0.0), r + jnp.minimum(h_len, room)),
        (jnp.maximum(rf - h_len, 0.0), rf + jnp.minimum(h_len, room)),
    ]


def difference_scale(lo: Array, hi: Array, tangent: Array) -> Array:
    """`tangent / (hi - lo)`, 0 where the two points coincide (no room either side)."""
    span = hi - lo
    ok = span > 0
    return jnp.where(ok, tangent / jnp.where(ok, span, 1.0), 0.0)


@partial(jax.custom_jvp, nondiff_argnums=(0,))
def _fd_correction(static: _Static, geom: tuple, rest: tuple) -> Array:
    """`T(r, r_f) - T(r, 0)` for `geom = (ti, b, l1, r, rf)` (broadcast), differentiated in the
    geometry by differences (`fillet_difference_points`) and in `rest` (index, viewing angle,
    broadening: they do not move a ray) through the rays. docs/rounded.md §11: rays grazing a
    tip arc make the per-ray derivative in the geometry heavy-tailed, so its sum is not a
    usable derivative (0.7-1.7 times the slope in `r_f`, up to 12 in `theta_i`). Only the
    arguments with a (symbolically) non-zero tangent are differenced: in a fit, `r` and `r_f`."""
    return _correction_from_rays(static.kind, _pair_rays(*geom, static.rays, static.bounces), rest)


def _is_zero(t: object) -> bool:
    return type(t) is jax.custom_derivatives.SymbolicZero


def _fd_correction_jvp(static: _Static, primals: tuple, tangents: tuple) -> tuple:
    """One batched trace serves the value and every difference: the geometry at the primal and
    at each differenced argument's points is stacked on a new leading axis and traced in one
    `_pair_rays` call (one tracer in the compiled program, not one per point: a full Jacobian
    would otherwise hold eleven, and compile for as many times as long). The difference in
    `r_f` is one pair (`r_f` at its upper point against its lower, `fillet_rays`); every other
    argument's is two pairs (the correction at its upper point minus at its lower)."""
    geom, rest = primals
    d_geom, d_rest = tangents
    moved = [k for k in range(len(geom)) if not _is_zero(d_geom[k])]
    points = fillet_difference_points(*geom)
    stack, other = [], [jnp.zeros_like(geom[4])]
    for k in moved:
        other += [points[4][0]] if k == 4 else [jnp.zeros_like(geom[4])] * 2
    for j, g in enumerate(geom):
        column = [g]
        for k in moved:
            if k == 4:
                column += [points[4][1] if j == 4 else g]
            else:
                column += [points[k][0], points[k][1]] if j == k else [g, g]
        stack.append(jnp.stack(column))
    rays_all = _pair_rays(*stack, static.rays, static.bounces, jnp.stack(other))
    rays = jax.tree_util.tree_map(lambda a: a[0], rays_all)
    if all(_is_zero(t) for t in d_rest):
        out = _correction_from_rays(static.kind, rays, rest)
        d_out = jnp.zeros_like(out)
    else:
        d_rest = tuple(
            jnp.zeros_like(p) if _is_zero(t) else t for p, t in zip(rest, d_rest, strict=True)
        )
        out, d_out = jax.jvp(lambda *a: _correction_from_rays(static.kind, rays, a), rest, d_rest)
    if not moved:
        return out, d_out
    moved_rays = jax.tree_util.tree_map(lambda a: a[1:], rays_all)
    at = jax.vmap(lambda r: _correction_from_rays(static.kind, r, rest))(moved_rays)
    i = 0
    for k in moved:
        if k == 4:
            slope, i = at[i], i + 1
        else:
            slope, i = at[i + 1] - at[i], i + 2
        d = d_geom[k]
        scale = difference_scale(*points[k], d)
        d_out = d_out + slope * scale.reshape(d.shape + (1,) * (out.ndim - d.ndim))
    return out, d_out


_fd_correction.defjvp(_fd_correction_jvp, symbolic_zeros=True)


# --------------------------------------------------------------------------------------------
# The public functions
# --------------------------------------------------------------------------------------------


def _filleted(static: _Static, base: Array, ti, b, l1, r, rf, *rest) -> Array:  # noqa: ANN001
    """The rounded `base` plus the fillet correction (broadcast geometry)."""
    geom = tuple(jnp.broadcast_arrays(ti, b, l1, r, rf))
    return base + _fd_correction(static, geom, rest)


def brdf_filleted(
    theta_i: ArrayLike,
    theta_o: ArrayLike,
    beta2: ArrayLike,
    n: ArrayLike,
    sigma: ArrayLike,
    layer_um: ArrayLike,
    edge_radius_um: ArrayLike,
    fillet_radius_um: ArrayLike,
    *,
    resolution: int = ROUNDED_RESOLUTION,
    rays: int = FILLET_RAYS,
    bounces: int = FILLET_BOUNCES,
) -> Float[Array, "..."]:
    """In-plane reflectance density (1/rad) of the staircase with tip arcs and fillets.

    `brdf_rounded` plus the fillet correction (docs/rounded.md §11): each escaping ray's power
    spread by the same hemisphere-truncated Gaussian of width `sigma` (radians, > 0)
    [conventions §4, §5]. `fillet_radius_um` is `r_f` (micrometres,
    `0 <= r_f <= max_fillet_radius`); at 0 this is `brdf_rounded`. `rays` and `bounces`
    (static) are the correction's rays per period and reflections per ray. The rays are traced
    once per broadcast element of the geometry (theta_i, beta2, layer_um, radii): give several
    viewing angles, indices or widths per geometry on their own axes (or use
    `fillet_geometry` + `brdf_filleted_from_geometry` on distinct geometries).
    """
    check_fillet_radius(beta2, layer_um, edge_radius_um, fillet_radius_um)
    ti, to, b, n, sg, l1, r, rf = _args(
        theta_i, theta_o, beta2, n, sigma, layer_um, edge_radius_um, fillet_radius_um
    )
    base = brdf_rounded(ti, to, b, n, sg, l1, r, resolution=resolution)
    rho = _filleted(_Static("brdf", rays, bounces), base, ti, b, l1, r, rf, n, to, sg)
    return jnp.where(rho >= 0, rho, 0.0)


def filleted_binned(
    theta_i: ArrayLike,
    bin_edges: ArrayLike,
    beta2: ArrayLike,
    n: ArrayLike,
    layer_um: ArrayLike,
    edge_radius_um: ArrayLike,
    fillet_radius_um: ArrayLike,
    *,
    resolution: int = ROUNDED_RESOLUTION,
    rays: int = FILLET_RAYS,
    bounces: int = FILLET_BOUNCES,
) -> Float[Array, "... n_bins"]:
    """Reflected power per `theta_o` bin without broadening, per unit incident power: the
    filleted counterpart of `rounded_binned` (same bin convention, trailing bin axis)."""
    check_fillet_radius(beta2, layer_um, edge_radius_um, fillet_radius_um)
    ti, b, n, l1, r, rf = _args(theta_i, beta2, n, layer_um, edge_radius_um, fillet_radius_um)
    base = rounded_binned(ti, bin_edges, b, n, l1, r, resolution=resolution)
    e = jnp.asarray(bin_edges, base.dtype)
    return _filleted(_Static("binned", rays, bounces), base, ti, b, l1, r, rf, n, e)


def filleted_total(
    theta_i: ArrayLike,
    beta2: ArrayLike,
    n: ArrayLike,
    layer_um: ArrayLike,
    edge_radius_um: ArrayLike,
    fillet_radius_um: ArrayLike,
    *,
    resolution: int = ROUNDED_RESOLUTION,
    rays: int = FILLET_RAYS,
    bounces: int = FILLET_BOUNCES,
) -> Float[Array, "..."]:
    """Total reflectance (reflected / incident power) with tip arcs and fillets [conventions §4]."""
    check_fillet_radius(beta2, layer_um, edge_radius_um, fillet_radius_um)
    ti, b, n, l1, r, rf = _args(theta_i, beta2, n, layer_um, edge_radius_um, fillet_radius_um)
    base = rounded_total(ti, b, n, l1, r, resolution=resolution)
    return _filleted(_Static("total", rays, bounces), base, ti, b, l1, r, rf, n)
