"""Regions of interest: polygons in pixel coordinates, rasterised and eroded with OpenCV.

Pixel convention (docs/imaging.md §Pixels): x to the right, y down, (0, 0) is the centre of the
top-left pixel of the visible raw image, so pixel `data[y, x]` covers [x - 0.5, x + 0.5] x
[y - 0.5, y + 0.5]. A polygon may therefore reach from -0.5 to W - 0.5 in x (and likewise in y).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from ._errors import ImagingError

Polygon = tuple[tuple[float, float], ...]
"""A polygon: at least 3 (x, y) vertices, in order (either orientation)."""

_SHIFT = 8  # fixed-point bits for cv2.fillPoly: vertices are placed to 1/256 px

MAX_ERODE_PX = 64
"""The largest erosion radius: the disk erosion's time grows about as radius^2 x area, so larger
radii on large ROIs take seconds (benchmarks/bench_limits.py; docs/imaging.md §Pixels)."""


def as_polygon(points: Iterable[Sequence[float]], what: str) -> Polygon:
    """`points` as a Polygon of floats; an ImagingError naming `what` if it is not one."""
    try:
        items = list(points)
        poly = tuple((float(p[0]), float(p[1])) for p in items if len(p) == 2)
        n_in = len(items)
    except (TypeError, ValueError, IndexError):
        poly, n_in = (), -1
    if len(poly) < 3 or len(poly) != n_in or not all(map(math.isfinite, sum(poly, ()))):
        raise ImagingError(
            f"{what}: a polygon must be a list of at least 3 finite [x, y] points, "
            "e.g. [[10, 10], [200, 10], [200, 150]]"
        )
    return poly


def _too_narrow(
    box: np.ndarray, erode_px: int, inner_y: tuple[bool, bool], inner_x: tuple[bool, bool]
) -> bool:
    """Whether erosion by a disk of `erode_px` must leave nothing (checked before eroding).

    A pixel survives only if the whole disk around it, `2 erode_px + 1` pixels across, is
    inside the filled polygon; along an axis where the box does not reach the image border
    (`inner_*`: away from the first and last row or column), a fill narrower than that cannot
    hold it. At the image border the outside counts as inside, so nothing is decided there.
    """
    width = 2 * erode_px + 1
    rows, cols = np.flatnonzero(box.any(axis=1)), np.flatnonzero(box.any(axis=0))
    if rows.size == 0:
        return True
    tall = rows[-1] - rows[0] + 1
    wide = cols[-1] - cols[0] + 1
    return (all(inner_y) and tall < width) or (all(inner_x) and wide < width)


def _erode(
    box: np.ndarray, erode_px: int, inner_y: tuple[bool, bool], inner_x: tuple[bool, bool]
) -> tuple[np.ndarray, bool]:
    """The filled `box` eroded by a disk of radius `erode_px`, and whether it was too narrow.

    `inner_*` say, per side, whether the box is away from the image border. Outside the box is
    outside the polygon, except at the image border, which is not an edge of the face: erode
    with a border of ones only there. A box known to be emptied (`_too_narrow`) is not eroded.
    """
    if erode_px == 0:
        return box, False
    if _too_narrow(box, erode_px, inner_y, inner_x):  # not worth an erosion of minutes
        return np.zeros_like(box), True
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * erode_px + 1, 2 * erode_px + 1))
    top, bottom = (erode_px if inner else 0 for inner in inner_y)
    left, right = (erode_px if inner else 0 for inner in inner_x)
    padded = np.pad(box, ((top, bottom), (left, right)))
    eroded = cv2.erode(padded, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=1)
    return eroded[top : top + box.shape[0], left : left + box.shape[1]], False


@dataclass(frozen=True, eq=False)
class RoiMask:
    """The pixels of one region of interest after erosion.

    Attributes:
        name: the wedge (or reference patch) name.
        polygon: the polygon before erosion, pixel coordinates.
        source: "polygon" (given in pixels) or "markers" (placed from ArUco markers).
        y0, x0: the image coordinates of `mask[0, 0]`.
        mask: boolean mask of the eroded region, shape (h, w), a box of the image.
        n_before_erosion: pixels inside the polygon before erosion.
    """

    name: str
    polygon: Polygon
    source: str
    y0: int
    x0: int
    mask: np.ndarray
    n_before_erosion: int

    @property
    def n_pixels(self) -> int:
        """Pixels in the eroded region."""
        return int(self.mask.sum())

    def box(self) -> tuple[slice, slice]:
        """(rows, columns) slices of the image that `mask` covers."""
        h, w = self.mask.shape
        return slice(self.y0, self.y0 + h), slice(self.x0, self.x0 + w)


def roi_mask(
    polygon: Polygon,
    image_shape: tuple[int, int],
    erode_px: int,
    *,
    photo: str,
    wedge: str,
    source: str = "polygon",
) -> RoiMask:
    """Rasterise a polygon (cv2.fillPoly) and erode it by `erode_px` pixels (cv2.erode, disk).

    Args:
        polygon: vertices in pixel coordinates (docs/imaging.md §Pixels).
        image_shape: (height, width) of the visible image.
        erode_px: erosion radius in pixels (>= 0): a pixel is kept only if every pixel within
            this distance is inside the polygon, so edges and background never leak in.
        photo, wedge: names used in error messages.
        source: "polygon" or "markers", recorded and used in messages.

    Raises:
        ImagingError: a vertex lies outside the image, or nothing is left after erosion.
    """
    h_img, w_img = int(image_shape[0]), int(image_shape[1])
    pts = np.asarray(polygon, dtype=np.float64)
    how = "placed from the markers" if source == "markers" else "given in pixels"
    fix = (
        "check the face's face_mm and the marker layout"
        if source == "markers"
        else "fix its roi_px polygon: pixel coordinates of the visible raw image, origin at the "
        "centre of the top-left pixel (see docs/imaging.md)"
    )
    outside = (
        (pts[:, 0] < -0.5)
        | (pts[:, 0] > w_img - 0.5)
        | (pts[:, 1] < -0.5)
        | (pts[:, 1] > h_img - 0.5)
    )
    if outside.any():
        x, y = pts[int(np.argmax(outside))]
        raise ImagingError(
            f"photo {photo!r}, wedge {wedge!r}: the ROI ({how}) has a vertex at "
            f"({x:.1f}, {y:.1f}), outside the image ({w_img} x {h_img} px: x in [-0.5, "
            f"{w_img - 0.5}], y in [-0.5, {h_img - 0.5}]); {fix}"
        )
    x0 = max(0, math.floor(pts[:, 0].min()) - 1)
    y0 = max(0, math.floor(pts[:, 1].min()) - 1)
    x1 = min(w_img, math.ceil(pts[:, 0].max()) + 2)
    y1 = min(h_img, math.ceil(pts[:, 1].max()) + 2)
    box = np.zeros((y1 - y0, x1 - x0), dtype=np.uint8)
    fixed = np.round((pts - (x0, y0)) * (1 << _SHIFT)).astype(np.int32)
    cv2.fillPoly(box, [fixed], 1, lineType=cv2.LINE_8, shift=_SHIFT)
    n_before = int(box.sum())
    box, narrow = _erode(box, erode_px, (y0 > 0, y1 < h_img), (x0 > 0, x1 < w_img))
    mask = box.astype(bool)
    if not mask.any():
        raise ImagingError(
            f"photo {photo!r}, wedge {wedge!r}: the ROI ({how}) is empty after eroding it by "
            f"{erode_px} px ({n_before} px before erosion"
            + (f"; narrower than the {2 * erode_px + 1} px erosion disk" if narrow else "")
            + "); enlarge the polygon or lower extraction.erode_px"
        )
    rows = np.flatnonzero(mask.any(axis=1))
    cols = np.flatnonzero(mask.any(axis=0))
    mask = mask[rows[0] : rows[-1] + 1, cols[0] : cols[-1] + 1]
    return RoiMask(
        name=wedge,
        polygon=tuple(map(tuple, pts.tolist())),  # type: ignore[arg-type]
        source=source,
        y0=y0 + int(rows[0]),
        x0=x0 + int(cols[0]),
        mask=np.ascontiguousarray(mask),
        n_before_erosion=n_before,
    )


INCIDENCE_AXES: dict[str, tuple[float, float]] = {"vertical": (0.0, 1.0), "horizontal": (1.0, 0.0)}
"""Image direction (x, y in px) of the plane of incidence for pixel polygons, by the scene's
`[camera] plane_of_incidence` (docs/imaging.md §Viewing spread)."""


def polygon_axis_variance(polygon: Polygon, axis: np.ndarray) -> float:
    """Variance (px^2) of the coordinate along the unit vector `axis` over the polygon's area
    (its second moment by Green's theorem; 0 for a degenerate polygon)."""
    p = np.asarray(polygon, dtype=np.float64).reshape(-1, 2)
    a = np.asarray(axis, dtype=np.float64)
    t = p @ a
    w = p @ np.array([-a[1], a[0]])
    t1, w1 = np.roll(t, -1), np.roll(w, -1)
    cross = t * w1 - t1 * w
    area = 0.5 * cross.sum()
    if abs(area) < 1e-12:
        return 0.0
    m1 = ((t + t1) * cross).sum() / (6 * area)
    m2 = ((t * t + t * t1 + t1 * t1) * cross).sum() / (12 * area)
    return max(float(m2 - m1 * m1), 0.0)


def view_spread(roi: RoiMask, axis: np.ndarray) -> float:
    """The fraction of its polygon's spread along `axis` (a unit image vector, the face's
    in-plane direction) that the eroded ROI keeps: the ratio of the standard deviations of the
    coordinate along `axis` over the eroded pixels (as unit squares) and over the polygon.
    The fit narrows the face's viewing-angle spread by it (docs/imaging.md §Viewing spread);
    1.0 when either is undefined."""
    ys, xs = np.nonzero(roi.mask)
    full = polygon_axis_variance(roi.polygon, axis)
    if xs.size < 2 or full <= 0:
        return 1.0
    t = (xs + roi.x0) * float(axis[0]) + (ys + roi.y0) * float(axis[1])
    kept = float(t.var()) + 1.0 / 12.0  # a pixel is a unit square, not a point
    return float(np.sqrt(min(kept / full, 1.0)))
