"""A second, deliberately simple renderer of photo folders, independent of stairfit's own.

It writes what a real session of the paper's setup (Sec. 3.3 and Fig. 9) would give: six
wedges (10-60 deg, 150 um layers) photographed at -80..80 deg with the light along the faces'
normal (theta_i = 0 on every face), a pinhole camera at 900 mm, one fixed exposure for every
view, lens vignetting (15% in the corners, a little different per colour), a flat-field photo
of a uniform target through the same lens, ArUco markers with a white quiet zone on a dark
plate, 1600 x 1200 RGGB 14-bit DNGs with black level 512 and the exposure tags in IFD0 (where
TIFF/EP puts them), shot and read noise, and a surface texture correlated over a few pixels.

How the light is at theta_i = 0 on every face at once: the paper's Fig. 9 computes all six
wedges at theta_i = 0 in the face frame and speaks of observation angles relative to the faces
(e.g. "a direct reflection toward -90 deg" of the 45-deg wedge, which is the riser lobe at
theta_i = 0 in the face frame). With one distant light this requires the six faces to be
parallel. Here they are set into the marker plate, tilted so that every face lies flush with
the plate surface (z = 0); the light is along the plate normal and the camera turns about the
layer lines (y), so `view_deg` is the face-frame theta_o of every wedge and the scene says
`angles_relative_to = "face"`. The faces, the markers and the plate are then one plane, and
`face_mm` is the true outline of each face on it (height 0).

Independent means: its own geometry (camera pose, projection, the plane-to-pixel mapping by ray
casting), its own conversion of BRDF values into radiance and DN (conventions §9, docs/imaging.md
§Units), its own noise, texture (NumPy FFT), vignetting and its own DNG writer (tifffile). It
imports nothing from `stairfit.imaging.synthetic`, `stairfit.simulation` or
`stairfit._specimen_layout`. It does use `stairfit.model.brdf` for the BRDF values (the physics
under test), and nothing else of stairfit.

A second layout, `standing_setup()`, stands the wedges on the plate instead (each face rising
along +x by its wedge angle, the base-frame convention of `face_mm`), lit from -10 deg: its faces
are not in the plane of the markers, for testing placement in 3-D.

API: `render_folder(path, truth, seed, megapixels=..., views=..., setup=...)` writes
`scene.toml`, the DNGs, `FLAT_01.dng` and `truth.json`, and returns the truth as a dict.
A folder of 16 photos at 1.9 MP takes a few seconds.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field, replace
from fractions import Fraction
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import tifffile
import tomli_w

DEG = math.pi / 180.0
VIEWS_DEG: tuple[float, ...] = tuple(
    float(v) for v in (*range(-80, 0, 10), *range(10, 90, 10))
)  # the paper took no photo at 0 deg
PLA_INDEX = 1.46  # the paper's representative value; the scene's material "pla"
CAMERA = "Nikon 5100 (NPL)"


@dataclass(frozen=True)
class Truth:
    """The physical parameters the photos are rendered from (stairfit's units)."""

    sigma_deg: float = 6.0
    delta_n: float = 0.0
    scale: float = 2.0e6
    floor: float = 4000.0


@dataclass(frozen=True)
class Setup:
    """Everything about the session other than the physics; defaults are the paper's setup.

    Attributes:
        wedges_deg, layer_um: the specimen (footprint `face_mm` x `face_mm` each, in a row
            along y, `gap_mm` apart).
        views_deg: camera angles from the plate normal (in the flush layout every face's
            normal too), about the layer lines.
        width, height: image size (pixels, even).
        distance_mm: camera centre to the middle of the wedge row.
        light_diameter_deg, light_shape: angular size of the (distant) light, "disk" (round)
            or "square" (sides along and across the plane of incidence).
        vignetting: (R, G, B) fall-off in the image corners.
        flat_photos: flat-field photos to write and declare (0 for none).
        texture, texture_px: relative amplitude and Gaussian correlation scale (px) of the
            multiplicative surface texture (independent in every photo).
        gain_e_per_dn, read_noise_dn, black_dn, bits: the sensor at ISO 100.
        f_number, iso, fill: the one exposure of the session: the brightest face of all views
            at `fill` of the raw range, rounded down to a third of a stop.
        exposure_tags: "ifd0" (exposure tags in IFD0 only) or "scene" (no tags in the files;
            the exposure written as overrides in scene.toml, for decoders that read only the
            EXIF IFD).
        write_intrinsics: write `[camera] focal_length_px` and `principal_point_px`.
        marker_mm, plate_albedo, marker_albedo: markers (ArUco 4x4, white quiet zone of one
            cell), the plate's and the markers' white diffuse radiance relative to `floor`.
        layout: "flush" (the paper's setup: every face set into the plate, in its plane) or
            "standing" (the wedges stand on the plate, each face rising along +x by its wedge
            angle; scenes relative to the base, `standing_setup`).
        light_deg: the light's angle from the plate normal (positive: downhill side).
    """

    wedges_deg: tuple[float, ...] = (10.0, 20.0, 30.0, 40.0, 45.0, 60.0)
    layer_um: float = 150.0
    face_mm: float = 20.0
    gap_mm: float = 6.0
    views_deg: tuple[float, ...] = VIEWS_DEG
    width: int = 1600
    height: int = 1200
    distance_mm: float = 900.0
    light_diameter_deg: float = 0.6
    light_shape: str = "disk"
    vignetting: tuple[float, float, float] = (0.16, 0.15, 0.14)
    flat_photos: int = 1
    texture: float = 0.02
    texture_px: float = 1.5
    gain_e_per_dn: float = 0.8
    read_noise_dn: float = 2.5
    black_dn: int = 512
    bits: int = 14
    f_number: float = 8.0
    iso: float = 100.0
    fill: float = 0.7
    exposure_tags: str = "ifd0"
    write_intrinsics: bool = True
    marker_mm: float = 12.0
    plate_albedo: float = 0.3
    marker_albedo: float = 25.0
    markers: tuple[tuple[int, float, float], ...] = field(
        default=((0, -20.0, -4.0), (1, -20.0, 70.0), (2, -20.0, 144.0),
                 (3, 28.0, -4.0), (4, 28.0, 70.0), (5, 28.0, 144.0))
    )  # fmt: skip
    """Marker id and the plate position (x0, y0) of its top-left corner (mm)."""
    layout: str = "flush"
    light_deg: float = 0.0


STANDING_MARKERS = ((0, -20.0, -20.0), (1, 28.0, -20.0), (2, -20.0, 158.0), (3, 28.0, 158.0))
"""Markers beyond the row's ends, where no standing wedge can hide them."""


def standing_setup(**changes: Any) -> Setup:
    """Wedges standing on the plate (the base-frame convention of `face_mm`: a point (x, y) of
    the outline is on the face at height (x - x_min) tan(beta2)), lit at -10 deg from the plate
    normal, seen from -50 to 20 deg: geometry that needs 3-D placement from the markers."""
    base = {
        "layout": "standing", "light_deg": -10.0, "markers": STANDING_MARKERS,
        "views_deg": (-50.0, -40.0, -30.0, -20.0, -10.0, 0.0, 10.0, 20.0),
    }  # fmt: skip
    return replace(Setup(), **{**base, **changes})


# --- geometry: the plate, the faces, a pinhole camera ------------------------------------------


def face_rect(setup: Setup, k: int) -> tuple[float, float, float, float]:
    """(x0, x1, y0, y1) of wedge k's face on the plate (mm); x uphill, y along the layers."""
    y0 = k * (setup.face_mm + setup.gap_mm)
    return 0.0, setup.face_mm, y0, y0 + setup.face_mm


def tilt_rad(setup: Setup, k: int) -> float:
    """How far wedge k's face normal leans downhill from the plate normal (rad)."""
    return 0.0 if setup.layout == "flush" else setup.wedges_deg[k] * DEG


def face_corners(setup: Setup, k: int) -> np.ndarray:
    """(4, 3) corners of wedge k's face: foot (x0), top (x1), in the outline's order."""
    x0, x1, y0, y1 = face_rect(setup, k)
    h = (x1 - x0) * math.tan(tilt_rad(setup, k))
    return np.array([[x0, y0, 0.0], [x1, y0, h], [x1, y1, h], [x0, y1, 0.0]])


def face_angles_deg(setup: Setup, view_deg: float, k: int) -> tuple[float, float]:
    """Nominal face-frame (theta_i, theta_o) of wedge k (the scene's rule, conventions §1)."""
    t = tilt_rad(setup, k) / DEG
    return setup.light_deg - t, view_deg + t


def face_visible(setup: Setup, view_deg: float, k: int) -> bool:
    """Lit and seen (both face angles below 89 deg), as stairfit's scene decides."""
    return all(abs(a) < 89.0 for a in face_angles_deg(setup, view_deg, k))


def marker_corners(setup: Setup, x0: float, y0: float) -> np.ndarray:
    """(4, 2) plate corners (x, y) of a marker in ArUco order: the printed image's top-left,
    top-right, bottom-right, bottom-left (its rows run along +x, its columns along +y)."""
    s = setup.marker_mm
    return np.array([[x0, y0], [x0, y0 + s], [x0 + s, y0 + s], [x0 + s, y0]])


@dataclass(frozen=True)
class Pinhole:
    """A pinhole camera: centre (mm), rotation world -> camera, focal length and centre (px).

    Camera axes: x to the image's right, y down, z forward. Pixel (u, v) = (column, row), the
    centre of the top-left pixel at (0, 0).
    """

    centre: np.ndarray
    rotation: np.ndarray
    focal_px: float
    cx: float
    cy: float

    def project(self, points: np.ndarray) -> np.ndarray:
        """(..., 3) world points (mm) -> (..., 2) pixels."""
        p = (np.asarray(points, float) - self.centre) @ self.rotation.T
        return np.stack(
            [self.focal_px * p[..., 0] / p[..., 2] + self.cx,
             self.focal_px * p[..., 1] / p[..., 2] + self.cy], axis=-1,
        )  # fmt: skip

    def rays(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World directions (not normalised) of the rays through pixels (u, v)."""
        xc, yc = (u - self.cx) / self.focal_px, (v - self.cy) / self.focal_px
        r = self.rotation  # camera -> world is r.T
        return tuple(r[0, i] * xc + r[1, i] * yc + r[2, i] for i in range(3))  # type: ignore[return-value]

    def plate_points(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Where the rays through pixels (u, v) meet the plate z = 0: (x, y) in mm.

        The ray through p = (u, v, 1) has the world direction d = M p, M = R^T K^-1; it meets
        z = 0 at C - (C_z / d_z) d, so (x, y) = ((C_x M_2 - C_z M_0) p, (C_y M_2 - C_z M_1) p)
        / (M_2 p): a homography image -> plate.
        """
        k_inv = np.array(
            [[1 / self.focal_px, 0, -self.cx / self.focal_px],
             [0, 1 / self.focal_px, -self.cy / self.focal_px], [0, 0, 1.0]]
        )  # fmt: skip
        m = self.rotation.T @ k_inv
        c = self.centre
        hx, hy, hw = c[0] * m[2] - c[2] * m[0], c[1] * m[2] - c[2] * m[1], m[2]
        w = hw[0] * u + hw[1] * v + hw[2]
        return (hx[0] * u + hx[1] * v + hx[2]) / w, (hy[0] * u + hy[1] * v + hy[2]) / w


def camera_for(setup: Setup, view_deg: float) -> Pinhole:
    """The camera at `view_deg` from the plate normal, on the uphill (+x) side for positive
    angles, looking at the middle of the wedge row; the focal length frames the markers."""
    n = len(setup.wedges_deg)
    target = np.array([setup.face_mm / 2, (n * setup.face_mm + (n - 1) * setup.gap_mm) / 2, 0.0])
    v = view_deg * DEG
    centre = target + setup.distance_mm * np.array([math.sin(v), 0.0, math.cos(v)])
    forward = (target - centre) / np.linalg.norm(target - centre)
    right = np.array([0.0, 1.0, 0.0])
    down = np.cross(forward, right)
    rotation = np.stack([right, down, forward])
    ys = [y for _, _, y0 in setup.markers for y in (y0, y0 + setup.marker_mm)]
    half_span = max(abs(y - target[1]) for y in ys) + 8.0  # the row and its markers
    focal = 0.5 * setup.width * setup.distance_mm / half_span
    return Pinhole(centre, rotation, focal, (setup.width - 1) / 2, (setup.height - 1) / 2)


# --- physics: BRDF values (stairfit.model) to radiance (our own code) ---------------------------


LIGHT_NODES = 64
"""Quadrature nodes across the light: enough for the kink of a lobe weight at a regime
boundary (the 45-deg wedge at theta_i = 0), where a few nodes err by several per cent."""


def light_nodes(diameter_deg: float, shape: str = "disk") -> tuple[np.ndarray, np.ndarray]:
    """In-plane angles (rad) and weights across the light.

    A round light ("disk") has the semicircle distribution of in-plane offsets (Gauss-Chebyshev
    quadrature of the second kind); a square one with sides along and across the plane
    ("square") has a uniform distribution (midpoint rule).
    """
    n = LIGHT_NODES
    if shape == "disk":
        k = np.arange(1, n + 1)
        x, w = np.cos(k * math.pi / (n + 1)), np.sin(k * math.pi / (n + 1)) ** 2
    elif shape == "square":
        x, w = (np.arange(n) + 0.5) / n * 2.0 - 1.0, np.ones(n)
    else:
        raise ValueError(f"light shape {shape!r}: use 'disk' or 'square'")
    return x * 0.5 * diameter_deg * DEG, w / w.sum()


def face_radiance(
    truth: Truth, setup: Setup, beta2_deg: np.ndarray, theta_o: np.ndarray, theta_i: np.ndarray
) -> np.ndarray:
    """Relative radiance of wedge faces (wedge angles `beta2_deg`) lit at `theta_i` and seen
    at `theta_o` (rad, face frame), all broadcast together; one `model.brdf` call for all.

    `L = scale cos(theta_i) rho / cos(theta_o) + floor cos(theta_i)` [conventions §9], averaged
    over the light's size. The index is the constant PLA value (plus delta_n), so
    every wavelength, and hence every camera channel, sees the same rho [conventions §8]:
    dispersion is not rendered.
    """
    from stairfit import model

    offsets, wi = light_nodes(setup.light_diameter_deg, setup.light_shape)
    b2 = np.asarray(beta2_deg, float) * DEG
    to = np.asarray(theta_o, float)
    shape = np.broadcast_shapes(b2.shape, to.shape, np.shape(theta_i))
    ti = offsets.reshape(-1, *[1] * len(shape)) + np.asarray(theta_i, float)
    n = PLA_INDEX + truth.delta_n
    rho = np.asarray(model.brdf(ti, to, b2, n, truth.sigma_deg * DEG))  # (light nodes, *shape)
    cos_i = np.cos(ti)
    cos_o = np.maximum(np.cos(to), math.cos(89.9 * DEG))
    rad = truth.scale * cos_i * rho / cos_o + truth.floor * cos_i
    return np.tensordot(wi, rad, axes=1)


# --- rendering one photo -----------------------------------------------------------------------


SUBSAMPLES = np.array([-0.375, -0.125, 0.125, 0.375])
"""Each pixel of a face or marker averages 4 x 4 samples at these offsets (anti-aliased edges,
placed to 1/8 px)."""


def _cfa_colour(setup: Setup) -> np.ndarray:
    """(H, W) colour index of each pixel of the RGGB mosaic (0 = R, 1 = G, 2 = B)."""
    tile = np.array([[0, 1], [1, 2]])
    return np.tile(tile, (setup.height // 2, setup.width // 2))


def _box_samples(
    cam: Pinhole, corners: np.ndarray, setup: Setup
) -> tuple[tuple[slice, slice], np.ndarray, np.ndarray] | None:
    """The pixel box around the image of a polygon ((n, 3) world points, 1 px margin) and its
    sample positions (u, v), shape (h, w, 16); None if it is outside the image."""
    px = cam.project(corners)
    c0, r0 = np.floor(px.min(axis=0)).astype(int) - 1
    c1, r1 = np.ceil(px.max(axis=0)).astype(int) + 2
    c0, r0 = max(c0, 0), max(r0, 0)
    c1, r1 = min(c1, setup.width), min(r1, setup.height)
    if c0 >= c1 or r0 >= r1:
        return None
    du, dv = np.meshgrid(SUBSAMPLES, SUBSAMPLES)
    u = np.arange(c0, c1, dtype=float)[None, :, None] + du.ravel()
    v = np.arange(r0, r1, dtype=float)[:, None, None] + dv.ravel()
    u, v = np.broadcast_arrays(u, v)
    return (slice(r0, r1), slice(c0, c1)), u, v


def _marker_image(marker_id: int) -> np.ndarray:
    """The marker's cells with a one-cell white quiet zone: 8 x 8 values in {0, 1}."""
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    cells = dictionary.markerSize + 2
    img = cv2.aruco.generateImageMarker(dictionary, marker_id, cells, borderBits=1)
    return np.pad(img.astype(float) / 255.0, 1, constant_values=1.0)


def _draw_markers(value: np.ndarray, cam: Pinhole, truth: Truth, setup: Setup) -> None:
    """Draw the markers (with their quiet zones) on the plate, in place (grey: every channel)."""
    cell = setup.marker_mm / 6.0
    for mid, x0, y0 in setup.markers:
        lo, hi = -cell, 7 * cell  # the quiet zone: one cell around the 6-cell marker
        quiet = np.array([[x0 + lo, y0 + lo, 0], [x0 + lo, y0 + hi, 0], [x0 + hi, y0 + hi, 0],
                          [x0 + hi, y0 + lo, 0]], float)  # fmt: skip
        box = _box_samples(cam, quiet, setup)
        if box is None:
            continue
        where, u, v = box
        x, y = cam.plate_points(u, v)
        img = _marker_image(mid)
        r = np.floor((x - (x0 - cell)) / cell).astype(int)  # rows along +x, quiet zone first
        c = np.floor((y - (y0 - cell)) / cell).astype(int)
        inside = (r >= 0) & (r < 8) & (c >= 0) & (c < 8)
        white = img[np.clip(r, 0, 7), np.clip(c, 0, 7)]
        albedo = setup.plate_albedo + (setup.marker_albedo - setup.plate_albedo) * white
        level = truth.floor * np.where(inside, albedo, setup.plate_albedo)
        value[where] = level.mean(axis=-1)


def _draw_face(
    value: np.ndarray, cam: Pinhole, setup: Setup, k: int, table: tuple[np.ndarray, np.ndarray],
    colour_map: np.ndarray, plate_level: float,
) -> np.ndarray:  # fmt: skip
    """Draw face k in place; return its (3,) mean radiance over the pixels wholly inside it."""
    x0, x1, y0, y1 = face_rect(setup, k)
    box = _box_samples(cam, face_corners(setup, k), setup)
    assert box is not None, "every face is in the image"
    where, u, v = box
    x, y, z = _face_points(cam, setup, k, u, v)
    on = (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)
    theta_o = _theta_o(cam, setup, k, x, z)
    colours = colour_map[where]
    grid, rad = table
    lum = np.empty(x.shape)
    for c in range(3):
        sel = colours == c
        lum[sel] = np.interp(theta_o[sel], grid, rad[c])
    pixel = np.where(on, lum, plate_level).mean(axis=-1)
    value[where] = np.where(on.any(axis=-1), pixel, value[where])
    whole = on.all(axis=-1)
    return np.array([pixel[whole & (colours == c)].mean() for c in range(3)])


def _face_points(
    cam: Pinhole, setup: Setup, k: int, u: np.ndarray, v: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where the rays through (u, v) meet face k's plane, z = (x - x0) tan(tilt): (x, y, z)."""
    if setup.layout == "flush":
        x, y = cam.plate_points(u, v)
        return x, y, np.zeros_like(x)
    x0 = face_rect(setup, k)[0]
    slope = math.tan(tilt_rad(setup, k))
    dx, dy, dz = cam.rays(u, v)
    c = cam.centre
    t = (slope * (c[0] - x0) - c[2]) / (dz - slope * dx)
    return c[0] + t * dx, c[1] + t * dy, c[2] + t * dz


def _theta_o(cam: Pinhole, setup: Setup, k: int, x: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Face-frame viewing angle (rad) of face points: the in-plane angle of the direction to
    the camera from the plate normal, plus the face's tilt [conventions §1]."""
    return np.arctan2(cam.centre[0] - x, cam.centre[2] - z) + tilt_rad(setup, k)


def _field(
    view: float, truth: Truth, setup: Setup, tables: list[tuple[np.ndarray, np.ndarray]]
) -> tuple[np.ndarray, dict[int, np.ndarray]]:
    """The noise-free radiance of every pixel in its own colour (H, W), and per visible face
    the per-channel mean radiance over the pixels wholly inside it."""
    cam = camera_for(setup, view)
    plate = setup.plate_albedo * truth.floor
    value = np.full((setup.height, setup.width), plate)
    _draw_markers(value, cam, truth, setup)
    colour_map = _cfa_colour(setup)
    means = {
        k: _draw_face(value, cam, setup, k, tables[k], colour_map, plate)
        for k in range(len(setup.wedges_deg))
        if face_visible(setup, view, k)
    }
    return value, means


def _vignetting(setup: Setup) -> np.ndarray:
    """(H, W) the lens's relative illumination of each pixel in its own colour: 1 at the
    centre, 1 - falloff[c] in the corners, `1 - f (0.7 r^2 + 0.3 r^4)` with r = 1 at a corner."""
    h, w = setup.height, setup.width
    yy, xx = np.mgrid[0:h, 0:w]
    r2 = ((xx - (w - 1) / 2) ** 2 + (yy - (h - 1) / 2) ** 2) / (
        ((w - 1) / 2) ** 2 + ((h - 1) / 2) ** 2
    )
    falloff = np.asarray(setup.vignetting)[_cfa_colour(setup)]
    return 1.0 - falloff * (0.7 * r2 + 0.3 * r2**2)


def _texture(setup: Setup, rng: np.random.Generator) -> np.ndarray:
    """1 + a n: n white noise smoothed by a Gaussian of `texture_px` (FFT), unit variance."""
    if setup.texture <= 0:
        return np.ones((setup.height, setup.width))
    noise = rng.standard_normal((setup.height, setup.width))
    fy = np.fft.fftfreq(setup.height)[:, None]
    fx = np.fft.rfftfreq(setup.width)[None, :]
    kernel = np.exp(-2.0 * (math.pi * setup.texture_px) ** 2 * (fx**2 + fy**2))
    smooth = np.fft.irfft2(np.fft.rfft2(noise) * kernel, s=noise.shape)
    return 1.0 + setup.texture * (smooth - smooth.mean()) / smooth.std()


def _sensor(mean_dn: np.ndarray, setup: Setup, rng: np.random.Generator) -> np.ndarray:
    """Shot noise (Poisson in electrons), read noise, black level, rounding and clipping."""
    gain = setup.gain_e_per_dn * 100.0 / setup.iso
    electrons = rng.poisson(np.maximum(mean_dn, 0.0) * gain)
    dn = electrons / gain + rng.normal(0.0, setup.read_noise_dn, mean_dn.shape) + setup.black_dn
    return np.clip(np.rint(dn), 0, 2**setup.bits - 1).astype(np.uint16)


def dn_per_radiance(setup: Setup, exposure_time_s: float) -> float:
    """DN above black per unit relative radiance: t (ISO / 100) / N^2 (docs/imaging.md §Units)."""
    return exposure_time_s * (setup.iso / 100.0) / setup.f_number**2


# --- files --------------------------------------------------------------------------------------


def _rational(x: float) -> tuple[int, int]:
    f = Fraction(x).limit_denominator(100_000)
    return f.numerator, f.denominator


def write_dng(path: Path, mosaic: np.ndarray, setup: Setup, exposure_time_s: float | None) -> None:
    """A CFA DNG (RGGB) with tifffile; exposure tags in IFD0 (TIFF/EP), if a time is given."""
    tags = [
        (271, "s", 0, "Independent", True),  # Make
        (272, "s", 0, "Renderer", True),  # Model
        (33421, "H", 2, (2, 2), True),  # CFARepeatPatternDim
        (33422, "B", 4, (0, 1, 1, 2), True),  # CFAPattern: R G / G B
        (50706, "B", 4, (1, 4, 0, 0), True),  # DNGVersion
        (50708, "s", 0, "Independent Renderer", True),  # UniqueCameraModel
        (50710, "B", 3, (0, 1, 2), True),  # CFAPlaneColor
        (50714, "I", 1, setup.black_dn, True),  # BlackLevel
        (50717, "I", 1, 2**setup.bits - 1, True),  # WhiteLevel
        (50721, "2i", 9, (1, 1, 0, 1, 0, 1, 0, 1, 1, 1, 0, 1, 0, 1, 0, 1, 1, 1), True),  # identity
        (50778, "H", 1, 21, True),  # CalibrationIlluminant1: D65
    ]  # fmt: skip
    if exposure_time_s is not None and setup.exposure_tags == "ifd0":
        tags += [
            (33434, "2I", 1, _rational(exposure_time_s), True),  # ExposureTime
            (33437, "2I", 1, _rational(setup.f_number), True),  # FNumber
            (34855, "H", 1, round(setup.iso), True),  # ISOSpeedRatings
        ]
    tifffile.imwrite(path, mosaic, photometric=32803, extratags=tags, metadata=None)


def _exposure_time(truth: Truth, setup: Setup, tables: list) -> float:
    """The session's one exposure: the brightest face of any view at `fill` of the raw range,
    rounded down to a third of a stop."""
    peak = max(
        float(table.max())
        for view, per_view in zip(setup.views_deg, tables, strict=True)
        for k, (_, table) in enumerate(per_view)
        if face_visible(setup, view, k)
    )
    full = 2**setup.bits - 1 - setup.black_dn
    t = setup.fill * full / peak / dn_per_radiance(setup, 1.0)
    return float(2.0 ** (math.floor(math.log2(t) * 3) / 3))


def _tables(truth: Truth, setup: Setup) -> list[list[tuple[np.ndarray, np.ndarray]]]:
    """Per view and face: (theta_o grid spanning the face, (3, n) radiance there)."""
    grids = []
    for view in setup.views_deg:
        cam = camera_for(setup, view)
        row = []
        for k in range(len(setup.wedges_deg)):
            corners = face_corners(setup, k)
            ends = _theta_o(cam, setup, k, corners[:, 0], corners[:, 2])
            row.append(np.linspace(ends.min() - 2e-3, ends.max() + 2e-3, 33))
        grids.append(row)
    grid = np.array(grids)  # (views, wedges, 33)
    beta2 = np.asarray(setup.wedges_deg)[None, :, None]
    tilt = np.array([tilt_rad(setup, k) for k in range(len(setup.wedges_deg))])[None, :, None]
    rad = face_radiance(truth, setup, beta2, grid, setup.light_deg * DEG - tilt)
    return [
        [(grid[p, k], np.broadcast_to(rad[p, k], (3, grid.shape[2]))) for k in range(grid.shape[1])]
        for p in range(grid.shape[0])
    ]


def _wedge_name(beta2_deg: float) -> str:
    return f"w{beta2_deg:g}"


def _photo_entry(setup: Setup, view: float, name: str, exposure_time_s: float) -> dict[str, Any]:
    """The [[photos]] entry: the angles, the visible faces' ROIs from our own projection."""
    cam = camera_for(setup, view)
    rois = {
        _wedge_name(b): np.round(cam.project(face_corners(setup, k)), 3).tolist()
        for k, b in enumerate(setup.wedges_deg)
        if face_visible(setup, view, k)
    }
    entry: dict[str, Any] = {
        "file": name, "light_deg": setup.light_deg, "view_deg": view, "roi_px": rois
    }  # fmt: skip
    if setup.exposure_tags == "scene":
        entry |= {"exposure_time_s": exposure_time_s, "f_number": setup.f_number,
                  "iso": setup.iso}  # fmt: skip
    return entry


def _scene(setup: Setup, photos: list[dict[str, Any]], flats: list[str]) -> dict[str, Any]:
    """scene.toml as a dict (docs/scene.md)."""
    cam = camera_for(setup, 0.0)
    camera: dict[str, Any] = {
        "sensitivity": CAMERA,
        # the spread of viewing angles across one face seen from the camera
        "angular_extent_deg": round(setup.face_mm / setup.distance_mm / DEG, 4),
    }
    if setup.write_intrinsics:
        camera |= {"focal_length_px": round(cam.focal_px, 3),
                   "principal_point_px": [cam.cx, cam.cy]}  # fmt: skip
    wedges = []
    for k, beta2 in enumerate(setup.wedges_deg):
        x0, x1, y0, y1 = face_rect(setup, k)
        face = [[x0, y0], [x1, y0], [x1, y1], [x0, y1]]
        wedges.append({"name": _wedge_name(beta2), "angle_deg": beta2, "face_mm": face})
    scene: dict[str, Any] = {
        "version": 1,
        "angles_relative_to": "face" if setup.layout == "flush" else "base",
        "specimen": {"layer_um": setup.layer_um, "material": "pla", "wedges": wedges},
        "light": {
            "illuminant": "D65",
            "angular_diameter_deg": setup.light_diameter_deg,
            "shape": "disk" if setup.light_shape == "disk" else "uniform",
        },
        "camera": camera,
        "markers": {
            "dictionary": "DICT_4X4_50",
            "marker": [
                {"id": m, "corners_mm": marker_corners(setup, x0, y0).tolist()}
                for m, x0, y0 in setup.markers
            ],
        },
        "photos": photos,
    }
    if flats:
        scene["calibration"] = {"flat_field": flats}
    return scene


def render_photo(
    truth: Truth, setup: Setup, view: float, tables: list, exposure_time_s: float,
    rng: np.random.Generator,
) -> tuple[np.ndarray, dict[int, np.ndarray]]:  # fmt: skip
    """One photo's mosaic (uint16) and the true mean radiance of each face (per channel)."""
    radiance, face_means = _field(view, truth, setup, tables)
    mean_dn = radiance * _texture(setup, rng) * _vignetting(setup)
    mean_dn *= dn_per_radiance(setup, exposure_time_s)
    return _sensor(mean_dn, setup, rng), face_means


def render_flat(setup: Setup, rng: np.random.Generator) -> tuple[np.ndarray, float]:
    """A flat-field photo: a uniform diffuse target through the same lens, its centre at half of
    the raw range, 0.2% texture; the mosaic and its exposure time."""
    full = 2**setup.bits - 1 - setup.black_dn
    t = 1.0 / 50
    level = 0.5 * full / dn_per_radiance(setup, t)
    flat = replace(setup, texture=0.002)
    mean_dn = level * _texture(flat, rng) * _vignetting(setup) * dn_per_radiance(setup, t)
    return _sensor(mean_dn, setup, rng), t


def render_folder(
    path: str | Path,
    truth: Truth | None = None,
    seed: int = 0,
    *,
    megapixels: float | None = None,
    views: tuple[float, ...] | None = None,
    setup: Setup | None = None,
) -> dict[str, Any]:
    """Write a photo folder (DNGs, a flat-field photo, scene.toml, truth.json) into `path`.

    `megapixels` scales the image (4:3, even sides; the default is the setup's 1600 x 1200),
    `views` replaces the viewing angles. Returns the truth (also written to truth.json, which
    the fit never reads): parameters, the exposure, the camera and, per photo, wedge and channel
    the noise-free mean radiance over each face (no texture, no vignetting; None where the face
    is turned away). That is the mean over the whole face: an eroded ROI's mean differs from it
    by up to a few 0.1% where the radiance changes steeply across a face (measured against the
    eroded ROIs' own noise-free means, stairfit's ROI means have pulls of mean 0.01, sd 1.01).
    """
    truth = truth or Truth()
    setup = setup or Setup()
    if megapixels is not None:
        h = round(math.sqrt(megapixels * 1e6 * 3 / 4) / 2) * 2
        setup = replace(setup, width=round(h * 4 / 3 / 2) * 2, height=h)
    if views is not None:
        setup = replace(setup, views_deg=tuple(float(v) for v in views))
    folder = Path(path)
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    tables = _tables(truth, setup)
    t = _exposure_time(truth, setup, tables)
    photos, means = [], []
    for p, view in enumerate(setup.views_deg):
        mosaic, face_means = render_photo(truth, setup, view, tables[p], t, rng)
        name = f"DSC_{p + 1:04d}.dng"
        write_dng(folder / name, mosaic, setup, t)
        photos.append(_photo_entry(setup, view, name, t))
        means.append(
            [face_means[k].tolist() if k in face_means else None for k in range(len(tables[p]))]
        )  # None: the face is turned away from the light or the camera in this view
    flats = []
    for k in range(setup.flat_photos):
        mosaic, t_flat = render_flat(setup, rng)
        flats.append(f"FLAT_{k + 1:02d}.dng")
        write_dng(folder / flats[-1], mosaic, setup, t_flat)
    (folder / "scene.toml").write_text(tomli_w.dumps(_scene(setup, photos, flats)))
    cam = camera_for(setup, 0.0)
    result = {
        "renderer": "tests/independent_photos.py",
        "parameters": {**asdict(truth), "edge_radius_um": 0.0},
        "setup": asdict(setup),
        "exposure": {"exposure_time_s": t, "f_number": setup.f_number, "iso": setup.iso},
        "camera": {
            "focal_length_px": cam.focal_px,
            "principal_point_px": [cam.cx, cam.cy],
            "distance_mm": setup.distance_mm,
        },
        "photos": [p["file"] for p in photos],
        "wedges": [_wedge_name(b) for b in setup.wedges_deg],
        "face_radiance": means,
    }
    (folder / "truth.json").write_text(json.dumps(result, indent=1))
    return result
