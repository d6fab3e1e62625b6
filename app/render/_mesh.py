"""Triangle meshes for rendering: a minimal Wavefront OBJ reader, vertex normals, and the
per-triangle staircase frame of a printed object (docs/render.md, "Your own object").

Each triangle of a printed object carries the staircase of its own wedge angle, the angle of its
normal from the build axis (`face_frame`); the wedge angles are grouped into bins, one RGL table
per bin, and each bin's triangles get texture coordinates whose `u` runs along the layer lines
and `v` uphill, which is how Mitsuba orients an anisotropic material (its shading frame's `s`
is `dp/du`).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from stairfit.errors import UserError

from ._material import BETA2_LIMITS_DEG, face_frame

MAX_OBJ_BYTES = 200 * 2**20
"""A larger OBJ file is refused (a render of it would not finish in minutes anyway)."""


class Mesh(NamedTuple):
    """Triangles: `vertices` (V, 3), `faces` (F, 3) vertex indices (counter-clockwise seen from
    outside), unit vertex `normals` (V, 3), optional `uvs` (V, 2) and `weights` (V,) (a
    per-vertex blend between two materials)."""

    vertices: NDArray
    faces: NDArray
    normals: NDArray
    uvs: NDArray | None = None
    weights: NDArray | None = None


def read_obj(path: str | Path) -> Mesh:
    """The triangles of an OBJ file (`v`, `vn`, `f` with any of the `v`, `v/vt`, `v//vn`,
    `v/vt/vn` forms; polygons fanned into triangles). Normals: the file's, else the
    area-weighted mean of the faces around each vertex. UserError naming the line for what it
    cannot read."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: no such file; give a Wavefront OBJ mesh (--mesh)")
    if path.stat().st_size > MAX_OBJ_BYTES:
        raise UserError(f"{path}: larger than {MAX_OBJ_BYTES >> 20} MB; give a smaller mesh")
    verts: list[list[float]] = []
    norms: list[list[float]] = []
    tris: list[tuple[int, int, int]] = []
    tri_norms: list[tuple[int, int, int] | None] = []
    text = path.read_text(encoding="utf-8", errors="replace")
    for k, line in enumerate(text.splitlines(), start=1):
        parts = line.split()
        if not parts or parts[0].startswith("#"):
            continue
        try:
            if parts[0] == "v":
                verts.append([float(x) for x in parts[1:4]])
            elif parts[0] == "vn":
                norms.append([float(x) for x in parts[1:4]])
            elif parts[0] == "f":
                idx = [_obj_index(p.split("/")[0], len(verts)) for p in parts[1:]]
                nidx = [p.split("/")[2] if p.count("/") == 2 and p.split("/")[2] else None
                        for p in parts[1:]]  # fmt: skip
                for j in range(1, len(idx) - 1):
                    tris.append((idx[0], idx[j], idx[j + 1]))
                    ns = (nidx[0], nidx[j], nidx[j + 1])
                    tri_norms.append(None if None in ns else
                                     tuple(_obj_index(n, len(norms)) for n in ns))  # fmt: skip
        except (ValueError, IndexError):
            raise UserError(f"{path}: line {k}: cannot read {line.strip()[:60]!r}") from None
    if not tris:
        raise UserError(f"{path}: no faces ('f' lines); give a triangle or polygon mesh")
    v = np.asarray(verts, float)
    f = np.asarray(tris, np.int64)
    if f.min() < 0 or f.max() >= len(v):
        raise UserError(f"{path}: a face refers to a vertex that is not there")
    if norms and all(t is not None for t in tri_norms):  # one normal per corner: split vertices
        n = np.asarray(norms, float)[np.asarray(tri_norms, np.int64)].reshape(-1, 3)
        v = v[f].reshape(-1, 3)
        f = np.arange(len(v)).reshape(-1, 3)
    else:
        n = vertex_normals(v, f)
    n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    return Mesh(v, f, n)


def _obj_index(token: str, count: int) -> int:
    i = int(token)
    return i - 1 if i > 0 else count + i


def face_normals(vertices: NDArray, faces: NDArray) -> NDArray:
    """Unit geometric normals (F, 3) of counter-clockwise triangles."""
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    n = np.cross(b - a, c - a)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


def vertex_normals(vertices: NDArray, faces: NDArray) -> NDArray:
    """Area-weighted mean of the faces' normals around each vertex (V, 3)."""
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    area_n = np.cross(b - a, c - a)
    out = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(out, faces[:, k], area_n)
    return out / np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-300)


def wedge_nodes(step_deg: float) -> NDArray:
    """Wedge angles (deg) at which the material is tabulated, evenly spaced over
    `BETA2_LIMITS_DEG` at most `step_deg` apart."""
    lo, hi = BETA2_LIMITS_DEG
    count = max(2, math.ceil((hi - lo) / step_deg - 1e-9) + 1)
    return np.linspace(lo, hi, count)


def printed_parts(
    mesh: Mesh, build_axis: NDArray, step_deg: float
) -> tuple[NDArray, list[tuple[int, Mesh]]]:
    """The wedge-angle nodes (`wedge_nodes`) and the mesh split by the interval between two
    nodes that each triangle's wedge angle (`face_frame` of its geometric normal and
    `build_axis`) falls in: `(k, part)` for the interval `[nodes[k], nodes[k + 1]]`. Each part
    has its own vertices, texture coordinates `u = p . s`, `v = p . t` (`s = -y` of the
    triangle's face frame, along the layer lines; `t = n x s` its uphill x; mm) and per-vertex
    `weights`, the position of the vertex normal's wedge angle in the interval (0 at
    `nodes[k]`, 1 at `nodes[k + 1]`): the renderer blends the two nodes' tables by it, so that
    the staircase changes smoothly over a curved surface."""
    normals = face_normals(mesh.vertices, mesh.faces)
    beta2, rot = face_frame(normals, build_axis)
    nodes = wedge_nodes(step_deg)
    which = np.clip(np.searchsorted(nodes, beta2) - 1, 0, len(nodes) - 2)
    vertex_beta2, _ = face_frame(mesh.normals, build_axis)
    parts = []
    for k in range(len(nodes) - 1):
        sel = np.nonzero(which == k)[0]
        if sel.size == 0:
            continue
        corners = mesh.faces[sel]  # (m, 3)
        pts = mesh.vertices[corners]  # (m, 3, 3)
        s_dir = -rot[sel, 1, :]
        t_dir = rot[sel, 0, :]
        uv = np.stack([np.einsum("mkj,mj->mk", pts, s_dir),
                       np.einsum("mkj,mj->mk", pts, t_dir)], axis=-1)  # fmt: skip
        w = (vertex_beta2[corners] - nodes[k]) / (nodes[k + 1] - nodes[k])
        parts.append((k, Mesh(
            vertices=pts.reshape(-1, 3), faces=np.arange(3 * sel.size).reshape(-1, 3),
            normals=mesh.normals[corners].reshape(-1, 3), uvs=uv.reshape(-1, 2),
            weights=np.clip(w, 0.0, 1.0).reshape(-1),
        )))  # fmt: skip
    return nodes, parts


def bounding_sphere(mesh: Mesh) -> tuple[NDArray, float]:
    """Centre and radius of a sphere around the mesh (the box's centre and half diagonal)."""
    lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    return 0.5 * (lo + hi), float(0.5 * np.linalg.norm(hi - lo))


def uv_sphere(radius: float = 10.0, rings: int = 24, segments: int = 48) -> Mesh:
    """A UV sphere centred on the origin (z up): the printed test object (tests/data)."""
    verts = [[0.0, 0.0, radius]]
    for i in range(1, rings):
        th = math.pi * i / rings
        for j in range(segments):
            ph = 2.0 * math.pi * j / segments
            verts.append([radius * math.sin(th) * math.cos(ph),
                          radius * math.sin(th) * math.sin(ph), radius * math.cos(th)])  # fmt: skip
    verts.append([0.0, 0.0, -radius])
    faces = []
    last = len(verts) - 1
    for j in range(segments):
        faces.append((0, 1 + j, 1 + (j + 1) % segments))
    for i in range(rings - 2):
        a, b = 1 + i * segments, 1 + (i + 1) * segments
        for j in range(segments):
            j1 = (j + 1) % segments
            faces += [(a + j, b + j, b + j1), (a + j, b + j1, a + j1)]
    base = 1 + (rings - 2) * segments
    for j in range(segments):
        faces.append((base + j, last, base + (j + 1) % segments))
    v = np.asarray(verts)
    return Mesh(v, np.asarray(faces, np.int64), v / radius)


def write_obj(path: str | Path, mesh: Mesh) -> None:
    """The mesh as an OBJ file (positions, normals, faces `v//vn`)."""
    lines = [f"v {x:.6g} {y:.6g} {z:.6g}" for x, y, z in mesh.vertices]
    lines += [f"vn {x:.6g} {y:.6g} {z:.6g}" for x, y, z in mesh.normals]
    lines += [f"f {a + 1}//{a + 1} {b + 1}//{b + 1} {c + 1}//{c + 1}" for a, b, c in mesh.faces]
    Path(path).write_text("\n".join(lines) + "\n", encoding="utf-8")
