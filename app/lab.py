"""The lab geometry of a scene: each measured face's 3-D light and view directions, from the
lamp's position, the camera poses the markers gave and the faces' points (docs/fitting.md
§10; conventions §11).

`lab_reason` says whether a scene needs the lab model (a near lamp, or faces seen out of the
plane of incidence); `lab_geometry` builds the fit's `fitting.LabGeometry` for the rows of its
observation table; `out_of_plane` lists each face's out-of-plane angles for the report.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from stairfit import fitting
from stairfit.imaging import MeasurementRow

from .errors import UserError
from .scene import Photo, Scene, Wedge

OUT_OF_PLANE_LIMIT_DEG = 1.0
"""A scene whose light or view directions leave the plane of incidence of some face by more
than this (or that has a near lamp) is fitted with the lab model; below it the in-plane model
is exact to well under a per cent of the signal (docs/fitting.md §10)."""

LAMP_DISK: tuple[tuple[float, float, float], ...] = (
    (0.0, 0.0, 0.25),
    *((math.sqrt(2.0 / 3.0) * math.cos(a), math.sqrt(2.0 / 3.0) * math.sin(a), 0.125)
      for a in np.arange(6) * math.pi / 3.0),
)  # fmt: skip
"""A round lamp's nodes (x, y on the unit disk, weight): the 7-point rule exact for
polynomials of degree 3 on the disk (centre 1/4, six points at radius sqrt(2/3), 1/8 each)."""


class FaceGeometry(NamedTuple):
    """One measured face in one photo: its points (base frame, mm) with weights, the camera
    centre (None: at infinity along `view_dir`) and the lamp (None: distant along
    `light_dir`)."""

    points: np.ndarray
    weights: np.ndarray
    camera: np.ndarray | None
    view_dir: np.ndarray
    lamp: np.ndarray | None
    light_dir: np.ndarray


def _direction(deg: float, light: bool) -> np.ndarray:
    """Unit vector (base frame) at `deg` about y: towards a light (`(-sin, 0, cos)`: a positive
    light_deg is downhill) or a camera (`(sin, 0, cos)`) [conventions §1]."""
    a = math.radians(deg)
    return np.array([-math.sin(a) if light else math.sin(a), 0.0, math.cos(a)])


def _parse_points(text: str) -> tuple[np.ndarray, np.ndarray] | None:
    """`face_points_mm` ("x y z w;...") as (points, weights), or None when empty."""
    if not text:
        return None
    values = np.array([[float(v) for v in item.split()] for item in text.split(";")])
    return values[:, :3], values[:, 3] / values[:, 3].sum()


def _face_centre(wedge: Wedge, tilt_deg: float) -> np.ndarray | None:
    """The centre of a wedge's face (base frame, mm) from its `face_mm` outline, or None."""
    if wedge.face_mm is None:
        return None
    xy = np.asarray(wedge.face_mm, float)
    z = (xy[:, 0] - xy[:, 0].min()) * math.tan(math.radians(tilt_deg))
    return np.column_stack([xy, z]).mean(axis=0)


def face_geometry(scene: Scene, photo: Photo, wedge: Wedge, row: MeasurementRow) -> FaceGeometry:
    """The geometry of one measured face (see `FaceGeometry`): the ROI's face points from the
    measurement (`face_points_mm`), else the face's centre; the camera's centre from a pinhole
    pose (`camera_mm`), else a camera at infinity along `view_deg`; the lamp from the scene.
    Raises UserError when a near lamp meets a face whose position is unknown."""
    tilt = 0.0 if scene.angles_relative_to == "face" else wedge.angle_deg
    parsed = _parse_points(row.face_points_mm)
    if parsed is None:
        centre = _face_centre(wedge, tilt)
        if centre is None:
            centre = np.zeros(3)
            if scene.light.near:
                raise UserError(
                    f"{scene.path}: specimen.wedges '{wedge.name}': a near lamp ([light] "
                    "distance_mm or position_mm) needs each face's position: give its outline "
                    "on the base (face_mm) and [markers] to place it (docs/scene.md)"
                )
        parsed = (centre[None, :], np.ones(1))
    cam = np.array([float(v) for v in row.camera_mm.split()]) if row.camera_mm else None
    lamp = scene.lamp_position_mm(photo)
    return FaceGeometry(
        points=parsed[0],
        weights=parsed[1],
        camera=cam,
        view_dir=_direction(photo.view_deg or 0.0, light=False),
        lamp=None if lamp is None else np.asarray(lamp, float),
        light_dir=_direction(photo.light_deg or 0.0, light=True),
    )


def _to_face(v: np.ndarray, tilt_deg: float) -> np.ndarray:
    """Base-frame vectors in a wedge's face frame: a rotation about y by the wedge angle
    [conventions §11]."""
    b = math.radians(tilt_deg)
    c, s = math.cos(b), math.sin(b)
    return np.stack([v[..., 0] * c + v[..., 2] * s, v[..., 1], -v[..., 0] * s + v[..., 2] * c], -1)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


LAMP_DISK_MIN_DEG = 1.0
"""A lamp smaller than this (its angular diameter seen from the origin) is a point: next to
the facets' own spread of a few degrees its size changes a face's radiance by far less than
its measurement error, and every node costs one evaluation per face point."""


def _lamp_nodes(scene: Scene) -> tuple[tuple[float, float, float], ...]:
    """The lamp's disk nodes: `LAMP_DISK` for a lamp of `LAMP_DISK_MIN_DEG` or more, else its
    centre."""
    big = scene.light.angular_diameter_deg >= LAMP_DISK_MIN_DEG
    return LAMP_DISK if big and (scene.light.diameter_mm or 0.0) > 0 else ((0.0, 0.0, 1.0),)


def reference_distance_mm(scene: Scene) -> float:
    """The distance the fitted `scale` refers to: the lamp's distance from the base frame's
    origin in the first photo (irradiance elsewhere is `(d_ref / d)^2` of it); 1 for a
    distant light."""
    lamp = scene.lamp_position_mm(scene.photos[0])
    return 1.0 if lamp is None else float(np.linalg.norm(lamp))


def nodes(scene: Scene, face: FaceGeometry, tilt_deg: float) -> tuple[np.ndarray, ...]:
    """The face's nodes in its face frame: (w_i, w_o, weight, irradiance), one per face point
    and lamp node."""
    pts = face.points  # (m, 3)
    w_o = _unit(face.camera[None, :] - pts) if face.camera is not None else (
        np.broadcast_to(face.view_dir, pts.shape)
    )  # fmt: skip
    if face.lamp is None:
        w_i = np.broadcast_to(face.light_dir, pts.shape)[:, None, :]
        irr = np.ones((pts.shape[0], 1))
        lamp_w = np.ones(1)
    else:
        radius = 0.5 * (scene.light.diameter_mm or 0.0)
        axis = _unit(face.lamp - pts.mean(axis=0))
        u = _unit(
            np.cross(axis, [0.0, 1.0, 0.0]) if abs(axis[1]) < 0.9 else np.cross(axis, [1.0, 0, 0])
        )
        v = np.cross(axis, u)
        disk = np.array(_lamp_nodes(scene))
        spots = face.lamp + radius * (disk[:, :1] * u + disk[:, 1:2] * v)  # (L, 3)
        to_lamp = spots[None, :, :] - pts[:, None, :]  # (m, L, 3)
        dist = np.linalg.norm(to_lamp, axis=-1)
        w_i = to_lamp / dist[..., None]
        irr = (reference_distance_mm(scene) / dist) ** 2
        lamp_w = disk[:, 2] / disk[:, 2].sum()
    m, n_lamp = w_i.shape[:2]
    w_o = np.broadcast_to(w_o[:, None, :], (m, n_lamp, 3))
    weight = face.weights[:, None] * lamp_w[None, :]
    return (
        _to_face(w_i.reshape(-1, 3), tilt_deg),
        _to_face(np.asarray(w_o).reshape(-1, 3), tilt_deg),
        weight.reshape(-1),
        irr.reshape(-1),
    )


def lab_geometry(scene: Scene, rows: Sequence[MeasurementRow]) -> fitting.LabGeometry:
    """The lab geometry of the observation table built from `rows` (one per table row, in its
    order; `stairfit.pipeline.observations`): one key per photo x wedge, its nodes padded
    to the largest count with zero weight."""
    assert scene.specimen is not None
    wedges = {w.name: (k, w) for k, w in enumerate(scene.specimen.wedges)}
    photos = {p.file: p for p in scene.photos}
    keys: dict[tuple[str, str], int] = {}
    per_key: list[tuple[np.ndarray, ...]] = []
    wedge_of: list[int] = []
    row_key = []
    for r in rows:
        pair = (r.photo, r.wedge)
        if pair not in keys:
            k, wedge = wedges[r.wedge]
            tilt = 0.0 if scene.angles_relative_to == "face" else wedge.angle_deg
            face = face_geometry(scene, photos[r.photo], wedge, r)
            keys[pair] = len(per_key)
            per_key.append(nodes(scene, face, tilt))
            wedge_of.append(k)
        row_key.append(keys[pair])
    size = max(n[0].shape[0] for n in per_key)

    def pad(a: np.ndarray, fill: float) -> np.ndarray:
        extra = size - a.shape[0]
        if extra == 0:
            return a
        tail = np.broadcast_to(a[-1:], (extra, *a.shape[1:])) if fill is None else np.full(
            (extra, *a.shape[1:]), fill
        )  # fmt: skip
        return np.concatenate([a, tail])

    return fitting.LabGeometry(
        w_i=np.stack([pad(n[0], None) for n in per_key]),
        w_o=np.stack([pad(n[1], None) for n in per_key]),
        weight=np.stack([pad(n[2], 0.0) for n in per_key]),
        irradiance=np.stack([pad(n[3], None) for n in per_key]),
        wedge=np.asarray(wedge_of, int),
        key=np.asarray(row_key, int),
        plate_albedo=scene.specimen.plate_albedo,
    )


class OutOfPlane(NamedTuple):
    """A face's largest out-of-plane angles (deg) over its nodes: of the light, of the view."""

    photo: str
    wedge: str
    light_deg: float
    view_deg: float


def out_of_plane(scene: Scene, rows: Sequence[MeasurementRow]) -> list[OutOfPlane]:
    """Each measured face's largest out-of-plane angles of its light and view directions
    (`asin |t|`, conventions §11): what the in-plane model ignores."""
    geo = lab_geometry(scene, rows)
    seen: dict[int, tuple[str, str]] = {}
    for r, k in zip(rows, geo.key, strict=True):
        seen.setdefault(int(k), (r.photo, r.wedge))
    out = []
    for k, (photo, wedge) in seen.items():
        used = geo.weight[k] > 0
        t_i = np.abs(geo.w_i[k, used, 1]).max()
        t_o = np.abs(geo.w_o[k, used, 1]).max()
        out.append(OutOfPlane(photo, wedge, math.degrees(math.asin(min(t_i, 1.0))),
                              math.degrees(math.asin(min(t_o, 1.0)))))  # fmt: skip
    return out


def max_out_of_plane(scene: Scene, rows: Sequence[MeasurementRow]) -> OutOfPlane | None:
    """The face seen furthest out of its plane of incidence (light or view), or None when no
    face was placed in 3-D (no face points)."""
    if not any(r.face_points_mm for r in rows):
        return None
    return max(out_of_plane(scene, rows), key=lambda f: max(f.light_deg, f.view_deg))


class LabChoice(NamedTuple):
    """Whether the fit uses the lab model (`use`), why (`reason`), and a warning when the
    model chosen ignores what the scene shows (`warning`, None if none)."""

    use: bool
    reason: str
    warning: str | None = None


def uses_lab_model(scene: Scene) -> bool:
    """Whether the fit models the directions in 3-D (`lab_choice`): `[fit] geometry` "lab",
    or "auto" with a near lamp."""
    mode = scene.fit.geometry
    return mode == "lab" or (mode == "auto" and scene.light.near)


def lab_choice(scene: Scene, rows: Sequence[MeasurementRow]) -> LabChoice:
    """Which model of the directions the fit uses, by the scene's `[fit] geometry`
    (`scene.GEOMETRIES`): "lab" always, "in_plane" never, "auto" when the lamp is near. A
    warning when the in-plane model is used on a scene with a near lamp or with a face seen
    more than `OUT_OF_PLANE_LIMIT_DEG` out of its plane of incidence."""
    mode = scene.fit.geometry
    near = scene.light.near
    if mode == "lab":
        return LabChoice(True, 'the scene asks for it ([fit] geometry = "lab")')
    if uses_lab_model(scene):
        return LabChoice(True, "the lamp is near (its position is given): each face is lit "
                               "from its own direction")  # fmt: skip
    why = ('the scene asks for it ([fit] geometry = "in_plane")' if mode == "in_plane"
           else "the lamp is distant")  # fmt: skip
    if near:
        return LabChoice(False, why, "the lamp is near, but the fit models one direction of "
                         'light for every face; set [fit] geometry = "auto" or "lab"')  # fmt: skip
    worst = max_out_of_plane(scene, rows)
    if worst is not None:
        angle = max(worst.light_deg, worst.view_deg)
        if angle > OUT_OF_PLANE_LIMIT_DEG:
            return LabChoice(False, why, (
                f"face '{worst.wedge}' in {worst.photo} is seen {angle:.2g} deg out of its "
                "plane of incidence, which the in-plane model ignores (above "
                f'{OUT_OF_PLANE_LIMIT_DEG:g} deg); set [fit] geometry = "lab" to model it'
            ))  # fmt: skip
    return LabChoice(False, why)
