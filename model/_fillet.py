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
    _room_np,
    brdf_rounded,
    check_edge_radius,
    max_edge_radius,
    rounded_binned,
    rounded_total,
)
from ._shapes import same_rank, with_rank

HALF_PI = np.pi / 2

FILLET_RAYS = 2048
"""Default number of rays per period in the fillet correction (docs/rounded.md §11)."""

FILLET_BOUNCES = 16
"""Default number of reflections traced per ray (the bound of docs/rounded.md §1)."""

FILLET_FD_STEP = 0.01
"""Steps of the correction's derivatives in the geometry, as a fraction of `min(l1, l2)` (the
radii), of `l1`, and of 15 deg (the angles) (docs/rounded.md §11)."""

_EPS = 1e-9  # smallest accepted ray parameter, in periods (rejects a ray's own start point)
_SHIFTS = (-1, 0, 1)  # cells whose tread, fillet and riser are tested
_TIP_SHIFTS = (-1, 0, 1, 2)  # cells whose tip arc is tested (the cell holds two tip halves)


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


class _Candidates(NamedTuple):
    """Every primitive's hit for a batch of rays: ray parameter `t` (inf = none) and the
    outward normal at the hit, each `(n_primitives, n_rays)`; `shift` the cell of each
    primitive (static)."""

    t: Array
    nx: Array
    nz: Array
    shift: np.ndarray


def _unit(angle: Array) -> tuple[Array, Array]:
    """`(x, z)` of the unit vector at `angle` from z towards +x [conventions §1]."""
    return jnp.sin(angle), jnp.cos(angle)


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


def _candidates(ray: tuple, b: Array, l1: Array, r: Array, rf: Array) -> _Candidates:
    """All primitives of cells -1..+1 (tip arcs -1..+2) against the rays [conventions §2]:
    tread `[r, l2 - r_f]` from the tip at the origin, riser `[r, l1 - r_f]` down from the tip
    at `(L, 0)`, tip arc (convex) and fillet (concave), normals in `[beta2 - 90 deg, beta2]`."""
    sb, cb = jnp.sin(b), jnp.cos(b)
    l2, period = l1 * cb / sb, l1 / sb
    eps = _EPS * period
    n_tr, n_ri = (sb, cb), (-cb, sb)
    mid = _unit(b - np.pi / 4)
    c_tip = (-r * (sb - cb), -r * (cb + sb))
    c_fil = (l2 * cb + rf * (sb - cb), -l2 * sb + rf * (cb + sb))
    ts, nxs, nzs, shifts = [], [], [], []

    def add(t: Array, nx: Array, nz: Array, shift: int) -> None:
        ts.append(t)
        nxs.append(jnp.broadcast_to(nx, t.shape))
        nzs.append(jnp.broadcast_to(nz, t.shape))
        shifts.append(shift)

    for s in _SHIFTS:
        x0 = s * period
        add(_line_hit(ray, (x0, 0.0), (cb, -sb), n_tr, r, l2 - rf, eps), *n_tr, s)
        add(_line_hit(ray, (x0 + period, 0.0), (-sb, -cb), n_ri, r, l1 - rf, eps), *n_ri, s)
        add(*_circle_hit(ray, (c_fil[0] + x0, c_fil[1]), rf, -1.0, mid, eps), s)
    for s in _TIP_SHIFTS:
        add(*_circle_hit(ray, (c_tip[0] + s * period, c_tip[1]), r, 1.0, mid, eps), s)
    return _Candidates(jnp.stack(ts), jnp.stack(nxs), jnp.stack(nzs), np.asarray(shifts))


class _Rays(NamedTuple):
    """The traced rays of one geometry: per bounce (trailing axis) the cosine of the local
    angle of incidence and whether the ray reflected there; whether it escaped, and where to."""

    cos: Float[Array, "n_rays bounces"]
    hit: Array
    escaped: Array
    theta_o: Float[Array, " n_rays"]


def _trace_one(
    ti: Array, b: Array, l1: Array, r: Array, rf: Array, rays: int, bounces: int
) -> _Rays:
    """Trace `rays` rays, stratified (midpoints) across one period of the ray front, for up to
    `bounces` reflections [conventions §1, §2]. A ray still reflecting after that is dropped."""
    sb, cb = jnp.sin(b), jnp.cos(b)
    period = l1 / sb
    x_top, z_top = -r * (sb - cb), -r * (cb + sb) + r
    frac = (jnp.arange(rays, dtype=ti.dtype) + 0.5) / rays
    px = x_top + frac * period
    pz = jnp.broadcast_to(z_top, px.shape)
    dx = jnp.broadcast_to(jnp.sin(ti), px.shape)
    dz = jnp.broadcast_to(-jnp.cos(ti), px.shape)

    def step(carry: tuple, _: None) -> tuple:
        px, pz, dx, dz, active, esc = carry
        c = _candidates((px, pz, dx, dz), b, l1, r, rf)
        j = jnp.argmin(c.t, axis=0)[None]
        t = jnp.take_along_axis(c.t, j, 0)[0]
        hit = active & jnp.isfinite(t)
        esc = esc | (active & ~hit & (dz > 0))
        t = jnp.where(hit, t, 0.0)
        nx, nz = (jnp.take_along_axis(a, j, 0)[0] for a in (c.nx, c.nz))
        shift = jnp.asarray(c.shift, px.dtype)[j[0]]
        dn = dx * nx + dz * nz
        new = (px + t * dx - shift * period, pz + t * dz, dx - 2 * dn * nx, dz - 2 * dn * nz)
        px, pz, dx, dz = (jnp.where(hit, a, o) for a, o in zip(new, (px, pz, dx, dz), strict=True))
        return (px, pz, dx, dz, hit, esc), (jnp.where(hit, -dn, 1.0), hit)

    start = (px, pz, dx, dz, jnp.ones(rays, bool), jnp.zeros(rays, bool))
    (px, pz, dx, dz, active, esc), (cos, hit) = jax.lax.scan(step, start, None, length=bounces)
    last = _candidates((px, pz, dx, dz), b, l1, r, rf)
    esc = esc | (active & ~jnp.any(jnp.isfinite(last.t), axis=0) & (dz > 0))
    return _Rays(cos=cos.T, hit=hit.T, escaped=esc, theta_o=jnp.arctan2(dx, dz))


# --------------------------------------------------------------------------------------------
# The correction T(r, r_f) - T(r, 0) and the public functions
# --------------------------------------------------------------------------------------------


def _pair_rays(
    ti: Array, b: Array, l1: Array, r: Array, rf: Array, rays: int, bounces: int
) -> _Rays:
    """The rays for `r_f` and for 0 on a new axis before the ray axis: `(..., 2, rays[, K])`.

    One vectorised computation on both lanes, so a ray that misses the fillet gives the same
    bits in both and cancels exactly."""
    ti, b, l1, r, rf = jnp.broadcast_arrays(ti, b, l1, r, rf)
    pair = [jnp.stack([a, a], axis=-1) for a in (ti, b, l1, r)]
    pair.append(jnp.stack([rf, jnp.zeros_like(rf)], axis=-1))

    def one(*args: Array) -> tuple:
        return tuple(_trace_one(*args, rays=rays, bounces=bounces))

    out = jnp.vectorize(one, signature="(),(),(),(),()->(n,k),(n,k),(n),(n)")(*pair)
    return _Rays(*out)


def _ray_power(traced: _Rays, n: Array) -> Float[Array, "... 2 n_rays"]:
    """Each escaping ray's unpolarised power per unit incident power, signed `+` for the
    filleted lane and `-` for the `r_f = 0` lane (Fresnel per polarisation per bounce,
    [conventions §6]). `n` has the rank of the geometry."""
    f = fresnel_sp(traced.cos, n[..., None, None, None])
    p_s = jnp.prod(jnp.where(traced.hit, f.s, 1.0), axis=-1)
    p_p = jnp.prod(jnp.where(traced.hit, f.p, 1.0), axis=-1)
    sign = with_rank(jnp.asarray([1.0, -1.0], p_s.dtype)[:, None], p_s.ndim)
    return 0.5 * (p_s + p_p) * traced.escaped * sign / traced.cos.shape[-2]


def _pair_sum(x: Array) -> Array:
    """Sum over the trailing (pair, ray) axes, the pair first: a ray that misses the fillet
    then contributes `x + (-x) = 0` exactly, so `r_f = 0` is the rounded model to the bit."""
    # an explicit add, not a reduction: XLA merges consecutive reductions and reorders them
    return jnp.sum(x[..., 0, :] + x[..., 1, :], axis=-1)


def _args(*arrays: ArrayLike) -> tuple[Array, ...]:
    """The arguments at one rank and one float dtype (radians, micrometres) [conventions §10]."""
    dtype = jnp.result_type(*(a for a in arrays if not jnp.iscomplexobj(a)))
    if not jnp.issubdtype(dtype, jnp.floating):
        dtype = jnp.result_type(float)
    return same_rank(*(a if jnp.iscomplexobj(a) else jnp.asarray(a, dtype) for a in arrays))


class _Static(NamedTuple):
    """The static knobs of a correction (hashable: a `custom_jvp` non-differentiable arg)."""

    kind: str  # "brdf", "binned" or "total"
    rays: int
    bounces: int


def _correction(
    static: _Static, rf: Array, ti: Array, b: Array, l1: Array, r: Array, *rest: Array
) -> Array:
    """`T(r, r_f) - T(r, 0)` for one output kind; `rest` is `(n,)`, `(n, edges)` or
    `(n, theta_o, sigma)`."""
    traced = _pair_rays(ti, b, l1, r, rf, static.rays, static.bounces)
    w = _ray_power(traced, rest[0])
    if static.kind == "total":
        return _pair_sum(w)
    if static.kind == "brdf":
        to, sg = rest[1], rest[2]
        return _pair_sum(
            w * hemisphere_gaussian(to[..., None, None], traced.theta_o, sg[..., None, None])
        )
    e = rest[1]
    th = traced.theta_o[..., None]
    e_d = with_rank(e, th.ndim)
    inside = (th >= e_d[..., :-1]) & (th < e_d[..., 1:])
    inside = inside.at[..., -1].set(inside[..., -1] | (th[..., 0] == e[-1]))
    return _pair_sum(jnp.moveaxis(w[..., None] * inside, -1, -3))


def _cap(b: Array, l1: Array) -> Array:
    """`min(l1, l2)`, the room for `r + r_f` [conventions §2]."""
    return max_edge_radius(b, l1)


def _fd_points(geom: tuple) -> list[tuple[Array, Array]]:
    """For each geometric argument `(ti, b, l1, r, rf)`, the two values the difference uses:
    `+-` a step (`FILLET_FD_STEP` of 15 deg for the angles, of `l1` for the layer, of
    `min(l1, l2)` for the radii), one-sided where a side would leave the domain (grazing
    incidence, a wedge or layer on which `r + r_f` no longer fits, a radius below 0)."""
    ti, b, l1, r, rf = geom
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


@partial(jax.custom_jvp, nondiff_argnums=(0,))
def _fd_correction(static: _Static, geom: tuple, rest: tuple) -> Array:
    """`_correction(static, rf, ti, b, l1, r, *rest)` for `geom = (ti, b, l1, r, rf)`,
    differentiated in the geometry by differences (`_fd_points`) and in `rest` (index,
    viewing angle, broadening: they do not move a ray) through the rays. docs/rounded.md §11:
    rays grazing a tip arc make the per-ray derivative in the geometry heavy-tailed, so its
    sum is not a usable derivative (0.7-1.7 times the slope in `r_f`, up to 12 in `theta_i`)."""
    ti, b, l1, r, rf = geom
    return _correction(static, rf, ti, b, l1, r, *rest)


@_fd_correction.defjvp
def _fd_correction_jvp(static: _Static, primals: tuple, tangents: tuple) -> tuple:
    geom, rest = primals
    d_geom, d_rest = tangents
    ti, b, l1, r, rf = geom
    out, d_out = jax.jvp(lambda *a: _correction(static, rf, ti, b, l1, r, *a), rest, d_rest)
    for k, (lo, hi) in enumerate(_fd_points(geom)):
        span = hi - lo
        ok = span > 0
        at = [list(geom), list(geom)]
        at[0][k], at[1][k] = lo, hi
        slope = _fd_correction(static, tuple(at[1]), rest) - _fd_correction(
            static, tuple(at[0]), rest
        )
        d = d_geom[k]
        scale = jnp.where(ok, d / jnp.where(ok, span, 1.0), 0.0)
        d_out = d_out + slope * scale.reshape(d.shape + (1,) * (out.ndim - d.ndim))
    return out, d_out


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
    (static) are the correction's rays per period and reflections per ray.
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
