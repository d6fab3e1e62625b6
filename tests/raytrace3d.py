"""The independent ray tracer of tests/raytrace.py, extended to 3-D rays and rough facets.

Plain NumPy; shares no code and no formula with `stairfit.model`. The profile is extruded along
the layer lines (y), so a ray's intersections with it depend only on its direction's (x, z)
part: the 2-D intersection code of `raytrace` is reused with that part normalised, and the y
component is carried along. At each hit:

* the surface's normal is the profile's (x, 0, z) normal, or for a rough facet a micro-normal
  `m` drawn from `D(m) (m . n)` (GGX or Beckmann, written here from Walter et al. 2007);
* the ray is mirrored about it, and its weight is multiplied by the microfacet estimator
  `G1(i) G1(o) (i . m) / ((i . n)(m . n))` (1 for a smooth facet); a ray sent below the facet
  or into the back of its micro-facet ends there (single scattering per facet);
* polarisation is tracked exactly: two orthogonal input states as complex 3-D Jones vectors,
  split at every reflection into the s and p components of that reflection's own plane of
  incidence and multiplied by the textbook Fresnel amplitudes (`raytrace.fresnel_sp`'s Snell
  form, as amplitudes); the unpolarised power is the mean of the two states' powers.

Frame [conventions §1, §11]: x uphill, y along the layer lines, z the face normal; `w_i` is the
unit vector towards the light, an escaped ray leaves along its unit direction `w_o`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from raytrace import ACTIVE, ESCAPED, LOST, TRAPPED, Staircase, _hit_arcs, _hit_segments


def fresnel_amplitudes(cos_i: NDArray, n: complex) -> tuple[NDArray, NDArray]:
    """Textbook amplitude reflection coefficients `(r_s, r_p)` (Hecht), from Snell's law."""
    cos_i = np.clip(cos_i, 0.0, 1.0)
    sin_t = np.sqrt(1.0 - cos_i**2) / complex(n)
    cos_t = np.sqrt(1.0 - sin_t**2 + 0j)
    r_s = (cos_i - n * cos_t) / (cos_i + n * cos_t)
    r_p = (n * cos_i - cos_t) / (n * cos_i + cos_t)
    return r_s, r_p


@dataclass(frozen=True)
class Rough:
    """Rough facets: roughness `alpha` of distribution `kind` ("ggx" or "beckmann")."""

    alpha: float
    kind: str = "ggx"


def _ndf_tan2(u: NDArray, rough: Rough) -> NDArray:
    """`tan^2` of micro-normals drawn from `D(m)(m . n)`: GGX `a^2 u / (1 - u)`, Beckmann
    `-a^2 log(1 - u)` (inverting their cumulative distributions in `tan^2`)."""
    a2 = rough.alpha**2
    if rough.kind == "ggx":
        return a2 * u / (1.0 - u)
    if rough.kind == "beckmann":
        return -a2 * np.log1p(-u)
    raise ValueError(f"unknown distribution {rough.kind!r}")


def _g1(cos_v: NDArray, cos_vm: NDArray, rough: Rough) -> NDArray:
    """Smith G1: GGX `2 / (1 + sqrt(1 + a^2 tan^2))`; Beckmann `1 / (1 + Lambda)` with the
    exact Lambda (erf), written here independently."""
    from math import erf, exp, pi, sqrt

    c = np.clip(cos_v, 1e-12, 1.0)
    tan2 = (1.0 - c * c) / (c * c)
    if rough.kind == "ggx":
        g = 2.0 / (1.0 + np.sqrt(1.0 + rough.alpha**2 * tan2))
    else:
        a = 1.0 / (rough.alpha * np.sqrt(np.maximum(tan2, 1e-300)))
        lam = np.array(
            [0.0 if x > 6 else ((1 - erf(x)) * -0.5 + exp(-x * x) / (2 * x * sqrt(pi))) for x in a]
        )
        g = 1.0 / (1.0 + lam)
    return np.where((cos_v > 0) & (cos_vm > 0), g, 0.0)


def _frame(nrm: NDArray) -> tuple[NDArray, NDArray]:
    """Two unit tangents perpendicular to each unit normal (rows)."""
    y = np.broadcast_to(np.array([0.0, 1.0, 0.0]), nrm.shape)
    t1 = np.cross(y, nrm)
    t1 /= np.linalg.norm(t1, axis=-1, keepdims=True)
    return t1, np.cross(nrm, t1)


def _perp(d: NDArray) -> NDArray:
    """A unit vector perpendicular to each row of `d`."""
    a = np.where(np.abs(d[:, [0]]) < 0.9, np.array([1.0, 0, 0]), np.array([0.0, 0, 1.0]))
    p = np.cross(d, a)
    return p / np.linalg.norm(p, axis=-1, keepdims=True)


@dataclass(frozen=True)
class Trace3D:
    """Escaped rays of one `trace3d`: unit directions `w_o` (toward a viewer) and the power each
    carries (unpolarised, a fraction of the power incident on one period), plus the number of
    bounces; `status` per ray as in `raytrace`."""

    w_o: NDArray
    power: NDArray
    n_bounces: NDArray
    status: NDArray

    @property
    def total(self) -> float:
        """Reflected power over incident power."""
        return float(np.sum(self.power))


def trace3d(
    st: Staircase,
    w_i: NDArray,
    n: complex,
    *,
    rough: Rough | None = None,
    n_rays: int = 200_000,
    max_bounces: int = 20,
    seed: int = 0,
) -> Trace3D:
    """Trace `n_rays` parallel rays arriving from the unit direction `w_i` (towards the light,
    face frame, `w_i . z > 0`) over one period of the extruded profile; see the module text."""
    rng = np.random.default_rng(seed)
    w_i = np.asarray(w_i, dtype=float) / np.linalg.norm(w_i)
    prim = st.primitives()
    L = st.period_um
    eps = 1e-12 * L
    x_top, z_top = st.top
    cell = (x_top, x_top + L)
    x0 = x_top + (np.arange(n_rays) + rng.uniform()) / n_rays * L
    p = np.stack([x0, np.full(n_rays, z_top)], axis=-1)
    d = np.tile(-w_i, (n_rays, 1))
    e1 = _perp(d).astype(complex)
    e2 = np.cross(d, e1.real).astype(complex)
    weight = np.ones(n_rays)
    status = np.zeros(n_rays, dtype=np.int8)
    bounces = np.zeros(n_rays, dtype=np.int64)
    self_seg = np.full(n_rays, -1, dtype=np.int64)
    self_arc = np.full(n_rays, -1, dtype=np.int64)
    n_arcs = len(prim.arc_radius)
    for bounce in range(max_bounces + 1):
        idx = np.flatnonzero(status == ACTIVE)
        if idx.size == 0:
            break
        dxz = d[idx][:, [0, 2]]
        c = np.linalg.norm(dxz, axis=-1)
        d2 = dxz / c[:, None]
        pa = p[idx]
        t_s, sh_s, j_s = _hit_segments(pa, d2, prim, L, cell, self_seg[idx], eps)
        if n_arcs:
            t_a, sh_a, j_a = _hit_arcs(pa, d2, prim, L, self_arc[idx], eps)
        else:
            t_a = np.full(idx.size, np.inf)
            sh_a = j_a = np.zeros(idx.size, dtype=np.int64)
        use_arc = t_a < t_s
        t = np.where(use_arc, t_a, t_s)
        shift = np.where(use_arc, sh_a, sh_s)
        miss = ~np.isfinite(t)
        status[idx[miss & (d2[:, 1] > 0)]] = ESCAPED
        status[idx[miss & (d2[:, 1] <= 0)]] = LOST
        hit = ~miss
        if bounce == max_bounces:
            status[idx[hit]] = TRAPPED
            break
        h = idx[hit]
        ua, th, sh = use_arc[hit], t[hit], shift[hit]
        q = pa[hit] + th[:, None] * d2[hit] - np.stack([sh * L, np.zeros(h.size)], axis=-1)
        js, ja = j_s[hit], j_a[hit]
        nrm2 = prim.seg_normal[js] if len(prim.seg_a) else np.zeros((h.size, 2))
        if n_arcs:
            radial = (q - prim.arc_centre[ja]) / prim.arc_radius[ja][:, None]
            nrm2 = np.where(ua[:, None], prim.arc_sigma[ja][:, None] * radial, nrm2)
        nrm = np.stack([nrm2[:, 0], np.zeros(h.size), nrm2[:, 1]], axis=-1)
        dh = d[h]
        wi_loc = -dh
        if rough is None:
            m = nrm
            est = np.ones(h.size)
        else:
            tan2 = _ndf_tan2(rng.uniform(size=h.size), rough)
            cos_m = 1.0 / np.sqrt(1.0 + tan2)
            sin_m = np.sqrt(1.0 - cos_m**2)
            phi = rng.uniform(0, 2 * np.pi, size=h.size)
            t1, t2 = _frame(nrm)
            m = (cos_m[:, None] * nrm + sin_m[:, None] * (np.cos(phi)[:, None] * t1
                 + np.sin(phi)[:, None] * t2))  # fmt: skip
        cos_im = np.einsum("ij,ij->i", wi_loc, m)
        d_new = dh + 2.0 * cos_im[:, None] * m
        if rough is not None:
            cos_in = np.einsum("ij,ij->i", wi_loc, nrm)
            cos_on = np.einsum("ij,ij->i", d_new, nrm)
            cos_mn = np.einsum("ij,ij->i", m, nrm)
            g = _g1(cos_in, cos_im, rough) * _g1(cos_on, cos_im, rough)
            est = np.where((cos_im > 0) & (cos_on > 0), g * cos_im / (cos_in * cos_mn), 0.0)
        # polarisation: split into this reflection's s and p
        s = np.cross(dh, m)
        s_norm = np.linalg.norm(s, axis=-1, keepdims=True)
        s = np.where(s_norm > 1e-12, s / np.maximum(s_norm, 1e-300), _perp(dh))
        p_in, p_out = np.cross(s, dh), np.cross(s, d_new)
        r_s, r_p = fresnel_amplitudes(np.abs(cos_im), n)
        for e in (e1, e2):
            es = np.einsum("ij,ij->i", e[h], s)
            ep = np.einsum("ij,ij->i", e[h], p_in)
            e[h] = (r_s * es)[:, None] * s + (r_p * ep)[:, None] * p_out
        weight[h] *= est
        dead = weight[h] <= 0
        status[h[dead]] = LOST + 1  # absorbed by the micro-surface (rough facets only)
        d[h] = d_new
        p[h] = q
        self_seg[h] = np.where(ua, -1, js)
        self_arc[h] = np.where(ua, ja, -1)
        bounces[h] += 1
    esc = status == ESCAPED
    power = 0.5 * (np.sum(np.abs(e1) ** 2, -1) + np.sum(np.abs(e2) ** 2, -1)) * weight / n_rays
    return Trace3D(w_o=d[esc], power=power[esc], n_bounces=bounces[esc], status=status)


def direction(theta_deg: float, out_of_plane_deg: float, light: bool = False) -> NDArray:
    """The unit vector whose projection onto (x, z) has the in-plane angle `theta_deg`
    [conventions §1] and which leaves that plane by `out_of_plane_deg` towards +y; `light`: a
    direction towards the light (`x = -sin theta`)."""
    th, ps = np.deg2rad(theta_deg), np.deg2rad(out_of_plane_deg)
    sign = -1.0 if light else 1.0
    return np.array([sign * np.cos(ps) * np.sin(th), np.sin(ps), np.cos(ps) * np.cos(th)])
