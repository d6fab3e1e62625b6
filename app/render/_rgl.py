"""The staircase as an RGL measured material (`.bsdf`): the tabulated format of Dupuy and Jakob
(2018, "An adaptive parameterization for efficient material acquisition and rendering") that
Mitsuba's `measured` plugin and pbrt-v4's `measured` material read (docs/render.md).

How Mitsuba reconstructs it (`src/bsdfs/measured.cpp`): for the direction `w_i` towards the
camera (elevation `theta_i`, azimuth `phi_i`, the tables' parameters) and the direction `w_o`
towards the light, the half vector `m = normalize(w_i + w_o)` is mapped to the unit square
(`u = (sqrt(2 theta_m / pi), (phi_m + pi) / 2 pi)`), the `vndf` warp of `w_i` (a 2-D
distribution on that square, bilinear between its nodes) is inverted to a point `s` of the
sample square, and the value is `spectra(s) * ndf(u_m) / (4 sigma(u_i))`: the tables
interpolated bilinearly in `s`, linearly between the parameters' nodes; `ndf` and `sigma` are
2-D tables on the unit square. Sampling draws `s` from `luminance` and warps it by `vndf`.

What the file holds here: `spectra` at every node `s` of the sample grid is the model's value
at the light direction that node stands for (`vndf.sample(s)`, computed with Mitsuba's own warp
algorithm, `_warp`), divided by the `ndf / (4 sigma)` factor Mitsuba will multiply it by, so
that at every node the reconstruction returns the model exactly; between nodes it interpolates.
The `ndf` is the staircase's backscatter, `D(m) ~ p(m, m) cos(theta_m)` (the microfacet
relation `f(m, m) = F G D(m) / 4 cos^2`, which the RGL pipeline measures), normalised so that
`integral D cos = 1` and mixed with a uniform share (`NDF_FLOOR`) so that every direction has
nodes; it peaks at the tread's and the riser's normals and along the plane across the layers,
where the two-bounce path's and the rounded edges' half vectors lie. `sigma` is the NDF's
projected area, `vndf` the visible normals `D(m) (w_i . m) / sigma` [Dupuy and Jakob, Eq. 5].

Local frame: z the surface normal, x (Mitsuba's shading tangent `s`, the mesh's `dp/du`) along
the layer lines, y (`t = n x s`) uphill across them: the face frame of conventions §11 is
`(x_f, y_f, z_f) = (y, -x, z)`. Values are Mitsuba's `eval`: the BRDF for light from `w_o`
seen from `w_i` times the cosine of `w_o`, i.e. `p(w_o -> w_i) (w_o . z) / (w_i . z)`
[conventions §11], in the colour channels R, G, B (the RGB file variant).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from stairfit.model import roughness_alpha

from ._material import ArcGrid, Material, arc_grid, clamp_beta2_deg, density
from ._tensorfile import tensor_bytes
from ._warp import sample_continuous

NDF_FLOOR = 0.05
"""Share of a uniform distribution (`1 / pi`) in the NDF the tables are warped by: it gives
every direction some nodes (the diffuse body and the lobes' tails live there) and bounds the
ratio the `spectra` table stores."""

LUMINANCE = np.array([0.2126, 0.7152, 0.0722])
"""Rec. 709 luminance weights of R, G, B: the `luminance` table that sampling follows."""


class Resolution(NamedTuple):
    """The tables' sizes (docs/render.md, "Resolution"; the tabulation error each gives is
    measured by benchmarks/bench_render_tables.py).

    Attributes:
        theta_i, phi_i: nodes of the camera direction's elevation (0 to `theta_max_deg`) and
            azimuth (-180 to 180 deg, both ends: the staircase has no symmetry that Mitsuba's
            folding could use).
        samples: the sample square's nodes per side (`spectra`, `luminance`).
        vndf: (elevation, azimuth) nodes of each visible-normal table.
        ndf: (elevation, azimuth) nodes of the NDF table (and of the quadrature of `sigma`).
        sigma: (elevation, azimuth) nodes of the projected-area table.
        theta_max_deg: the last elevation node (beyond it the last table is used).
        arcs: the rounded edges' `ArcGrid` (projected angles, values of `|t|`).
    """

    theta_i: int = 24
    phi_i: int = 25
    samples: int = 48
    vndf: tuple[int, int] = (64, 128)
    ndf: tuple[int, int] = (128, 256)
    sigma: tuple[int, int] = (32, 64)
    theta_max_deg: float = 87.0
    arcs: tuple[int, int] = (73, 13)


DEFAULT_RESOLUTION = Resolution()
"""The tables' sizes `stairfit render` writes: the camera's elevation every 3.8 deg, its azimuth
every 15 deg, 48 x 48 light directions per camera direction (31 MB per table)."""

QUALITIES: dict[str, Resolution] = {
    "draft": Resolution(theta_i=8, phi_i=13, samples=24, vndf=(32, 64), ndf=(64, 128),
                        sigma=(16, 32), arcs=(37, 7)),
    "default": DEFAULT_RESOLUTION,
    "fine": Resolution(theta_i=48, phi_i=49, samples=64),
}  # fmt: skip
"""`stairfit render --quality`: a quick look, the default, and finer tables (about 8 times the
time and size of the default)."""


# --- the unit square of Mitsuba's measured.cpp -------------------------------------------------


def u_to_theta(u: NDArray) -> NDArray:
    return np.square(u) * (np.pi / 2)


def u_to_phi(u: NDArray) -> NDArray:
    return (2.0 * u - 1.0) * np.pi


def theta_to_u(theta: NDArray) -> NDArray:
    return np.sqrt(np.asarray(theta) * (2.0 / np.pi))


def phi_to_u(phi: NDArray) -> NDArray:
    return (np.asarray(phi) + np.pi) / (2.0 * np.pi)


def spherical(theta: NDArray, phi: NDArray) -> NDArray:
    """Unit vectors at elevation `theta` and azimuth `phi` (local frame)."""
    st = np.sin(theta)
    return np.stack([np.cos(phi) * st, np.sin(phi) * st, np.cos(theta)], axis=-1)


def jacobian(u_theta: NDArray) -> NDArray:
    """Solid angle per unit area of the square at `u_theta`: `2 pi^2 u sin(theta(u))`."""
    return 2.0 * np.pi**2 * u_theta * np.sin(u_to_theta(u_theta))


def bilinear(table: NDArray, u: NDArray) -> NDArray:
    """Mitsuba's `Marginal2D::eval` of an unnormalised table `(ny, nx)` at points `u`
    `(..., 2)` (x first) of the unit square, nodes at `linspace(0, 1, n)` on each axis."""
    ny, nx = table.shape
    pos = np.clip(u, 0.0, 1.0) * np.array([nx - 1, ny - 1])
    off = np.minimum(pos.astype(int), np.array([nx - 2, ny - 2]))
    fx, fy = (pos - off)[..., 0], (pos - off)[..., 1]
    i, j = off[..., 0], off[..., 1]
    return ((1 - fy) * ((1 - fx) * table[j, i] + fx * table[j, i + 1])
            + fy * ((1 - fx) * table[j + 1, i] + fx * table[j + 1, i + 1]))  # fmt: skip


def grid(nx: int, ny: int) -> NDArray:
    """The nodes of an `(ny, nx)` table as points `(ny, nx, 2)` of the unit square (x first)."""
    x, y = np.meshgrid(np.linspace(0.0, 1.0, nx), np.linspace(0.0, 1.0, ny))
    return np.stack([x, y], axis=-1)


def trapezoid_weights(nx: int, ny: int) -> NDArray:
    """`(ny, nx)` weights of the trapezoid rule on the unit square."""
    wx = np.full(nx, 1.0 / (nx - 1))
    wx[[0, -1]] *= 0.5
    wy = np.full(ny, 1.0 / (ny - 1))
    wy[[0, -1]] *= 0.5
    return wy[:, None] * wx[None, :]


# --- the model in the local frame ------------------------------------------------------------


def to_face(v: NDArray) -> NDArray:
    """Local-frame vectors (x along the layer lines, y uphill) in the face frame (conventions
    §11): `(y, -x, z)`."""
    return np.stack([v[..., 1], -v[..., 0], v[..., 2]], axis=-1)


def to_local(v: NDArray) -> NDArray:
    """The inverse of `to_face`: `(-y_f, x_f, z_f)`."""
    return np.stack([-v[..., 1], v[..., 0], v[..., 2]], axis=-1)


def mitsuba_value(
    material: Material, beta2_deg: float, w_i: NDArray, w_o: NDArray, arcs: ArcGrid | None = None
) -> NDArray:
    """Mitsuba's BSDF value `(..., C)` for the camera direction `w_i` and the light direction
    `w_o` (local frame): `p(w_o -> w_i) (w_o . z) / (w_i . z)`, 0 below the surface. `arcs`:
    see `density`."""
    w_i, w_o = np.broadcast_arrays(np.asarray(w_i, float), np.asarray(w_o, float))
    up = (w_i[..., 2] > 0.0) & (w_o[..., 2] > 0.0)
    out = np.zeros((*up.shape, len(material.index)))
    # only pairs above the surface are evaluated: the model's costly part
    cam, light = w_i[up], w_o[up]
    p = density(material, beta2_deg, to_face(light), to_face(cam), arcs)
    out[up] = p * (light[:, 2] / cam[:, 2])[:, None]
    return out


# --- the tables ------------------------------------------------------------------------------


class Tables(NamedTuple):
    """The fields of a `.bsdf` file (float32 but `description` and `jacobian`)."""

    theta_i: NDArray
    phi_i: NDArray
    ndf: NDArray
    sigma: NDArray
    vndf: NDArray
    luminance: NDArray
    rgb: NDArray
    description: str

    def fields(self) -> dict[str, NDArray | str]:
        """The fields in the order Mitsuba's RGL files have them."""
        return {
            "description": self.description,
            "jacobian": np.array([1], np.uint8),
            "theta_i": self.theta_i, "phi_i": self.phi_i, "ndf": self.ndf,
            "sigma": self.sigma, "vndf": self.vndf, "luminance": self.luminance,
            "rgb": self.rgb,
        }  # fmt: skip


def backscatter_ndf(
    material: Material, beta2_deg: float, size: tuple[int, int], arcs: ArcGrid | None = None
) -> NDArray:
    """The NDF table `(n_phi, n_theta)` (see the module's docstring): `(1 - NDF_FLOOR) D_bs +
    NDF_FLOOR / pi`, `D_bs ~ p(m, m) cos(theta_m)` (luminance of the channels) normalised to
    `integral D cos = 1` by the trapezoid rule on the unit square."""
    n_theta, n_phi = size
    u = grid(n_theta, n_phi)
    m = spherical(u_to_theta(u[..., 0]), u_to_phi(u[..., 1]))
    m[..., 2] = np.maximum(m[..., 2], 1e-6)  # the last row: grazing, still above the surface
    m /= np.linalg.norm(m, axis=-1, keepdims=True)
    back = density(material, beta2_deg, to_face(m), to_face(m), arcs) @ LUMINANCE
    d = np.maximum(back, 0.0) * m[..., 2]
    weights = trapezoid_weights(n_theta, n_phi) * jacobian(u[..., 0])
    norm = np.sum(d * m[..., 2] * weights)
    return (1.0 - NDF_FLOOR) * d / norm + NDF_FLOOR / np.pi


def projected_area(ndf: NDArray, size: tuple[int, int]) -> NDArray:
    """The sigma table `(n_phi, n_theta)`: `sigma(w) = integral D(m) max(0, w . m) dm` at its
    nodes, by the trapezoid rule on the NDF's own nodes."""
    n_theta, n_phi = ndf.shape[1], ndf.shape[0]
    u = grid(n_theta, n_phi)
    m = spherical(u_to_theta(u[..., 0]), u_to_phi(u[..., 1])).reshape(-1, 3)
    dm = (ndf * trapezoid_weights(n_theta, n_phi) * jacobian(u[..., 0])).reshape(-1)
    s = grid(*size)
    w = spherical(u_to_theta(s[..., 0]), u_to_phi(s[..., 1])).reshape(-1, 3)
    blocks = np.array_split(w, max(1, len(w) // 128))  # small blocks: no (n_w, n_m) array
    return np.concatenate([np.maximum(b @ m.T, 0.0) @ dm for b in blocks]).reshape(size[1], size[0])


def tabulate(
    material: Material,
    beta2_deg: float,
    resolution: Resolution = DEFAULT_RESOLUTION,
    progress: Callable[[str], None] | None = None,
) -> Tables:
    """The `.bsdf` tables of the staircase at wedge angle `beta2_deg` (see the module's
    docstring). The sample nodes are warped by Mitsuba's own algorithm (`_warp`), so that
    they are where its `measured` plugin will look."""
    res = resolution
    beta2 = float(clamp_beta2_deg(beta2_deg))
    say = progress or (lambda _: None)
    arcs = arc_grid(material, beta2, res.arcs) if material.edge_radius_um > 0.0 else None
    ndf = backscatter_ndf(material, beta2, res.ndf, arcs).astype(np.float32)
    sigma = projected_area(ndf.astype(float), res.sigma).astype(np.float32)
    say("NDF and projected area")
    theta_i = np.linspace(0.0, math.radians(res.theta_max_deg), res.theta_i)
    phi_i = np.linspace(-np.pi, np.pi, res.phi_i)
    cams = spherical(*np.meshgrid(theta_i, phi_i))  # (n_phi, n_theta, 3)
    u_cam = np.stack(np.broadcast_arrays(theta_to_u(theta_i)[None, :],
                                         phi_to_u(phi_i)[:, None]), axis=-1)  # fmt: skip
    sig = bilinear(sigma.astype(float), u_cam)  # (n_phi, n_theta)
    vndf = visible_normals(ndf, cams, sig, res.vndf)
    say("visible normals")
    s = grid(res.samples, res.samples).reshape(-1, 2)
    lights, factor, to_pdf = [], [], []
    for a in range(res.phi_i):
        for b in range(res.theta_i):
            u_m, pdf_u = (x.astype(float) for x in sample_continuous(vndf[a, b], s))
            m = spherical(u_to_theta(u_m[:, 0]), u_to_phi(u_m[:, 1]))
            cos = m @ cams[a, b]
            lights.append(2.0 * cos[:, None] * m - cams[a, b])
            factor.append(4.0 * sig[a, b] / bilinear(ndf.astype(float), u_m))
            # the light direction's density under the warp alone (per steradian)
            to_pdf.append(pdf_u / np.maximum(jacobian(u_m[:, 0]) * 4.0 * cos, 1e-12))
        say(f"sample nodes {a + 1}/{res.phi_i}")
    n_s = s.shape[0]
    cam_rows = np.repeat(cams.reshape(-1, 3), n_s, axis=0)
    value = mitsuba_value(material, beta2, cam_rows, np.concatenate(lights), arcs)
    say("values")
    ratio = value * np.concatenate(factor)[:, None]
    shape = (res.phi_i, res.theta_i, res.samples, res.samples)
    rgb = np.moveaxis(ratio.reshape(*shape, 3), -1, 2).astype(np.float32)
    # sampling follows luminance(value) / (the warp's density): the product is ~ the value
    lum = (value @ LUMINANCE) / np.maximum(np.concatenate(to_pdf), 1e-12)
    lum = lum.reshape(res.phi_i * res.theta_i, -1)
    lum = lum + 1e-3 * np.maximum(lum.mean(axis=1, keepdims=True), 1e-12)
    return Tables(
        theta_i=theta_i.astype(np.float32), phi_i=phi_i.astype(np.float32), ndf=ndf,
        sigma=sigma, vndf=vndf, luminance=lum.reshape(shape).astype(np.float32), rgb=rgb,
        description=description(material, beta2, res),
    )  # fmt: skip


def visible_normals(ndf: NDArray, cams: NDArray, sig: NDArray, size: tuple[int, int]) -> NDArray:
    """The `vndf` tables `(n_phi, n_theta, size[1], size[0])`: for each camera direction the
    NDF's visible normals `D(m) max(0, w_i . m) / sigma(w_i)` on the unit square of half
    vectors, times the square's Jacobian (a density per unit area of the square)."""
    u = grid(*size)
    m = spherical(u_to_theta(u[..., 0]), u_to_phi(u[..., 1])).reshape(-1, 3)
    jac = jacobian(u[..., 0]).reshape(-1)
    d = bilinear(ndf.astype(float), u).reshape(-1)
    cos = np.maximum(cams.reshape(-1, 3) @ m.T, 0.0)  # (n_cam, n_m)
    out = d[None, :] * cos / sig.reshape(-1, 1) * jac[None, :]
    return out.reshape(*cams.shape[:2], size[1], size[0]).astype(np.float32)


def description(material: Material, beta2_deg: float, resolution: Resolution) -> str:
    """The file's description: what it is, the material's parameters and the tables'
    sizes."""
    width = material.width_rad(beta2_deg)
    name = "sigma" if material.kernel == "gaussian" else "alpha"
    value = math.degrees(width) if material.kernel == "gaussian" else float(roughness_alpha(width))
    n = ", ".join(f"{complex(x).real:.4g}" for x in material.index)
    return (
        f"stairfit staircase: wedge {beta2_deg:.4g} deg, {material.layer_um:g} um layers, "
        f"edge radius {material.radius_at(beta2_deg):.3g} um, {material.kernel} facets "
        f"({name} {value:.4g}), index (R, G, B) {n}, body albedo {material.body_albedo:.4g}; "
        f"layer lines along the tangent u (x), uphill along v (y). {material.source} "
        f"Tables: {tuple(resolution)}."
    )


def write_bsdf(
    path: str | Path,
    material: Material,
    beta2_deg: float,
    resolution: Resolution = DEFAULT_RESOLUTION,
    progress: Callable[[str], None] | None = None,
) -> Path:
    """Write the staircase at `beta2_deg` as an RGL `.bsdf` file (atomically) and return its
    path. Refuses (FileExistsError) to replace a file that is already there."""
    from stairfit.fileio import atomic_bytes

    path = Path(path)
    if path.exists():
        raise FileExistsError(f"{path} exists; remove it or write elsewhere")
    tables = tabulate(material, beta2_deg, resolution, progress)
    return atomic_bytes(path, tensor_bytes(tables.fields()))
