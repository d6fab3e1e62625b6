"""`stairfit render`'s work: the fitted material on the photographed specimen from every
photographed view, or on a user's printed object (docs/render.md).

Everything is written into a folder (`FITDIR/renders`) that the command stages and moves into
place when complete: `materials/*.bsdf` (the RGL tables, one per wedge angle, for any renderer
that reads them), per view `NAME_render.exr` (float, the photos' relative radiance) and
`NAME_render.png`, `NAME_photo.png` (the photo developed the same way) and `renders.json` (the
views, the files, each face's mean in photo and render, the settings and timings).
"""

from __future__ import annotations

import json
import math
import shutil
import time
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
from numpy.typing import NDArray

from stairfit.errors import UserError

from . import _scene as sc
from ._fit import FitFolder
from ._material import Material
from ._mesh import bounding_sphere, printed_parts, read_obj
from ._rgl import DEFAULT_RESOLUTION, Resolution, description, write_bsdf
from ._tensorfile import read_tensor_file

if TYPE_CHECKING:
    from stairfit._jsontypes import Record
    from stairfit.imaging import RawFrame
    from stairfit.scene import Scene

Progress = Callable[[str], None]


class RenderOptions(NamedTuple):
    """How to render (docs/render.md, "Options").

    Attributes:
        downscale: the specimen's renders group the photos' colour pixels (each 2 x 2 raw
            pixels) in blocks of this many a side (1: the colour pixels themselves).
        spp: samples per pixel.
        max_depth: the path tracer's longest path (3: the lamp's light after one more bounce,
            off the plate or a neighbouring wedge).
        plate_albedo: the plate's Lambertian albedo (the fit does not measure it).
        resolution: the RGL tables' sizes.
        threads: Mitsuba's threads (None: all cores).
        seed: the samplers' seed.
        views: the photos to render (empty: all).
        size: a mesh render's width and height (px).
        step_deg: a mesh's wedge angles are grouped in bins this wide, one table each.
    """

    downscale: int = 2
    spp: int = 16
    max_depth: int = 3
    plate_albedo: float = 0.03
    resolution: Resolution = DEFAULT_RESOLUTION
    threads: int | None = None
    seed: int = 0
    views: tuple[str, ...] = ()
    size: int = 512
    step_deg: float = 10.0


DEFAULT_OPTIONS = RenderOptions()
"""`stairfit render`'s defaults."""


# --- materials ---------------------------------------------------------------------------------


def material_tables(
    material: Material,
    angles: list[float],
    folder: Path,
    resolution: Resolution,
    progress: Progress,
    reuse: Path | None = None,
) -> dict[float, Path]:
    """One RGL table per wedge angle, `folder/wedge_ANGLE.bsdf`; a table of the same
    description (material, angle and resolution) in `reuse` is copied instead of computed."""
    folder.mkdir(parents=True, exist_ok=True)
    out = {}
    for k, angle in enumerate(angles):
        name = f"wedge_{angle:.4g}deg.bsdf"
        path = folder / name
        want = description(material, angle, resolution)
        old = None if reuse is None else reuse / name
        if old is not None and old.is_file() and _description(old) == want:
            shutil.copyfile(old, path)
            progress(f"material {k + 1}/{len(angles)}: {angle:.4g} deg, reused {name}")
        else:
            t0 = time.perf_counter()
            write_bsdf(path, material, angle, resolution)
            progress(f"material {k + 1}/{len(angles)}: {angle:.4g} deg tabulated in "
                     f"{time.perf_counter() - t0:.1f} s")  # fmt: skip
        out[angle] = path
    return out


def _description(path: Path) -> str | None:
    try:
        return bytes(read_tensor_file(path)["description"]).decode("utf8")
    except (OSError, ValueError, KeyError):
        return None


# --- images ------------------------------------------------------------------------------------


def develop(frame: RawFrame, scale: float) -> NDArray:
    """A photo as `(H/2, W/2, 3)` relative radiance (docs/imaging.md §Units, without the flat
    field): each 2 x 2 block of the colour mosaic one pixel (its red, the mean of its greens,
    its blue), `(DN - black) * scale`; a linear (demosaiced) file is averaged in 2 x 2 blocks."""
    data = np.asarray(frame.data, float)
    h, w = (data.shape[0] // 2) * 2, (data.shape[1] // 2) * 2
    if frame.cfa is None:
        img = (data[:h, :w] - np.asarray(frame.black, float)) * scale
        return img.reshape(h // 2, 2, w // 2, 2, 3).mean(axis=(1, 3))
    cfa = np.asarray(frame.cfa)
    black = np.asarray(frame.black, float)
    out = np.zeros((h // 2, w // 2, 3))
    count = np.zeros(3)
    for dy in range(2):
        for dx in range(2):
            c = int(cfa[dy % cfa.shape[0], dx % cfa.shape[1]])
            b = black[dy % black.shape[0], dx % black.shape[1]]
            out[..., c] += (data[dy:h:2, dx:w:2] - b) * scale
            count[c] += 1
    return out / np.maximum(count, 1)


def to_png(img: NDArray, white: float, path: Path) -> Path:
    """An sRGB PNG of a linear image, `white` mapped to full scale (atomically)."""
    import cv2

    from stairfit.fileio import atomic_bytes

    x = np.clip(np.asarray(img, float) / max(white, 1e-300), 0.0, 1.0)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    ok, data = cv2.imencode(".png", np.round(srgb[..., ::-1] * 255).astype(np.uint8))
    if not ok:
        raise OSError(f"{path}: PNG encoding failed")
    return atomic_bytes(path, data.tobytes())


def to_exr(mi: ModuleType, img: NDArray, path: Path) -> Path:
    """A float32 OpenEXR of an image (Mitsuba's writer)."""
    mi.Bitmap(np.ascontiguousarray(img, np.float32)).write(str(path))
    return path


def white_point(img: NDArray) -> float:
    """The display white of a photo: its 99.7th percentile (a few specular pixels clip)."""
    v = np.asarray(img, float).max(axis=-1).ravel()
    return float(np.percentile(v[np.isfinite(v)], 99.7)) or 1.0


def polygon_mean(img: NDArray, polygon: NDArray, erode_px: int = 2) -> list[float] | None:
    """Mean `(3,)` of the pixels whose centre lies inside `polygon` (px), eroded; None if
    none."""
    import cv2

    mask = np.zeros(img.shape[:2], np.uint8)
    cv2.fillPoly(mask, [np.round(np.asarray(polygon) * 256).astype(np.int32)], 1, shift=8)
    if erode_px > 0:
        disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * erode_px + 1,) * 2)
        mask = cv2.erode(mask, disk)
    sel = mask.astype(bool)
    return img[sel].mean(axis=0).tolist() if sel.any() else None


# --- the specimen -------------------------------------------------------------------------------


def specimen_shapes(
    mi: ModuleType, scene: Scene, tables: dict[float, Path], material: Material,
    plate_albedo: float,
) -> sc.MitsubaDict:  # fmt: skip
    """The wedges, plate and markers of the scene (no lamp)."""
    shapes: sc.MitsubaDict = {}
    for w in scene.specimen.wedges:
        if w.face_mm is None:
            continue
        face, walls = sc.wedge_solid(w.face_mm, w.angle_deg)
        shapes[f"face_{w.name}"] = sc.mitsuba_mesh(mi, f"face_{w.name}", face,
                                                   sc.measured(tables[w.angle_deg]))  # fmt: skip
        shapes[f"walls_{w.name}"] = sc.mitsuba_mesh(mi, f"walls_{w.name}", walls,
                                                    sc.diffuse(material.body_albedo))  # fmt: skip
    up = np.array([0.0, 0.0, 1.0])
    for k, (corners, albedo) in enumerate(sc.marker_quads(scene)):
        quad = sc.quad_mesh(corners, up)
        shapes[f"marker_{k}"] = sc.mitsuba_mesh(mi, f"marker_{k}", quad, sc.diffuse(albedo, mi))
    half = 1000.0
    shapes["plate"] = {"type": "rectangle",
                       "to_world": mi.ScalarTransform4f().scale([half, half, 1.0]),
                       "bsdf": sc.diffuse(plate_albedo)}  # fmt: skip
    return shapes


def check_specimen(scene: Scene) -> None:
    """UserError unless the scene can be rendered as a specimen: wedges with `face_mm`,
    angles relative to the base, markers and a pinhole camera to place each photo."""
    where = f"{scene.path}"
    if scene.angles_relative_to != "base":
        raise UserError(f"{where}: rendering the specimen needs angles_relative_to = \"base\" "
                        "(the wedges' faces placed on the base); use --mesh for an object")
    if not any(w.face_mm is not None for w in scene.specimen.wedges):
        raise UserError(f"{where}: no wedge has a face_mm outline, so there is nothing to place "
                        "in 3-D; give the outlines (docs/scene.md) or use --mesh")
    if scene.markers is None or scene.camera.focal_length_px is None:
        raise UserError(f"{where}: rendering the photographed views needs [markers] and "
                        "[camera] focal_length_px, to find each photo's camera pose")


def render_specimen(
    fit: FitFolder, out: Path, options: RenderOptions = DEFAULT_OPTIONS,
    progress: Progress = lambda _: None, reuse: Path | None = None,
) -> Record:  # fmt: skip
    """Render the fitted material on the photographed specimen from every photo's camera pose
    (from its markers, as `stairfit measure` finds it) under its lamp, next to the photo
    developed the same way; write everything into `out` (see the module's docstring) and
    return the record written to `out/renders.json`."""
    from stairfit import imaging
    from stairfit.imaging_specs import photo_specs
    from stairfit.scene import visible

    scene, material = fit.scene, fit.material
    check_specimen(scene)
    photos = {p.file: p for p in scene.photos}
    specs = [s for s in photo_specs(scene) if not options.views or s.name in options.views]
    missing = set(options.views) - {s.name for s in specs}
    if missing:
        raise UserError(f"--view: no photo {sorted(missing)[0]!r} in {scene.path}")
    mi = sc.mitsuba("scalar_rgb", options.threads)
    t_start = time.perf_counter()
    angles = sorted({w.angle_deg for w in scene.specimen.wedges if w.face_mm is not None})
    tables = material_tables(material, angles, out / "materials", options.resolution, progress,
                             reuse)  # fmt: skip
    t_tables = time.perf_counter() - t_start
    shapes = specimen_shapes(mi, scene, tables, material, options.plate_albedo)
    scale = material.photo_scale or 1.0
    views = []
    for i, spec in enumerate(specs):
        t0 = time.perf_counter()
        frame = imaging.decode_raw(spec.path, spec.name)
        _, pose, _ = imaging.place_faces(frame, spec)
        if pose is None or pose.model != "pinhole":
            progress(f"view {i + 1}/{len(specs)} {spec.name}: no pinhole pose, skipped")
            continue
        exposure = imaging.resolve_exposure(frame, spec.exposure_time_s, spec.f_number, spec.iso)
        photo = develop(frame, exposure.scale)
        cam = sc.camera_from_pose(pose, frame.data.shape[1], frame.data.shape[0])
        cam = cam.scaled(2 * options.downscale)
        lamp = sc.scene_lamp(scene, photos[spec.name])
        img = sc.render(mi, {**shapes, **sc.lamp_shapes(lamp)}, cam, options.spp,
                        options.max_depth, options.seed + i) * scale  # fmt: skip
        photo = _block_mean(photo, options.downscale)
        stem = Path(spec.name).stem
        white = white_point(photo)
        to_png(photo, white, out / f"{stem}_photo.png")
        to_png(img, white, out / f"{stem}_render.png")
        to_exr(mi, img, out / f"{stem}_render.exr")
        faces = []
        for w in scene.specimen.wedges:
            if w.face_mm is None or not visible(scene, photos[spec.name], w):
                continue
            face, _ = sc.wedge_solid(w.face_mm, w.angle_deg)
            poly = cam.project(face.vertices)
            faces.append({"wedge": w.name, "photo": polygon_mean(photo, poly),
                          "render": polygon_mean(img, poly)})  # fmt: skip
        seconds = time.perf_counter() - t0
        views.append({"photo": spec.name, "light_deg": photos[spec.name].light_deg,
                      "view_deg": photos[spec.name].view_deg, "photo_png": f"{stem}_photo.png",
                      "render_png": f"{stem}_render.png", "render_exr": f"{stem}_render.exr",
                      "faces": faces, "seconds": round(seconds, 2)})  # fmt: skip
        progress(f"view {i + 1}/{len(specs)} {spec.name} rendered in {seconds:.1f} s")
    record = {
        "kind": "specimen",
        "units": "render_exr: the photos' relative radiance (docs/imaging.md §Units): the "
                 "render's radiance per unit lamp irradiance times the fit's scale",
        "material": material._asdict() | {"index": [str(n) for n in material.index]},
        "tables": {f"{a:g}": f"materials/{p.name}" for a, p in tables.items()},
        "options": _options_record(options),
        "views": views,
        "seconds": {"tables": round(t_tables, 1),
                    "total": round(time.perf_counter() - t_start, 1)},
    }  # fmt: skip
    _write_json(out / "renders.json", record)
    return record


def _block_mean(img: NDArray, k: int) -> NDArray:
    if k <= 1:
        return img
    h, w = (img.shape[0] // k) * k, (img.shape[1] // k) * k
    return img[:h, :w].reshape(h // k, k, w // k, k, -1).mean(axis=(1, 3))


def _options_record(options: RenderOptions) -> Record:
    rec = options._asdict()
    rec["resolution"] = options.resolution._asdict()
    rec["views"] = list(options.views)
    return rec


def _write_json(path: Path, record: Record) -> None:
    from stairfit.fileio import atomic_bytes

    atomic_bytes(path, (json.dumps(record, indent=1) + "\n").encode("utf8"))


# --- a user's object ----------------------------------------------------------------------------


def parse_axis(text: str) -> NDArray:
    """A build axis: "x", "y", "z" (optionally signed, "-y") or three numbers; UserError
    otherwise."""
    t = text.strip().lower()
    named = {"x": [1.0, 0, 0], "y": [0, 1.0, 0], "z": [0, 0, 1.0]}
    sign = -1.0 if t.startswith("-") else 1.0
    if t.lstrip("+-") in named:
        return sign * np.array(named[t.lstrip("+-")])
    try:
        v = np.array([float(x) for x in t.replace(",", " ").split()], float)
    except ValueError:
        v = np.zeros(0)
    if v.shape != (3,) or not np.all(np.isfinite(v)) or np.linalg.norm(v) == 0:
        raise UserError(f"--build-axis {text!r}: give x, y, z (optionally -x ...) or three "
                        "numbers such as '0 0 1'")  # fmt: skip
    return v / np.linalg.norm(v)


def render_mesh(
    material: Material, obj: Path, build_axis: NDArray, out: Path,
    options: RenderOptions = DEFAULT_OPTIONS, progress: Progress = lambda _: None,
    reuse: Path | None = None,
) -> Record:  # fmt: skip
    """Render a printed object: the mesh `obj` (mm), each point with the staircase of its wedge
    angle from the build axis (`printed_parts`: tables every `step_deg` at most, blended
    between the two nearest by each vertex's angle), seen from 30 deg above the layer plane
    and lit by a small lamp from the other side plus a dim uniform sky (not seen directly);
    write
    `NAME_render.exr`/`.png`, the tables and `renders.json` into `out`."""
    mi = sc.mitsuba("scalar_rgb", options.threads)
    t_start = time.perf_counter()
    mesh = read_obj(obj)
    nodes, parts = printed_parts(mesh, build_axis, options.step_deg)
    used = sorted({k for k, _ in parts} | {k + 1 for k, _ in parts})
    progress(f"{obj.name}: {len(mesh.faces)} triangles, wedge angles {nodes[used[0]]:.3g}-"
             f"{nodes[used[-1]]:.3g} deg in {len(used)} tables")  # fmt: skip
    tables = material_tables(material, [float(nodes[k]) for k in used], out / "materials",
                             options.resolution, progress, reuse)  # fmt: skip
    t_tables = time.perf_counter() - t_start
    shapes = {}
    for k, part in parts:
        bsdf = sc.blend(sc.measured(tables[float(nodes[k])]),
                        sc.measured(tables[float(nodes[k + 1])]))  # fmt: skip
        shapes[f"part_{k}"] = sc.mitsuba_mesh(mi, f"part_{k}", part, bsdf)
    centre, radius = bounding_sphere(mesh)
    cam, lamp_pos = _mesh_view(centre, radius, build_axis, options.size)
    lamp = sc.Lamp(lamp_pos, (lamp_pos - centre) / np.linalg.norm(lamp_pos - centre),
                   0.2 * radius, float(np.linalg.norm(lamp_pos - centre)))  # fmt: skip
    shapes |= sc.lamp_shapes(lamp)
    shapes["sky"] = {"type": "constant", "radiance": {"type": "rgb", "value": [SKY] * 3}}
    t0 = time.perf_counter()
    img = sc.render(mi, shapes, cam, options.spp, options.max_depth, options.seed,
                    hide_emitters=True)  # fmt: skip
    stem = obj.stem
    to_exr(mi, img, out / f"{stem}_render.exr")
    to_png(img, white_point(img), out / f"{stem}_render.png")
    seconds = time.perf_counter() - t0
    progress(f"{stem}: {options.size} x {options.size} px rendered in {seconds:.1f} s")
    record = {
        "kind": "mesh",
        "mesh": str(obj),
        "build_axis": build_axis.tolist(),
        "units": "render_exr: radiance per unit lamp irradiance at the object's centre (1/sr)",
        "material": material._asdict() | {"index": [str(n) for n in material.index]},
        "tables": {f"{a:g}": f"materials/{p.name}" for a, p in tables.items()},
        "options": _options_record(options),
        "views": [{"mesh": obj.name, "render_png": f"{stem}_render.png",
                   "render_exr": f"{stem}_render.exr", "seconds": round(seconds, 2)}],
        "seconds": {"tables": round(t_tables, 1),
                    "total": round(time.perf_counter() - t_start, 1)},
    }  # fmt: skip
    _write_json(out / "renders.json", record)
    return record


SKY = 0.02
"""A mesh render's uniform sky radiance, per unit lamp irradiance (1/sr): it shows the shape
where the lamp does not reach."""


def _mesh_view(centre: NDArray, radius: float, axis: NDArray,
               size: int) -> tuple[sc.Camera, NDArray]:  # fmt: skip
    """A camera 30 deg above the layer plane at 4 radii, looking at the centre with the build
    axis up in the image, and the lamp's position (45 deg up, 100 deg round from the camera)."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(axis, helper)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)

    def direction(elev: float, azim: float) -> NDArray:
        a, b = math.radians(elev), math.radians(azim)
        return math.cos(a) * (math.cos(b) * e1 + math.sin(b) * e2) + math.sin(a) * axis

    eye = centre + 4.0 * radius * direction(30.0, 35.0)
    forward = (centre - eye) / np.linalg.norm(centre - eye)
    right = np.cross(forward, axis)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    focal = size / 2.0 / math.tan(math.radians(18.0))
    cam = sc.Camera(np.stack([right, down, forward]), eye, focal,
                    ((size - 1) / 2.0, (size - 1) / 2.0), size, size)  # fmt: skip
    return cam, centre + 6.0 * radius * direction(45.0, 135.0)


def update_report(fit: Path) -> Path | None:
    """Put the renders' section (`stairfit.report.renders_html`) into `fit/report.html`, in
    place of an earlier one; None when the fit folder has no report."""
    from stairfit.fileio import atomic_bytes
    from stairfit.report import renders_html, with_renders

    path = Path(fit) / "report.html"
    if not path.is_file():
        return None
    text = path.read_text(encoding="utf-8")
    return atomic_bytes(path, with_renders(text, renders_html(Path(fit))).encode("utf-8"))
