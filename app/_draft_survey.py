"""What the RAW files of a photo folder are, for `stairfit init` (app/draft.py): each file's
size, camera, exposure and tags, whether it is a photograph, a flat field or a dark frame, and
which photographs are one view taken at several exposures (an HDR bracket).

Flat fields and dark frames are recognised from the image alone (docs/first-photo-set.md): a
dark frame has no signal anywhere (the lens capped), a flat field is bright and uniform up to a
smooth fall-off towards the corners (vignetting). A bracket is a run of consecutive files
(in name order) of one size whose exposures differ and whose images, scaled by their exposures,
agree block by block wherever both are well exposed.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from stairfit.imaging import CameraTags, Exposure

RAW_EXTENSIONS: frozenset[str] = frozenset(
    {
        ".dng", ".nef", ".nrw", ".cr2", ".cr3", ".crw", ".arw", ".srf", ".sr2", ".raf", ".orf",
        ".rw2", ".raw", ".pef", ".ptx", ".srw", ".x3f", ".3fr", ".fff", ".iiq", ".erf", ".kdc",
        ".dcr", ".mef", ".mos", ".mrw", ".rwl", ".gpr",
    }
)  # fmt: skip
"""File extensions (lower case) `stairfit init` reads as camera RAW files; others are left out."""

BLOCK_COLUMNS = 256
"""A file's image is reduced to block means on a grid at most this many blocks wide (its aspect
kept) to compare exposures of a bracket and to judge uniformity..."""

MIN_BLOCK_PX = 4
"""...each block at least this many pixels of the 2 x 2 binned image wide (fewer blocks on a
small image, so that each still averages its pixels' noise down)."""

DARK_MAX_LEVEL = 0.01
"""A dark frame: its brightest blocks (99th percentile) are below this fraction of the raw range
above black (imaging's own check of a dark frame uses the same level for the median)."""

DARK_MAX_SPREAD = 0.005
"""...and its blocks differ by less than this fraction of the raw range (no image at all)."""

FLAT_MIN_LEVEL = 0.05
"""A flat field: its median is at least this fraction of the raw range above black
(imaging refuses a darker flat)..."""

FLAT_MAX_TEXTURE = 0.01
"""...and its blocks depart from a smooth surface (a polynomial of `FLAT_SURFACE_DEGREE`, which
follows vignetting) by less than this RMS fraction of their mean: a photo of wedges and markers
departs by tens of per cent."""

FLAT_SURFACE_DEGREE = 4
"""Total degree of the smooth surface a flat field's blocks are compared with."""

FLAT_MAX_CLIPPED = 0.001
"""A flat field has at most this fraction of clipped pixels (as imaging requires)."""

CLIP_LEVEL = 0.98
"""A raw value at or above this fraction of the range above black is clipped (the scene's
default `saturation_level`)."""

BRACKET_LEVELS = (0.003, 0.8)
"""Blocks between these fractions of the raw range above black (in both files) are compared
when deciding whether two exposures show one view: above noise and below clipping."""

BRACKET_MAX_MEDIAN = 0.1
"""Two exposures show one view when the median |log ratio| of their exposure-scaled blocks is
below this..."""

BRACKET_MAX_TAIL = 0.25
"""...and the 99.9th percentile below this: a view turned by a degree moves the faces' edges,
which changes a few blocks by far more."""

BRACKET_MIN_BLOCKS = 50
"""Fewer comparable blocks than this and two exposures are not taken as one view."""

EXPOSURE_STEP = 1.05
"""Exposures (relative radiance per DN) that differ by less than this factor are the same
exposure: two such files are two photos, never one bracket."""


@dataclass(frozen=True, eq=False)
class RawFile:
    """One RAW file of the folder as `stairfit init` sees it.

    Attributes:
        name: the file name (relative to the folder).
        width, height: the visible image in pixels.
        cfa: the CFA tile ("RGGB"; "" for a linear file).
        camera: make and model from the tags ("" when absent).
        exposure: the exposure from the file's tags (`imaging.Exposure`), None when a tag is
            missing; `exposure_problem` then says which.
        tag_exposure: the tags' (exposure time s, f-number, ISO), None where absent.
        tags: focal length, pixel pitch and capture time (`imaging.CameraTags`).
        level: the median signal above black, as a fraction of the raw range.
        peak: the 99th percentile of the block means, as a fraction of the raw range.
        spread: the 99th minus the 1st percentile of the block means, as a fraction of the range.
        texture: the RMS departure of the block means from a smooth surface, relative to
            their mean (inf for a black image).
        clipped: the fraction of clipped pixels.
        blocks: (rows, `BLOCK_COLUMNS`) block means of the signal above black (fraction of
            the raw range), NaN where a block holds a clipped pixel.
    """

    name: str
    width: int
    height: int
    cfa: str
    camera: str
    exposure: Exposure | None
    exposure_problem: str
    tag_exposure: tuple[float | None, float | None, float | None]
    tags: CameraTags
    level: float
    peak: float
    spread: float
    texture: float
    clipped: float
    blocks: np.ndarray


def raw_files(folder: Path) -> list[Path]:
    """The camera RAW files directly in `folder` (by extension, `RAW_EXTENSIONS`), in name
    order; hidden files (a leading dot) and sub-folders are left out."""
    return sorted(
        (p for p in folder.iterdir()
         if p.suffix.lower() in RAW_EXTENSIONS and not p.name.startswith(".")),
        key=lambda p: p.name,
    )  # fmt: skip


def survey(path: Path) -> RawFile:
    """Decode one RAW file and summarise it (`RawFile`).

    Raises:
        imaging.ImagingError: the file cannot be decoded (the message names it).
    """
    from stairfit import imaging

    frame = imaging.decode_raw(path)
    try:
        exposure, problem = imaging.resolve_exposure(frame), ""
    except imaging.ImagingError:
        missing = [
            tag for tag, v in (("ExposureTime", frame.exif_exposure_time_s),
                               ("FNumber", frame.exif_f_number), ("ISO", frame.exif_iso))
            if v is None
        ]  # fmt: skip
        exposure, problem = None, f"no usable {', '.join(missing)} tag"
    linear, _factor = imaging.binned_linear(frame)
    black = float(np.mean(frame.black))
    span = max(float(frame.white_level) - black, 1.0)
    per_pixel = 3 if frame.cfa is None else 4  # binned_linear sums 4 mosaic pixels or 3 planes
    signal = linear / np.float32(per_pixel * span)
    clip = frame.data >= np.float32(black + CLIP_LEVEL * span)
    blocks = _block_means(signal, _block_any(_binned(clip, signal.shape)))
    finite = blocks[np.isfinite(blocks)]
    sample = signal[:: max(1, signal.shape[0] // 512), :: max(1, signal.shape[1] // 512)]
    return RawFile(
        name=path.name,
        width=frame.width,
        height=frame.height,
        cfa=frame.cfa_string,
        camera=frame.camera,
        exposure=exposure,
        exposure_problem=problem,
        tag_exposure=(frame.exif_exposure_time_s, frame.exif_f_number, frame.exif_iso),
        tags=imaging.read_camera_tags(path),
        level=float(np.median(sample)),
        peak=float(np.percentile(finite, 99)) if finite.size else math.inf,
        spread=float(np.ptp(np.percentile(finite, [1, 99]))) if finite.size else math.inf,
        texture=_texture(blocks),
        clipped=float(clip.mean()),
        blocks=blocks,
    )


def _grid(shape: tuple[int, ...]) -> tuple[int, int]:
    """(rows, columns) of the block grid of an image of `shape`."""
    cols = max(1, min(BLOCK_COLUMNS, shape[1] // MIN_BLOCK_PX))
    return max(1, round(cols * shape[0] / shape[1])), cols


def _binned(mask: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """A full-resolution mask on the pixels of `imaging.binned_linear`'s image of `shape`:
    True where any of the pixels binned into one is (a 2 x 2 tile, or the 3 planes)."""
    if mask.ndim == 3:
        return mask.any(axis=2)
    h, w = shape[:2]
    return mask[: 2 * h, : 2 * w].reshape(h, 2, w, 2).any(axis=(1, 3))


def _block_any(mask: np.ndarray) -> np.ndarray:
    """Whether each block of the grid holds a True pixel of `mask` (the binned image's size)."""
    import cv2

    rows, cols = _grid(mask.shape)
    return cv2.resize(mask.astype(np.float32), (cols, rows), interpolation=cv2.INTER_AREA) > 0


def _block_means(image: np.ndarray, bad: np.ndarray) -> np.ndarray:
    """Block means of `image` on the grid, NaN where `bad`."""
    import cv2

    rows, cols = _grid(image.shape)
    means = cv2.resize(image.astype(np.float32), (cols, rows), interpolation=cv2.INTER_AREA)
    return np.where(bad, np.nan, means.astype(np.float64))


def _texture(blocks: np.ndarray) -> float:
    """RMS departure of the finite blocks from a smooth surface (total degree
    `FLAT_SURFACE_DEGREE` in Legendre polynomials), relative to their mean."""
    rows, cols = blocks.shape
    ok = np.isfinite(blocks)
    mean = float(np.mean(blocks[ok])) if ok.any() else 0.0
    if mean <= 0 or ok.sum() < 4 * (FLAT_SURFACE_DEGREE + 1) ** 2:
        return math.inf
    d = FLAT_SURFACE_DEGREE
    y, x = np.mgrid[0:rows, 0:cols]
    vy = np.polynomial.legendre.legvander(2 * y[ok] / max(rows - 1, 1) - 1, d)
    vx = np.polynomial.legendre.legvander(2 * x[ok] / max(cols - 1, 1) - 1, d)
    design = np.stack([vy[:, i] * vx[:, j] for i in range(d + 1) for j in range(d + 1 - i)], 1)
    coef, *_ = np.linalg.lstsq(design, blocks[ok], rcond=None)
    return float(np.sqrt(np.mean((blocks[ok] - design @ coef) ** 2)) / mean)


def kind(f: RawFile) -> tuple[str, str]:
    """("dark", "flat" or "photo", why) of one file: see the module docstring."""
    if f.peak < DARK_MAX_LEVEL and f.spread < DARK_MAX_SPREAD:
        return "dark", (
            f"no image: its brightest blocks at {100 * f.peak:.2g}% of the raw range above black"
        )
    if (
        f.level >= FLAT_MIN_LEVEL
        and f.texture < FLAT_MAX_TEXTURE
        and (f.clipped <= FLAT_MAX_CLIPPED)
    ):
        return "flat", (
            f"uniform to {100 * f.texture:.2g}% RMS after a smooth fall-off, at "
            f"{100 * f.level:.0f}% of the raw range"
        )
    return "photo", ""


def same_view(a: RawFile, b: RawFile) -> tuple[bool, str]:
    """Whether `b` is another exposure of `a`'s view (a bracket), and why not if not.

    Both need exposures from their tags that differ (`EXPOSURE_STEP`), one size and CFA, and
    block means that agree once scaled by their exposures (`BRACKET_*`).
    """
    if (a.width, a.height, a.cfa) != (b.width, b.height, b.cfa):
        return False, "another image size"
    if a.exposure is None or b.exposure is None:
        return False, "no exposure tags to compare"
    if not _other_exposure(a, b):
        return False, "the same exposure"
    ratio = a.exposure.scale / b.exposure.scale
    lo, hi = BRACKET_LEVELS
    ok = (a.blocks > lo) & (a.blocks < hi) & (b.blocks > lo) & (b.blocks < hi)
    if ok.sum() < BRACKET_MIN_BLOCKS:
        return False, "too few blocks well exposed in both"
    # radiance = DN x scale: the two agree when the files show the same view
    log_ratio = np.abs(np.log(a.blocks[ok] * ratio / b.blocks[ok]))
    median, tail = float(np.median(log_ratio)), float(np.percentile(log_ratio, 99.9))
    if median < BRACKET_MAX_MEDIAN and tail < BRACKET_MAX_TAIL:
        return True, ""
    return False, f"the images differ (median {median:.2g}, 99.9th percentile {tail:.2g})"


def _other_exposure(a: RawFile, b: RawFile) -> bool:
    """Whether the two files' exposures differ (`EXPOSURE_STEP`)."""
    if a.exposure is None or b.exposure is None:
        return False
    ratio = a.exposure.scale / b.exposure.scale
    return max(ratio, 1 / ratio) >= EXPOSURE_STEP


@dataclass(frozen=True)
class View:
    """One view: its files (an HDR bracket's shortest exposure first, the reference) and the
    surveys of those files."""

    files: tuple[RawFile, ...]

    @property
    def names(self) -> tuple[str, ...]:
        """The file names, the reference first."""
        return tuple(f.name for f in self.files)


def group_views(photos: Sequence[RawFile]) -> tuple[View, ...]:
    """The photographs (in name order) grouped into views: a file joins the run before it when
    it shows the same view as the run's last file at another exposure (`same_view`; a
    bracket's neighbours overlap most in what both expose well) and an exposure none of the run
    has. A bracket lists its shortest exposure first (the reference: the photo's name and
    exposure)."""
    runs: list[list[RawFile]] = []
    for f in photos:
        if runs and same_view(runs[-1][-1], f)[0] and all(_other_exposure(g, f) for g in runs[-1]):
            runs[-1].append(f)
        else:
            runs.append([f])
    return tuple(
        View(tuple(sorted(run, key=lambda g: -g.exposure.scale if g.exposure else 0.0)))
        for run in runs
    )
