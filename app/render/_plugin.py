"""A Mitsuba 3 BSDF plugin, `"type": "stairfit_staircase"`: the staircase's reflectance for any
pair of directions, evaluated by the model itself (`density`), sampled by `Mixture`.

Parameters (docs/render.md, "The Python plugin"): `fit` (a fit folder, read with `read_fit`;
`photos` its photo folder when not the sibling), or the material itself: `kernel` ("gaussian",
"ggx", "beckmann"), `width_deg` (sigma or the roughness angle, `alpha = tan(width)`) or
`alpha`, `edge_radius_um`, `layer_um`, `index` (one for every channel) or `index_r`,
`index_g`, `index_b`, `body_albedo`. Orientation: `build_axis` (a world vector, "x y z" or
three numbers; each point's wedge angle and layer lines from its shading normal), else the layer
lines follow the surface's tangent `u` (the shading frame's `s`), uphill along `t = n x s`, at
`wedge_deg`.

Mitsuba's conventions: `si.wi` points to where the path came from (the camera in its radiance
mode), `wo` to the light; `eval` is the BRDF for light from `wo` seen from `wi` times the cosine
of `wo`, i.e. `p(wo -> wi) (wo . n) / (wi . n)` [conventions §11]; in the importance mode
(light tracing) the roles swap. Every method takes Mitsuba's scalar values or its JIT arrays
(evaluated, not recorded: Python's model runs on NumPy/JAX arrays), so it is slow per ray in the
scalar variants: for renders, `stairfit render` writes `.bsdf` tables for the C++ `measured`
plugin instead (docs/render.md).
"""

from __future__ import annotations

import functools
import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ._material import Material, density, face_frame
from ._rgl import to_face
from ._sampling import Mixture

PLUGIN_NAME = "stairfit_staircase"


def _float(props: Any, name: str, default: float | None = None) -> float | None:
    return float(props.get(name)) if name in props else default


def material_from_props(props: Any) -> Material:
    """The plugin's material from its parameters (see the module's docstring)."""
    if "fit" in props:
        from ._fit import read_fit

        photos = props.get("photos") if "photos" in props else None
        return read_fit(str(props.get("fit")), photos).material
    kernel = str(props.get("kernel")) if "kernel" in props else "ggx"
    if "alpha" in props:
        width = math.atan(float(props.get("alpha")))
    else:
        width = math.radians(_float(props, "width_deg", 3.6))
    if "index" in props:
        index = (float(props.get("index")),) * 3
    else:
        index = tuple(_float(props, f"index_{c}", 1.5) for c in "rgb")
    return Material(
        kernel=kernel,
        widths=((0.0, width),),
        edge_radius_um=_float(props, "edge_radius_um", 0.0),
        layer_um=_float(props, "layer_um", 150.0),
        index=index,
        body_albedo=_float(props, "body_albedo", 0.0),
        source="Given as plugin parameters.",
    ).check()


def _vector(value: Any) -> NDArray:
    if isinstance(value, str):
        value = [float(x) for x in value.replace(",", " ").split()]
    v = np.asarray(list(value), float).reshape(3)
    return v / np.linalg.norm(v)


def _rows(v: Any) -> NDArray:
    """A Mitsuba 3-vector (scalar or JIT array) as `(N, 3)`."""
    a = np.array(v, dtype=float)
    return a[None, :] if a.ndim == 1 else a.T


def _scalars(v: Any) -> NDArray:
    a = np.array(v, dtype=float)
    return a.reshape(-1)


class _Query:
    """One call's directions in the face frame, the wedge angle and the frame's rotation."""

    def __init__(self, bsdf: Any, si: Any, wo: Any | None = None):
        wi = _rows(si.wi)
        if bsdf.build_axis is None:
            self.beta2 = np.full(wi.shape[0], bsdf.wedge_deg)
            self.rot = None
        else:
            b = _rows(si.to_local(bsdf.mi.Vector3f(*bsdf.build_axis)))
            normal = np.zeros_like(b)
            normal[:, 2] = 1.0
            self.beta2, self.rot = face_frame(normal, b)
        self.wi = self.to_face(wi)
        self.wo = None if wo is None else self.to_face(_rows(wo))

    def to_face(self, v: NDArray) -> NDArray:
        if self.rot is None:
            return to_face(v)
        return np.einsum("nij,nj->ni", self.rot, v)

    def to_local(self, v: NDArray) -> NDArray:
        if self.rot is None:
            return np.stack([-v[:, 1], v[:, 0], v[:, 2]], axis=-1)
        return np.einsum("nji,nj->ni", self.rot, v)


def plugin_value(material: Material, q: _Query, importance: bool) -> NDArray:
    """Mitsuba's `eval` `(N, 3)` for the query's directions (see the module's docstring)."""
    light, view = (q.wi, q.wo) if importance else (q.wo, q.wi)
    p = density(material, q.beta2, light, view)
    up = (q.wi[:, 2] > 0.0) & (q.wo[:, 2] > 0.0)
    if importance:
        return np.where(up[:, None], p, 0.0)
    ratio = np.where(up, q.wo[:, 2] / np.where(up, q.wi[:, 2], 1.0), 0.0)
    return p * ratio[:, None]


def plugin_pdf(material: Material, q: _Query, importance: bool) -> NDArray:
    """The sampling density (1/sr) of `q.wo` given `q.wi` (see `Mixture`)."""
    draw = "view" if importance else "light"
    return Mixture(material, q.beta2, q.wi, draw).pdf(q.wo)


@functools.cache
def _bsdf_class(variant: str) -> type:
    """The plugin's class for one Mitsuba variant (a subclass of that variant's `BSDF`)."""
    import mitsuba as mi

    class StaircaseBSDF(mi.BSDF):
        """The fitted staircase (see stairfit.render._plugin)."""

        def __init__(self, props: Any) -> None:
            mi.BSDF.__init__(self, props)
            self.mi = mi
            self.material = material_from_props(props)
            axis = props.get("build_axis") if "build_axis" in props else None
            self.build_axis = None if axis is None else _vector(axis)
            self.wedge_deg = _float(props, "wedge_deg", 45.0)
            flags = mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.FrontSide
            self.m_components = [flags]
            self.m_flags = flags

        def _color(self, rows: NDArray) -> Any:
            if rows.shape[0] == 1 and not mi.variant().startswith(("llvm", "cuda")):
                return mi.Color3f(*[float(x) for x in rows[0]])
            return mi.Color3f(*(mi.Float(np.ascontiguousarray(rows[:, k])) for k in range(3)))

        def _float_out(self, values: NDArray) -> Any:
            if values.shape[0] == 1 and not mi.variant().startswith(("llvm", "cuda")):
                return float(values[0])
            return mi.Float(np.ascontiguousarray(values))

        def eval(self, ctx: Any, si: Any, wo: Any, active: Any = True) -> Any:
            importance = ctx.mode == mi.TransportMode.Importance
            q = _Query(self, si, wo)
            return self._color(plugin_value(self.material, q, importance))

        def pdf(self, ctx: Any, si: Any, wo: Any, active: Any = True) -> Any:
            importance = ctx.mode == mi.TransportMode.Importance
            return self._float_out(plugin_pdf(self.material, _Query(self, si, wo), importance))

        def eval_pdf(self, ctx: Any, si: Any, wo: Any, active: Any = True) -> Any:
            importance = ctx.mode == mi.TransportMode.Importance
            q = _Query(self, si, wo)
            value = plugin_value(self.material, q, importance)
            return self._color(value), self._float_out(plugin_pdf(self.material, q, importance))

        def sample(self, ctx: Any, si: Any, sample1: Any, sample2: Any, active: Any = True) -> Any:
            importance = ctx.mode == mi.TransportMode.Importance
            q = _Query(self, si)
            u1 = _scalars(sample1)
            u2 = _rows(sample2)[:, :2]
            draw = "view" if importance else "light"
            wo, pdf = Mixture(self.material, q.beta2, q.wi, draw).sample(u1, u2)
            q.wo = wo
            value = plugin_value(self.material, q, importance)
            weight = np.where((pdf > 0.0)[:, None], value / np.where(pdf > 0, pdf, 1.0)[:, None],
                              0.0)  # fmt: skip
            local = q.to_local(wo)
            bs = mi.BSDFSample3f()
            if local.shape[0] == 1 and not mi.variant().startswith(("llvm", "cuda")):
                bs.wo = mi.Vector3f(*[float(x) for x in local[0]])
            else:
                bs.wo = mi.Vector3f(*(mi.Float(np.ascontiguousarray(local[:, k]))
                                      for k in range(3)))  # fmt: skip
            bs.pdf = self._float_out(pdf)
            bs.eta = 1.0
            bs.sampled_type = mi.UInt32(int(mi.BSDFFlags.GlossyReflection))
            bs.sampled_component = mi.UInt32(0)
            return bs, self._color(weight)

        def traverse(self, callback: Any) -> None:
            return None

        def parameters_changed(self, keys: Any) -> None:
            return None

        def to_string(self) -> str:
            return f"StaircaseBSDF[{self.material}]"

    return StaircaseBSDF


def register_bsdf() -> str:
    """Register `"type": "stairfit_staircase"` with Mitsuba for its current variant (set one
    first, `mitsuba.set_variant`); return the plugin's name. Registering again is harmless."""
    import mitsuba as mi

    variant = mi.variant()
    if variant is None:
        raise RuntimeError("set a Mitsuba variant first (mitsuba.set_variant('scalar_rgb'))")
    cls = _bsdf_class(variant)
    mi.register_bsdf(PLUGIN_NAME, lambda props: cls(props))
    return PLUGIN_NAME
