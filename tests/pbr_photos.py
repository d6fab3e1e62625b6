"""A physically based renderer of photo folders (issue 40): Mitsuba 3 path-traces printed wedges.

The scene is the lab of the issue "The real lab": six wedges (10-60 deg) printed in 150 um layers
whose convex step edges are rounded (25 um), as real triangle meshes with smooth normals on the
arcs; microfacet-rough facets (GGX, alpha 0.06) of index 1.46 over a dark diffuse body (black
PLA), through Mitsuba's polarised plastic (`pplastic`), so that every reflection, the two-bounce
paths inside a step included, carries s and p through its own plane of incidence; the wedges in
one row along the layer lines (+-70 mm) on a dark plate with four ArUco markers (white quiet
zone); a 6 mm LED ball 500 mm away (a sphere emitting a D65 spectrum); a pinhole camera 900 mm
away with the field of a 135 mm lens (0.133 mm per pixel at 1800 x 1200 px); views at two lamp
angles; RGGB 14-bit DNGs with black level, exposure tags, shot and read noise and vignetting;
flat-field photos; a `scene.toml` written from docs/scene.md alone; `truth.json`.

The rendering is spectral and polarised (`scalar_spectral_polarized`); the film integrates the
camera's channel sensitivities (`specfilm`, the scene's "Nikon 5100 (NPL)"), each normalised so
that a spectrally flat surface under the lamp's D65 reads the same in every channel (the fit's
convention, conventions §8: a white reflector gives 1 in every channel). A `fast` setup renders
in `scalar_rgb` (unpolarised, RGB) at low resolution and few samples, for the default tests.

Units. Every rendered pixel is a radiance divided by the lamp's reference irradiance `E_ref`, the
irradiance normal to the beam that the lamp gives at its reference distance (`lamp_distance_mm`,
or the length of `lamp_position_mm`): unit 1/sr, so a white Lambertian plate facing the lamp at
that distance reads 1/pi. The camera turns it into DN as `DN - black = k_cam * that * vignetting
* t (ISO / 100) / N^2`, so stairfit's relative radiance (docs/imaging.md §Units: DN above black
per second at f/1 and ISO 100, divided by the flat field's gain, 1 at the image centre) is
`k_cam * radiance / E_ref`: that is the unit of truth.json's face values.

Independent of stairfit: its own geometry (meshes, the pinhole camera's poses, its own
projection of the faces for the truth), Mitsuba's physics (no stairfit model), its own sensor
noise, vignetting and DNG writer. It imports nothing from stairfit; from tests/independent_photos
it takes the `Pinhole` camera (projection and rays).

API: `PbrSetup` (defaults: the issue's scene), `fast_setup()`, `staircase_mesh()`,
`patch_radiance()` (one wedge's mean radiance under chosen 3-D directions, the BRDF-level check),
`render_folder(path, setup, seed)`.
"""

from __future__ import annotations

import json
import math
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, replace
from fractions import Fraction
from pathlib import Path
from typing import Any, NamedTuple

import cv2
import numpy as np
import tifffile
from independent_photos import Pinhole

DEG = math.pi / 180.0
CHANNELS = ("R", "G", "B")
VIEWS_LAMP_0: tuple[float, ...] = (
    -80.0,
    -70.0,
    -60.0,
    -50.0,
    -40.0,
    -30.0,
    -20.0,
    -10.0,
    10.0,
    20.0,
    30.0,
    45.0,
    60.0,
    75.0,
)
"""Views with the lamp above the origin (0 deg): none within 10 deg of the lamp's direction,
where the lamp would stand in front of the camera."""
VIEWS_LAMP_20: tuple[float, ...] = (
    -80.0,
    -70.0,
    -60.0,
    -50.0,
    -40.0,
    -30.0,
    -10.0,
    0.0,
    10.0,
    20.0,
    30.0,
    45.0,
    60.0,
    75.0,
)
"""Views with the lamp at 20 deg (downhill side): the same, -20 left out."""
DEFAULT_PHOTOS: tuple[tuple[float, float], ...] = tuple(
    [(0.0, v) for v in VIEWS_LAMP_0] + [(20.0, v) for v in VIEWS_LAMP_20]
)
"""(light_deg, view_deg) of the 28 photos. The lamp at 20 deg lights the risers (at 70 deg local
incidence) besides the treads, the riser-to-tread ratio carries the index; at 0 deg the risers are
grazing and only the treads and the rounded edges are lit."""
MARKERS: tuple[tuple[int, float, float], ...] = (
    (0, -30.0, -106.0),
    (1, 12.0, -106.0),
    (2, -30.0, 88.0),
    (3, 12.0, 88.0),
)
"""Marker id and the base-frame (x, y) of its black square's corner of smallest x and y (mm):
beyond the ends of the row (|y| > 80), where no wedge can hide them from a view about y."""


@dataclass(frozen=True)
class PbrSetup:
    """The physics and the session; defaults are the scene of issue 40.

    Base frame (docs/scene.md): millimetres, x uphill (every wedge rises along +x), y along the
    layer lines, z up out of the plate; the origin is the middle of the row's footprint.

    Attributes:
        wedges_deg, layer_um: the wedge angles and the layer thickness l1.
        edge_radius_um, arc_segments: the convex step edges are circular arcs of this radius,
            tangent to both facets, each of `arc_segments` flat pieces with smooth (interpolated)
            vertex normals; the concave corners are sharp.
        distribution, alpha: the facets' microfacet distribution ("ggx" or "beckmann") and its
            roughness (Mitsuba's alpha; for Beckmann the RMS slope).
        index: the facets' refractive index (constant over wavelength; air outside, n = 1).
        body_diffuse: the dark body's diffuse reflectance under the facets (`pplastic`'s
            diffuse_reflectance; Mitsuba applies the two Fresnel transmissions to it).
        footprint_mm, row_pitch_mm: each wedge stands on a square footprint, x from
            -footprint/2 (its foot) to +footprint/2, its centre at y = (k - (n - 1) / 2) pitch.
        plate_albedo, paper_albedo, ink_albedo: Lambertian reflectances of the plate, the
            markers' white paper (quiet zone) and their black ink.
        marker_mm, marker_quiet_cells, markers: ArUco DICT_4X4_50 markers (6 cells a side, the
            black square `marker_mm` wide) on white paper `marker_quiet_cells` cells wider on
            every side, at the positions of `MARKERS`.
        lamp_diameter_mm, lamp_distance_mm, lamp_position_mm: a sphere emitting uniformly; a
            photo's light_deg puts its centre at distance * (-sin L, 0, cos L), or at the one
            fixed `lamp_position_mm` if given.
        photos: (light_deg, view_deg) per photo; the camera at `camera_distance_mm` from the
            origin at view_deg about y (positive: uphill side), looking at the origin, the layer
            lines along the image rows.
        focal_length_mm, pixel_pitch_um, width, height: the pinhole (focal length in pixels =
            focal_length_mm / pixel_pitch) and the image.
        sensitivity: the camera's channel sensitivities (colour-science's name; the scene's).
        black_dn, bits, gain_e_per_dn, read_noise_dn: the sensor at ISO 100.
        f_number, iso, fill: each photo's exposure puts its brightest noise-free pixel at
            `fill` of the raw range, rounded down to a third of a stop.
        k_cam: DN per second at f/1 and ISO 100 per unit of radiance / E_ref (1/sr).
        vignetting: (R, G, B) relative fall-off in the image corners.
        flat_photos: flat-field photos (a uniform target through the same lens).
        variant, max_depth: Mitsuba's variant and path depth (3: the two-bounce paths inside a
            step; 4 adds one more bounce, e.g. face -> plate -> face).
        spp, spp_markers, spp_background: samples per pixel on the faces (a box around each
            visible face), the markers (a box around each one's paper) and everywhere else.
        truth_erode_px: the truth averages pixels at least this far inside a face's polygon.
        erode_px: written as the scene's `[extraction] erode_px` when given.
    """

    wedges_deg: tuple[float, ...] = (10.0, 20.0, 30.0, 40.0, 45.0, 60.0)
    layer_um: float = 150.0
    edge_radius_um: float = 25.0
    arc_segments: int = 16
    distribution: str = "ggx"
    alpha: float = 0.06
    index: float = 1.46
    body_diffuse: float = 0.02
    footprint_mm: float = 20.0
    row_pitch_mm: float = 28.0
    plate_albedo: float = 0.03
    paper_albedo: float = 0.8
    ink_albedo: float = 0.03
    marker_mm: float = 18.0
    marker_quiet_cells: float = 1.0
    markers: tuple[tuple[int, float, float], ...] = MARKERS
    lamp_diameter_mm: float = 6.0
    lamp_distance_mm: float = 500.0
    lamp_position_mm: tuple[float, float, float] | None = None
    photos: tuple[tuple[float, float], ...] = DEFAULT_PHOTOS
    camera_distance_mm: float = 900.0
    focal_length_mm: float = 135.0
    pixel_pitch_um: float = 20.0
    width: int = 1800
    height: int = 1200
    sensitivity: str = "Nikon 5100 (NPL)"
    black_dn: int = 1024
    bits: int = 14
    gain_e_per_dn: float = 2.0
    read_noise_dn: float = 2.0
    f_number: float = 8.0
    iso: float = 100.0
    fill: float = 0.75
    k_cam: float = 2.0e7
    vignetting: tuple[float, float, float] = (0.12, 0.11, 0.10)
    flat_photos: int = 2
    variant: str = "scalar_spectral_polarized"
    spp: int = 256
    spp_markers: int = 64
    spp_background: int = 8
    max_depth: int = 4
    truth_erode_px: float = 4.0
    erode_px: int | None = None

    @property
    def focal_px(self) -> float:
        """The pinhole's focal length in pixels."""
        return self.focal_length_mm / (self.pixel_pitch_um * 1e-3)

    @property
    def lamp_reference_mm(self) -> float:
        """The distance at which the lamp's irradiance is the unit E_ref."""
        if self.lamp_position_mm is not None:
            return float(np.linalg.norm(self.lamp_position_mm))
        return self.lamp_distance_mm


def fast_setup(**changes: Any) -> PbrSetup:
    """A small, quick version for the default tests: `scalar_rgb` (unpolarised), 600 x 400 px of
    60 um (the same field: 0.4 mm per pixel), 16 samples per pixel, two photos lit from 20 deg,
    a flat field, the scene's erosion 4 px."""
    base: dict[str, Any] = {
        "variant": "scalar_rgb",
        "width": 600,
        "height": 400,
        "pixel_pitch_um": 60.0,
        "spp": 16,
        "spp_markers": 16,
        "spp_background": 4,
        "max_depth": 3,
        "photos": ((20.0, -40.0), (20.0, 10.0)),
        "flat_photos": 1,
        "erode_px": 4,
        "truth_erode_px": 3.0,
    }
    return replace(PbrSetup(), **{**base, **changes})


VARIANT_VIEWS: dict[float, tuple[float, ...]] = {
    -10.0: (-80.0, -66.0, -52.0, -38.0, -24.0, -10.0, 0.0, 24.0, 38.0, 52.0, 66.0, 80.0),
    30.0: (-80.0, -66.0, -52.0, -14.0, -4.0, 6.0, 16.0, 26.0, 38.0, 52.0, 66.0, 80.0),
}
"""The second set's views per lamp angle, clear of the lamp (`lamp_in_frame`)."""


def variant_setup(**changes: Any) -> PbrSetup:
    """A second lab made the same way with other parameters (the held-back-style check of issue
    40): wedges of 15-65 deg in 200 um layers with 40 um edges, Beckmann facets (alpha 0.10) of
    index 1.53 over a body of 0.03, a 10 mm lamp 350 mm away at -10 and 30 deg, the camera
    700 mm away with a 105 mm lens (the same 0.133 mm per pixel), 24 photos."""
    base: dict[str, Any] = {
        "wedges_deg": (15.0, 25.0, 35.0, 50.0, 55.0, 65.0),
        "layer_um": 200.0,
        "edge_radius_um": 40.0,
        "distribution": "beckmann",
        "alpha": 0.10,
        "index": 1.53,
        "body_diffuse": 0.03,
        "row_pitch_mm": 27.0,
        "lamp_diameter_mm": 10.0,
        "lamp_distance_mm": 350.0,
        "camera_distance_mm": 700.0,
        "focal_length_mm": 105.0,
        "photos": tuple((light, v) for light, views in VARIANT_VIEWS.items() for v in views),
    }
    return replace(PbrSetup(), **{**base, **changes})


# --- geometry: one wedge's mesh ------------------------------------------------------------------


class Profile(NamedTuple):
    """The staircase's cross-section (u = x - foot, z), as straight pieces from `start` to `end`
    (each (n, 2), mm) with outward unit normals at both ends (`normal_start`, `normal_end`):
    equal on a facet, the arc's own normals at an arc piece's ends."""

    start: np.ndarray
    end: np.ndarray
    normal_start: np.ndarray
    normal_end: np.ndarray


def staircase_profile(
    beta2_deg: float, layer_um: float, edge_radius_um: float, arc_segments: int, length_mm: float
) -> Profile:
    """The printed staircase from its foot (u = 0, on the plate) to `length_mm` along x.

    Layers are horizontal; going uphill, each period is a riser (vertical, l1 high, normal -x),
    the rounded convex edge, a tread (horizontal, l2 = l1 cot beta2 long, normal +z) and a sharp
    concave corner. The sharp tips lie at `z = u tan(beta2) + l1 / 2` and the concave corners at
    `u tan(beta2) - l1 / 2`, so the face's mean plane is `z = u tan(beta2)`, the plane of the
    scene's face_mm outline (docs/scene.md); the first riser starts on the plate at (0, 0). An
    edge of radius r is the arc, centre `tip + (r, -r)`, from the riser's `tip - (0, r)` to the
    tread's `tip + (r, 0)`. The profile is cut at `u = length_mm`.
    """
    l1 = layer_um * 1e-3
    l2 = l1 / math.tan(beta2_deg * DEG)
    r = edge_radius_um * 1e-3
    if not 0.0 <= r < min(l1 / 2.0, l2):
        raise ValueError(f"edge radius {edge_radius_um} um must be below min(l1 / 2, l2)")
    pieces: list[
        tuple[tuple[float, float], tuple[float, float], tuple[float, float], tuple[float, float]]
    ] = []
    riser, tread = (-1.0, 0.0), (0.0, 1.0)
    phis = np.linspace(math.pi, math.pi / 2.0, arc_segments + 1)
    for k in range(math.ceil(length_mm / l2) + 1):
        u = k * l2
        tip = (u, (k + 0.5) * l1)
        foot = 0.0 if k == 0 else (k - 0.5) * l1
        pieces.append(((u, foot), (u, tip[1] - r), riser, riser))
        if r > 0.0:
            centre = (u + r, tip[1] - r)
            pts = [(centre[0] + r * math.cos(p), centre[1] + r * math.sin(p)) for p in phis]
            nrm = [(math.cos(p), math.sin(p)) for p in phis]
            pieces += [(pts[j], pts[j + 1], nrm[j], nrm[j + 1]) for j in range(arc_segments)]
        pieces.append(((u + r, tip[1]), (u + l2, tip[1]), tread, tread))
    start, end, n0, n1 = (np.array(a, float) for a in zip(*pieces, strict=True))
    return _cut(Profile(start, end, n0, n1), length_mm)


def _cut(profile: Profile, length_mm: float) -> Profile:
    """Keep the pieces (or parts of pieces) with u < length_mm."""
    s, e, n0, n1 = profile
    keep = s[:, 0] < length_mm - 1e-12
    s, e, n0, n1 = s[keep], e[keep].copy(), n0[keep], n1[keep].copy()
    over = e[:, 0] > length_mm
    if np.any(over):
        t = (length_mm - s[over, 0]) / (e[over, 0] - s[over, 0])
        e[over] = s[over] + t[:, None] * (e[over] - s[over])
        nn = n0[over] + t[:, None] * (n1[over] - n0[over])
        n1[over] = nn / np.linalg.norm(nn, axis=1, keepdims=True)
    return Profile(s, e, n0, n1)


class Mesh(NamedTuple):
    """A triangle mesh: vertices (V, 3) mm, faces (F, 3) vertex indices, unit vertex normals
    (V, 3). Every triangle is wound counter-clockwise seen from outside (its geometric normal
    points out of the solid, as its vertex normals do)."""

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray


def staircase_mesh(
    beta2_deg: float,
    layer_um: float = 150.0,
    edge_radius_um: float = 25.0,
    arc_segments: int = 16,
    footprint_mm: tuple[float, float] = (20.0, 20.0),
    foot_x_mm: float = -10.0,
    centre_y_mm: float = 0.0,
    closed: bool = True,
) -> Mesh:
    """One printed wedge standing on the plate (z = 0): its stepped face rising along +x from
    its foot at `x = foot_x_mm`, `footprint_mm` = (along x, along y) centred on `centre_y_mm`.

    The face is the `staircase_profile` extruded along y; each straight piece is two triangles
    with its own vertices (sharp creases between facets), the arc pieces carry the arc's normals
    at their ends, so that the shading normal turns smoothly over a rounded edge. With `closed`
    the solid is closed by its two side walls (the region under the profile), the vertical back
    wall at the far end of the footprint and the bottom.
    """
    length, width = footprint_mm
    prof = staircase_profile(beta2_deg, layer_um, edge_radius_um, arc_segments, length)
    y0, y1 = centre_y_mm - width / 2.0, centre_y_mm + width / 2.0
    parts = [_extruded_face(prof, foot_x_mm, y0, y1)]
    if closed:
        parts += _walls(prof, foot_x_mm, length, y0, y1)
    return _join(parts)


def _extruded_face(prof: Profile, x0: float, y0: float, y1: float) -> Mesh:
    """Two triangles per profile piece, four vertices each: (start, y0), (end, y0), (end, y1),
    (start, y1)."""
    n = len(prof.start)

    def at(p: np.ndarray, y: float) -> np.ndarray:
        return np.column_stack([x0 + p[:, 0], np.full(n, y), p[:, 1]])

    def nrm(q: np.ndarray) -> np.ndarray:
        return np.column_stack([q[:, 0], np.zeros(n), q[:, 1]])

    verts = np.stack(
        [at(prof.start, y0), at(prof.end, y0), at(prof.end, y1), at(prof.start, y1)], axis=1
    ).reshape(-1, 3)
    normals = np.stack(
        [
            nrm(prof.normal_start),
            nrm(prof.normal_end),
            nrm(prof.normal_end),
            nrm(prof.normal_start),
        ],
        axis=1,
    ).reshape(-1, 3)
    b = 4 * np.arange(n)[:, None]
    faces = np.concatenate([b + np.array([0, 1, 2]), b + np.array([0, 2, 3])])
    return Mesh(verts, faces.astype(np.int64), normals)


def _walls(prof: Profile, x0: float, length: float, y0: float, y1: float) -> list[Mesh]:
    """The side walls (strips under each profile piece that advances along x), the back wall
    and the bottom, flat-shaded, wound outwards."""
    s, e = prof.start, prof.end
    adv = e[:, 0] - s[:, 0] > 1e-12
    quads = []
    for y, sign in ((y0, -1.0), (y1, 1.0)):
        a, b = s[adv], e[adv]
        q = np.stack(
            [
                np.column_stack([x0 + a[:, 0], np.full(len(a), y), np.zeros(len(a))]),
                np.column_stack([x0 + b[:, 0], np.full(len(a), y), np.zeros(len(a))]),
                np.column_stack([x0 + b[:, 0], np.full(len(a), y), b[:, 1]]),
                np.column_stack([x0 + a[:, 0], np.full(len(a), y), a[:, 1]]),
            ],
            axis=1,
        )
        quads.append(_quads(q, np.array([0.0, sign, 0.0])))
    top = e[-1, 1]
    back = np.array(
        [
            [
                [x0 + length, y0, 0.0],
                [x0 + length, y1, 0.0],
                [x0 + length, y1, top],
                [x0 + length, y0, top],
            ]
        ]
    )
    bottom = np.array(
        [[[x0, y0, 0.0], [x0 + length, y0, 0.0], [x0 + length, y1, 0.0], [x0, y1, 0.0]]]
    )
    return [
        *quads,
        _quads(back, np.array([1.0, 0.0, 0.0])),
        _quads(bottom, np.array([0.0, 0.0, -1.0])),
    ]


def _quads(q: np.ndarray, normal: np.ndarray) -> Mesh:
    """Flat quads (n, 4, 3), corners in order around each, as two triangles each, wound so that
    their geometric normal is along `normal`."""
    n = len(q)
    b = 4 * np.arange(n)[:, None]
    faces = np.concatenate([b + np.array([0, 1, 2]), b + np.array([0, 2, 3])])
    verts = q.reshape(-1, 3)
    geo = np.cross(verts[faces[:, 1]] - verts[faces[:, 0]], verts[faces[:, 2]] - verts[faces[:, 0]])
    flip = geo @ normal < 0
    faces[flip] = faces[flip][:, ::-1]
    return Mesh(verts, faces.astype(np.int64), np.tile(normal, (len(verts), 1)))


def _join(parts: Sequence[Mesh]) -> Mesh:
    """One mesh of several (vertex indices offset)."""
    offsets = np.cumsum([0] + [len(p.vertices) for p in parts[:-1]])
    return Mesh(
        np.concatenate([p.vertices for p in parts]),
        np.concatenate([p.faces + o for p, o in zip(parts, offsets, strict=True)]),
        np.concatenate([p.normals for p in parts]),
    )


# --- the lab: lamp, camera, plate and markers ----------------------------------------------------


def lamp_centre(setup: PbrSetup, light_deg: float) -> np.ndarray:
    """The lamp's centre (mm, base frame) for a photo lit from `light_deg` (docs/scene.md §A near
    lamp: `distance * (-sin L, 0, cos L)`), or the setup's fixed position."""
    if setup.lamp_position_mm is not None:
        return np.asarray(setup.lamp_position_mm, float)
    a = light_deg * DEG
    return setup.lamp_distance_mm * np.array([-math.sin(a), 0.0, math.cos(a)])


def camera_for(setup: PbrSetup, view_deg: float) -> Pinhole:
    """The camera at `view_deg` about y (positive: on the uphill, +x, side), `camera_distance_mm`
    from the origin and looking at it; image right is +y (the layer lines run along the image
    rows), image down is the camera's forward x right. Principal point at the image centre."""
    v = view_deg * DEG
    centre = setup.camera_distance_mm * np.array([math.sin(v), 0.0, math.cos(v)])
    forward = -centre / np.linalg.norm(centre)
    right = np.array([0.0, 1.0, 0.0])
    down = np.cross(forward, right)
    rotation = np.stack([right, down, forward])
    return Pinhole(centre, rotation, setup.focal_px, (setup.width - 1) / 2, (setup.height - 1) / 2)


def lamp_in_frame(
    setup: PbrSetup, light_deg: float, view_deg: float, margin_px: float = 50.0
) -> bool:
    """Whether the lamp would show in the photo (within `margin_px` of the frame), standing in
    front of the specimen: a session avoids those views."""
    cam = camera_for(setup, view_deg)
    lamp = lamp_centre(setup, light_deg)
    if (lamp - cam.centre) @ cam.rotation[2] <= 0:
        return False  # behind the camera
    u, v = cam.project(lamp)
    return bool(
        -margin_px <= u <= setup.width + margin_px and -margin_px <= v <= setup.height + margin_px
    )


def wedge_name(beta2_deg: float) -> str:
    """A wedge's name in the scene file."""
    return f"w{beta2_deg:g}"


def wedge_centre_y(setup: PbrSetup, k: int) -> float:
    """Wedge k's centre along the layer lines (mm)."""
    return (k - (len(setup.wedges_deg) - 1) / 2.0) * setup.row_pitch_mm


def face_corners(setup: PbrSetup, k: int) -> np.ndarray:
    """(4, 3) corners of wedge k's face on its mean plane: foot at y0, top at y0, top at y1, foot
    at y1 (the scene's face_mm outline, lifted by z = (x - x_foot) tan beta2)."""
    half = setup.footprint_mm / 2.0
    yc = wedge_centre_y(setup, k)
    h = setup.footprint_mm * math.tan(setup.wedges_deg[k] * DEG)
    return np.array(
        [
            [-half, yc - half, 0.0],
            [half, yc - half, h],
            [half, yc + half, h],
            [-half, yc + half, 0.0],
        ]
    )


def face_normal(beta2_deg: float) -> np.ndarray:
    """The outward normal of a face's mean plane: the base normal tilted downhill by beta2."""
    b = beta2_deg * DEG
    return np.array([-math.sin(b), 0.0, math.cos(b)])


def marker_corners_mm(setup: PbrSetup, x0: float, y0: float) -> np.ndarray:
    """(4, 2) base corners of a marker's black square in ArUco order (the printed image's
    top-left, top-right, bottom-right, bottom-left): its rows along +x, its columns along +y,
    as the camera (image down = +x at view 0, right = +y) sees it unmirrored."""
    s = setup.marker_mm
    return np.array([[x0, y0], [x0, y0 + s], [x0 + s, y0 + s], [x0 + s, y0]])


def marker_cells(marker_id: int) -> np.ndarray:
    """The marker's 6 x 6 cells (border included): 1 where black ink is printed."""
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    img = cv2.aruco.generateImageMarker(dictionary, marker_id, 6, borderBits=1)
    return (img < 128).astype(int)


def _marker_meshes(setup: PbrSetup) -> tuple[Mesh, Mesh]:
    """The markers' white paper (quiet zone included) 20 um above the plate and their black ink
    cells 40 um above it, as flat quads facing up."""
    cell = setup.marker_mm / 6.0
    q = setup.marker_quiet_cells * cell
    paper, ink = [], []
    for mid, x0, y0 in setup.markers:
        lo_x, lo_y, hi_x, hi_y = x0 - q, y0 - q, x0 + setup.marker_mm + q, y0 + setup.marker_mm + q
        paper.append(
            [[lo_x, lo_y, 0.02], [hi_x, lo_y, 0.02], [hi_x, hi_y, 0.02], [lo_x, hi_y, 0.02]]
        )
        for r, c in zip(*np.nonzero(marker_cells(mid)), strict=True):
            ax, ay = x0 + r * cell, y0 + c * cell  # rows along +x, columns along +y
            ink.append(
                [
                    [ax, ay, 0.04],
                    [ax + cell, ay, 0.04],
                    [ax + cell, ay + cell, 0.04],
                    [ax, ay + cell, 0.04],
                ]
            )
    up = np.array([0.0, 0.0, 1.0])
    return _quads(np.array(paper), up), _quads(np.array(ink), up)


# --- Mitsuba: spectra, scene, render -------------------------------------------------------------


def _mitsuba(variant: str, threads: int | None = None) -> Any:
    """Mitsuba with `variant` selected (Mitsuba keeps one variant per process) and Dr.Jit's
    thread pool at `threads` workers if given."""
    import drjit as dr
    import mitsuba as mi

    if mi.variant() != variant:
        mi.set_variant(variant)
        mi.set_log_level(mi.LogLevel.Error)  # not the sampler's "sample count rounded up to"
    if threads is not None and dr.thread_count() != threads:
        dr.set_thread_count(threads)
    return mi


def _is_spectral(variant: str) -> bool:
    return "spectral" in variant


WAVELENGTHS_NM = np.arange(380.0, 781.0, 5.0)
"""The spectral grid of the illuminant and the camera's sensitivities."""


def _d65() -> np.ndarray:
    import colour

    return colour.SDS_ILLUMINANTS["D65"].copy().align(colour.SpectralShape(380, 780, 5)).values


def _product_integral(a: np.ndarray, b: np.ndarray, step: float) -> float:
    """Exact integral of the product of two piecewise-linear functions on one grid."""
    return float(
        step
        * np.sum(a[:-1] * b[:-1] / 3 + a[:-1] * b[1:] / 6 + a[1:] * b[:-1] / 6 + a[1:] * b[1:] / 3)
    )


def channel_sensitivities(name: str) -> np.ndarray:
    """(3, n) sensitivities on `WAVELENGTHS_NM`, each scaled so that its integral against D65
    (the lamp's spectrum as Mitsuba interpolates it: linearly between the nodes) is 1: a
    spectrally flat surface then reads alike in every channel [conventions §8]."""
    import colour

    msds = colour.MSDS_CAMERA_SENSITIVITIES[name].copy().align(colour.SpectralShape(380, 780, 5))
    s = np.clip(np.asarray(msds.values, float).T, 0.0, None)  # alignment leaves -1e-22
    d65 = _d65()
    return np.stack([c / _product_integral(c, d65, 5.0) for c in s])


def _spectrum(values: np.ndarray) -> dict[str, Any]:
    return {
        "type": "irregular",
        "wavelengths": ", ".join(f"{w:g}" for w in WAVELENGTHS_NM),
        "values": ", ".join(f"{v:.9g}" for v in values),
    }


def _grey(variant: str, value: float) -> dict[str, Any]:
    """A spectrally flat (grey) reflectance or radiance in this variant."""
    if _is_spectral(variant):
        return {"type": "uniform", "value": value}
    return {"type": "rgb", "value": [value, value, value]}


def _emission(variant: str, radiance: float) -> dict[str, Any]:
    """The lamp's radiance: D65 scaled so that the film's channels read `radiance`."""
    if _is_spectral(variant):
        return _spectrum(radiance * _d65())
    return {"type": "rgb", "value": [radiance, radiance, radiance]}


def _film(setup: PbrSetup, width: int, height: int) -> dict[str, Any]:
    """A box-filtered film (each pixel the mean over its own area): the camera's three channel
    sensitivities in a spectral variant, else plain RGB."""
    film: dict[str, Any] = {"width": width, "height": height, "rfilter": {"type": "box"}}
    if _is_spectral(setup.variant):
        srf = channel_sensitivities(setup.sensitivity)
        bands = {f"b{i}_{c}": _spectrum(srf[i]) for i, c in enumerate(CHANNELS)}
        return {"type": "specfilm", "component_format": "float32", **film, **bands}
    return {"type": "hdrfilm", "pixel_format": "rgb", "component_format": "float32", **film}


def lamp_radiance(setup: PbrSetup) -> float:
    """The lamp's radiance in units of E_ref per sr: a uniform sphere of radius r seen from
    distance D gives the irradiance `pi L (r / D)^2` normal to the beam, which is 1 at the
    reference distance."""
    r = setup.lamp_diameter_mm / 2.0
    return 1.0 / (math.pi * (r / setup.lamp_reference_mm) ** 2)


def _pplastic(setup: PbrSetup) -> dict[str, Any]:
    return {
        "type": "pplastic",
        "diffuse_reflectance": _grey(setup.variant, setup.body_diffuse),
        "int_ior": setup.index,
        "ext_ior": 1.0,
        "distribution": setup.distribution,
        "alpha": setup.alpha,
    }


def _diffuse(setup: PbrSetup, albedo: float) -> dict[str, Any]:
    return {"type": "diffuse", "reflectance": _grey(setup.variant, albedo)}


def mitsuba_mesh(mi: Any, name: str, mesh: Mesh, bsdf: dict[str, Any]) -> Any:
    """A Mitsuba mesh with vertex normals from our arrays."""
    props = mi.Properties()
    props["bsdf"] = mi.load_dict(bsdf)
    out = mi.Mesh(name, len(mesh.vertices), len(mesh.faces), props, has_vertex_normals=True)
    params = mi.traverse(out)
    params["vertex_positions"] = mesh.vertices.astype(np.float32).ravel()
    params["faces"] = mesh.faces.astype(np.uint32).ravel()
    params["vertex_normals"] = mesh.normals.astype(np.float32).ravel()
    params.update()
    return out


def _to_world(mi: Any, cam: Pinhole) -> Any:
    """Mitsuba's camera-to-world transform for our pinhole: Mitsuba's camera looks along its +z
    with +x to the image's left and +y up."""
    right, down, forward = cam.rotation
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = -right, -down, forward, cam.centre
    return mi.ScalarTransform4f(m.tolist())


def _sensor(mi: Any, setup: PbrSetup, cam: Pinhole, spp: int, seed: int) -> dict[str, Any]:
    fov = 2.0 * math.degrees(math.atan(setup.width / 2.0 / cam.focal_px))
    return {
        "type": "perspective",
        "fov": fov,
        "fov_axis": "x",
        "near_clip": 1.0,
        "far_clip": 1e5,
        "to_world": _to_world(mi, cam),
        "film": _film(setup, setup.width, setup.height),
        "sampler": {"type": "multijitter", "sample_count": spp, "seed": seed},
    }


def plate_shape(mi: Any, bsdf: dict[str, Any], size_mm: float = 2000.0) -> dict[str, Any]:
    """The plate: a square in z = 0 centred on the origin, facing up."""
    half = size_mm / 2.0
    return {
        "type": "rectangle",
        "to_world": mi.ScalarTransform4f().scale([half, half, 1.0]),
        "bsdf": bsdf,
    }


def lamp_shape(setup: PbrSetup, centre: np.ndarray) -> dict[str, Any]:
    """The LED ball: a black sphere of `lamp_diameter_mm` emitting `lamp_radiance` uniformly."""
    return {
        "type": "sphere",
        "center": np.asarray(centre, float).tolist(),
        "radius": setup.lamp_diameter_mm / 2.0,
        "bsdf": _diffuse(setup, 0.0),
        "emitter": {"type": "area", "radiance": _emission(setup.variant, lamp_radiance(setup))},
    }


def lab_shapes(mi: Any, setup: PbrSetup, light_deg: float) -> dict[str, Any]:
    """The wedges, the plate, the markers and the lamp of one photo, for `mi.load_dict`."""
    shapes: dict[str, Any] = {}
    for k, beta2 in enumerate(setup.wedges_deg):
        mesh = staircase_mesh(
            beta2,
            setup.layer_um,
            setup.edge_radius_um,
            setup.arc_segments,
            (setup.footprint_mm, setup.footprint_mm),
            -setup.footprint_mm / 2.0,
            wedge_centre_y(setup, k),
        )
        shapes[wedge_name(beta2)] = mitsuba_mesh(mi, wedge_name(beta2), mesh, _pplastic(setup))
    paper, ink = _marker_meshes(setup)
    shapes["paper"] = mitsuba_mesh(mi, "paper", paper, _diffuse(setup, setup.paper_albedo))
    shapes["ink"] = mitsuba_mesh(mi, "ink", ink, _diffuse(setup, setup.ink_albedo))
    shapes["plate"] = plate_shape(mi, _diffuse(setup, setup.plate_albedo))
    shapes["lamp"] = lamp_shape(setup, lamp_centre(setup, light_deg))
    return shapes


def load_scene(mi: Any, setup: PbrSetup, shapes: dict[str, Any]) -> Any:
    """A Mitsuba scene of `shapes` with the path tracer at `max_depth` (no sensor: the camera
    is passed to each render)."""
    return mi.load_dict(
        {"type": "scene", "integrator": {"type": "path", "max_depth": setup.max_depth}, **shapes}
    )


class Render(NamedTuple):
    """One photo's noise-free radiance / E_ref (1/sr), (H, W, 3) in the channels R, G, B (each
    pixel the mean over its area), and per pixel the Monte Carlo variance of that mean (from
    two independent half renders; NaN outside the faces' and markers' boxes)."""

    radiance: np.ndarray
    mc_variance: np.ndarray


def render_photo_radiance(
    setup: PbrSetup, light_deg: float, view_deg: float, seed: int = 0, threads: int | None = None
) -> Render:
    """Path-trace one photo of the lab: the whole frame at `spp_background` samples per pixel,
    then each visible face's and each marker's box (their outlines projected through our own
    camera, 6 px margin) at `spp` / `spp_markers`, as two independent halves whose difference
    gives the Monte Carlo variance."""
    mi = _mitsuba(setup.variant, threads)
    cam = camera_for(setup, view_deg)
    scene = load_scene(mi, setup, lab_shapes(mi, setup, light_deg))
    base = seed * 1_000_003 + 7919 * round(view_deg * 10) + round(light_deg * 10)
    full = render_view(mi, scene, setup, cam, None, setup.spp_background, base)
    var = np.full(full.shape, np.nan)
    for j, (box, spp) in enumerate(_boxes(setup, cam, light_deg, view_deg)):
        halves = [
            render_view(mi, scene, setup, cam, box, spp // 2, base + 2 * j + h + 1) for h in (0, 1)
        ]
        x0, y0, x1, y1 = box
        full[y0:y1, x0:x1] = 0.5 * (halves[0] + halves[1])
        var[y0:y1, x0:x1] = 0.25 * (halves[0] - halves[1]) ** 2
    return Render(full, var)


def render_view(
    mi: Any,
    scene: Any,
    setup: PbrSetup,
    cam: Pinhole,
    box: tuple[int, int, int, int] | None,
    spp: int,
    seed: int,
) -> np.ndarray:
    """(H, W, 3) radiance / E_ref through our camera `cam`: the whole frame, or only the pixels
    x0 <= x < x1, y0 <= y < y1 of `box`."""
    sensor = _sensor(mi, setup, cam, spp, seed % 2**31)
    if box is not None:
        x0, y0, x1, y1 = box
        sensor["film"] |= {
            "crop_offset_x": x0,
            "crop_offset_y": y0,
            "crop_width": x1 - x0,
            "crop_height": y1 - y0,
        }
    img = mi.render(scene, sensor=mi.load_dict(sensor), spp=spp, seed=seed % 2**31)
    return np.array(img, dtype=np.float64)


def face_visible(setup: PbrSetup, light_deg: float, view_deg: float, k: int) -> bool:
    """Lit and seen as stairfit decides from the photo's nominal angles (docs/scene.md: both
    face-frame angles within 89 deg): theta_i = light_deg - beta2, theta_o = view_deg + beta2."""
    b = setup.wedges_deg[k]
    return abs(light_deg - b) < 89.0 and abs(view_deg + b) < 89.0


def _boxes(
    setup: PbrSetup, cam: Pinhole, light_deg: float, view_deg: float
) -> list[tuple[tuple[int, int, int, int], int]]:
    """Pixel boxes (x0, y0, x1, y1) around every visible face and every marker's paper, with
    their samples per pixel."""
    polys = [
        (cam.project(face_corners(setup, k)), setup.spp)
        for k in range(len(setup.wedges_deg))
        if face_visible(setup, light_deg, view_deg, k)
    ]
    cell = setup.marker_mm / 6.0
    q = setup.marker_quiet_cells * cell
    for _, x0, y0 in setup.markers:
        lo, hi = -q, setup.marker_mm + q
        paper = np.array([[x0 + a, y0 + b, 0.0] for a in (lo, hi) for b in (lo, hi)])
        polys.append((cam.project(paper), setup.spp_markers))
    out = []
    for px, spp in polys:
        x0, y0 = np.floor(px.min(axis=0)).astype(int) - 6
        x1, y1 = np.ceil(px.max(axis=0)).astype(int) + 7
        x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, setup.width), min(y1, setup.height)
        if x0 < x1 and y0 < y1:
            out.append(((int(x0), int(y0), int(x1), int(y1)), spp))
    return out


# --- the truth: each face's mean over its own projected polygon ---------------------------------


def face_mask(
    cam: Pinhole, corners: np.ndarray, erode_px: float, width: int, height: int
) -> np.ndarray:
    """(H, W) pixels whose centre lies inside the projected (convex) face polygon, at least
    `erode_px` from each of its edges. Straight edges stay straight through a pinhole, so the
    projected corners give the exact outline."""
    px = cam.project(corners)
    area = 0.5 * np.sum(px[:, 0] * np.roll(px[:, 1], -1) - np.roll(px[:, 0], -1) * px[:, 1])
    yy, xx = np.mgrid[0:height, 0:width].astype(float)
    inside = np.ones((height, width), bool)
    for a, b in zip(px, np.roll(px, -1, axis=0), strict=True):
        edge = b - a
        # signed distance, positive on the polygon's side
        dist = (edge[0] * (yy - a[1]) - edge[1] * (xx - a[0])) / np.hypot(*edge)
        inside &= np.sign(area) * dist >= erode_px
    return inside


def _face_directions(
    setup: PbrSetup, cam: Pinhole, k: int, mask: np.ndarray, lamp: np.ndarray
) -> dict[str, Any]:
    """Mean directions from the face points the masked pixels see (their centres back-projected
    onto the face's mean plane) to the lamp's centre and to the camera, in the base frame, and
    the face-frame angles [conventions §1]: in-plane theta_i, theta_o (deg) and the angles out
    of the plane of incidence (towards +y positive)."""
    v, u = np.nonzero(mask)
    d = np.stack(cam.rays(u.astype(float), v.astype(float)), axis=-1)
    n = face_normal(setup.wedges_deg[k])
    p0 = face_corners(setup, k)[0]
    t = ((p0 - cam.centre) @ n) / (d @ n)
    pts = cam.centre + t[:, None] * d
    to_light = lamp - pts
    to_light /= np.linalg.norm(to_light, axis=1, keepdims=True)
    to_cam = cam.centre - pts
    to_cam /= np.linalg.norm(to_cam, axis=1, keepdims=True)
    b = setup.wedges_deg[k] * DEG
    e = np.array([math.cos(b), 0.0, math.sin(b)])  # uphill along the face
    deg = 180.0 / math.pi
    return {
        "light_dir": _unit_mean(to_light),
        "view_dir": _unit_mean(to_cam),
        "theta_i_deg": float(np.mean(np.arctan2(-(to_light @ e), to_light @ n)) * deg),
        "theta_o_deg": float(np.mean(np.arctan2(to_cam @ e, to_cam @ n)) * deg),
        "light_out_of_plane_deg": float(np.mean(np.arcsin(to_light[:, 1])) * deg),
        "view_out_of_plane_deg": float(np.mean(np.arcsin(to_cam[:, 1])) * deg),
    }


def _unit_mean(vectors: np.ndarray) -> list[float]:
    m = vectors.mean(axis=0)
    return (m / np.linalg.norm(m)).tolist()


def roi_mask(
    cam: Pinhole, corners: np.ndarray, erode_px: int, width: int, height: int
) -> np.ndarray:
    """(H, W) the face's outline through our camera, rasterised and eroded by the rule
    docs/imaging.md states for stairfit's ROIs (cv2.fillPoly with vertices to 1/256 px, then
    cv2.erode with a disk of radius `erode_px`, the image border not an edge): the region a
    measurement of that face averages, drawn here from the renderer's own projection."""
    poly = np.round(cam.project(corners) * 256).astype(np.int32)
    mask = np.zeros((height, width), np.uint8)
    cv2.fillPoly(mask, [poly], 1, lineType=cv2.LINE_8, shift=8)
    disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * erode_px + 1, 2 * erode_px + 1))
    return cv2.erode(mask, disk).astype(bool)


def _region_mean(setup: PbrSetup, render: Render, mask: np.ndarray) -> dict[str, Any]:
    """The mean relative radiance per channel over `mask` and its Monte Carlo error."""
    n = int(mask.sum())
    if n == 0:
        return {"radiance": None, "mc_stderr": None, "n_pixels": 0}
    mean = setup.k_cam * render.radiance[mask].mean(axis=0)
    mc = setup.k_cam * np.sqrt(render.mc_variance[mask].sum(axis=0)) / n
    return {"radiance": mean.tolist(), "mc_stderr": mc.tolist(), "n_pixels": n}


def face_truths(
    setup: PbrSetup, render: Render, cam: Pinhole, light_deg: float, view_deg: float
) -> dict[str, dict[str, Any] | None]:
    """Per wedge: None where the face is not measured (turned away, face_visible), else its mean
    relative radiance per channel (`k_cam` x the render's mean over the pixels whose centre lies
    `truth_erode_px` inside the face's projected outline: stairfit's units), the Monte Carlo
    standard error of that mean, the pixel count and the mean directions (`_face_directions`);
    and the same mean over the region stairfit's ROI would cover (`roi_mask` with the scene's
    erosion, default 8 px) as `roi_radiance`, `roi_mc_stderr`, `roi_n_pixels`. The two differ
    where a face's resolved layer stripes or gradients make its mean depend on the region."""
    out: dict[str, dict[str, Any] | None] = {}
    lamp = lamp_centre(setup, light_deg)
    erode = 8 if setup.erode_px is None else setup.erode_px
    for k, beta2 in enumerate(setup.wedges_deg):
        corners = face_corners(setup, k)
        mask = face_mask(cam, corners, setup.truth_erode_px, setup.width, setup.height)
        if not face_visible(setup, light_deg, view_deg, k) or not mask.any():
            out[wedge_name(beta2)] = None
            continue
        roi = _region_mean(setup, render, roi_mask(cam, corners, erode, setup.width, setup.height))
        out[wedge_name(beta2)] = {
            **_region_mean(setup, render, mask),
            **{f"roi_{key}": value for key, value in roi.items()},
            **_face_directions(setup, cam, k, mask, lamp),
        }
    return out


def retruth(folder: str | Path) -> dict[str, Any]:
    """Take every photo's truth again from its kept render (`keep_render`) with this module's
    `face_truths`, rewrite the truth parts and truth.json; return the truth."""
    folder = Path(folder)
    setup = setup_from_truth(json.loads((folder / "truth.json").read_text()))
    photos = []
    for i, (light_deg, view_deg) in enumerate(setup.photos):
        part = folder / "truth_parts" / f"{photo_name(i)}.json"
        photo = json.loads(part.read_text())
        cam = camera_for(setup, view_deg)
        photo["faces"] = face_truths(setup, load_render(folder, i), cam, light_deg, view_deg)
        _write_text(part, json.dumps(photo, indent=1))
        photos.append(photo)
    truth = json.loads((folder / "truth.json").read_text())
    truth = _truth(setup, truth["seed"], photos, truth["flat_fields"])
    _write_text(folder / "truth.json", json.dumps(truth, indent=1))
    return truth


# --- the sensor and its files --------------------------------------------------------------------


def _cfa(setup: PbrSetup) -> np.ndarray:
    """(H, W) colour of each pixel of the RGGB mosaic (0 = R, 1 = G, 2 = B)."""
    return np.tile(np.array([[0, 1], [1, 2]]), (setup.height // 2, setup.width // 2))


def vignetting(setup: PbrSetup) -> np.ndarray:
    """(H, W, 3) the lens's relative illumination per channel: 1 at the centre, `1 - f (0.7 r^2
    + 0.3 r^4)` with r = 1 in a corner (a polynomial, which the flat field's fit follows)."""
    h, w = setup.height, setup.width
    yy, xx = np.mgrid[0:h, 0:w]
    r2 = ((xx - (w - 1) / 2) ** 2 + (yy - (h - 1) / 2) ** 2) / (
        ((w - 1) / 2) ** 2 + ((h - 1) / 2) ** 2
    )
    f = np.asarray(setup.vignetting)
    return 1.0 - f * (0.7 * r2 + 0.3 * r2**2)[..., None]


def dn_per_value(setup: PbrSetup, exposure_time_s: float) -> float:
    """DN above black per unit of stairfit's relative radiance: t (ISO / 100) / N^2."""
    return exposure_time_s * (setup.iso / 100.0) / setup.f_number**2


def exposure_time(setup: PbrSetup, render: Render) -> float:
    """The photo's exposure: its brightest pixel (noise-free, vignetted) at `fill` of the raw
    range, rounded down to a third of a stop."""
    peak = float(np.max(render.radiance * vignetting(setup))) * setup.k_cam
    full = 2**setup.bits - 1 - setup.black_dn
    t = setup.fill * full / peak / dn_per_value(setup, 1.0)
    third = 2.0 ** (math.floor(math.log2(t) * 3) / 3)
    return float(Fraction(third).limit_denominator(1_000_000))  # exactly the tag's rational


def sensor_mosaic(setup: PbrSetup, mean_dn: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(H, W) uint16 RGGB mosaic of an (H, W, 3) image of mean DN above black: each pixel keeps
    its own colour; Poisson shot noise in electrons, Gaussian read noise, the black level,
    rounding, clipping at the white level."""
    cfa = _cfa(setup)
    dn = np.take_along_axis(mean_dn, cfa[..., None], axis=2)[..., 0]
    gain = setup.gain_e_per_dn * 100.0 / setup.iso
    electrons = rng.poisson(np.maximum(dn, 0.0) * gain)
    raw = electrons / gain + rng.normal(0.0, setup.read_noise_dn, dn.shape) + setup.black_dn
    return np.clip(np.rint(raw), 0, 2**setup.bits - 1).astype(np.uint16)


def _rational(x: float) -> tuple[int, int]:
    f = Fraction(x).limit_denominator(1_000_000)
    return f.numerator, f.denominator


def write_dng(path: Path, mosaic: np.ndarray, setup: PbrSetup, exposure_time_s: float) -> None:
    """A CFA DNG (RGGB) with black and white levels and the exposure tags in IFD0 (where
    TIFF/EP puts them), written to a temporary file and renamed: a folder never holds half a
    photo."""
    tags = [
        (271, "s", 0, "stairfit tests", True),  # Make
        (272, "s", 0, "Mitsuba 3 lab", True),  # Model
        (33421, "H", 2, (2, 2), True),  # CFARepeatPatternDim
        (33422, "B", 4, (0, 1, 1, 2), True),  # CFAPattern: R G / G B
        (50706, "B", 4, (1, 4, 0, 0), True),  # DNGVersion
        (50708, "s", 0, "Mitsuba 3 lab", True),  # UniqueCameraModel
        (50710, "B", 3, (0, 1, 2), True),  # CFAPlaneColor
        (50714, "I", 1, setup.black_dn, True),  # BlackLevel
        (50717, "I", 1, 2**setup.bits - 1, True),  # WhiteLevel
        (50721, "2i", 9, (1, 1, 0, 1, 0, 1, 0, 1, 1, 1, 0, 1, 0, 1, 0, 1, 1, 1), True),  # identity
        (50778, "H", 1, 21, True),  # CalibrationIlluminant1: D65
        (33434, "2I", 1, _rational(exposure_time_s), True),  # ExposureTime
        (33437, "2I", 1, _rational(setup.f_number), True),  # FNumber
        (34855, "H", 1, round(setup.iso), True),  # ISOSpeedRatings
    ]
    tmp = path.with_name(path.name + ".part")
    tifffile.imwrite(tmp, mosaic, photometric=32803, extratags=tags, metadata=None)
    os.replace(tmp, path)


def _write_text(path: Path, text: str) -> None:
    """Write a text file atomically (a temporary file, then a rename)."""
    tmp = path.with_name(path.name + ".part")
    tmp.write_text(text)
    os.replace(tmp, path)


# --- the folder: scene.toml, DNGs, flat fields, truth.json ---------------------------------------


def photo_name(i: int) -> str:
    return f"DSC_{i + 1:04d}.dng"


def scene_dict(setup: PbrSetup) -> dict[str, Any]:
    """scene.toml as a dict, written from docs/scene.md: wedges by their face_mm outlines placed
    from the markers through the pinhole (`[camera] focal_length_px`), the near lamp by its
    diameter and distance (or position), a flat field, the photos' light and view angles."""
    half = setup.footprint_mm / 2.0
    wedges = []
    for k, beta2 in enumerate(setup.wedges_deg):
        yc = wedge_centre_y(setup, k)
        face = [[-half, yc - half], [half, yc - half], [half, yc + half], [-half, yc + half]]
        wedges.append({"name": wedge_name(beta2), "angle_deg": beta2, "face_mm": face})
    specimen: dict[str, Any] = {"layer_um": setup.layer_um, "plate_albedo": setup.plate_albedo}
    if setup.index == 1.46:
        specimen["material"] = "pla"
    else:
        specimen["index"] = {"model": "constant", "n": setup.index}
    light: dict[str, Any] = {
        "illuminant": "D65",
        "shape": "disk",
        "diameter_mm": setup.lamp_diameter_mm,
    }
    if setup.lamp_position_mm is None:
        light["distance_mm"] = setup.lamp_distance_mm
    else:
        light["position_mm"] = list(setup.lamp_position_mm)
    scene: dict[str, Any] = {
        "version": 1,
        "angles_relative_to": "base",
        "specimen": {**specimen, "wedges": wedges},
        "light": light,
        "camera": {
            "sensitivity": setup.sensitivity,
            # the spread of viewing angles across one footprint seen from the camera
            "angular_extent_deg": round(setup.footprint_mm / setup.camera_distance_mm / DEG, 4),
            "focal_length_px": round(setup.focal_px, 3),
            "principal_point_px": [(setup.width - 1) / 2, (setup.height - 1) / 2],
        },
        "markers": {
            "dictionary": "DICT_4X4_50",
            "marker": [
                {"id": m, "corners_mm": marker_corners_mm(setup, x0, y0).tolist()}
                for m, x0, y0 in setup.markers
            ],
        },
        "photos": [
            {"file": photo_name(i), "light_deg": light_deg, "view_deg": view_deg}
            for i, (light_deg, view_deg) in enumerate(setup.photos)
        ],
        "truth": {"edge_radius_um": setup.edge_radius_um, "fillet_radius_um": 0.0, "delta_n": 0.0},
    }
    if setup.erode_px is not None:
        scene["extraction"] = {"erode_px": setup.erode_px}
    if setup.flat_photos:
        scene["calibration"] = {
            "flat_field": [f"FLAT_{k + 1:02d}.dng" for k in range(setup.flat_photos)]
        }
    return scene


def toml_text(doc: dict[str, Any], prefix: str = "") -> str:
    """A small TOML writer for scene files: plain values and number lists inline, nested tables
    and arrays of tables below (what tomli_w writes, with each number list on one line)."""

    def value(v: Any) -> str:
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, str):
            return json.dumps(v)
        if isinstance(v, list | tuple):
            return "[" + ", ".join(value(x) for x in v) + "]"
        if isinstance(v, dict):
            return "{ " + ", ".join(f"{k} = {value(x)}" for k, x in v.items()) + " }"
        return repr(float(v)) if isinstance(v, float) else str(v)

    def is_tables(v: Any) -> bool:
        return isinstance(v, list) and bool(v) and all(isinstance(x, dict) for x in v)

    plain = [
        f"{k} = {value(v)}"
        for k, v in doc.items()
        if not (isinstance(v, dict) and prefix + k not in INLINE_TABLES) and not is_tables(v)
    ]
    out = "\n".join(plain) + ("\n" if plain else "")
    for k, v in doc.items():
        name = prefix + k
        if isinstance(v, dict) and name not in INLINE_TABLES:
            out += f"\n[{name}]\n" + toml_text(v, name + ".")
        elif is_tables(v):
            for item in v:
                out += f"\n[[{name}]]\n" + toml_text(item, name + ".")
    return out


INLINE_TABLES = {"specimen.index"}
"""Tables written inline (`index = { model = "constant", n = 1.53 }`, as docs/scene.md shows)."""


def render_one(
    setup: PbrSetup,
    folder: Path,
    i: int,
    seed: int,
    threads: int | None = None,
    keep_render: bool = False,
) -> dict[str, Any]:
    """Render photo i into `folder` (its DNG) and return its truth (also written to
    `truth_parts/`, after the DNG, so that a part marks a finished photo). With `keep_render`
    the noise-free render is kept as `renders/NAME.npz` (float32 `radiance` and `mc_variance`),
    from which other truths (another erosion, other regions) can be taken later."""
    light_deg, view_deg = setup.photos[i]
    t0 = time.perf_counter()
    render = render_photo_radiance(setup, light_deg, view_deg, seed, threads)
    seconds = time.perf_counter() - t0
    if keep_render:
        (folder / "renders").mkdir(exist_ok=True)
        tmp = folder / "renders" / f"{photo_name(i)}.part.npz"
        np.savez_compressed(
            tmp,
            radiance=render.radiance.astype(np.float32),
            mc_variance=render.mc_variance.astype(np.float32),
        )
        os.replace(tmp, folder / "renders" / f"{photo_name(i)}.npz")
    cam = camera_for(setup, view_deg)
    t = exposure_time(setup, render)
    mean_dn = setup.k_cam * render.radiance * vignetting(setup) * dn_per_value(setup, t)
    rng = np.random.default_rng([seed, i])
    write_dng(folder / photo_name(i), sensor_mosaic(setup, mean_dn, rng), setup, t)
    truth = {
        "file": photo_name(i),
        "light_deg": light_deg,
        "view_deg": view_deg,
        "lamp_centre_mm": lamp_centre(setup, light_deg).tolist(),
        "camera": {
            "centre_mm": cam.centre.tolist(),
            "rotation": cam.rotation.tolist(),
            "focal_px": cam.focal_px,
            "principal_point_px": [cam.cx, cam.cy],
        },
        "exposure_time_s": t,
        "f_number": setup.f_number,
        "iso": setup.iso,
        "render_seconds": seconds,
        "faces": face_truths(setup, render, cam, light_deg, view_deg),
    }
    parts = folder / "truth_parts"
    parts.mkdir(exist_ok=True)
    _write_text(parts / f"{photo_name(i)}.json", json.dumps(truth, indent=1))
    return truth


def write_flats(setup: PbrSetup, folder: Path, seed: int) -> list[str]:
    """Flat-field photos: a uniform diffuse target through the same lens, its centre at half of
    the raw range at 1/50 s."""
    names = []
    t = 1.0 / 50.0
    full = 2**setup.bits - 1 - setup.black_dn
    for k in range(setup.flat_photos):
        names.append(f"FLAT_{k + 1:02d}.dng")
        if (folder / names[-1]).exists():
            continue
        rng = np.random.default_rng([seed, 10_000 + k])
        write_dng(
            folder / names[-1], sensor_mosaic(setup, 0.5 * full * vignetting(setup), rng), setup, t
        )
    return names


UNITS = (
    "face radiance: stairfit's relative radiance (docs/imaging.md §Units: DN above black per "
    "second at f/1 and ISO 100, after the flat field, whose gain is 1 at the image centre) = "
    "k_cam x (radiance / E_ref), E_ref being the irradiance normal to the beam that the lamp "
    "gives at its reference distance; radiance / E_ref is in 1/sr (a white Lambertian plate "
    "facing the lamp at that distance reads 1/pi). Each value is the mean of the photo's own "
    "noise-free render (before vignetting, mosaic and sensor noise) over the pixels whose centre "
    "lies truth_erode_px inside the face's mean-plane outline projected through the camera; "
    "mc_stderr is its Monte Carlo error against the infinitely sampled render. roi_radiance is "
    "the same mean over the region stairfit's ROI covers (that outline filled and eroded by "
    "roi_erode_px as docs/imaging.md says), for comparing a measurement over the same pixels."
)


def render_folder(
    path: str | Path,
    setup: PbrSetup | None = None,
    seed: int = 0,
    *,
    threads: int | None = None,
    progress: Callable[[str], None] | None = None,
    keep_render: bool = False,
) -> dict[str, Any]:
    """Write a photo folder: the DNGs, the flat fields, scene.toml and truth.json (which stairfit
    never reads); return the truth.

    Resumable: a photo whose DNG and truth part (`truth_parts/NAME.json`) both exist is not
    rendered again; every file is written atomically. `progress` gets one line per photo;
    `keep_render` keeps each photo's noise-free render (`render_one`).
    """
    setup = setup or PbrSetup()
    folder = Path(path)
    folder.mkdir(parents=True, exist_ok=True)
    photos = []
    for i in range(len(setup.photos)):
        part = folder / "truth_parts" / f"{photo_name(i)}.json"
        if part.exists() and (folder / photo_name(i)).exists():
            photos.append(json.loads(part.read_text()))
            msg = "already there"
        else:
            photos.append(render_one(setup, folder, i, seed, threads, keep_render))
            msg = f"rendered in {photos[-1]['render_seconds']:.1f} s"
        if progress:
            light_deg, view_deg = setup.photos[i]
            progress(
                f"{i + 1}/{len(setup.photos)} {photo_name(i)} light {light_deg:g} deg, "
                f"view {view_deg:g} deg: {msg}"
            )
    flats = write_flats(setup, folder, seed)
    _write_text(folder / "scene.toml", toml_text(scene_dict(setup)))
    truth = _truth(setup, seed, photos, flats)
    _write_text(folder / "truth.json", json.dumps(truth, indent=1))
    return truth


def _truth(
    setup: PbrSetup, seed: int, photos: list[dict[str, Any]], flats: list[str]
) -> dict[str, Any]:
    import mitsuba as mi

    names = [wedge_name(b) for b in setup.wedges_deg]
    return {
        "renderer": "tests/pbr_photos.py",
        "mitsuba": mi.__version__,
        "seed": seed,
        "setup": asdict(setup),
        "units": UNITS,
        "roi_erode_px": 8 if setup.erode_px is None else setup.erode_px,
        "k_cam": setup.k_cam,
        "lamp": {
            "radiance_per_e_ref": lamp_radiance(setup),
            "reference_distance_mm": setup.lamp_reference_mm,
            "diameter_mm": setup.lamp_diameter_mm,
        },
        "camera": {
            "focal_length_px": setup.focal_px,
            "principal_point_px": [(setup.width - 1) / 2, (setup.height - 1) / 2],
            "distance_mm": setup.camera_distance_mm,
        },
        "wedges": names,
        "flat_fields": flats,
        "photos": photos,
        "face_radiance": [
            [p["faces"][w]["radiance"] if p["faces"][w] else None for w in names] for p in photos
        ],
    }


def load_render(folder: str | Path, i: int) -> Render:
    """Photo i's noise-free render kept by `render_folder(..., keep_render=True)`: with
    `face_truths(replace(setup, truth_erode_px=...), render, camera_for(setup, view), light,
    view)` it gives the truth over other regions without rendering again."""
    with np.load(Path(folder) / "renders" / f"{photo_name(i)}.npz") as z:
        return Render(z["radiance"].astype(np.float64), z["mc_variance"].astype(np.float64))


def setup_from_truth(truth: dict[str, Any]) -> PbrSetup:
    """The `PbrSetup` a truth.json was rendered with (JSON's lists back to tuples)."""

    def tup(v: Any) -> Any:
        return tuple(tup(x) for x in v) if isinstance(v, list) else v

    return PbrSetup(**{k: tup(v) for k, v in truth["setup"].items()})


# --- one patch under chosen directions: the BRDF-level check -------------------------------------


class PatchRadiance(NamedTuple):
    """A patch's mean radiance under a light of unit irradiance.

    Attributes:
        value: (3,) the mean reflected radiance over the patch divided by the irradiance normal
            to the beam E_perp (1/sr), channels R, G, B: for a flat surface this is
            `f(l, v) cos(theta_i)`, the BRDF times the cosine of the incidence angle on the
            mean plane; for the staircase it is the same quantity of the macroscopic surface
            (the face's mean plane), shadowing, masking and interreflections included.
        stderr: (3,) its Monte Carlo standard error (the scatter of `repeats` renders).
        periods: whole layer periods the patch spans across the layer lines.
        size_mm: (across the layer lines along the face, along them) of the patch on the mean
            plane.
    """

    value: np.ndarray
    stderr: np.ndarray
    periods: int
    size_mm: tuple[float, float]


def patch_radiance(
    setup: PbrSetup,
    beta2_deg: float,
    light_dir: Sequence[float],
    view_dir: Sequence[float],
    *,
    light_distance_mm: float | None = None,
    frame: str = "base",
    surface: str = "staircase",
    min_length_mm: float = 5.0,
    periods: int | None = None,
    spp: int = 256,
    pixels: int = 32,
    repeats: int = 4,
    seed: int = 0,
    threads: int | None = None,
) -> PatchRadiance:
    """Render one wedge's face, seen from far along `view_dir` and lit along `light_dir`, and
    return its mean radiance per unit irradiance (`PatchRadiance.value`, 1/sr).

    Directions are unit vectors pointing from the surface towards the light and towards the
    camera, both above the face's mean plane, in the wedge's base frame (`frame="base"`: x
    uphill, y along the layer lines, z the plate's normal; the face's normal is
    `(-sin beta2, 0, cos beta2)`) or in its face frame (`frame="face"`, conventions §11: x
    uphill along the face, y along the layers, z the face's normal). In §11's units the value is
    `(w_i . z) p / (w_o . z)`, p = f cos(theta_o) the lab model's density.

    The light is distant (a `directional` emitter of unit irradiance normal to the beam), or
    with `light_distance_mm` the lab's LED ball (`setup.lamp_diameter_mm`) at that distance
    from the patch centre along `light_dir`, normalised so that its irradiance normal to the
    beam at the patch centre is 1 (Mitsuba's single-precision sphere sampling makes it 0.08%
    higher at 6 mm and 500 mm, tests/validation/test_pbr_photos.py). The camera is orthographic;
    the patch is a rectangle on the mean plane spanning exactly `periods` layer periods across the
    layer lines (default: the fewest that reach `min_length_mm`), so that no part of a period is
    over- or under-counted, cut from a staircase extending 10 mm beyond it on every side
    (shadows and masking from the neighbouring steps included). The material, layers, edges and
    Mitsuba variant are the setup's. `surface="flat"` renders the mean plane itself (a flat
    sheet of the facets' material), whose value is the material's `f cos theta_i`.
    """
    mi = _mitsuba(setup.variant, threads)
    b = beta2_deg * DEG
    n = face_normal(beta2_deg)
    e = np.array([math.cos(b), 0.0, math.sin(b)])
    light, view = _unit(light_dir), _unit(view_dir)
    if frame == "face":
        light, view = face_to_base(light, beta2_deg), face_to_base(view, beta2_deg)
    elif frame != "base":
        raise ValueError(f"frame {frame!r}: use 'base' or 'face'")
    if light @ n <= 0.0 or view @ n <= 0.0:
        raise ValueError("light_dir and view_dir must point above the face's mean plane")
    period = setup.layer_um * 1e-3 / math.sin(b)
    m = periods or max(1, math.ceil(min_length_mm / period))
    along, width = m * period, 2.0
    mesh, centre = _patch_mesh(setup, beta2_deg, surface, along, width)
    sensor = _patch_sensor(mi, setup, centre, n, e, view, along, width, pixels, spp)
    shapes = {
        "patch": mitsuba_mesh(mi, "patch", mesh, _pplastic(setup)),
        "light": _patch_light(setup, centre, light, light_distance_mm),
    }
    scene = load_scene(mi, setup, shapes)
    means = []
    for r in range(repeats):
        sensor["sampler"]["seed"] = seed * 1000 + r
        img = mi.render(scene, sensor=mi.load_dict(sensor), spp=spp, seed=seed * 1000 + r)
        means.append(np.array(img, dtype=np.float64).mean(axis=(0, 1)))
    means_arr = np.array(means)
    stderr = (
        means_arr.std(axis=0, ddof=1) / math.sqrt(repeats) if repeats > 1 else np.full(3, np.nan)
    )
    return PatchRadiance(means_arr.mean(axis=0), stderr, m, (along, width))


def base_to_face(w: Sequence[float], beta2_deg: float) -> np.ndarray:
    """A direction in a wedge's base frame in its face frame (conventions §11):
    `x_face = x cos b2 + z sin b2`, `z_face = -x sin b2 + z cos b2`."""
    b = beta2_deg * DEG
    return np.array(
        [w[0] * math.cos(b) + w[2] * math.sin(b), w[1], -w[0] * math.sin(b) + w[2] * math.cos(b)]
    )


def face_to_base(w: Sequence[float], beta2_deg: float) -> np.ndarray:
    """A direction in a wedge's face frame in its base frame (the inverse of `base_to_face`)."""
    b = beta2_deg * DEG
    return np.array(
        [w[0] * math.cos(b) - w[2] * math.sin(b), w[1], w[0] * math.sin(b) + w[2] * math.cos(b)]
    )


def _unit(v: Sequence[float]) -> np.ndarray:
    a = np.asarray(v, float)
    return a / np.linalg.norm(a)


def _patch_mesh(
    setup: PbrSetup, beta2_deg: float, surface: str, along: float, width: float
) -> tuple[Mesh, np.ndarray]:
    """The surface around the patch and the patch's centre on the mean plane: the staircase (its
    foot at x = 0) or its flat mean plane, 10 mm beyond the patch on every side."""
    b = beta2_deg * DEG
    margin = 10.0
    length_x = (along + 2.0 * margin) * math.cos(b)
    ux = length_x / 2.0
    centre = np.array([ux, 0.0, ux * math.tan(b)])
    ly = width + 2.0 * margin
    if surface == "flat":
        h = length_x * math.tan(b)
        quad = np.array(
            [
                [
                    [0.0, -ly / 2, 0.0],
                    [length_x, -ly / 2, h],
                    [length_x, ly / 2, h],
                    [0.0, ly / 2, 0.0],
                ]
            ]
        )
        return _quads(quad, face_normal(beta2_deg)), centre
    if surface != "staircase":
        raise ValueError(f"surface {surface!r}: use 'staircase' or 'flat'")
    mesh = staircase_mesh(
        beta2_deg,
        setup.layer_um,
        setup.edge_radius_um,
        setup.arc_segments,
        (length_x, ly),
        0.0,
        0.0,
        closed=False,
    )
    return mesh, centre


def _patch_sensor(
    mi: Any,
    setup: PbrSetup,
    centre: np.ndarray,
    n: np.ndarray,
    e: np.ndarray,
    view: np.ndarray,
    along: float,
    width: float,
    pixels: int,
    spp: int,
) -> dict[str, Any]:
    """An orthographic camera looking along -view whose square film covers exactly the patch:
    its x axis is the layer lines' direction projected onto the film (moving along it moves the
    seen point along the layer lines only), its y axis spans `along` across the layers."""
    f = -view
    y = np.array([0.0, 1.0, 0.0])
    a_raw = y - (y @ f) * f
    a = a_raw / np.linalg.norm(a_raw)
    b = np.cross(f, a)
    # the seen point moves by y / |a_raw| per unit along a, by b - (n.b)/(n.f) f along b
    kappa = abs(e @ (b - (n @ b) / (n @ f) * f))
    sx, sy = width * np.linalg.norm(a_raw) / 2.0, along / (2.0 * kappa)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = sx * a, sy * b, f, centre + 100.0 * view
    return {
        "type": "orthographic",
        "to_world": mi.ScalarTransform4f(m.tolist()),
        "near_clip": 1e-3,
        "far_clip": 1e4,
        "film": _film(replace(setup, width=pixels, height=pixels), pixels, pixels),
        "sampler": {"type": "multijitter", "sample_count": spp, "seed": 0},
    }


def _patch_light(
    setup: PbrSetup, centre: np.ndarray, light: np.ndarray, distance_mm: float | None
) -> dict[str, Any]:
    """A distant light of unit irradiance, or the LED ball at `distance_mm` giving unit
    irradiance at the patch centre."""
    if distance_mm is None:
        return {
            "type": "directional",
            "direction": (-light).tolist(),
            "irradiance": _emission(setup.variant, 1.0),
        }
    near = replace(setup, lamp_distance_mm=distance_mm, lamp_position_mm=None)
    return lamp_shape(near, centre + distance_mm * light)
