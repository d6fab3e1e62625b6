"""An independent generator of textured Bayer ROIs, to calibrate imaging's standard errors.

Plain NumPy on purpose: it shares no code and no assumption with `stairfit.imaging.synthetic`
or with the estimator in `stairfit.imaging`, so that the calibration study
(benchmarks/bench_roi_errors.py, tests/imaging/test_blockvar.py) does not test the estimator against
its own model of the data.

* **Texture**: a stationary Gaussian random field `T` of unit variance and zero (ensemble) mean
  with the autocorrelation `exp(-r^2 / ell^2)` (`ell` = `ell_px`, the *correlation length*: the
  distance at which the correlation falls to 1/e, as in rough-surface optics), made by filtering
  white noise in the Fourier domain with the square root of its power spectrum,
  `exp(-ell^2 |k|^2 / 8)`; `ell = 0` is white. The field is periodic over the image; ROIs are
  placed in tiles at least `3 ell` apart, so their textures are independent. It is normalised
  by its exact ensemble variance, never by its sample mean or spread, so that the untextured
  radiance is the ensemble mean of every ROI mean.
* **Signal** (DN above black) at a pixel of colour c: `I_c(x) (1 + a T(x))` (multiplicative
  texture), `I_c(x) + a I0_c T(x)` (additive: the same field, not modulated by the
  illumination) or `I_c(x)` (none). `I_c(x) = I0_c` (uniform) or
  `I0_c (1 + g u . (x - x_centre) / half_length)` (graded: a linear ramp of +-g along a random
  direction u across the ROI). The field is achromatic: R, G and B pixels sample the same `T`
  at their own positions of an RGGB mosaic.
* **Sensor**: electrons = signal x gain, Poisson; Gaussian read noise (DN); black level;
  rounding to integers; clipping to the 14-bit range.

The truths of every ROI and channel are values at the centroid of all the ROI's pixels, where
imaging evaluates each channel's fitted plane (docs/imaging.md §Channel sites): the illumination
`I_c` there (`untextured`: the radiance a model of the surface predicts; `I_c` is linear, so this
is `I0_c` times the mean of the ramp over all the ROI's pixels), and the noise-free signal with its
texture (`exact`: what noise-free photos of *this* surface would give), taken as the mean over
the ROI's pixels of that colour moved by the same ramp to the centroid (the texture's own slope
times the sub-pixel offset between the colour's sites and the centroid is left out). `pixel_mean`
keeps the plain mean over the ROI's pixels of each colour of the noise-free textured signal.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from stairfit import imaging

CFA = np.array([[0, 1], [1, 2]], dtype=np.uint8)
"""RGGB: colour index (0 R, 1 G, 2 B) of each position of the 2 x 2 tile."""

BLACK_DN = 512
WHITE_DN = 16383
GAIN_E_PER_DN = 1.0
READ_NOISE_DN = 3.0
LEVELS_DN = (1500.0, 3000.0, 1000.0)
"""Mean signal above black of R, G and B at level 1 (each ROI draws a level in [0.4, 1.6])."""

BLOCK_PX = 8
"""ROI sizes are counted in blocks of BLOCK_PX x BLOCK_PX raw pixels (the area / 64)."""


@dataclass(frozen=True)
class Cell:
    """One case of the calibration grid.

    Attributes:
        texture: "none", "mult" (multiplicative) or "add" (additive).
        ell_px: correlation length of the texture (px; 0 = white).
        roi_blocks: ROI area in blocks of 8 x 8 px.
        graded: a linear illumination ramp of +-`gradient` across the ROI (else uniform).
        amplitude: relative standard deviation `a` of the texture.
        gradient: the ramp's relative amplitude `g` at the ROI's ends.
    """

    texture: str
    ell_px: float
    roi_blocks: int
    graded: bool
    amplitude: float = 0.03
    gradient: float = 0.3

    def label(self) -> str:
        tex = "none" if self.texture == "none" else f"{self.texture} {self.ell_px:g} px"
        return f"{tex}, {self.roi_blocks} blocks, {'graded' if self.graded else 'uniform'}"


@dataclass(frozen=True)
class RoiTruth:
    """One ROI of a rendered mosaic with its truths per channel (DN above black; module
    docstring): at the ROI's centroid with and without texture, and the plain pixel means."""

    roi: imaging.RoiMask
    exact: np.ndarray
    untextured: np.ndarray
    pixel_mean: np.ndarray


def gaussian_field(shape: tuple[int, int], ell_px: float, rng: np.random.Generator) -> np.ndarray:
    """Periodic Gaussian random field, unit variance, autocorrelation exp(-r^2 / ell^2)."""
    white = rng.standard_normal(shape)
    if ell_px <= 0:
        return white
    ky = 2 * np.pi * np.fft.fftfreq(shape[0])[:, None]
    amp = np.exp(-(ell_px**2) * (ky**2 + (2 * np.pi * np.fft.rfftfreq(shape[1])) ** 2) / 8.0)
    field = np.fft.irfft2(np.fft.rfft2(white) * amp, s=shape)
    # the exact ensemble variance of the filtered field: the mean of amp^2 over all frequencies
    k2 = ky**2 + (2 * np.pi * np.fft.fftfreq(shape[1])) ** 2
    return field / math.sqrt(float(np.mean(np.exp(-(ell_px**2) * k2 / 4.0))))


def roi_polygon(
    roi_blocks: int, centre: tuple[float, float], angle: float
) -> list[tuple[float, float]]:
    """A rectangle of area roi_blocks x 64 px^2, aspect 4:3, rotated by `angle` (rad)."""
    area = roi_blocks * BLOCK_PX**2
    half_w, half_h = math.sqrt(area * 4 / 3) / 2, math.sqrt(area * 3 / 4) / 2
    c, s = math.cos(angle), math.sin(angle)
    pts = [(-half_w, -half_h), (half_w, -half_h), (half_w, half_h), (-half_w, half_h)]
    return [(centre[0] + c * x - s * y, centre[1] + s * x + c * y) for x, y in pts]


def tile_px(cell: Cell) -> int:
    """Side of the square tile holding one ROI: its diagonal plus a 3 ell margin each side."""
    area = cell.roi_blocks * BLOCK_PX**2
    diag = math.sqrt(area * 4 / 3 + area * 3 / 4)
    return 2 * math.ceil((diag + 6 * cell.ell_px + 8) / 2)


def render(cell: Cell, n_rois: int, rng: np.random.Generator) -> tuple[np.ndarray, list[RoiTruth]]:
    """A mosaic (uint16, DN) holding `n_rois` independent ROIs of `cell`, and their truths."""
    tile = tile_px(cell)
    per_row = math.ceil(math.sqrt(n_rois))
    rows = math.ceil(n_rois / per_row)
    shape = (rows * tile, per_row * tile)
    colour = np.tile(CFA, (shape[0] // 2, shape[1] // 2))
    field = gaussian_field(shape, cell.ell_px, rng) if cell.texture != "none" else None
    signal = np.zeros(shape)
    ramp = np.zeros(shape)  # the illumination over its level: 1 (uniform) or the linear ramp
    placed, levels = [], []
    for k in range(n_rois):
        ty, tx = divmod(k, per_row)
        centre = ((tx + 0.5) * tile + rng.uniform(-1, 1), (ty + 0.5) * tile + rng.uniform(-1, 1))
        poly = roi_polygon(cell.roi_blocks, centre, rng.uniform(0, math.pi / 2))
        box = (slice(ty * tile, (ty + 1) * tile), slice(tx * tile, (tx + 1) * tile))
        level = np.array(LEVELS_DN) * rng.uniform(0.4, 1.6)
        illum = _illumination(cell, rng, box, centre, level, colour[box])
        ramp[box] = illum / level[colour[box]]
        signal[box] = _textured(cell, illum, level[colour[box]], field, box)
        placed.append(poly)
        levels.append(level)
    mosaic = sensor(signal, rng)
    truths = []
    for k, (poly, level) in enumerate(zip(placed, levels, strict=True)):
        roi = imaging.roi_mask(poly, shape, 0, photo="roi_fields", wedge=f"r{k}")
        sub = (slice(roi.y0, roi.y0 + roi.mask.shape[0]), slice(roi.x0, roi.x0 + roi.mask.shape[1]))
        cols = colour[sub][roi.mask]
        ramp_roi = ramp[sub][roi.mask]
        pixel_mean = np.array([signal[sub][roi.mask][cols == c].mean() for c in range(3)])
        own_sites = np.array([level[c] * ramp_roi[cols == c].mean() for c in range(3)])
        untextured = np.asarray(level, dtype=float) * ramp_roi.mean()
        truths.append(RoiTruth(roi, pixel_mean + untextured - own_sites, untextured, pixel_mean))
    return mosaic, truths


def _illumination(
    cell: Cell,
    rng: np.random.Generator,
    box: tuple[slice, slice],
    centre: tuple[float, float],
    level: np.ndarray,
    colour: np.ndarray,
) -> np.ndarray:
    base = level[colour]
    if not cell.graded:
        return base
    phi = rng.uniform(0, 2 * math.pi)
    y, x = np.mgrid[box[0], box[1]]
    half = math.sqrt(cell.roi_blocks * BLOCK_PX**2 * 4 / 3) / 2
    u = ((x - centre[0]) * math.cos(phi) + (y - centre[1]) * math.sin(phi)) / half
    return base * (1 + cell.gradient * u)


def _textured(
    cell: Cell,
    illum: np.ndarray,
    level: np.ndarray,
    field: np.ndarray | None,
    box: tuple[slice, slice],
) -> np.ndarray:
    if field is None:
        return illum
    t = cell.amplitude * field[box]
    return illum * (1 + t) if cell.texture == "mult" else illum + level * t


def sensor(signal: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """DN of a noise-free signal (DN above black): Poisson electrons, read noise, black, 14 bits."""
    electrons = rng.poisson(np.maximum(signal, 0) * GAIN_E_PER_DN)
    dn = electrons / GAIN_E_PER_DN + READ_NOISE_DN * rng.standard_normal(signal.shape)
    return np.clip(np.rint(dn + BLACK_DN), 0, WHITE_DN).astype(np.uint16)


def frame(mosaic: np.ndarray) -> imaging.RawFrame:
    """A RawFrame built in memory around a mosaic from `render` (RGGB, black 512)."""
    return imaging.RawFrame(
        path=Path("roi_fields.dng"),
        name="roi_fields",
        sha256="",
        data=mosaic,
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
