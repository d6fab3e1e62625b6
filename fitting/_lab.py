"""The lab model as fits see it: each row's 3-D light and view directions over its face and the
lamp, and the staircase evaluated at every one of them [conventions §9, §11, §12].

A row (photo x wedge x channel) measures the mean radiance over its ROI's pixels. In the lab
model its geometry is a set of nodes, each a pair of unit directions in the wedge's face frame
(towards the light, towards the camera) with a conversion weight `conv = w E (w_i . z) /
(w_o . z)`: the node's share of the ROI's pixels (and of the lamp's disk) times the irradiance
relative to the scene's reference distance, `(d_ref / d)^2`, times the radiance conversion of
[conventions §11]. The model's value is then
`sum over nodes of conv (scale p(w_i, w_o) + floor body(w_i, w_o)) + scale plate R(w_o)`, with `p`
the staircase's reflected power per steradian, `body` its diffuse body per unit albedo
(`stairfit.model.lab_body`) and `R` the share of the lit base plate's radiance that the risers
reflect into the view (`stairfit.model.plate_reflectance`), `plate` the node's share times the
plate's Lambertian radiance per unit `scale` (`plate_conv`). The channels of one ROI share its
nodes (the geometry key).
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int
from numpy.typing import NDArray

from stairfit import model

from ._errors import FitInputError
from ._params import clamp_index

COS_O_FLOOR = float(np.cos(np.deg2rad(89.9)))
"""`w_o . z` is floored here in the conversion weight, as `cos(theta_o)` is in the in-plane
model's radiance [conventions §9]."""


class LabGeometry(NamedTuple):
    """The 3-D geometry of a scene's rows for the lab model (NumPy, validated by `check`).

    Per geometry key (G; one per photo x wedge) and node (K, padded with zero weight):
    `w_i`, `w_o` `(G, K, 3)` unit directions in the key's wedge face frame
    [conventions §11]; `weight` `(G, K)`, the node's share of the ROI and lamp (each key's sum
    1); `irradiance` `(G, K)`, the lamp's irradiance at the node relative to the reference
    distance (1 for a distant light). `wedge` `(G,)`. Per row (N): `key`, its geometry key.
    `plate_albedo`: the Lambertian reflectance of the plate the wedges stand on (0: its
    reflected light is not modelled).
    """

    w_i: NDArray
    w_o: NDArray
    weight: NDArray
    irradiance: NDArray
    wedge: NDArray
    key: NDArray
    plate_albedo: float = 0.0

    def check(self, n_rows: int) -> LabGeometry:
        """This geometry, or a `FitInputError` naming what is wrong."""
        g, k = self.weight.shape
        shapes = {"w_i": (g, k, 3), "w_o": (g, k, 3), "irradiance": (g, k), "wedge": (g,),
                  "key": (n_rows,)}  # fmt: skip
        for name, shape in shapes.items():
            if np.shape(getattr(self, name)) != shape:
                raise FitInputError(
                    f"lab geometry: {name} has shape {np.shape(getattr(self, name))}, "
                    f"expected {shape}"
                )
        for name in ("w_i", "w_o", "weight", "irradiance"):
            if not np.all(np.isfinite(getattr(self, name))):
                raise FitInputError(f"lab geometry: {name} has non-finite entries")
        if not 0.0 <= self.plate_albedo <= 1.0:
            raise FitInputError(f"lab geometry: plate_albedo {self.plate_albedo} is not in [0, 1]")
        if np.any(self.key < 0) or np.any(self.key >= g):
            raise FitInputError("lab geometry: a row's key is outside 0 .. G-1")
        if not np.allclose(self.weight.sum(axis=1), 1.0, atol=1e-9):
            raise FitInputError("lab geometry: each key's node weights must sum to 1")
        return self


class LabData(NamedTuple):
    """The traced arrays of the lab model (see `LabGeometry`): `w_i`, `w_o` `(G, K, 3)`, `conv`
    `(G, K)` (weight x irradiance x `(w_i . z) / (w_o . z)`), `b2`, `layer`, `wedge` `(G,)`, `key`
    `(N,)`; the distinct channels' index samples `n` and their summed weights `w` `(C', L)`
    (`distinct_samples`, `distinct_channels`) and each channel's row of them, `channel` `(C,)`;
    `plate` `(G, K)` (`plate_conv`). A scene without lab geometry carries one dummy key (never
    read)."""

    w_i: Float[Array, "G K 3"]
    w_o: Float[Array, "G K 3"]
    conv: Float[Array, "G K"]
    b2: Float[Array, " G"]
    layer: Float[Array, " G"]
    wedge: Int[Array, " G"]
    key: Int[Array, " N"]
    n: Array
    w: Float[Array, "C L"]
    channel: Int[Array, " C"]
    plate: Float[Array, "G K"]


def distinct_channels(n: NDArray, w: NDArray) -> tuple[NDArray, NDArray, NDArray]:
    """The distinct rows of `(n, w)` `(C, L)` and each channel's row among them: channels that
    see the same index samples with the same weights (a constant index) are evaluated once."""
    rows = np.concatenate([n, w], axis=1)
    uniq, channel = np.unique(rows, axis=0, return_inverse=True)
    size = n.shape[1]
    return uniq[:, :size], uniq[:, size:], channel.ravel()


def distinct_samples(n_base: NDArray, weights: NDArray) -> tuple[NDArray, NDArray]:
    """Each channel's distinct index values and the sum of their weights, `(C, L)`, padded
    with zero weights to the largest count: the same band averages as `(n_base, weights)`,
    exactly, with one sample per distinct value (a constant index needs one, not 81)."""
    rows = []
    for n_c, w_c in zip(np.asarray(n_base), np.asarray(weights, float), strict=True):
        values, inverse = np.unique(n_c, return_inverse=True)
        rows.append((values, np.bincount(inverse.ravel(), w_c, minlength=values.size)))
    size = max(v.size for v, _ in rows)
    n = np.stack([np.concatenate([v, np.repeat(v[-1:], size - v.size)]) for v, _ in rows])
    w = np.stack([np.concatenate([w_, np.zeros(size - w_.size)]) for _, w_ in rows])
    return n, w


def lab_data(
    geo: LabGeometry | None,
    beta2_w: NDArray,
    layer_w: NDArray,
    n_rows: int,
    spectral: tuple[NDArray, NDArray],
    size: int = 0,
) -> LabData:
    """The traced arrays for `geo` (its keys padded to `size` by copies of the last, never
    read) and the spectral samples `(n_base, weights)`, or the dummy of a scene without lab
    geometry."""
    if geo is None:
        up = np.zeros((1, 1, 3))
        up[..., 2] = 1.0
        return LabData(up, up, np.zeros((1, 1)), np.full(1, 0.5), np.full(1, 150.0),
                       np.zeros(1, int), np.zeros(n_rows, int), np.full((1, 1), 1.5),
                       np.ones((1, 1)), np.zeros(1, int), np.zeros((1, 1)))  # fmt: skip
    n, w, channel = distinct_channels(*distinct_samples(*spectral))
    cos_i = np.clip(geo.w_i[..., 2], 0.0, None)
    cos_o = np.maximum(geo.w_o[..., 2], COS_O_FLOOR)
    conv = geo.weight * geo.irradiance * cos_i / cos_o
    g = geo.weight.shape[0]
    size = max(size, g)

    def pad(a: NDArray) -> NDArray:
        return a if size == g else np.concatenate([a, np.repeat(a[-1:], size - g, axis=0)])

    wedge = np.asarray(geo.wedge, int)
    b2 = np.asarray(beta2_w, float)[wedge]
    plate = plate_conv(geo.w_i, geo.weight * geo.irradiance, b2, geo.plate_albedo)
    return LabData(
        pad(geo.w_i), pad(geo.w_o), pad(conv), pad(b2), pad(np.asarray(layer_w)[wedge]),
        pad(wedge), np.asarray(geo.key, int), n, w, channel, pad(plate),
    )  # fmt: skip


def plate_conv(w_i: NDArray, share: NDArray, beta2: NDArray, albedo: float) -> NDArray:
    """Each node's share (`weight x irradiance`, `(G, K)`) times the plate's Lambertian
    radiance per unit irradiance and `scale`, `albedo / pi (w_i . z_plate)`, `z_plate` the
    plate's normal in the face frame, which is the tread's (`stairfit.model.facet_normals`):
    the plate in front of a wedge is taken as lit like the wedge's own foot, unshadowed
    [conventions §2, §11]."""
    z_plate = np.stack([np.sin(beta2), np.zeros_like(beta2), np.cos(beta2)], axis=-1)
    cos_p = np.clip(np.einsum("gkj,gj->gk", w_i, z_plate), 0.0, None)
    return share * albedo / np.pi * cos_p


def lab_grid(
    width_g: Array,
    dn: Array,
    lab: LabData,
    kernel: str,
    radius_um: Array | None = None,
    resolution: int | None = None,
) -> tuple[Array, Array]:
    """(specular, body) per geometry key and channel, `(G, C)`: each node's staircase density
    (`stairfit.model.lab_density_gaussian`, or `lab_density_microfacet` for a microfacet
    `kernel`; `lab_density_rounded` with tip radius `radius_um`) and diffuse body,
    band-averaged over the channel's wavelength samples and summed over the nodes with `conv`
    [conventions §8, §11, §12]. `width_g` is each key's width in rad: the Gaussian's sigma, or
    for a microfacet kernel the roughness angle (`stairfit.model.roughness_alpha`). The arcs'
    panels are computed once per key, at the mean projected angle of incidence of its nodes;
    the flats' delta weights and the arcs' single reflection at every node (docs/model.md
    §7.6). Derivatives by `_lab_grid_jvp`."""
    rounded = radius_um is not None
    radius = jnp.zeros((), width_g.dtype) if radius_um is None else jnp.asarray(radius_um)
    return _lab_grid(width_g, jnp.asarray(dn, width_g.dtype), radius, (kernel, rounded,
                     resolution), lab)  # fmt: skip


@functools.partial(jax.custom_jvp, nondiff_argnums=(3,))
def _lab_grid(
    width_g: Array, dn: Array, radius: Array, cfg: tuple, lab: LabData
) -> tuple[Array, Array]:
    """`_lab_impl` with a JVP that needs three directional derivatives whatever the number of
    parameters: each key depends on its own width only, and on `delta_n` and the radius, so one
    direction with every width moved at once, one along `delta_n` and one along the radius give
    the whole Jacobian (as `_forward.sharp_grid_density`). `lab` is data."""
    return _lab_impl(width_g, dn, radius, cfg, lab)


@_lab_grid.defjvp
def _lab_grid_jvp(cfg: tuple, primals: tuple, tangents: tuple) -> tuple:
    width_g, dn, radius, lab = primals
    t_w, t_dn, t_r, _ = tangents
    rounded = cfg[1]

    def f(eps: Array) -> tuple[Array, Array]:
        return _lab_impl(width_g + eps[0], dn + eps[1], radius + eps[2], cfg, lab)

    eps0 = jnp.zeros(3 if rounded else 2, dtype=width_g.dtype)
    value, lin = jax.linearize(f, eps0)
    jac = jax.vmap(lin, out_axes=-1)(jnp.eye(eps0.shape[0], dtype=eps0.dtype))

    def tangent(j: Array) -> Array:  # (G, C, 2|3) -> (G, C)
        out = j[..., 0] * t_w[:, None] + j[..., 1] * t_dn
        return out + j[..., 2] * t_r if rounded else out

    return value, tuple(tangent(j) for j in jac)


def _mean_direction(w: Array, conv: Array) -> Array:
    """Each key's `conv`-weighted mean unit direction, `(G, 3)`."""
    m = jnp.einsum("gk,gkj->gj", conv, w)
    return m / jnp.maximum(jnp.linalg.norm(m, axis=-1, keepdims=True), 1e-300)


def _lab_impl(
    width_g: Array, dn: Array, radius: Array, cfg: tuple, lab: LabData
) -> tuple[Array, Array]:
    """The computation of `lab_grid`; `cfg = (kernel, rounded, resolution)`."""
    kernel, rounded, resolution = cfg
    n, weights = clamp_index(lab.n + dn), lab.w  # (C, L): band-averaged inside
    w_i = lab.w_i[:, :, None, :]  # (G, K, 1, 3): the channel axis third
    w_o = lab.w_o[:, :, None, :]
    b2 = lab.b2[:, None, None]
    width = width_g[:, None, None]
    if kernel != "gaussian":
        width = model.roughness_alpha(width)
    if rounded:
        theta = jnp.sum(model.projected_incidence(lab.w_i).theta * lab.conv, axis=1) / jnp.maximum(
            jnp.sum(lab.conv, axis=1), 1e-300
        )  # (G,): each key's conv-weighted mean projected angle
        res = model.ROUNDED_RESOLUTION if resolution is None else resolution
        geo = model.rounded_geometry(theta, lab.b2, lab.layer, radius, resolution=res)
        p = model.rounded_flats(
            w_i, w_o, b2, n, width, lab.layer[:, None, None], radius, kernel, weights
        )
        # the arcs' broad lobes once per key, at its nodes' mean directions (docs/model.md §7.6)
        mean_i, mean_o = (_mean_direction(w, lab.conv)[:, None, :] for w in (lab.w_i, lab.w_o))
        arcs = model.arc_panels(
            mean_i, mean_o, lab.b2[:, None], n, width[:, :, 0],
            jax.tree_util.tree_map(lambda a: a[:, None], geo), kernel, weights,
        )  # (G, C')  # fmt: skip
        p = p + arcs[:, None, :]  # every node of a key gets its key's arcs
        if kernel != "gaussian":  # the arcs' single reflection at every node
            p = p + model.arc_single(w_i, w_o, b2, n, width, lab.layer[:, None, None], radius,
                                     kernel, weights)  # fmt: skip
    elif kernel == "gaussian":
        p = model.lab_density_gaussian(w_i, w_o, b2, n, width, spectral_weight=weights)
    else:
        p = model.lab_density_microfacet(w_i, w_o, b2, n, width, kernel, weights)
    body = (model.lab_body_rounded(w_i, w_o, b2, n, lab.layer[:, None, None], radius, weights)
            if rounded else model.lab_body(w_i, w_o, b2, n, weights))  # fmt: skip
    plate = model.plate_reflectance(w_o, b2, n, width_g[:, None, None], kernel, weights)
    spec = jnp.einsum("gk,gkc->gc", lab.conv, p) + jnp.einsum("gk,gkc->gc", lab.plate, plate)
    spec = spec[:, lab.channel]
    diffuse = jnp.einsum("gk,gkc->gc", lab.conv, body)[:, lab.channel]
    return spec, diffuse
