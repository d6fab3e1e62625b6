"""Preview PNGs: the photo at reduced size with ROIs, markers and saturated pixels drawn.

For a person to check the ROIs, not for measuring: a colour image of the mosaic without
demosaic (each 2 x 2 CFA tile gives one pixel, its two greens averaged), shrunk to at most
`PREVIEW_MAX_SIZE` px on the longer side, grey-world balanced, with a 1/2.2 gamma. Saturated
pixels are magenta, eroded ROIs are outlined in green with their names, the polygons before
erosion in yellow, and detected ArUco markers in cyan with their ids. Coordinates are those of
the raw image (docs/imaging.md §Pixels), so positions can be read off the preview.

Speed (docs/imaging.md §Previews): the mosaic is shrunk while still 16-bit (one `cv2.resize` of
each pair of CFA rows), and black level, balance, scale and gamma are one 65536-entry lookup
table per channel applied at the preview's size; nothing is converted to float at full size. The
PNG is written with Huffman-only deflate and the "sub" filter, which on noisy photographs is
about as small as the default and faster to write.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

import cv2
import numpy as np

from stairfit.fileio import atomic_bytes

from ._decode import RawFrame
from ._errors import ImagingError
from ._markers import MarkerDetection, grey_for_detection
from ._roi import RoiMask

PREVIEW_MAX_SIZE = 1600
"""Default longest side of a preview, in pixels (a 12 MP photo: 1600 x 1200, 0.4 px per raw px)."""

PREVIEW_VERSION = 2
"""Part of every cached preview's name: bump it when a change to this module changes the PNG."""

_GREEN = (0, 220, 0)
_YELLOW = (0, 220, 255)
_CYAN = (255, 255, 0)
_MAGENTA = (255, 0, 255)


def _png_params() -> list[int]:
    """imencode parameters: Huffman-only deflate, and the "sub" filter where OpenCV offers it."""
    params = [cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_HUFFMAN_ONLY]
    if hasattr(cv2, "IMWRITE_PNG_FILTER"):  # OpenCV >= 4.11
        params += [cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_SUB]
    return params


def preview_size(frame: RawFrame, max_size: int = PREVIEW_MAX_SIZE) -> tuple[int, int]:
    """The preview's (width, height): the 2 x 2 binned mosaic (or a linear file) shrunk to fit."""
    h, w = (frame.height, frame.width) if frame.cfa is None else _binned_shape(frame)
    shrink = min(1.0, max_size / max(h, w))
    return max(1, round(w * shrink)), max(1, round(h * shrink))


def _binned_shape(frame: RawFrame) -> tuple[int, int]:
    return frame.height // 2, frame.width // 2


def _resize(img: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Shrink `img` to `size` (width, height); the image itself when it already has that size.

    Whole factors are area averages (OpenCV's fast path for an integer factor, after dropping
    the last rows and columns that do not fill a bin); the remaining factor, between 1/2 and 1,
    is bilinear, 2-3 times faster than a fractional area average and alike to the eye.
    """
    h, w = img.shape[:2]
    if (w, h) == size:
        return img
    k = min(w // size[0], h // size[1])
    if k >= 2:
        img = cv2.resize(
            img[: h // k * k, : w // k * k], (w // k, h // k), interpolation=cv2.INTER_AREA
        )
        if (img.shape[1], img.shape[0]) == size:
            return img
    return cv2.resize(img, size, interpolation=cv2.INTER_LINEAR)


def _colour_planes(
    frame: RawFrame, size: tuple[int, int]
) -> tuple[list[np.ndarray], list[float]] | None:
    """The R, G, B planes at preview size, uint16 raw DN (black not subtracted), and their blacks.

    A 2 x 2 mosaic is read as two images of 2-channel pixels (even rows: positions (0, 0) and
    (0, 1) of each tile; odd rows: (1, 0), (1, 1)), each shrunk with one `cv2.resize`; a colour
    seen at two positions (the greens) is the mean of both. None for another CFA.
    """
    if frame.cfa is None:
        small = _resize(frame.data, size)
        return [small[..., c] for c in range(3)], [float(b) for b in frame.black]
    if frame.cfa.shape != (2, 2):
        return None
    h2, w2 = _binned_shape(frame)
    rows = [
        _resize(frame.data[dy : 2 * h2 : 2, : 2 * w2].reshape(h2, w2, 2), size) for dy in (0, 1)
    ]
    found: list[list[tuple[np.ndarray, float]]] = [[], [], []]
    for dy in range(2):
        for dx in range(2):
            found[int(frame.cfa[dy, dx])].append((rows[dy][..., dx], float(frame.black[dy, dx])))
    planes, blacks = [], []
    for pairs in found:
        if len(pairs) == 1:
            planes.append(pairs[0][0])
        else:  # two positions (never more: R, G and B are all present in a 2 x 2 tile)
            planes.append(cv2.addWeighted(pairs[0][0], 0.5, pairs[1][0], 0.5, 0.0))
        blacks.append(float(np.mean([b for _, b in pairs])))
    return planes, blacks


def _tone_mapped(planes: list[np.ndarray], blacks: list[float]) -> np.ndarray:
    """8-bit BGR from raw R, G, B planes: black subtracted, grey-world balance, 99.5% white, gamma.

    The balance and the white point come from every 4th pixel; the mapping of each channel is a
    lookup table over all 65536 uint16 values (display only).
    """
    sample = [
        p[::4, ::4].astype(np.float32) - np.float32(b) for p, b in zip(planes, blacks, strict=True)
    ]
    means = np.array([float(np.mean(s)) for s in sample])
    gains = np.where(means > 0, means.max() / np.where(means > 0, means, 1.0), 1.0)
    balanced = np.max([s * np.float32(g) for s, g in zip(sample, gains, strict=True)], axis=0)
    hi = float(np.percentile(balanced, 99.5))
    hi = hi if hi > 0 else 1.0
    levels = np.arange(65536, dtype=np.float32)
    out = []
    for p, b, g in zip(planes, blacks, gains, strict=True):
        linear = np.clip((levels - np.float32(b)) * np.float32(g / hi), 0.0, 1.0)
        lut = (linear ** np.float32(1 / 2.2) * 255).astype(np.uint8)
        out.append(np.take(lut, p))
    return cv2.merge(out[::-1])  # RGB -> BGR for OpenCV


def _saturated(frame: RawFrame, saturation_level: float) -> np.ndarray | None:
    """Saturated pixels at the binned resolution (a tile with any saturated pixel); None if none.

    The test is the measurement's (docs/imaging.md §Saturation), per pixel with its own black
    level; a photo whose largest value is below every threshold needs no per-pixel pass.
    """
    d, white = frame.data, frame.white_level
    if frame.cfa is None:
        thr = frame.black + saturation_level * (white - frame.black)
        if float(d.max()) < float(thr.min()):
            return None
        return (d >= thr).any(axis=2)
    if frame.cfa.shape != (2, 2):
        return None
    h2, w2 = _binned_shape(frame)
    thr = {
        (dy, dx): math.ceil(frame.black[dy, dx] + saturation_level * (white - frame.black[dy, dx]))
        for dy in range(2)
        for dx in range(2)
    }
    if int(d.max()) < min(thr.values()):
        return None
    sat = np.zeros((h2, w2), dtype=bool)
    for (dy, dx), t in thr.items():
        sat |= d[dy : 2 * h2 : 2, dx : 2 * w2 : 2] >= t
    return sat


_GRID_STEPS = (10, 20, 25, 50, 100, 200, 250, 500, 1000, 2000, 2500, 5000, 10000)
_GREY = (160, 160, 160)


def grid_step(width: int, height: int, lines: int = 12) -> int:
    """A round spacing (raw px) giving at most about `lines` grid lines on the longer side."""
    need = max(width, height) / lines
    return next((s for s in _GRID_STEPS if s >= need), _GRID_STEPS[-1])


def _draw_grid(img: np.ndarray, width: int, height: int, scale: float) -> None:
    """Grey lines every `grid_step` raw pixels, labelled in raw pixel coordinates at the edges.

    For drawing `roi_px` by hand on a photo that could not be measured (docs/imaging.md §Pixels).
    """
    step = grid_step(width, height)
    font = max(0.35, img.shape[1] / 2000)
    for x in range(0, width, step):
        u = round((x + 0.5) * scale - 0.5)
        cv2.line(img, (u, 0), (u, img.shape[0] - 1), _GREY, 1)
        cv2.putText(img, f"x {x}", (u + 2, 12), cv2.FONT_HERSHEY_SIMPLEX, font, _GREY, 1)
    for y in range(0, height, step):
        v = round((y + 0.5) * scale - 0.5)
        cv2.line(img, (0, v), (img.shape[1] - 1, v), _GREY, 1)
        cv2.putText(img, f"y {y}", (2, v - 3), cv2.FONT_HERSHEY_SIMPLEX, font, _GREY, 1)


Outlines = Mapping[str, Sequence[Sequence[float]]]
"""Named polygons in raw pixel coordinates."""


def _draw_outlines(img: np.ndarray, outlines: Outlines, scale: float) -> None:
    """Polygons (raw pixel coordinates) in yellow with their names, wherever they lie."""
    for name, poly in outlines.items():
        pts = np.round(((np.asarray(poly, dtype=np.float64) + 0.5) * scale - 0.5) * 16)
        cv2.polylines(img, [pts.astype(np.int32)], True, _YELLOW, 1, cv2.LINE_AA, shift=4)
        cx, cy = np.asarray(poly, dtype=np.float64).mean(axis=0)
        org = (int((cx + 0.5) * scale), int((cy + 0.5) * scale))
        cv2.putText(img, name, org, cv2.FONT_HERSHEY_SIMPLEX, 0.5, _YELLOW, 1, cv2.LINE_AA)


def render_preview(
    frame: RawFrame,
    rois: Mapping[str, RoiMask] | Iterable[RoiMask] = (),
    markers: MarkerDetection | None = None,
    *,
    saturation_level: float = 0.98,
    max_size: int = PREVIEW_MAX_SIZE,
    grid: bool = False,
    outlines: Outlines | None = None,
) -> np.ndarray:
    """The preview as an 8-bit BGR image (see the module docstring).

    A preview pixel is magenta when any raw pixel it covers is saturated. `grid` adds a pixel
    grid labelled in raw coordinates and `outlines` polygons (raw px) that are not ROIs, e.g.
    the given ROIs of a photo that could not be measured.
    """
    size = preview_size(frame, max_size)
    colour = _colour_planes(frame, size)
    if colour is None:  # a CFA other than 2 x 2 (e.g. X-Trans): the grey detection image
        grey, _factor = grey_for_detection(frame)
        img = cv2.cvtColor(_resize(grey, size), cv2.COLOR_GRAY2BGR)
    else:
        img = _tone_mapped(*colour)
    sat = _saturated(frame, saturation_level)
    if sat is not None:
        img[_resize(sat.astype(np.uint8) * np.uint8(255), size) > 0] = _MAGENTA
    scale = img.shape[1] / frame.width  # preview px per raw px
    font = max(0.4, img.shape[1] / 1600)
    thick = max(1, round(img.shape[1] / 800))

    def to_preview(xy: np.ndarray) -> np.ndarray:
        return np.round(((xy + 0.5) * scale - 0.5) * 16).astype(np.int32)  # 4 fractional bits

    if grid:
        _draw_grid(img, frame.width, frame.height, scale)
    if outlines:
        _draw_outlines(img, outlines, scale)
    roi_list = list(rois.values()) if isinstance(rois, Mapping) else list(rois)
    for roi in roi_list:
        poly = to_preview(np.asarray(roi.polygon, dtype=np.float64))
        cv2.polylines(img, [poly], True, _YELLOW, 1, cv2.LINE_AA, shift=4)
        contours, _ = cv2.findContours(
            roi.mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE
        )
        for cnt in contours:
            pts = cnt.reshape(-1, 2).astype(np.float64) + np.array([roi.x0, roi.y0])
            cv2.polylines(img, [to_preview(pts)], True, _GREEN, thick, cv2.LINE_AA, shift=4)
        cx, cy = np.asarray(roi.polygon).mean(axis=0)
        org = (int((cx + 0.5) * scale), int((cy + 0.5) * scale))
        cv2.putText(img, roi.name, org, cv2.FONT_HERSHEY_SIMPLEX, font, _GREEN, thick, cv2.LINE_AA)
    if markers is not None:
        for mid, corners in zip(markers.ids, markers.corners_px, strict=True):
            cv2.polylines(img, [to_preview(corners)], True, _CYAN, thick, cv2.LINE_AA, shift=4)
            org = (int((corners[0, 0] + 0.5) * scale), int((corners[0, 1] + 0.5) * scale) - 4)
            cv2.putText(
                img, f"id {mid}", org, cv2.FONT_HERSHEY_SIMPLEX, font, _CYAN, thick, cv2.LINE_AA
            )
    return img


def encode_png(img: np.ndarray, photo: str) -> bytes:
    """A preview image as PNG bytes (Huffman-only deflate, "sub" filter; module docstring)."""
    ok, buf = cv2.imencode(".png", img, _png_params())
    if not ok:
        raise ImagingError(f"photo {photo!r}: OpenCV could not encode the preview PNG")
    return buf.tobytes()


def preview_png(
    frame: RawFrame,
    rois: Mapping[str, RoiMask] | Iterable[RoiMask],
    markers: MarkerDetection | None,
    *,
    saturation_level: float = 0.98,
    max_size: int = PREVIEW_MAX_SIZE,
    grid: bool = False,
    outlines: Outlines | None = None,
) -> bytes:
    """The preview of a photo as PNG bytes (`render_preview`, then `encode_png`)."""
    img = render_preview(
        frame,
        rois,
        markers,
        saturation_level=saturation_level,
        max_size=max_size,
        grid=grid,
        outlines=outlines,
    )
    return encode_png(img, frame.name)


def write_preview(
    frame: RawFrame,
    rois: Mapping[str, RoiMask] | Iterable[RoiMask],
    markers: MarkerDetection | None,
    path: str | Path,
    *,
    saturation_level: float = 0.98,
    max_size: int = PREVIEW_MAX_SIZE,
) -> Path:
    """Write the preview PNG of a photo (atomically) and return its path.

    Args:
        frame: the decoded photo.
        rois: the eroded ROIs to outline (a mapping name -> RoiMask, or RoiMasks).
        markers: detected markers to draw, or None.
        path: the PNG to write.
        saturation_level: as in `ExtractionSettings` (which pixels are shown magenta).
        max_size: the preview's longer side in pixels, at most.
    """
    png = preview_png(frame, rois, markers, saturation_level=saturation_level, max_size=max_size)
    return atomic_bytes(path, png)
