"""Automatic ROI placement from ArUco markers on the specimen base (OpenCV `cv2.aruco`).

The scene gives each marker's 4 corners and each wedge face's outline in one coordinate system
on the flat specimen base (millimetres). Markers are detected on a half-resolution grey image
made from the mosaic; their corners give a homography base plane -> image
(`cv2.findHomography`, least squares over all corners), which places every face polygon in the
photo. See docs/imaging.md §Markers for the layout format and the planar approximation.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from ._decode import RawFrame
from ._errors import ImagingError
from ._roi import Polygon, as_polygon

ARUCO_DICTIONARIES: tuple[str, ...] = tuple(
    n for n in dir(cv2.aruco) if n.startswith("DICT_") and isinstance(getattr(cv2.aruco, n), int)
)
"""Names of OpenCV's predefined ArUco dictionaries (e.g. "DICT_4X4_50")."""


@dataclass(frozen=True)
class MarkerLayout:
    """Where the ArUco markers are on the specimen base, and how strict placement is.

    Attributes:
        markers: (id, corners) pairs; the 4 corners of the marker's outer black square in
            base-plane millimetres, in ArUco's order: the marker's own top-left, top-right,
            bottom-right, bottom-left (clockwise as printed, seen from the front). A mapping
            id -> corners is accepted too.
        dictionary: the OpenCV predefined dictionary the markers come from.
        min_markers: fewest layout markers that must be detected (default 2 = 8 corners: with
            one marker the 8 homography parameters are fixed by exactly 8 numbers, so the
            misfit cannot be checked and placement far from the marker is unconstrained).
        max_reprojection_error_px: largest accepted RMS distance (full-resolution pixels)
            between the detected corners and the layout corners mapped by the homography.
    """

    markers: tuple[tuple[int, Polygon], ...]
    dictionary: str = "DICT_4X4_50"
    min_markers: int = 2
    max_reprojection_error_px: float = 3.0

    def __post_init__(self) -> None:
        items = self.markers.items() if isinstance(self.markers, Mapping) else self.markers
        markers = []
        for mid, corners in items:
            poly = as_polygon(corners, f"marker layout, marker {mid}")
            if len(poly) != 4:
                raise ImagingError(f"marker layout, marker {mid}: give exactly 4 corners (mm)")
            markers.append((int(mid), poly))
        ids = [m for m, _ in markers]
        if len(set(ids)) != len(ids):
            raise ImagingError(
                f"marker layout: marker ids {sorted(ids)} repeat; ids must be unique"
            )
        if not markers:
            raise ImagingError("marker layout: no markers; give at least one marker's corners")
        if self.dictionary not in ARUCO_DICTIONARIES:
            raise ImagingError(
                f"marker layout: unknown ArUco dictionary {self.dictionary!r}; use one of "
                f"{', '.join(ARUCO_DICTIONARIES)}"
            )
        if self.min_markers < 1:
            raise ImagingError("marker layout: min_markers must be at least 1")
        if not self.max_reprojection_error_px > 0:
            raise ImagingError("marker layout: max_reprojection_error_px must be positive")
        object.__setattr__(self, "markers", tuple(markers))

    def corners_mm(self) -> dict[int, np.ndarray]:
        """id -> (4, 2) corners in millimetres."""
        return {m: np.asarray(c, dtype=np.float64) for m, c in self.markers}


@dataclass(frozen=True, eq=False)
class MarkerDetection:
    """Markers found in one photo.

    Attributes:
        ids: marker ids, one per detection (ids found more than once are dropped).
        corners_px: (n, 4, 2) corner positions in full-resolution pixel coordinates
            (docs/imaging.md §Pixels), in ArUco's corner order.
        dictionary: the dictionary searched.
        dropped_ids: ids that were detected more than once (ambiguous, not used).
    """

    ids: tuple[int, ...]
    corners_px: np.ndarray
    dictionary: str
    dropped_ids: tuple[int, ...] = ()


@dataclass(frozen=True, eq=False)
class Placement:
    """A fitted homography from the base plane (mm) to the image (px).

    Attributes:
        homography: 3 x 3 matrix, base-plane mm -> full-resolution pixel coordinates.
        rms_error_px: RMS reprojection error of the marker corners used (px).
        ids: the markers used.
    """

    homography: np.ndarray
    rms_error_px: float
    ids: tuple[int, ...]

    def to_image(self, points_mm: np.ndarray | Sequence[Sequence[float]]) -> np.ndarray:
        """Map (n, 2) base-plane points (mm) to (n, 2) pixel coordinates."""
        pts = np.asarray(points_mm, dtype=np.float64).reshape(-1, 1, 2)
        return cv2.perspectiveTransform(pts, self.homography).reshape(-1, 2)

    def polygon(self, polygon_mm: Polygon) -> Polygon:
        """A base-plane polygon (mm) as an image polygon (px)."""
        return tuple((float(x), float(y)) for x, y in self.to_image(polygon_mm))


def grey_for_detection(frame: RawFrame) -> tuple[np.ndarray, int]:
    """An 8-bit grey image for marker detection, and its binning factor.

    A mosaic is binned 2 x 2 (the sum of a CFA tile's 4 pixels minus black, so every output
    pixel sees R + 2G + B): half resolution, no demosaic. A linear file uses the sum of its
    planes at full resolution. Values are scaled to the 99.5th percentile and given a 1/2.2
    gamma through a lookup table (display only; detection thresholds adaptively). Output pixel
    (u, v) has its centre at full-resolution (f u + (f - 1) / 2, f v + (f - 1) / 2) for binning
    factor f.
    """
    if frame.cfa is None:
        summed = frame.data.sum(axis=2, dtype=np.uint32)
        black = float(np.sum(frame.black))
        factor = 1
    else:
        h2, w2 = frame.height // 2, frame.width // 2
        d = frame.data
        summed = d[0 : 2 * h2 : 2, 0 : 2 * w2 : 2].astype(np.uint32)
        summed += d[0 : 2 * h2 : 2, 1 : 2 * w2 : 2]
        summed += d[1 : 2 * h2 : 2, 0 : 2 * w2 : 2]
        summed += d[1 : 2 * h2 : 2, 1 : 2 * w2 : 2]
        black = 4.0 * float(frame.black.mean())  # exact for a 2 x 2 tile
        factor = 2
    sample = summed[:: max(1, summed.shape[0] // 512), :: max(1, summed.shape[1] // 512)]
    hi = float(np.percentile(sample, 99.5)) - black
    levels = np.arange(int(summed.max()) + 1, dtype=np.float64)
    lut = np.clip((levels - black) / (hi if hi > 0 else 1.0), 0.0, 1.0) ** (1 / 2.2) * 255.0
    return lut.astype(np.uint8)[summed], factor


def detect_markers(frame: RawFrame, dictionary: str = "DICT_4X4_50") -> MarkerDetection:
    """Find ArUco markers of `dictionary` in a photo (`cv2.aruco.ArucoDetector`, sub-pixel).

    Corners are detected on `grey_for_detection`'s image and mapped back to full-resolution
    pixel coordinates (docs/imaging.md §Pixels).
    """
    if dictionary not in ARUCO_DICTIONARIES:
        raise ImagingError(
            f"photo {frame.name!r}: unknown ArUco dictionary {dictionary!r}; use one of "
            f"{', '.join(ARUCO_DICTIONARIES)}"
        )
    grey, factor = grey_for_detection(frame)
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    detector = cv2.aruco.ArucoDetector(
        cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary)), params
    )
    corners, ids, _rejected = detector.detectMarkers(grey)
    if ids is None or len(ids) == 0:
        return MarkerDetection((), np.zeros((0, 4, 2)), dictionary)
    id_list = [int(i) for i in np.asarray(ids).ravel()]
    pts = np.stack([np.asarray(c, dtype=np.float64).reshape(4, 2) for c in corners])
    pts = pts * factor + (factor - 1) / 2.0
    counts = {i: id_list.count(i) for i in id_list}
    keep = [k for k, i in enumerate(id_list) if counts[i] == 1]
    dropped = tuple(sorted({i for i, c in counts.items() if c > 1}))
    return MarkerDetection(
        ids=tuple(id_list[k] for k in keep),
        corners_px=pts[keep] if keep else np.zeros((0, 4, 2)),
        dictionary=dictionary,
        dropped_ids=dropped,
    )


def fit_placement(
    detection: MarkerDetection,
    layout: MarkerLayout,
    *,
    photo: str,
    wedges: Iterable[str] = (),
) -> Placement:
    """Fit the base-plane -> image homography from the detected markers that are in the layout.

    Raises:
        ImagingError: fewer than `layout.min_markers` layout markers were detected, or the RMS
            reprojection error exceeds `layout.max_reprojection_error_px`; the message names the
            photo, the wedges that needed placement and what to check.
    """
    known = layout.corners_mm()
    used = sorted(
        ((i, c) for i, c in zip(detection.ids, detection.corners_px, strict=True) if i in known),
        key=lambda item: item[0],
    )
    wedge_list = sorted(wedges)
    need = f" to place the ROIs of {', '.join(map(repr, wedge_list))}" if wedge_list else ""
    if len(used) < layout.min_markers:
        unknown = sorted(set(detection.ids) - set(known))
        extra = f"; detected but not in the layout: {unknown}" if unknown else ""
        dup = (
            f"; detected twice (ignored): {list(detection.dropped_ids)}"
            if detection.dropped_ids
            else ""
        )
        raise ImagingError(
            f"photo {photo!r}: found {len(used)} of the layout's {len(known)} ArUco markers "
            f"(ids found: {sorted(i for i, _ in used)}{extra}{dup}); at least "
            f"{layout.min_markers} are needed{need}. Check that the markers are in the photo, "
            f"lit and in focus, that the dictionary ({layout.dictionary}) is the printed one, "
            "or give roi_px polygons for this photo"
        )
    src = np.concatenate([known[i] for i, _ in used]).astype(np.float64)
    dst = np.concatenate([c for _, c in used]).astype(np.float64)
    hom, _ = cv2.findHomography(src, dst, 0)
    if hom is None or not np.all(np.isfinite(hom)):
        raise ImagingError(
            f"photo {photo!r}: no homography fits the markers {sorted(i for i, _ in used)}; "
            "check the markers' corners_mm (are they distinct and not all on one line?)"
        )
    proj = cv2.perspectiveTransform(src.reshape(-1, 1, 2), hom).reshape(-1, 2)
    rms = math.sqrt(float(np.mean(np.sum((proj - dst) ** 2, axis=1))))
    if rms > layout.max_reprojection_error_px:
        raise ImagingError(
            f"photo {photo!r}: the marker homography misfits the detected corners by {rms:.2f} px "
            f"RMS (limit {layout.max_reprojection_error_px} px){need}. A marker's corners_mm may "
            "be wrong or in the wrong order (ArUco order: top-left, top-right, bottom-right, "
            "bottom-left of the printed marker), the base may not be flat, or the lens distorts "
            "strongly; fix the layout or give roi_px polygons for this photo"
        )
    return Placement(homography=hom, rms_error_px=rms, ids=tuple(i for i, _ in used))
