"""Scenes for Mitsuba 3: the photographed specimen from a photo's camera pose and lamp, or a
user's printed object; their rendering (docs/render.md).

Units: millimetres; every rendered pixel is a radiance divided by the lamp's reference
irradiance `E_ref` (the irradiance normal to the beam at the scene's reference distance, the
distance the fit's `scale` refers to; 1 for a distant light): 1/sr, so that the fit's `scale`
times a pixel is the photos' relative radiance [conventions §9, §11].

The specimen: each wedge a solid whose stepped face is its `face_mm` outline lifted onto the
face's mean plane (docs/scene.md) with the fitted material at its wedge angle (an RGL table,
`write_bsdf`), texture coordinates `u` along the layer lines (-y) and `v` uphill; its walls and
the plate diffuse (the fit does not know them: the walls take the body's albedo, the plate
`plate_albedo`); the markers on white paper (one cell of quiet zone, albedos 0.8 and 0.03); the
lamp a sphere of the scene's diameter emitting uniformly.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
from numpy.typing import NDArray

from stairfit.errors import UserError

from ._mesh import Mesh

if TYPE_CHECKING:
    from stairfit.imaging import CameraPose
    from stairfit.scene import Photo, Scene

MitsubaDict = dict[str, object]
"""A Mitsuba scene description (what `mi.load_dict` takes): plugin fields and nested dicts."""

PAPER_ALBEDO = 0.8
INK_ALBEDO = 0.03


class Camera(NamedTuple):
    """A pinhole: `rotation` rows (image right, image down, forward) in the base frame,
    `centre` (mm), `focal_px`, principal point `(cx, cy)` (pixel centres at integers), image
    `width` x `height`."""

    rotation: NDArray
    centre: NDArray
    focal_px: float
    principal: tuple[float, float]
    width: int
    height: int

    def scaled(self, factor: int) -> Camera:
        """The same camera with pixels `factor` times larger (each new pixel a block)."""
        cx, cy = self.principal
        return self._replace(
            focal_px=self.focal_px / factor,
            principal=((cx + 0.5) / factor - 0.5, (cy + 0.5) / factor - 0.5),
            width=self.width // factor,
            height=self.height // factor,
        )

    def project(self, points: NDArray) -> NDArray:
        """(n, 3) points to (n, 2) pixels."""
        p = (np.asarray(points, float) - self.centre) @ self.rotation.T
        return np.stack([self.focal_px * p[:, 0] / p[:, 2] + self.principal[0],
                         self.focal_px * p[:, 1] / p[:, 2] + self.principal[1]], -1)  # fmt: skip


class Lamp(NamedTuple):
    """A lamp: its centre (mm, None for a distant light), the direction towards it (unit, for
    a distant light), its diameter (mm) and the reference distance of `E_ref` (mm)."""

    position: NDArray | None
    direction: NDArray
    diameter_mm: float
    reference_mm: float


def camera_from_pose(pose: CameraPose, width: int, height: int) -> Camera:
    """A `Camera` from `stairfit.imaging.CameraPose` (pinhole) of a `width` x `height` photo."""
    import cv2

    rot, _ = cv2.Rodrigues(np.asarray(pose.rvec, float))
    k = np.asarray(pose.camera_matrix, float)
    return Camera(rot, -rot.T @ np.asarray(pose.tvec, float).reshape(3), float(k[0, 0]),
                  (float(k[0, 2]), float(k[1, 2])), width, height)  # fmt: skip


def scene_lamp(scene: Scene, photo: Photo) -> Lamp:
    """The photo's lamp from the scene (docs/scene.md "A near lamp"): its position and size, or
    a distant light along `light_deg` [conventions §1]."""
    from stairfit.lab import reference_distance_mm

    pos = scene.lamp_position_mm(photo)
    a = math.radians(photo.light_deg or 0.0)
    direction = np.array([-math.sin(a), 0.0, math.cos(a)])
    if pos is None:
        return Lamp(None, direction, 0.0, 1.0)
    pos = np.asarray(pos, float)
    ref = reference_distance_mm(scene)
    diameter = scene.light.diameter_mm
    if diameter is None:  # an angular size seen from the origin, else a small ball
        ang = math.radians(scene.light.angular_diameter_deg or 0.0)
        diameter = 2.0 * np.linalg.norm(pos) * math.tan(ang / 2.0) if ang > 0 else 1.0
    return Lamp(pos, pos / np.linalg.norm(pos), float(diameter), ref)


# --- the specimen's geometry -----------------------------------------------------------------


def wedge_solid(outline_mm: Sequence[Sequence[float]], beta2_deg: float) -> tuple[Mesh, Mesh]:
    """A wedge standing on the base: (its face, its walls and bottom). The face is the base
    outline lifted onto the plane `z = (x - x_min) tan(beta2)` (docs/scene.md), two triangles
    with texture coordinates `u = -y` (along the layer lines) and `v` the distance uphill; the
    walls join the face's edges to the base."""
    base = np.asarray(outline_mm, float)
    if base.shape != (4, 2):
        raise UserError("a wedge's face_mm must have 4 corners to be rendered as a solid")
    tan = math.tan(math.radians(beta2_deg))
    x0 = base[:, 0].min()
    top = np.column_stack([base, (base[:, 0] - x0) * tan])
    area = 0.5 * np.sum(base[:, 0] * np.roll(base[:, 1], -1) - np.roll(base[:, 0], -1) * base[:, 1])
    order = [0, 1, 2, 3] if area > 0 else [0, 3, 2, 1]  # counter-clockwise seen from above
    top = top[order]
    b = math.radians(beta2_deg)
    normal = np.array([-math.sin(b), 0.0, math.cos(b)])
    uv = np.column_stack([-top[:, 1], (top[:, 0] - x0) / math.cos(b)])
    face = Mesh(top, np.array([[0, 1, 2], [0, 2, 3]]), np.tile(normal, (4, 1)), uv)
    walls_v, walls_f, walls_n = [], [], []
    for i in range(4):
        j = (i + 1) % 4
        quad = np.array([top[i], top[j], [*top[j][:2], 0.0], [*top[i][:2], 0.0]])
        edge = quad[1] - quad[0]
        n = np.cross([0.0, 0.0, 1.0], edge)  # outwards for a counter-clockwise outline
        if np.linalg.norm(n) < 1e-12 or (quad[0][2] < 1e-9 and quad[1][2] < 1e-9):
            continue
        n = -n / np.linalg.norm(n)
        start = len(walls_v) * 4
        walls_v.append(quad)
        walls_n.append(np.tile(n, (4, 1)))
        walls_f += [[start, start + 2, start + 1], [start, start + 3, start + 2]]
    bottom = np.array([[*p[:2], 0.0] for p in top])
    start = len(walls_v) * 4
    walls_v.append(bottom)
    walls_n.append(np.tile([0.0, 0.0, -1.0], (4, 1)))
    walls_f += [[start, start + 2, start + 1], [start, start + 3, start + 2]]
    walls = Mesh(np.concatenate(walls_v), np.asarray(walls_f), np.concatenate(walls_n))
    return face, walls


def marker_quads(scene: Scene) -> list[tuple[NDArray, NDArray]]:
    """Each marker as (corners (4, 3) of its paper, 2 um above the base, counter-clockwise
    from above; its image, albedo (n, n)): the ArUco pattern of `[markers]` with one cell of
    white quiet zone around the black square's `corners_mm` (ArUco order: the printed image's
    top-left, top-right, bottom-right, bottom-left)."""
    import cv2

    if scene.markers is None:
        return []
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, scene.markers.dictionary))
    out = []
    for m in scene.markers.markers:
        c = np.asarray(m.corners_mm, float)
        cells = dictionary.markerSize + 2
        img = cv2.aruco.generateImageMarker(dictionary, m.id, cells, borderBits=1)
        pad = np.full((cells + 2, cells + 2), 255, np.uint8)
        pad[1:-1, 1:-1] = img
        albedo = np.where(pad < 128, INK_ALBEDO, PAPER_ALBEDO)
        # grow the square by one cell on every side (bilinear in the corners)
        centre = c.mean(axis=0)
        grown = centre + (c - centre) * (cells + 2) / cells
        out.append((np.column_stack([grown, np.full(4, 0.002)]), albedo))
    return out


# --- Mitsuba -----------------------------------------------------------------------------------


def mitsuba(variant: str = "scalar_rgb", threads: int | None = None) -> ModuleType:
    """Mitsuba with `variant` selected; UserError when it is not installed."""
    try:
        import drjit as dr
        import mitsuba as mi
    except ImportError:
        raise UserError(
            "rendering needs Mitsuba 3: install the render extra (pip install -e \".[render]\" "
            "or pip install mitsuba)"
        ) from None
    if mi.variant() != variant:
        mi.set_variant(variant)
        mi.set_log_level(mi.LogLevel.Error)
    if threads is not None and dr.thread_count() != threads:
        dr.set_thread_count(threads)
    return mi


def mitsuba_mesh(mi: ModuleType, name: str, mesh: Mesh, bsdf: MitsubaDict) -> object:
    """A Mitsuba mesh of our arrays (vertex normals, and texture coordinates if any)."""
    props = mi.Properties()
    props["bsdf"] = mi.load_dict(bsdf)
    has_uv = mesh.uvs is not None
    out = mi.Mesh(name, len(mesh.vertices), len(mesh.faces), props, has_vertex_normals=True,
                  has_vertex_texcoords=has_uv)  # fmt: skip
    params = mi.traverse(out)
    params["vertex_positions"] = np.asarray(mesh.vertices, np.float32).ravel()
    params["faces"] = np.asarray(mesh.faces, np.uint32).ravel()
    params["vertex_normals"] = np.asarray(mesh.normals, np.float32).ravel()
    if has_uv:
        params["vertex_texcoords"] = np.asarray(mesh.uvs, np.float32).ravel()
    if mesh.weights is not None:
        out.add_attribute("vertex_weight", 1, np.asarray(mesh.weights, np.float32).ravel())
    params.update()
    return out


def blend(first: MitsubaDict, second: MitsubaDict) -> MitsubaDict:
    """Two BSDFs blended by the mesh's per-vertex `weight` (0: the first, 1: the second)."""
    return {"type": "blendbsdf", "weight": {"type": "mesh_attribute", "name": "vertex_weight"},
            "bsdf_0": first, "bsdf_1": second}  # fmt: skip


def diffuse(albedo: float | NDArray, mi: ModuleType | None = None) -> MitsubaDict:
    """A Lambertian BSDF: a grey albedo, or an (n, m) albedo image (linear, nearest texels)."""
    if np.ndim(albedo) == 0:
        return {"type": "diffuse", "reflectance": {"type": "rgb", "value": [float(albedo)] * 3}}
    img = np.repeat(np.asarray(albedo, np.float32)[..., None], 3, axis=-1)
    tex = {"type": "bitmap", "bitmap": mi.Bitmap(img), "filter_type": "nearest", "raw": True,
           "wrap_mode": "clamp"}  # fmt: skip
    return {"type": "diffuse", "reflectance": tex}


def lamp_shapes(lamp: Lamp) -> MitsubaDict:
    """The lamp: a sphere of `diameter_mm` whose radiance gives the irradiance 1 (normal to the
    beam) at the reference distance, `1 / (pi (r / d_ref)^2)`; a distant light, a directional
    emitter of irradiance 1."""
    if lamp.position is None:
        return {"lamp": {"type": "directional", "direction": (-lamp.direction).tolist(),
                         "irradiance": {"type": "rgb", "value": [1.0, 1.0, 1.0]}}}  # fmt: skip
    r = lamp.diameter_mm / 2.0
    radiance = 1.0 / (math.pi * (r / lamp.reference_mm) ** 2)
    return {"lamp": {
        "type": "sphere", "center": lamp.position.tolist(), "radius": r,
        "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.0] * 3}},
        "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [radiance] * 3}},
    }}  # fmt: skip


def quad_mesh(corners: NDArray, up: NDArray | None = None) -> Mesh:
    """A flat quad (4, 3) with texture coordinates (0, 0), (1, 0), (1, 1), (0, 1) at its
    corners (texel rows run from the first edge), facing `up` (its triangles wound so that
    their normal has a positive component along it) or the side its corners' order gives."""
    a, b, c = corners[0], corners[1], corners[2]
    n = np.cross(b - a, c - a)
    n = n / np.linalg.norm(n)
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    if up is not None and n @ np.asarray(up, float) < 0.0:
        n, faces = -n, faces[:, ::-1]
    uv = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    return Mesh(np.asarray(corners, float), faces, np.tile(n, (4, 1)), uv)


def sensor(mi: ModuleType, cam: Camera, spp: int, seed: int = 0) -> object:
    """Mitsuba's perspective sensor for our pinhole (box-filtered pixels). Mitsuba's camera
    looks along its +z with +x to the image's left and +y up; a ray through the film position
    `p` (in film widths and heights, pixel edges at integers) leaves as if through `p + offset`,
    so the principal point `(c + 0.5) / size` takes the offset `0.5 - (c + 0.5) / size`."""
    right, down, forward = cam.rotation
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = -right, -down, forward, cam.centre
    cx, cy = cam.principal
    return mi.load_dict({
        "type": "perspective",
        "fov": 2.0 * math.degrees(math.atan(cam.width / 2.0 / cam.focal_px)),
        "fov_axis": "x",
        "principal_point_offset_x": 0.5 - (cx + 0.5) / cam.width,
        "principal_point_offset_y": 0.5 - (cy + 0.5) / cam.height,
        "near_clip": 1.0,
        "far_clip": 1e6,
        "to_world": mi.ScalarTransform4f(m.tolist()),
        "film": {"type": "hdrfilm", "width": cam.width, "height": cam.height,
                 "pixel_format": "rgb", "component_format": "float32",
                 "rfilter": {"type": "box"}},
        "sampler": {"type": "independent", "sample_count": spp, "seed": seed},
    })  # fmt: skip


def render(mi: ModuleType, shapes: MitsubaDict, cam: Camera, spp: int, max_depth: int,
           seed: int = 0, hide_emitters: bool = False) -> NDArray:  # fmt: skip
    """`(H, W, 3)` float64: the path tracer's image of `shapes` through `cam` (with
    `hide_emitters`, the emitters themselves, a sky, are black where seen directly)."""
    integrator = {"type": "path", "max_depth": max_depth, "hide_emitters": hide_emitters}
    scene = mi.load_dict({"type": "scene", "integrator": integrator, **shapes})
    img = mi.render(scene, sensor=sensor(mi, cam, spp, seed), spp=spp, seed=seed)
    return np.array(img, dtype=np.float64)


def measured(path: Path) -> MitsubaDict:
    """Mitsuba's `measured` BSDF of an RGL file."""
    return {"type": "measured", "filename": str(path)}
