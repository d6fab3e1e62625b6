"""A second renderer of photos whose faces show their layer lines, independent of stairfit's.

It draws what a camera that resolves the layers of an FDM print records: each face a plane
rectangle seen through its own homography (any orientation of the layer lines in the image, a
perspective change of the layer period across the face), its radiance periodic across the
layers with a period of 1-8 px in the image, integrated over each pixel's square and a Gaussian
lens blur (so that the pixel grid and the Bayer mosaic alias the stripes as a real sensor does),
lit by a near lamp (a smooth gradient across the face), optionally textured (irregular layers,
an isotropic surface texture, irregular layer positions), on an RGGB mosaic with Poisson shot
noise, Gaussian read noise, a black level and 14-bit clipping.

Independent means: its own geometry, pattern, texture, sensor and DNG writer (tifffile); it
imports nothing from `stairfit.imaging.synthetic`, nothing from `stairfit.commands` and nothing
from stairfit's model. Only `stairfit.imaging.RawFrame` (the decoder's data type, to hand a
mosaic to the library without a file) is used.

**The pattern** (`Pattern`) across one layer, as a function of the layer phase x in cycles:
channel c's radiance is `body_c D(x) + specular S(x)`: `D` a rounded square wave of duty
`duty` (tread against riser) of mean 1 and modulation `contrast`, `S` a periodic Gaussian
highlight (mean 1) at phase `spec_phase`. Both are finite Fourier series (`coefficients`), so
the average of a harmonic over a pixel's square is exact (`sinc` of its wave vector along the
two axes) and so is the Gaussian blur (a factor per harmonic). A grey face has equal `body`
in R, G, B; its raw R:G:B are then the sensor's channel sensitivities `QE`.

**Truths** (`FaceTruth`), per channel and in DN above black, computed from the continuous
pattern and never from pixels: `dc` is the layer-period average of the untextured pattern
(`body_c + specular`, D and S having mean 1) times the lamp's mean over the ROI's pixel centres
times the channel's sensitivity and exposure; this is what a model of the face predicts at the
ROI's centroid (the lamp is smooth, so its mean over the ROI is its value there to second
order). `roi_mean` is the mean of the continuous untextured radiance over the ROI's pixel
squares (16 x 16 points per pixel), partial periods at the ROI's edges included: it differs
from `dc` by the stripes' incomplete periods, the quantity a measurement of the face's radiance
must not carry (`dc` is the one the tests compare with).

**Texture** (optional, `Texture`): every layer brighter or darker by a random factor (`layers`,
relative sd; linearly interpolated between layer centres, so correlated along the whole layer
line), an isotropic Gaussian random field of correlation length `ell_px` (`surface`, relative
sd), and irregular layer positions (`positions`, sd in cycles). Each has ensemble mean 1 (the
positions' mean effect over whole periods is 0), so `dc` is the truth with and without it.

API: `render(spec, rng) -> Rendered` for arrays handed to the library (`frame(rendered)` gives a
`stairfit.imaging.RawFrame`), `random_faces(rng, ...)` for random scenes, and `write_folder(path,
...)` for a folder with DNGs, markers and scene.toml that `stairfit measure` reads.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, replace
from fractions import Fraction
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import tifffile
import tomli_w

from stairfit.imaging import RawFrame

CFA = np.array([[0, 1], [1, 2]], dtype=np.uint8)
"""RGGB: colour (0 R, 1 G, 2 B) of each position of the 2 x 2 tile."""

QE = (0.55, 1.0, 0.72)
"""The sensor's relative sensitivity of R, G and B: a grey face's raw R:G:B."""

HARMONICS = 48
"""Harmonics of the rendered pattern (the rounding makes the rest negligible)."""

BLACK_DN = 512
BITS = 14
WHITE_DN = 2**BITS - 1


# --- the pattern across a layer ---------------------------------------------------------------


@dataclass(frozen=True)
class Pattern:
    """Radiance across one layer, channel c: `body_c D(x) + specular S(x)`, x the phase (cycles).

    Attributes:
        body: the diffuse part of R, G and B (equal: a grey face).
        specular: the highlight's mean (white: the same in every channel).
        duty: the tread's share of a layer (D's square wave).
        contrast: D's modulation: D is 1 + contrast on the tread ... 1 - contrast' on the riser,
            mean 1, never below 1 - contrast.
        rounding: the square wave's edges, Gaussian sd in cycles.
        spec_width: the highlight's Gaussian sd in cycles.
        spec_phase: the highlight's centre (cycles).
    """

    body: tuple[float, float, float] = (1.0, 1.0, 1.0)
    specular: float = 0.0
    duty: float = 0.6
    contrast: float = 0.5
    rounding: float = 0.03
    spec_width: float = 0.08
    spec_phase: float = 0.3

    def coefficients(self, n: int = HARMONICS) -> np.ndarray:
        """(3, n + 1) complex c[c, h] with radiance_c(x) = Re sum_h c[c, h] exp(2 pi i h x)."""
        h = np.arange(n + 1)
        w = self.duty
        # square wave 1 on [0, w), 0 elsewhere: mean w, harmonic h: (1 - exp(-2 pi i h w)) /
        # (2 pi i h) per exp(2 pi i h x), doubled for the real part of a one-sided series
        sq = np.empty(n + 1, dtype=complex)
        sq[0] = w
        hh = h[1:]
        sq[1:] = 2 * (1 - np.exp(-2j * np.pi * hh * w)) / (2j * np.pi * hh)
        sq *= np.exp(-2 * (np.pi * h * self.rounding) ** 2)
        d = self.contrast * sq / max(w, 1 - w)
        d[0] = 1.0  # mean 1, the zero-mean square wave scaled by the contrast
        s = 2 * np.exp(-2 * (np.pi * h * self.spec_width) ** 2)
        s = s * np.exp(-2j * np.pi * h * self.spec_phase)
        s[0] = 1.0
        return np.stack([b * d + self.specular * s for b in self.body])

    def mean(self) -> np.ndarray:
        """(3,) the period average of each channel: body_c + specular."""
        return np.asarray(self.body) + self.specular

    def peak(self) -> float:
        """The largest radiance of any channel over a layer (for choosing the exposure)."""
        return float(self.values(np.linspace(0, 1, 2048, endpoint=False)).max())

    def values(self, x: np.ndarray) -> np.ndarray:
        """(3, ...) the continuous radiance at phases x (cycles), no pixel averaging: the
        series summed on 8192 phases per cycle and interpolated linearly (the pattern is
        smooth at that scale: its rounding is at least 0.02 cycles)."""
        grid = np.arange(8193) / 8192
        c = self.coefficients()
        e = np.exp(2j * np.pi * np.multiply.outer(np.arange(c.shape[1]), grid))
        table = np.real(np.tensordot(c, e, axes=1))
        frac = np.mod(x, 1.0)
        return np.stack([np.interp(frac, grid, t) for t in table])


def grey_pattern(rng: np.random.Generator, specular: bool = True) -> Pattern:
    """A random grey face: tread/riser shading and (optionally) a highlight."""
    return Pattern(
        body=(1.0, 1.0, 1.0),
        specular=float(rng.uniform(0.3, 1.5)) if specular else 0.0,
        duty=float(rng.uniform(0.35, 0.75)),
        contrast=float(rng.uniform(0.2, 0.8)),
        rounding=float(rng.uniform(0.02, 0.06)),
        spec_width=float(rng.uniform(0.05, 0.12)),
        spec_phase=float(rng.uniform(0.0, 1.0)),
    )


def sharp_pattern(rng: np.random.Generator) -> Pattern:
    """A grey face with a narrow highlight and sharp tread edges (glossy layer tips): its
    harmonics decay slowly, so that those shorter than half a pixel keep a few percent of the
    mean after the pixel's square (when the layer lines run along the pixel rows or columns)."""
    return replace(
        grey_pattern(rng),
        specular=float(rng.uniform(0.5, 2.0)),
        rounding=0.01,
        spec_width=float(rng.uniform(0.015, 0.03)),
    )


def coloured_pattern(rng: np.random.Generator) -> Pattern:
    """A coloured body with a white highlight: the stripes differ in shape between channels."""
    body = tuple(float(v) for v in rng.uniform(0.3, 1.2, size=3))
    return replace(grey_pattern(rng), body=body)  # type: ignore[arg-type]


# --- a face in the image ------------------------------------------------------------------------


@dataclass(frozen=True)
class Texture:
    """The face's own irregularities (relative sds; 0: none). See the module docstring."""

    layers: float = 0.0
    surface: float = 0.0
    ell_px: float = 1.5
    positions: float = 0.0


@dataclass(frozen=True)
class Face:
    """One face: a rectangle of `size_mm` (s across the layers, t along them) mapped to the image.

    Image point p = c + A [s, t] / (1 + e s + f t) for face coordinates (s, t) in mm about the
    face's centre: A = R(angle) diag(period_px / layer_mm, scale_t) (t turned by `skew_deg`),
    c = `centre`, (e, f) = `perspective`. So at the centre the layer period is `period_px`
    pixels, across the layer lines along the image direction (cos angle, sin angle).

    Attributes:
        centre: (x, y) image position of the face's centre (px).
        angle_deg: image direction of s (across the layer lines), from +x towards +y.
        period_px: the layer period in the image at the centre (px).
        size_mm: (S, T) the face's extent across and along the layers.
        scale_t: px per mm along the layer lines.
        perspective: (e, f) per mm: the period changes by about e x S across the face.
        phase: the layer phase at the centre (cycles).
        skew_deg: the layer lines' image direction off the perpendicular of `angle_deg`.
        pattern: the radiance across a layer.
        light: the lamp's level at the centre (relative; DN through `level_dn`).
        gradient: (gx, gy) relative change of the lamp per px.
        curvature: relative second-order change of the lamp over the face's half-diagonal.
        texture: irregularities.
        layer_mm: the layer pitch along s (mm).
    """

    centre: tuple[float, float]
    angle_deg: float
    period_px: float
    size_mm: tuple[float, float] = (20.0, 20.0)
    scale_t: float = 6.0
    perspective: tuple[float, float] = (0.0, 0.0)
    phase: float = 0.0
    skew_deg: float = 0.0
    pattern: Pattern = field(default_factory=Pattern)
    light: float = 1.0
    gradient: tuple[float, float] = (0.0, 0.0)
    curvature: float = 0.0
    texture: Texture = field(default_factory=Texture)
    layer_mm: float = 0.15

    def homography(self) -> np.ndarray:
        """3 x 3 matrix from (s, t, 1) in mm to image (x, y, 1) in px."""
        a = math.radians(self.angle_deg)
        b = a + math.pi / 2 + math.radians(self.skew_deg)
        ks = self.period_px / self.layer_mm
        lin = np.array([[ks * math.cos(a), self.scale_t * math.cos(b)],
                        [ks * math.sin(a), self.scale_t * math.sin(b)]])  # fmt: skip
        # p - c = A q / w with w = 1 + e s + f t: the perspective acts about the face's centre
        c, e = np.asarray(self.centre), np.asarray(self.perspective)
        h = np.eye(3)
        h[:2, :2] = lin + np.outer(c, e)
        h[:2, 2] = c
        h[2, :2] = e
        return h

    def outline_px(self) -> np.ndarray:
        """(4, 2) image corners, in order."""
        s, t = self.size_mm[0] / 2, self.size_mm[1] / 2
        return _apply(self.homography(), np.array([[-s, -t], [s, -t], [s, t], [-s, t]]))

    def across_px(self) -> np.ndarray:
        """Unit image vector across the layer lines at the centre: the normal to the image of
        the lines (t), on the side of +s."""
        h = self.homography()
        d = _apply(h, np.array([[0.0, 0.5]]))[0] - _apply(h, np.array([[0.0, -0.5]]))[0]
        n = np.array([-d[1], d[0]]) / np.hypot(*d)
        ds = _apply(h, np.array([[0.5, 0.0]]))[0] - _apply(h, np.array([[-0.5, 0.0]]))[0]
        return n if n @ ds > 0 else -n


def _apply(h: np.ndarray, pts: np.ndarray) -> np.ndarray:
    q = np.c_[pts, np.ones(len(pts))] @ h.T
    return q[:, :2] / q[:, 2:]


def face_coordinates(face: Face, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, ...]:
    """(s, t, ds/dx, ds/dy) in mm (and mm per px) at image points (x, y)."""
    hi = np.linalg.inv(face.homography())
    num_s = hi[0, 0] * x + hi[0, 1] * y + hi[0, 2]
    num_t = hi[1, 0] * x + hi[1, 1] * y + hi[1, 2]
    den = hi[2, 0] * x + hi[2, 1] * y + hi[2, 2]
    s, t = num_s / den, num_t / den
    dsdx = (hi[0, 0] * den - num_s * hi[2, 0]) / den**2
    dsdy = (hi[0, 1] * den - num_s * hi[2, 1]) / den**2
    return s, t, dsdx, dsdy


def lamp(face: Face, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The near lamp's relative level at image points: linear plus a quadratic bowl."""
    dx, dy = x - face.centre[0], y - face.centre[1]
    half = 0.5 * float(np.hypot(*np.ptp(face.outline_px(), axis=0)))
    lin = face.gradient[0] * dx + face.gradient[1] * dy
    return face.light * (1 + lin + face.curvature * (dx * dx + dy * dy) / half**2)


def _sinc(x: np.ndarray) -> np.ndarray:
    return np.sinc(x)  # sin(pi x) / (pi x)


def pixel_pattern(
    face: Face, x: np.ndarray, y: np.ndarray, blur_px: float, offsets: np.ndarray | None = None
) -> np.ndarray:
    """(3, n) the untextured pattern averaged over each pixel's square and the blur.

    Harmonic h of wave vector k (cycles per px, the local one at the pixel) averages over the
    unit square to sinc(h k_x) sinc(h k_y) times its centre value, and the Gaussian blur of sd
    `blur_px` multiplies it by exp(-2 pi^2 blur^2 h^2 |k|^2). `offsets` (n,) adds irregular
    layer positions (cycles).
    """
    s, _, dsdx, dsdy = face_coordinates(face, x, y)
    phase = s / face.layer_mm + face.phase + (0 if offsets is None else offsets)
    kx, ky = dsdx / face.layer_mm, dsdy / face.layer_mm
    coef = face.pattern.coefficients()
    out = np.zeros((3, x.size))
    base = np.exp(2j * np.pi * phase)
    term = np.ones_like(base)
    for h in range(coef.shape[1]):
        blur = np.exp(-2 * (np.pi * blur_px * h) ** 2 * (kx**2 + ky**2))
        att = _sinc(h * kx) * _sinc(h * ky) * blur
        val = term * att
        out += np.real(np.outer(coef[:, h], val))
        term = term * base
    return out


def roi_mean_truth(face: Face, mask: np.ndarray, y0: int, x0: int, sub: int = 8) -> np.ndarray:
    """(3,) mean of the continuous untextured radiance (lamp included, no sensor) over the
    pixel squares of `mask` (its [0, 0] at image (y0, x0)): sub x sub points per pixel."""
    ys, xs = np.nonzero(mask)
    o = (np.arange(sub) + 0.5) / sub - 0.5
    oy, ox = np.meshgrid(o, o, indexing="ij")
    total = np.zeros(3)
    for chunk in np.array_split(np.arange(ys.size), max(1, ys.size // 4000)):
        px = (xs[chunk] + x0)[:, None] + ox.ravel()[None, :]
        py = (ys[chunk] + y0)[:, None] + oy.ravel()[None, :]
        s, _, _, _ = face_coordinates(face, px.ravel(), py.ravel())
        vals = face.pattern.values(s / face.layer_mm + face.phase)
        total += (vals * lamp(face, px.ravel(), py.ravel())).sum(axis=1)
    return total / (ys.size * sub * sub)


# --- a photo --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Sensor:
    """Exposure and noise: `level_dn` is the DN above black of a face of radiance 1 in G."""

    level_dn: float = 2000.0
    gain_e_per_dn: float = 1.0
    read_noise_dn: float = 3.0
    blur_px: float = 0.4


@dataclass(frozen=True)
class PhotoSpec:
    """A photo of faces on a plain background (the plate)."""

    size: tuple[int, int]  # (height, width)
    faces: tuple[Face, ...]
    sensor: Sensor = field(default_factory=Sensor)
    background: float = 0.15


@dataclass(frozen=True)
class FaceTruth:
    """What is known about one face of one photo (see the module docstring)."""

    outline_px: np.ndarray
    face: Face


@dataclass(frozen=True)
class Rendered:
    mosaic: np.ndarray  # uint16 (H, W) RGGB
    faces: tuple[FaceTruth, ...]
    spec: PhotoSpec

    def truth_dc(self, k: int, mask: np.ndarray, y0: int, x0: int) -> np.ndarray:
        """(3,) face k's period-averaged radiance at the ROI's centroid, DN above black."""
        face = self.faces[k].face
        ys, xs = np.nonzero(mask)
        light = float(np.mean(lamp(face, xs + x0, ys + y0)))
        return face.pattern.mean() * light * np.asarray(QE) * self.spec.sensor.level_dn

    def truth_roi(self, k: int, mask: np.ndarray, y0: int, x0: int) -> np.ndarray:
        """(3,) the continuous untextured mean over the ROI's pixel squares, DN above black."""
        face = self.faces[k].face
        return roi_mean_truth(face, mask, y0, x0) * np.asarray(QE) * self.spec.sensor.level_dn


def _gaussian_field(shape: tuple[int, int], ell: float, rng: np.random.Generator) -> np.ndarray:
    """Unit-variance stationary field with correlation exp(-r^2 / ell^2) (FFT filtering)."""
    h, w = shape
    ky = np.fft.fftfreq(h)[:, None]
    kx = np.fft.rfftfreq(w)[None, :]
    k2 = (2 * np.pi) ** 2 * (kx**2 + ky**2)
    amp = np.exp(-(ell**2) * k2 / 8)
    white = np.fft.rfft2(rng.standard_normal(shape))
    f = np.fft.irfft2(white * amp, s=shape)
    norm = math.sqrt(float(np.sum(amp[:, 0] ** 2) + 2 * np.sum(amp[:, 1:] ** 2)) / (h * w))
    return f / norm if norm > 0 else f


def _layer_values(
    s_over: np.ndarray, rng: np.random.Generator, sd: float, smooth: bool = False
) -> np.ndarray:
    """A random value per layer (iid normal of sd `sd`) at layer coordinates `s_over` (layers,
    continuous): constant over each layer with a short ramp (0.1 layer) at its edges, as each
    extruded line has its own brightness; `smooth` interpolates linearly between the layer
    centres instead (for irregular positions, which bend the lines smoothly)."""
    lo = math.floor(float(s_over.min())) - 2
    hi = math.ceil(float(s_over.max())) + 2
    vals = sd * rng.standard_normal(hi - lo + 1)
    if smooth:
        return np.interp(s_over, np.arange(lo, hi + 1) + 0.5, vals)
    j = np.floor(s_over).astype(int) - lo
    frac = s_over - np.floor(s_over)
    # within 0.05 of a boundary the value ramps linearly to the next layer's
    t = np.clip((frac - 0.95) / 0.1, 0.0, 1.0)  # 0.95 .. 1.0 -> 0 .. 0.5
    u = np.clip((0.05 - frac) / 0.1, 0.0, 1.0)  # 0.0 .. 0.05 -> 0.5 .. 0
    own = vals[j]
    nxt = vals[np.minimum(j + 1, vals.size - 1)]
    prv = vals[np.maximum(j - 1, 0)]
    return own + t * (nxt - own) + u * (prv - own)


def _inside(face: Face, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    s, t, _, _ = face_coordinates(face, x, y)
    return (np.abs(s) <= face.size_mm[0] / 2) & (np.abs(t) <= face.size_mm[1] / 2)


def render(
    spec: PhotoSpec,
    rng: np.random.Generator,
    background: np.ndarray | None = None,
    noise_rng: np.random.Generator | None = None,
) -> Rendered:
    """The mosaic of one photo (uint16) and its faces' truths; `background` (3, H, W) replaces
    the plain plate (e.g. with markers drawn on it). The textures are drawn from `rng`, the
    sensor noise from `noise_rng` (default `rng`): the same surface photographed twice."""
    h, w = spec.size
    radiance = np.full((3, h, w), spec.background) if background is None else background.copy()
    for face in spec.faces:
        _draw_face(radiance, face, spec.sensor.blur_px, rng)
    truths = tuple(FaceTruth(f.outline_px(), f) for f in spec.faces)
    return Rendered(_sensor(radiance, spec.sensor, noise_rng or rng), truths, spec)


def _draw_face(radiance: np.ndarray, face: Face, blur_px: float, rng: np.random.Generator) -> None:
    """Paint one face into `radiance` (3, H, W), pixels at its edges by their coverage."""
    box = _face_box(face, radiance.shape[1:])
    if box is None:
        return
    ys, xs = np.mgrid[box[0] : box[1], box[2] : box[3]]
    x, y = xs.ravel().astype(float), ys.ravel().astype(float)
    cover = _coverage(face, x, y)
    sel = cover > 0
    x, y, cover = x[sel], y[sel], cover[sel]
    tex = face.texture
    s, _, _, _ = face_coordinates(face, x, y)
    layer = s / face.layer_mm + face.phase
    offsets = _layer_values(layer, rng, tex.positions) if tex.positions > 0 else None
    vals = pixel_pattern(face, x, y, blur_px, offsets) * lamp(face, x, y)
    factor = np.ones_like(x)
    if tex.layers > 0:
        factor *= 1 + _layer_values(layer, rng, tex.layers)
    if tex.surface > 0:
        grf = _gaussian_field((box[1] - box[0], box[3] - box[2]), tex.ell_px, rng)
        factor *= 1 + tex.surface * grf.ravel()[sel]
    yi, xi = y.astype(int), x.astype(int)
    radiance[:, yi, xi] = cover * vals * factor + (1 - cover) * radiance[:, yi, xi]


def _sensor(radiance: np.ndarray, sensor: Sensor, rng: np.random.Generator) -> np.ndarray:
    """Each pixel's colour picked by the RGGB mosaic, DN, Poisson and read noise, black, 14 bits."""
    h, w = radiance.shape[-2:]
    colour = CFA[np.arange(h)[:, None] % 2, np.arange(w)[None, :] % 2]
    qe = np.asarray(QE)[colour]
    mean_dn = np.take_along_axis(radiance, colour[None], axis=0)[0] * qe * sensor.level_dn
    electrons = rng.poisson(np.maximum(mean_dn, 0) * sensor.gain_e_per_dn)
    dn = electrons / sensor.gain_e_per_dn + sensor.read_noise_dn * rng.standard_normal((h, w))
    return np.clip(np.rint(dn + BLACK_DN), 0, WHITE_DN).astype(np.uint16)


def _face_box(face: Face, shape: tuple[int, int]) -> tuple[int, int, int, int] | None:
    pts = face.outline_px()
    y0 = max(0, math.floor(pts[:, 1].min()) - 1)
    y1 = min(shape[0], math.ceil(pts[:, 1].max()) + 2)
    x0 = max(0, math.floor(pts[:, 0].min()) - 1)
    x1 = min(shape[1], math.ceil(pts[:, 0].max()) + 2)
    return (y0, y1, x0, x1) if y1 > y0 and x1 > x0 else None


def _coverage(face: Face, x: np.ndarray, y: np.ndarray, sub: int = 4) -> np.ndarray:
    """The fraction of each pixel's square inside the face (sub x sub points)."""
    o = (np.arange(sub) + 0.5) / sub - 0.5
    total = np.zeros_like(x)
    for dy in o:
        for dx in o:
            total += _inside(face, x + dx, y + dy)
    return total / sub**2


def frame(rendered: Rendered, name: str = "striped") -> RawFrame:
    """A stairfit RawFrame holding the mosaic (RGGB, black 512, 14 bits), no file behind it."""
    return RawFrame(
        path=Path(f"{name}.dng"),
        name=name,
        sha256="",
        data=rendered.mosaic,
        cfa=CFA.copy(),
        black=np.full((2, 2), BLACK_DN, dtype=np.float32),
        white_level=float(WHITE_DN),
        camera_whitebalance=(1.0, 1.0, 1.0),
        exif_exposure_time_s=None,
        exif_f_number=None,
        exif_iso=None,
        make="",
        model="",
    )


# --- random scenes ----------------------------------------------------------------------------


def random_face(
    rng: np.random.Generator,
    centre: tuple[float, float],
    extent_px: float,
    *,
    period_px: float | None = None,
    grey: bool = True,
    texture: Texture | None = None,
    graded: bool = True,
    axis_aligned: bool = False,
    thickness_px: float | None = None,
    square: bool = False,
    sharp: bool = False,
) -> Face:
    """A face about `extent_px` across in the image, random in everything else; `thickness_px`
    makes it that thin across its layer lines (a face seen near grazing); `square` puts its
    layer lines exactly along the pixel rows or columns and keeps them parallel (a camera
    squared to the specimen: no turn, no skew, perspective only along the layers' normal);
    `sharp` gives it `sharp_pattern`."""
    period = period_px if period_px is not None else float(rng.uniform(1.0, 8.0))
    layer_mm = 0.15
    across_px = thickness_px if thickness_px is not None else rng.uniform(0.7, 1.0) * extent_px
    size = float(across_px) * layer_mm / period  # mm across the layers
    angle = (
        float(rng.choice([0.0, 90.0, 180.0, 270.0]))
        if axis_aligned or square
        else float(rng.uniform(0, 360))
    )
    if axis_aligned and not square:
        angle += float(rng.normal(0, 0.3))
    scale_t = float(rng.uniform(0.6, 1.0)) * extent_px / 20.0
    # perspective: the period changes by a few % across the face (a 135 mm lens at 0.9 m sees
    # a 20 mm face's ends 1% nearer and farther)
    pers = rng.normal(0, 0.01, size=2) / np.array([size, 20.0])
    grad = rng.normal(0, 0.25 / extent_px, size=2) if graded else np.zeros(2)
    phase = float(rng.uniform(0, 1))  # the draws in their historical order (seeded scenes)
    skew = float(rng.normal(0, 3))
    pattern = sharp_pattern(rng) if sharp else grey_pattern(rng) if grey else coloured_pattern(rng)
    if square:
        pers[1], skew = 0.0, 0.0
    return Face(
        centre=centre,
        angle_deg=angle,
        period_px=period,
        size_mm=(size, 20.0),
        scale_t=scale_t,
        perspective=(float(pers[0]), float(pers[1])),
        phase=phase,
        skew_deg=skew,
        pattern=pattern,
        light=float(rng.uniform(0.6, 1.0)),
        gradient=(float(grad[0]), float(grad[1])),
        curvature=float(rng.normal(0, 0.03)) if graded else 0.0,
        texture=texture or Texture(),
        layer_mm=layer_mm,
    )


def random_photo(
    rng: np.random.Generator,
    *,
    faces: int = 4,
    extent_px: float = 150.0,
    level_dn: float | None = None,
    texture: Texture | None = None,
    grey: bool = True,
    periods: tuple[float, ...] | None = None,
    axis_aligned: bool = False,
    read_noise_dn: float = 3.0,
    gain_e_per_dn: float = 1.0,
    thickness_px: tuple[float | None, ...] | None = None,
    square: bool = False,
    sharp: bool = False,
    blur_px: float | None = None,
) -> PhotoSpec:
    """Faces in a row, each in its own square cell of a photo (1.5 x `extent_px` wide);
    `thickness_px` (one per face, None: the default) makes faces thin across their layers;
    `square` and `sharp` as in `random_face`; `blur_px` the lens blur (default: drawn from
    0-0.5 px)."""
    cell = int(1.5 * extent_px) // 2 * 2
    h, w = cell + 40, faces * cell + 40
    out = []
    for k in range(faces):
        centre = (20 + cell * (k + 0.5) + rng.uniform(-3, 3), 20 + cell / 2 + rng.uniform(-3, 3))
        period = periods[k % len(periods)] if periods else None
        thick = thickness_px[k % len(thickness_px)] if thickness_px else None
        out.append(
            random_face(
                rng, centre, extent_px, period_px=period, grey=grey, texture=texture,
                axis_aligned=axis_aligned, thickness_px=thick, square=square, sharp=sharp,
            )
        )  # fmt: skip
    level = level_dn if level_dn is not None else float(rng.uniform(300, 4000))
    # the brightest stripe of the brightest face at most 70% of the raw range
    peak = max(f.pattern.peak() * f.light * 1.4 for f in out)
    level = min(level, 0.7 * (WHITE_DN - BLACK_DN) / peak)
    blur = float(rng.uniform(0.0, 0.5))
    sensor = Sensor(level_dn=level, gain_e_per_dn=gain_e_per_dn, read_noise_dn=read_noise_dn,
                    blur_px=blur if blur_px is None else blur_px)  # fmt: skip
    return PhotoSpec((h, w), tuple(out), sensor)


# --- files: DNG, markers, scene.toml -----------------------------------------------------------


def _rational(x: float) -> tuple[int, int]:
    f = Fraction(x).limit_denominator(100_000)
    return f.numerator, f.denominator


def write_dng(path: Path, mosaic: np.ndarray, exposure_time_s: float, f_number: float,
              iso: float) -> None:  # fmt: skip
    """A CFA DNG (RGGB, black 512, 14 bits) written with tifffile; exposure tags in IFD0."""
    tags = [
        (271, "s", 0, "Striped", True),  # Make
        (272, "s", 0, "Renderer", True),  # Model
        (33421, "H", 2, (2, 2), True),  # CFARepeatPatternDim
        (33422, "B", 4, (0, 1, 1, 2), True),  # CFAPattern: R G / G B
        (50706, "B", 4, (1, 4, 0, 0), True),  # DNGVersion
        (50708, "s", 0, "Striped Renderer", True),  # UniqueCameraModel
        (50710, "B", 3, (0, 1, 2), True),  # CFAPlaneColor
        (50714, "I", 1, BLACK_DN, True),  # BlackLevel
        (50717, "I", 1, WHITE_DN, True),  # WhiteLevel
        (50721, "2i", 9, (1, 1, 0, 1, 0, 1, 0, 1, 1, 1, 0, 1, 0, 1, 0, 1, 1, 1), True),
        (50778, "H", 1, 21, True),  # CalibrationIlluminant1: D65
        (33434, "2I", 1, _rational(exposure_time_s), True),  # ExposureTime
        (33437, "2I", 1, _rational(f_number), True),  # FNumber
        (34855, "H", 1, round(iso), True),  # ISOSpeedRatings
    ]  # fmt: skip
    tifffile.imwrite(path, mosaic, photometric=32803, extratags=tags, metadata=None)


MARKER_MM = 9.0
"""Side of each printed marker's black square (4 x 4 data cells + border: 1.5 mm cells)."""


def _marker_cells(marker_id: int) -> np.ndarray:
    """The 6 x 6 cells of a DICT_4X4_50 marker (1 white, 0 black), from OpenCV's dictionary."""
    d = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    img = cv2.aruco.generateImageMarker(d, marker_id, 60, borderBits=1)
    return (img[5::10, 5::10] > 127).astype(float)


def draw_markers(
    radiance: np.ndarray, base_to_px: np.ndarray, markers: dict[int, tuple[float, float]],
    paper: float, ink: float, sub: int = 4,
) -> dict[int, np.ndarray]:  # fmt: skip
    """Draw ArUco markers (each in a white quiet zone of one cell) on the base plane into
    `radiance` (H, W, all channels alike); return each marker's true image corners (4, 2)."""
    h, w = radiance.shape[-2:]
    inv = np.linalg.inv(base_to_px)
    corners = {}
    cell = MARKER_MM / 6
    for mid, (x0, y0) in markers.items():
        cells = _marker_cells(mid)
        quad = np.array([[x0, y0], [x0 + MARKER_MM, y0], [x0 + MARKER_MM, y0 + MARKER_MM],
                         [x0, y0 + MARKER_MM]])  # fmt: skip
        corners[mid] = _apply(base_to_px, quad)
        zone = _apply(base_to_px, quad + np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * cell)
        bx0, by0 = np.floor(zone.min(axis=0)).astype(int) - 1
        bx1, by1 = np.ceil(zone.max(axis=0)).astype(int) + 2
        bx0, by0, bx1, by1 = max(bx0, 0), max(by0, 0), min(bx1, w), min(by1, h)
        ys, xs = np.mgrid[by0:by1, bx0:bx1]
        acc = np.zeros(ys.shape)
        inzone = np.zeros(ys.shape)
        o = (np.arange(sub) + 0.5) / sub - 0.5
        for dy in o:
            for dx in o:
                q = _apply(inv, np.c_[xs.ravel() + dx, ys.ravel() + dy]).reshape(*ys.shape, 2)
                u = (q[..., 0] - x0) / cell
                v = (q[..., 1] - y0) / cell
                zone_hit = (u >= -1) & (u < 7) & (v >= -1) & (v < 7)
                iu = np.clip(np.floor(u).astype(int), 0, 5)
                iv = np.clip(np.floor(v).astype(int), 0, 5)
                in_marker = (u >= 0) & (u < 6) & (v >= 0) & (v < 6)
                white = np.where(in_marker, cells[iv, iu], 1.0)
                acc += np.where(zone_hit, np.where(white > 0, paper, ink), 0.0)
                inzone += zone_hit
        frac = inzone / sub**2
        region = radiance[..., by0:by1, bx0:bx1]
        region[...] = np.where(frac > 0, acc / sub**2 + (1 - frac) * region, region)
    return corners


def write_folder(
    path: str | Path,
    seed: int,
    *,
    photos: int = 3,
    size: tuple[int, int] = (700, 1000),
    periods: tuple[float, ...] = (1.3, 2.2, 3.1, 4.0, 5.5, 7.5),
    texture: Texture | None = None,
    level_dn: float = 2500.0,
) -> dict[str, Any]:
    """A folder `stairfit measure` reads: DNGs of striped faces flat on a base with four ArUco
    markers, scene.toml naming the faces as `[[patches]]` outlined on the base (mm, placed by
    the markers; layer lines along the base's y axis), and truth.json.

    Each photo sees the base through its own homography (scale, rotation, foreshortening,
    perspective), and each face has its own layer pitch, so that periods (drawn from `periods`,
    in px at the face's centre) and the stripes' orientation differ between faces and photos.
    truth.json holds per photo the base -> image homography, the markers' true image corners,
    and per face its parameters (`face_from_dict`, `folder_truth_dc`). Returns that dict.
    """
    rng = np.random.default_rng(seed)
    folder = Path(path)
    folder.mkdir(parents=True, exist_ok=True)
    n_faces, face_w, face_t, gap = 4, 10.0, 20.0, 3.0
    xs = [(k * (face_w + gap), k * (face_w + gap) + face_w) for k in range(n_faces)]
    total_x = xs[-1][1]
    m = MARKER_MM + 3.0
    markers = {0: (-m, -m), 1: (total_x + 3.0, -m), 2: (-m, face_t + 3.0),
               3: (total_x + 3.0, face_t + 3.0)}  # fmt: skip
    extent = np.array([[-m - 2, -m - 2], [total_x + m + 2, -m - 2],
                       [total_x + m + 2, face_t + m + 2], [-m - 2, face_t + m + 2]])  # fmt: skip
    patterns = [grey_pattern(rng) if k != 3 else coloured_pattern(rng) for k in range(n_faces)]
    t_exp, f_num, iso = 0.01, 4.0, 100.0
    h, w = size
    out: dict[str, Any] = {"photos": [], "qe": list(QE)}
    entries = []
    for p in range(photos):
        rot = math.radians(float(rng.uniform(-30, 30)) + (90.0 if p % 2 else 0.0))
        fore = float(rng.uniform(0.6, 1.0))  # foreshortening across the layers
        lin = np.array([[math.cos(rot), -math.sin(rot)], [math.sin(rot), math.cos(rot)]])
        lin = lin @ np.diag([fore, 1.0])
        centre_mm = extent.mean(axis=0)
        span = np.ptp((extent - centre_mm) @ lin.T, axis=0)
        scale = 0.88 * min(w / span[0], h / span[1])
        hmat = np.eye(3)
        hmat[:2, :2] = scale * lin
        hmat[:2, 2] = np.array([w / 2, h / 2]) - scale * lin @ centre_mm
        e = rng.normal(0, 0.002, size=2)
        hmat[2, :2] = e
        hmat[2, 2] = 1 - e @ centre_mm  # the layout's centre stays at the image centre
        hmat /= hmat[2, 2]
        radiance = np.full((3, h, w), 0.12)
        corners = draw_markers(radiance, hmat, markers, paper=1.6, ink=0.05)
        faces = []
        for k, (sx0, sx1) in enumerate(xs):
            period = float(periods[(p * n_faces + k) % len(periods)])
            faces.append(_base_face(hmat, (sx0, sx1), face_t, period, patterns[k], rng,
                                    texture or Texture()))  # fmt: skip
        sensor = Sensor(level_dn=level_dn, gain_e_per_dn=1.0, read_noise_dn=3.0,
                        blur_px=float(rng.uniform(0.2, 0.5)))  # fmt: skip
        spec = PhotoSpec((h, w), tuple(faces), sensor)
        mosaic = render(spec, rng, background=radiance).mosaic
        name = f"IMG_{p + 1:03d}.dng"
        write_dng(folder / name, mosaic, t_exp, f_num, iso)
        entries.append({"file": name})
        out["photos"].append({
            "file": name,
            "homography": hmat.tolist(),
            "marker_corners_px": {str(m): c.tolist() for m, c in corners.items()},
            "faces": [_face_dict(f) for f in faces],
            "level_dn": level_dn,
            "blur_px": sensor.blur_px,
        })  # fmt: skip
    out["dn_per_radiance"] = t_exp * (iso / 100.0) / f_num**2
    patches = [
        {"name": f"f{k}", "face_mm": [[a, 0.0], [b, 0.0], [b, face_t], [a, face_t]]}
        for k, (a, b) in enumerate(xs)
    ]
    marker_table = [
        {"id": m, "corners_mm": [[x0, y0], [x0 + MARKER_MM, y0],
                                 [x0 + MARKER_MM, y0 + MARKER_MM], [x0, y0 + MARKER_MM]]}
        for m, (x0, y0) in markers.items()
    ]  # fmt: skip
    scene = {
        "version": 1,
        "patches": patches,
        "markers": {"dictionary": "DICT_4X4_50", "marker": marker_table},
        "photos": entries,
    }
    (folder / "scene.toml").write_text(tomli_w.dumps(scene))
    (folder / "truth.json").write_text(json.dumps(out, indent=1))
    return out


def _base_face(
    hmat: np.ndarray, xs: tuple[float, float], face_t: float, period_px: float,
    pattern: Pattern, rng: np.random.Generator, texture: Texture,
) -> Face:  # fmt: skip
    """A face lying on the base: the base's homography moved to the face's centre, its layer
    pitch chosen so that the period is `period_px` at the centre."""
    cx, cy = (xs[0] + xs[1]) / 2, face_t / 2
    hf = hmat @ np.array([[1, 0, cx], [0, 1, cy], [0, 0, 1.0]])
    hf = hf / hf[2, 2]
    step = _apply(hf, np.array([[0.5, 0.0]]))[0] - _apply(hf, np.array([[-0.5, 0.0]]))[0]
    layer_mm = period_px / float(np.hypot(*step))
    grad = rng.normal(0, 0.002, size=2)
    return _HFace(
        centre=(float(hf[0, 2]), float(hf[1, 2])),
        angle_deg=0.0,
        period_px=period_px,
        size_mm=(xs[1] - xs[0], face_t),
        phase=float(rng.uniform(0, 1)),
        pattern=pattern,
        light=float(rng.uniform(0.5, 0.9)),
        gradient=(float(grad[0]), float(grad[1])),
        curvature=float(rng.normal(0, 0.03)),
        texture=texture,
        layer_mm=layer_mm,
        matrix=tuple(map(tuple, hf.tolist())),
    )


@dataclass(frozen=True)
class _HFace(Face):
    """A face whose homography is given (a face on the base of a `write_folder` photo)."""

    matrix: tuple[tuple[float, ...], ...] = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))

    def homography(self) -> np.ndarray:
        return np.array(self.matrix)


def _face_dict(face: Face) -> dict[str, Any]:
    d = {
        "centre": list(face.centre),
        "period_px": face.period_px,
        "size_mm": list(face.size_mm),
        "phase": face.phase,
        "light": face.light,
        "gradient": list(face.gradient),
        "curvature": face.curvature,
        "layer_mm": face.layer_mm,
        "pattern": {k: getattr(face.pattern, k) for k in
                    ("body", "specular", "duty", "contrast", "rounding", "spec_width",
                     "spec_phase")},
        "matrix": [list(r) for r in face.homography().tolist()],
    }  # fmt: skip
    return d


def face_from_dict(d: dict[str, Any]) -> Face:
    """A face of truth.json (`write_folder`) back as a Face."""
    return _HFace(
        centre=tuple(d["centre"]),  # type: ignore[arg-type]
        angle_deg=0.0,
        period_px=1.0,
        size_mm=tuple(d["size_mm"]),  # type: ignore[arg-type]
        phase=d["phase"],
        pattern=Pattern(**{k: tuple(v) if k == "body" else v for k, v in d["pattern"].items()}),
        light=d["light"],
        gradient=tuple(d["gradient"]),  # type: ignore[arg-type]
        curvature=d["curvature"],
        layer_mm=d["layer_mm"],
        matrix=tuple(map(tuple, d["matrix"])),
    )


def folder_truth_dc(truth: dict[str, Any], photo: int, face: int, mask: np.ndarray, y0: int,
                    x0: int) -> np.ndarray:  # fmt: skip
    """(3,) the period-averaged radiance of a `write_folder` face at the ROI's centroid, in
    stairfit's relative radiance (DN above black per t ISO / 100 / N^2)."""
    entry = truth["photos"][photo]
    f = face_from_dict(entry["faces"][face])
    ys, xs = np.nonzero(mask)
    light = float(np.mean(lamp(f, xs + x0, ys + y0)))
    dn = f.pattern.mean() * light * np.asarray(QE) * entry["level_dn"]
    return dn / truth["dn_per_radiance"]
