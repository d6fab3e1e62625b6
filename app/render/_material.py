"""The fitted material as a renderer needs it: the staircase's reflectance for any pair of 3-D
directions and wedge angle, per colour channel, with the diffuse body [conventions §11, §12].

A `Material` holds what a fit found (or what a user gives): the facets' kernel and width, the
edge radius, the layer thickness, the index per channel and the body's albedo. `density`
evaluates `p(w_i, w_o) = f cos(theta_o)` (1/sr, conventions §11) of the staircase plus its
Lambertian body, with the model's own functions (`stairfit.model`); nothing here is physics of
its own. `face_frame` turns a surface's shading frame and build axis into the face frame of
conventions §11.

The body: a fit's value is `scale p + floor body` with `body = lab_body` (per unit albedo, no
`1 / pi`) [docs/fitting.md §10], so the body's Lambertian albedo is `pi floor / scale`.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from stairfit.model import LAB_KERNELS, roughness_alpha

DEG = math.pi / 180.0

BETA2_LIMITS_DEG = (0.5, 89.5)
"""The wedge angles a surface's staircase is evaluated at: a surface closer to horizontal (a
flat top) or to vertical (a wall) takes the nearest limit; the model's cell is degenerate at 0
and 90 deg (one facet's length vanishes)."""


class Material(NamedTuple):
    """A printed material's staircase reflectance (docs/render.md).

    Attributes:
        kernel: how the facets spread their reflections, one of `stairfit.model.LAB_KERNELS`
            ("gaussian", "ggx", "beckmann").
        widths: `((beta2_deg, width_rad), ...)`: the facets' width per wedge angle (one entry:
            the same for every wedge; several: interpolated in the wedge angle, the ends held).
            For "gaussian" the broadening sigma; for a microfacet kernel the roughness angle,
            `alpha = tan(width)` (the fit's width slot, `stairfit.model.roughness_alpha`).
        edge_radius_um: the convex step edges' radius (0: sharp).
        layer_um: the layer thickness l1.
        index: the refractive index per colour channel (R, G, B), complex.
        body_albedo: the diffuse body's Lambertian albedo (0: none).
        photo_scale: a render's radiance per unit lamp irradiance (1/sr) times this is the
            photos' relative radiance (the fit's `scale`; None when not from a fit).
        source: where the numbers came from, for messages and file descriptions.
    """

    kernel: str
    widths: tuple[tuple[float, float], ...]
    edge_radius_um: float
    layer_um: float
    index: tuple[complex, ...]
    body_albedo: float
    photo_scale: float | None = None
    source: str = ""

    def width_rad(self, beta2_deg: ArrayLike) -> NDArray:
        """The facets' width (rad) at wedge angle(s) `beta2_deg` (linear between fitted
        wedges, the ends held)."""
        xs = np.array([w[0] for w in self.widths])
        ys = np.array([w[1] for w in self.widths])
        order = np.argsort(xs)
        return np.interp(np.asarray(beta2_deg, float), xs[order], ys[order])

    def model_width(self, beta2_deg: ArrayLike) -> NDArray:
        """The width the model functions take: sigma (rad) for "gaussian", alpha otherwise."""
        w = self.width_rad(beta2_deg)
        return w if self.kernel == "gaussian" else np.asarray(roughness_alpha(w), float)

    def radius_at(self, beta2_deg: ArrayLike) -> NDArray:
        """The edge radius (um) the cell at `beta2_deg` holds: the material's, or just under
        the largest the cell has room for (`stairfit.model.max_edge_radius`, min(l1, l2)) on a
        steep wall whose treads are shorter than the radius."""
        b = np.radians(np.asarray(beta2_deg, float))
        room = np.minimum(self.layer_um, self.layer_um * np.cos(b) / np.sin(b))
        return np.minimum(self.edge_radius_um, 0.98 * room)

    def check(self) -> Material:
        """This material, or ValueError naming the field that is out of range."""
        if self.kernel not in LAB_KERNELS:
            raise ValueError(f"kernel {self.kernel!r}: use one of {', '.join(LAB_KERNELS)}")
        if not self.widths or any(not (0.0 < w < math.pi / 2) for _, w in self.widths):
            raise ValueError("widths: each width must lie in (0, 90 deg)")
        if not (self.layer_um > 0.0 and self.edge_radius_um >= 0.0):
            raise ValueError("layer_um must be > 0 and edge_radius_um >= 0")
        if not self.index or any(complex(n).real < 1.0001 for n in self.index):
            raise ValueError("index: every channel's real part must be at least 1.0001")
        if not 0.0 <= self.body_albedo <= 1.0:
            raise ValueError(f"body_albedo {self.body_albedo}: must lie in [0, 1]")
        return self


def clamp_beta2_deg(beta2_deg: ArrayLike) -> NDArray:
    """Wedge angles held inside `BETA2_LIMITS_DEG`."""
    return np.clip(np.asarray(beta2_deg, float), *BETA2_LIMITS_DEG)


def density(
    material: Material,
    beta2_deg: ArrayLike,
    w_i: ArrayLike,
    w_o: ArrayLike,
    arcs: ArcGrid | None = None,
) -> NDArray:
    """`p(w_i, w_o)` (1/sr) per channel, `(..., C)`: the staircase's reflected power per
    steradian per unit incident power for light from `w_i` seen from `w_o` (unit vectors in
    the face frame, conventions §11) on a face at wedge angle(s) `beta2_deg` (deg; held inside
    `BETA2_LIMITS_DEG`), plus the body, `body_albedo / pi * lab_body` [conventions §11, §12];
    every leading shape broadcasts. 0 where either direction is below the face. float64,
    evaluated in chunks by one compiled program per kernel.

    `arcs`: the rounded edges' lobes interpolated from `arc_grid` (of this material and one
    wedge angle) instead of evaluated at every pair, the costly part of the rounded model."""
    w_i = np.asarray(w_i, float)
    w_o = np.asarray(w_o, float)
    beta2 = clamp_beta2_deg(beta2_deg)
    lead = np.broadcast_shapes(w_i.shape[:-1], w_o.shape[:-1], beta2.shape)
    wi = np.broadcast_to(w_i, (*lead, 3)).reshape(-1, 3)
    wo = np.broadcast_to(w_o, (*lead, 3)).reshape(-1, 3)
    b = np.broadcast_to(beta2, lead).reshape(-1)
    n, same = _channels(material)
    rows = _rows(material, b)
    fixed = (material.layer_um, material.body_albedo)
    rounded = material.edge_radius_um > 0.0
    part = ("rounded_flats" if arcs is not None else "rounded") if rounded else "sharp"
    out = _chunked(_program(material.kernel, part), (wi, wo, rows), (n, *fixed), n.size)
    if rounded and arcs is not None:
        out = out + arcs.evaluate(wi, wo, rows, n)
    if same:
        out = np.repeat(out, len(material.index), axis=-1)
    return out.reshape(*lead, len(material.index))


def _channels(material: Material) -> tuple[NDArray, bool]:
    """The distinct indices to evaluate (one when every channel has the same) and whether
    they are one."""
    index = np.asarray(material.index, complex)
    same = bool(np.all(index == index[0]))
    n = index[:1] if same else index
    return (n.real if np.all(n.imag == 0) else n), same


def _rows(material: Material, beta2_deg: NDArray) -> NDArray:
    """Per pair `(beta2 (rad), model width, edge radius)`, `(N, 3)`."""
    return np.stack([np.radians(beta2_deg), material.model_width(beta2_deg),
                     material.radius_at(beta2_deg)], axis=-1)  # fmt: skip


class ArcGrid(NamedTuple):
    """The rounded edges' lobes of one material at one wedge angle without their spread along
    the layer lines, on a grid of the projected angles of light and viewer and the light's
    component along the layer lines (which only enters the Fresnel factors):
    `rho(theta_i', theta_o', |t_i|)`, `(C, n, n, m)`. `rounded_arcs` is `rho` times that
    spread (`arc_deflection`, or `line_gaussian` for Gaussian facets) [docs/model.md §7.6]."""

    theta: NDArray
    t: NDArray
    rho: NDArray
    kernel: str

    def evaluate(self, wi: NDArray, wo: NDArray, rows: NDArray, n: NDArray) -> NDArray:
        """The arcs' density `(N, C)` at unit pairs `(N, 3)` (face frame): `rho` interpolated
        (trilinear) times the spread along the layer lines."""
        th_i = np.arctan2(-wi[:, 0], np.maximum(wi[:, 2], 1e-12))
        th_o = np.arctan2(wo[:, 0], np.maximum(wo[:, 2], 1e-12))
        t = np.abs(wi[:, 1])
        step = self.theta[1] - self.theta[0]
        fi = np.clip((th_i - self.theta[0]) / step, 0, len(self.theta) - 1 - 1e-9)
        fo = np.clip((th_o - self.theta[0]) / step, 0, len(self.theta) - 1 - 1e-9)
        k = np.clip(np.searchsorted(self.t, t) - 1, 0, len(self.t) - 2)
        ft = np.clip((t - self.t[k]) / (self.t[k + 1] - self.t[k]), 0.0, 1.0)
        i0, o0 = fi.astype(int), fo.astype(int)
        a, c = fi - i0, fo - o0
        out = 0.0
        for di, wa in ((0, 1 - a), (1, a)):
            for do, wc in ((0, 1 - c), (1, c)):
                for dk, wt in ((0, 1 - ft), (1, ft)):
                    i1 = np.minimum(i0 + di, len(self.theta) - 1)
                    o1 = np.minimum(o0 + do, len(self.theta) - 1)
                    out = out + (wa * wc * wt)[:, None] * self.rho[:, i1, o1, k + dk].T
        along = _chunked(_program(self.kernel, "arc_along"), (wi, wo, rows), (), 1)
        up = (wi[:, 2] > 0.0) & (wo[:, 2] > 0.0)
        return np.where(up[:, None], out * along, 0.0)


ARC_GRID = (73, 7)
"""Nodes of `arc_grid`: projected angles every 2.5 deg over [-90, 90] deg, and 7 values of
`|t_i|` (`sin` of 0, 15, ..., 90 deg). The arcs' lobes are spread by at least `sqrt(2) alpha`
(5 deg at alpha 0.06) in the plane, so linear interpolation misses a few per cent of their
peaks, a fraction of a per cent of the staircase's total."""


def arc_grid(material: Material, beta2_deg: float, size: tuple[int, int] = ARC_GRID) -> ArcGrid:
    """The `ArcGrid` of `material` at `beta2_deg` (rounded materials only)."""
    theta = np.linspace(-np.pi / 2, np.pi / 2, size[0])
    t = np.sin(np.linspace(0.0, np.pi / 2, size[1]))
    ti, to, tt = np.meshgrid(theta, theta, t, indexing="ij")
    c = np.sqrt(np.clip(1.0 - tt * tt, 0.0, 1.0))
    wi = np.stack([-c * np.sin(ti), tt, c * np.cos(ti)], axis=-1).reshape(-1, 3)
    wo = np.stack([c * np.sin(to), -tt, c * np.cos(to)], axis=-1).reshape(-1, 3)
    b = float(clamp_beta2_deg(beta2_deg))
    rows = _rows(material, np.full(wi.shape[0], b))
    n, _ = _channels(material)
    fixed = (material.layer_um,)
    rho = _chunked(_program(material.kernel, "arc_rho"), (wi, wo, rows), (n, *fixed), n.size)
    rho = np.where(np.isfinite(rho), rho, 0.0).T.reshape(n.size, *ti.shape)
    return ArcGrid(theta, t, rho, material.kernel)


CHUNK = 1 << 14
"""Direction pairs per compiled call: every call pads to a power of two up to this size, so a
few programs serve all."""


def _chunked(fn: Callable, arrays: tuple, fixed: tuple, width: int) -> NDArray:
    """`fn(*chunk_of_arrays, *fixed)` over the pairs in chunks, `(N, width)`."""
    total = arrays[0].shape[0]
    size = min(CHUNK, max(16, 1 << max(0, (total - 1)).bit_length()))
    out = np.empty((total, width))
    for start in range(0, total, size):
        stop = min(start + size, total)
        parts = [a[start:stop] for a in arrays]
        if stop - start < size:  # pad with copies of a harmless pair (straight up)
            extra = size - (stop - start)
            up = np.zeros((extra, 3))
            up[:, 2] = 1.0
            parts = [np.concatenate([parts[0], up]), np.concatenate([parts[1], up]),
                     *(np.concatenate([a, np.repeat(a[-1:], extra, axis=0)]) for a in parts[2:])]
        res = np.asarray(fn(*parts, *fixed))
        out[start:stop] = res.reshape(size, -1)[: stop - start]
    return out


@functools.cache
def _program(kernel: str, part: str) -> Callable:
    """The compiled density of one kernel (see `density`): `part` "sharp", "rounded",
    "rounded_flats" (without the arcs), "arc_rho" (the arcs over their spread along the
    layer lines, `ArcGrid`) or "arc_along" (that spread)."""
    import jax
    import jax.numpy as jnp

    from stairfit import model

    def along(wi, wo, width):  # noqa: ANN001
        if kernel == "gaussian":
            return model.line_gaussian(wo[..., 1], -wi[..., 1], width)
        return model.arc_deflection(wi, wo, width, kernel)

    def f(wi, wo, rows, *fixed):  # noqa: ANN001
        a, b = wi[:, None, :], wo[:, None, :]  # (N, 1, 3): a channel axis before the vector
        b2, width, radius = rows[:, 0], rows[:, 1], rows[:, 2]
        b2c, wc, rc = b2[:, None], width[:, None], radius[:, None]
        if part == "arc_along":
            return along(wi, wo, width)
        n, layer = fixed[0], fixed[1]
        if part != "sharp":
            theta = model.projected_incidence(wi).theta
            geo = model.rounded_geometry(theta, b2, layer, radius)
            geo = jax.tree_util.tree_map(lambda x: x[:, None], geo)
        if part == "arc_rho":
            arcs = model.rounded_arcs(a, b, b2c, n, wc, layer, rc, geo, kernel)
            spread = along(a, b, wc)
            return arcs / jnp.where(spread > 0.0, spread, 1.0)
        albedo = fixed[2]
        if part == "rounded":
            spec = model.lab_density_rounded(a, b, b2c, n, wc, layer, rc, kernel, geometry=geo)
        elif part == "rounded_flats":
            spec = model.rounded_flats(a, b, b2c, n, wc, layer, rc, kernel)
        elif kernel == "gaussian":
            spec = model.lab_density_gaussian(a, b, b2c, n, wc)
        else:
            spec = model.lab_density_microfacet(a, b, b2c, n, wc, kernel)
        body = (model.lab_body(a, b, b2c, n) if part == "sharp"
                else model.lab_body_rounded(a, b, b2c, n, layer, rc))  # fmt: skip
        return spec + albedo / jnp.pi * body

    with jax.enable_x64(True):
        compiled = jax.jit(f)

    def run(*args):
        with jax.enable_x64(True):
            return compiled(*(jnp.asarray(a) for a in args))

    return run


# --- frames ----------------------------------------------------------------------------------


def face_frame(normal: ArrayLike, build_axis: ArrayLike) -> tuple[NDArray, NDArray]:
    """The face frame of a surface with unit `normal` printed along `build_axis` (conventions
    §11): `(beta2_deg, R)` with `R` `(..., 3, 3)` whose rows are the face frame's x (uphill,
    across the layer lines), y (along them) and z (the normal), so that `R @ v` is `v` in the
    face frame.

    The wedge angle is the normal's angle from the build axis, folded into [0, 90] deg: a
    surface facing down (an overhang) is the mirror image through the layer plane of one
    facing up at `180 deg - angle`, with the same staircase; its "uphill" then points towards
    the plate. A surface parallel to the layers (a flat top or bottom) takes any tangent."""
    n = np.asarray(normal, float)
    n = n / np.linalg.norm(n, axis=-1, keepdims=True)
    b = np.asarray(build_axis, float)
    b = b / np.linalg.norm(b, axis=-1, keepdims=True)
    b = np.broadcast_to(b, n.shape)
    cos = np.sum(n * b, axis=-1)
    tangent = b - cos[..., None] * n
    length = np.linalg.norm(tangent, axis=-1)
    flat = length < 1e-9
    fallback = np.where(np.abs(n[..., :1]) < 0.9, [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    fallback = fallback - np.sum(fallback * n, axis=-1, keepdims=True) * n
    tangent = np.where(flat[..., None], fallback, tangent)
    x = tangent / np.linalg.norm(tangent, axis=-1, keepdims=True)
    x = x * np.where(cos < 0.0, -1.0, 1.0)[..., None]
    y = np.cross(n, x)
    beta2 = np.degrees(np.arccos(np.clip(np.abs(cos), 0.0, 1.0)))
    return beta2, np.stack([x, y, n], axis=-2)
