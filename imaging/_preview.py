"""Preview PNGs: the photo at reduced size with ROIs, markers and saturated pixels drawn.

For a person to check the ROIs, not for measuring: the rendering is a 2 x 2 binned (half
resolution) colour image of the mosaic, grey-world balanced, with a 1/2.2 gamma. Saturated
pixels are magenta, eroded ROIs are outlined in green with their names, the polygons before
erosion in yellow, and detected ArUco markers in cyan with their ids. Coordinates are those of
the raw image (docs/imaging.md §Pixels), so positions can be read off the preview.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from pathlib import Path

import cv2
import numpy as np

from ._decode import RawFrame
from ._errors import ImagingError
from ._io import atomic_write_bytes
from ._markers import MarkerDetection, grey_for_detection
from ._roi import RoiMask

_GREEN = (0, 220, 0)
_YELLOW = (0, 220, 255)
_CYAN = (255, 255, 0)
_MAGENTA = (255, 0, 255)


def _binned_rgb(frame: RawFrame, saturation_level: float) -> tuple[np.ndarray, np.ndarray, int]:
    """(rgb float32 (h, w, 3) above black, saturated mask (h, w), binning factor)."""
    if frame.cfa is None:
        data = frame.data.astype(np.float32)
        thr = frame.black + saturation_level * (frame.white_level - frame.black)
        sat = (data >= thr).any(axis=2)
        return data - frame.black, sat, 1
    if frame.cfa.shape != (2, 2):
        grey, factor = grey_for_detection(frame)
        g = grey.astype(np.float32)
        return np.repeat(g[..., None], 3, axis=2), np.zeros(g.shape, dtype=bool), factor
    h2, w2 = frame.height // 2, frame.width // 2
    d = frame.data[: 2 * h2, : 2 * w2]
    planes: list[np.ndarray | None] = [None, None, None]
    count = [0, 0, 0]
    sat = np.zeros((h2, w2), dtype=bool)
    for dy in range(2):
        for dx in range(2):
            c = int(frame.cfa[dy, dx])
            black = float(frame.black[dy, dx])
            sub = d[dy::2, dx::2]
            plane = sub.astype(np.float32)
            plane -= np.float32(black)
            planes[c] = plane if planes[c] is None else planes[c] + plane  # type: ignore[operator]
            count[c] += 1
            sat |= sub >= math.ceil(black + saturation_level * (frame.white_level - black))
    rgb = cv2.merge([p / np.float32(n) for p, n in zip(planes, count, strict=True)])  # type: ignore[operator]
    return rgb, sat, 2


def render_preview(
    frame: RawFrame,
    rois: Mapping[str, RoiMask] | Iterable[RoiMask] = (),
    markers: MarkerDetection | None = None,
    *,
    saturation_level: float = 0.98,
    max_size: int = 2048,
) -> np.ndarray:
    """The preview as an 8-bit BGR image (see the module docstring)."""
    rgb, sat, _factor = _binned_rgb(frame, saturation_level)
    h, w = sat.shape
    shrink = min(1.0, max_size / max(h, w))
    if shrink < 1.0:  # shrink first: the gamma below is the expensive part
        size = (round(w * shrink), round(h * shrink))
        rgb = cv2.resize(rgb, size, interpolation=cv2.INTER_AREA)
        sat = cv2.resize(sat.astype(np.uint8), size, interpolation=cv2.INTER_AREA) > 0
    means = np.array([np.mean(rgb[::4, ::4, c]) for c in range(3)], dtype=np.float64)
    gains = np.where(means > 0, means.max() / np.where(means > 0, means, 1.0), 1.0)
    rgb = rgb * gains.astype(np.float32)
    hi = float(np.percentile(rgb[::4, ::4].max(axis=2), 99.5))
    img = (np.clip(rgb / (hi if hi > 0 else 1.0), 0.0, 1.0) ** (1 / 2.2) * 255).astype(np.uint8)
    img = np.ascontiguousarray(img[..., ::-1])  # RGB -> BGR for OpenCV
    img[sat] = _MAGENTA
    scale = img.shape[1] / frame.width  # preview px per raw px
    font = max(0.4, img.shape[1] / 1600)
    thick = max(1, round(img.shape[1] / 800))

    def to_preview(xy: np.ndarray) -> np.ndarray:
        return np.round(((xy + 0.5) * scale - 0.5) * 16).astype(np.int32)  # 4 fractional bits

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


def write_preview(
    frame: RawFrame,
    rois: Mapping[str, RoiMask] | Iterable[RoiMask],
    markers: MarkerDetection | None,
    path: str | Path,
    *,
    saturation_level: float = 0.98,
    max_size: int = 2048,
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
    img = render_preview(frame, rois, markers, saturation_level=saturation_level, max_size=max_size)
    ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise ImagingError(f"photo {frame.name!r}: OpenCV could not encode the preview PNG")
    return atomic_write_bytes(path, buf.tobytes())
