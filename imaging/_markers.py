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
from dataclasses import dataclass, field

import cv2
import numpy as np

from ._decode import RawFrame
from ._errors import ImagingError
from ._roi import Polygon, as_polygon

ARUCO_DICTIONARIES: tuple[str, ...] = tuple(
    n for n in dir(cv2.aruco) if n.startswith("DICT_") and isinstance(getattr(cv2.aruco, n), int)
)
"""Names of OpenCV's predefined ArUco dictionaries (e.g. "DICT_4X4_50")."""


SMALL_CELL_PX = 6.0
"""Markers whose cells are smaller than this (full-resolution px) on the binned image are
searched for at full resolution too: there their corners start 3-5 times closer."""

TONE_MAPS: tuple[str, ...] = ("gamma", "linear", "log", "clahe")
"""Tone maps `detect_markers` can search: 99.5th-percentile white with a 1/2.2 gamma (the
former single map), linear to the 99.5th percentile, logarithmic over the whole range, and
local contrast (CLAHE on the logarithmic map)."""


@dataclass(frozen=True)
class DetectorSettings:
    """How `detect_markers` searches a photo (docs/imaging.md §Markers).

    Attributes:
        passes: (tone map, ArUco `adaptiveThreshConstant`) pairs searched on the 2 x 2 binned
            linear image; tone maps from `TONE_MAPS`. A marker found by several passes is
            merged into one. OpenCV's default constant is 7; 2 finds dim, low-contrast markers
            that 7 misses.
        full_resolution_passes: passes searched on the full-resolution image (the mosaic with
            its CFA positions balanced) when some expected marker was not found on the binned
            one, or was found with cells under `SMALL_CELL_PX`: it finds markers down to about
            half the cell size, with finer corners. Empty: never.
        refine: refine the merged corners to sub-pixel precision (`cv2.cornerSubPix` on the
            linear image) instead of ArUco's own refinement on each pass.
        min_marker_px: the smallest marker side (pixels of the searched image) a pass
            considers (sets ArUco's `minMarkerPerimeterRate`); smaller contours are not
            examined, which keeps low thresholds on noisy images fast. 0: OpenCV's default
            (a perimeter of 3% of the image's longer side).
    """

    passes: tuple[tuple[str, float], ...] = (
        ("log", 7.0),
        ("log", 2.0),
        ("clahe", 7.0),
        ("linear", 7.0),
    )
    full_resolution_passes: tuple[tuple[str, float], ...] = (("log", 2.0), ("clahe", 7.0))
    refine: bool = True
    min_marker_px: float = 8.0

    def __post_init__(self) -> None:
        passes = tuple((str(t), float(c)) for t, c in self.passes)
        full = tuple((str(t), float(c)) for t, c in self.full_resolution_passes)
        unknown = sorted({t for t, _ in passes + full if t not in TONE_MAPS})
        if unknown or not passes:
            raise ImagingError(
                f"marker detector: unknown tone maps {unknown} or no passes; tone maps are "
                f"{', '.join(TONE_MAPS)}"
            )
        if not all(math.isfinite(c) for _, c in passes + full):
            raise ImagingError("marker detector: threshold constants must be finite numbers")
        if not (math.isfinite(self.min_marker_px) and self.min_marker_px >= 0):
            raise ImagingError("marker detector: min_marker_px must be >= 0")
        object.__setattr__(self, "passes", passes)
        object.__setattr__(self, "full_resolution_passes", full)


LEGACY_DETECTOR = DetectorSettings(
    passes=(("gamma", 7.0),),
    full_resolution_passes=(),
    refine=False,
    min_marker_px=0.0,
)
"""The detector before issue 12: one gamma tone map, OpenCV's default parameters and ArUco's own
sub-pixel refinement. Kept for comparisons (tests, benchmarks/bench_markers.py)."""


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
            between the detected corners and the layout corners mapped by the fitted camera.
        max_view_error_deg: largest accepted difference between the photo's view_deg and the
            view direction the markers imply, when faces are placed in 3-D (docs/imaging.md
            §3-D placement).
        detector: how the markers are searched for (`DetectorSettings`).
    """

    markers: tuple[tuple[int, Polygon], ...]
    dictionary: str = "DICT_4X4_50"
    min_markers: int = 2
    max_reprojection_error_px: float = 3.0
    max_view_error_deg: float = 10.0
    detector: DetectorSettings = field(default_factory=DetectorSettings)

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
        if not 0 < self.max_view_error_deg <= 90:
            raise ImagingError("marker layout: max_view_error_deg must be in (0, 90]")
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
        dropped_ids: ids that were ambiguous (seen twice in one search, or found at places
            that disagree): not used.
        found_by: per marker, the searches that found it ("+"-joined `tone map/t<constant>`,
            "full:" for the full-resolution image), e.g. "clahe/t7+log/t2".
        cell_px: per marker, the smaller of its two cell sizes in full-resolution pixels
            (foreshortening shrinks one of them): docs/imaging.md §Markers.
    """

    ids: tuple[int, ...]
    corners_px: np.ndarray
    dictionary: str
    dropped_ids: tuple[int, ...] = ()
    found_by: tuple[str, ...] = ()
    cell_px: tuple[float, ...] = ()


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
    """An 8-bit grey image of a photo (the `gamma` tone map of the binned image) and its
    binning factor, for previews of files whose CFA is not 2 x 2.

    Output pixel (u, v) has its centre at full-resolution (f u + (f - 1) / 2, f v + (f - 1) / 2)
    for binning factor f.
    """
    linear, factor = binned_linear(frame)
    return tone_map(linear, "gamma"), factor


def binned_linear(frame: RawFrame) -> tuple[np.ndarray, int]:
    """The photo as a float32 linear grey image (DN above black), and its binning factor.

    A mosaic is binned 2 x 2 (the sum of a CFA tile's 4 pixels minus their black levels, so
    every output pixel sees R + 2G + B): half resolution, no demosaic, factor 2. A linear file
    gives the sum of its planes at full resolution, factor 1.
    """
    if frame.cfa is None:
        return frame.data.sum(axis=2, dtype=np.float32) - np.float32(np.sum(frame.black)), 1
    h2, w2 = frame.height // 2, frame.width // 2
    d = frame.data
    out = np.zeros((h2, w2), dtype=np.float32)
    for dy in range(2):
        for dx in range(2):
            out += d[dy : 2 * h2 : 2, dx : 2 * w2 : 2]
    out -= np.float32(4.0 * float(frame.black.mean()))  # exact for a 2 x 2 tile
    return out, 2


def full_linear(frame: RawFrame) -> np.ndarray:
    """The mosaic at full resolution as a float32 linear grey image (no demosaic).

    Each CFA position has its black level subtracted and is scaled so that its mean equals the
    mean of all positions (a grey-world balance of the channels): a neutral marker then shows
    no CFA pattern, whatever the camera's channel gains. A linear file gives the sum of its
    planes.
    """
    if frame.cfa is None:
        return binned_linear(frame)[0]
    ph, pw = frame.cfa.shape
    out = frame.data.astype(np.float32)
    means = {}
    for dy in range(ph):
        for dx in range(pw):
            plane = out[dy::ph, dx::pw]
            plane -= np.float32(frame.black[dy, dx])
            means[dy, dx] = float(np.mean(plane[::4, ::4]))
    target = float(np.mean(list(means.values())))
    for (dy, dx), m in means.items():
        if m > 0 and target > 0:
            out[dy::ph, dx::pw] *= np.float32(target / m)
    return out


def tone_map(linear: np.ndarray, name: str) -> np.ndarray:
    """An 8-bit rendering of a linear grey image: one of `TONE_MAPS`."""
    sample = linear[:: max(1, linear.shape[0] // 512), :: max(1, linear.shape[1] // 512)]
    hi = float(np.percentile(sample, 99.5))
    hi = hi if hi > 0 else 1.0
    if name in ("gamma", "linear"):
        scaled = np.clip(linear * np.float32(1.0 / hi), 0.0, 1.0)
        if name == "gamma":
            scaled = scaled ** np.float32(1 / 2.2)
        return (scaled * np.float32(255.0) + np.float32(0.5)).astype(np.uint8)
    log = log_map(linear, hi)
    if name == "log":
        return log
    if name == "clahe":
        tiles = max(2, round(max(linear.shape) / 128))
        return cv2.createCLAHE(clipLimit=3.0, tileGridSize=(tiles, tiles)).apply(log)
    raise ImagingError(f"unknown tone map {name!r}; use one of {', '.join(TONE_MAPS)}")


def log_map(linear: np.ndarray, hi: float) -> np.ndarray:
    """The logarithmic tone map: log(x / lo) over [lo, max], lo = 1e-4 of the 99.5th percentile
    (and at least 1 DN), so that a dim marker beside bright specular faces keeps its contrast."""
    lo = max(1.0, 1e-4 * hi)
    top = max(float(linear.max()), 10.0 * lo)
    scale = np.float32(255.0 / math.log(top / lo))
    out = np.log(np.maximum(linear, np.float32(lo)) * np.float32(1.0 / lo)) * scale
    return (out + np.float32(0.5)).astype(np.uint8)


@dataclass(frozen=True)
class _Candidate:
    """One detection of one marker on one tone map: corners in full-resolution pixels."""

    id: int
    corners_px: np.ndarray
    source: str  # e.g. "log/t2" or "full:clahe/t7"
    binned: bool


def _aruco_pass(
    image: np.ndarray,
    aruco_dict: cv2.aruco.Dictionary,
    constant: float,
    settings: DetectorSettings,
) -> tuple[list[int], list[np.ndarray]]:
    """ids and (4, 2) corners (in `image`'s pixels) of one ArUco pass."""
    params = cv2.aruco.DetectorParameters()
    params.adaptiveThreshConstant = constant
    if settings.min_marker_px > 0:
        params.minMarkerPerimeterRate = min(0.5, 4 * settings.min_marker_px / max(image.shape))
    params.cornerRefinementMethod = (
        cv2.aruco.CORNER_REFINE_NONE if settings.refine else cv2.aruco.CORNER_REFINE_SUBPIX
    )
    corners, ids, _rejected = cv2.aruco.ArucoDetector(aruco_dict, params).detectMarkers(image)
    if ids is None or len(ids) == 0:
        return [], []
    pts = [np.asarray(c, dtype=np.float64).reshape(4, 2) for c in corners]
    return [int(i) for i in np.asarray(ids).ravel()], pts


def _search(
    linear: np.ndarray,
    factor: int,
    aruco_dict: cv2.aruco.Dictionary,
    passes: tuple[tuple[str, float], ...],
    settings: DetectorSettings,
    expected: set[int],
) -> tuple[list[_Candidate], set[int]]:
    """The ArUco passes over one image: (candidates in full-resolution px, ids seen twice in
    one pass). Passes stop early once every id of a non-empty `expected` was found twice."""
    candidates, twice = [], set()
    images: dict[str, np.ndarray] = {}
    label = "" if factor > 1 else "full:"
    for name, constant in passes:
        if name not in images:
            images[name] = tone_map(linear, name)
        ids, pts = _aruco_pass(images[name], aruco_dict, constant, settings)
        twice |= {i for i in ids if ids.count(i) > 1}
        for i, c in zip(ids, pts, strict=True):
            full = c * factor + (factor - 1) / 2.0
            candidates.append(_Candidate(i, full, f"{label}{name}/t{constant:g}", factor > 1))
        found = [c.id for c in candidates]
        if expected and all(found.count(i) >= 2 for i in expected):
            break  # every expected marker found by two passes: enough to merge
    return candidates, twice


def marker_cell_px(corners_px: np.ndarray, cells: int) -> float:
    """The smaller of a marker's two cell sizes (px): mean side length along each of its two
    axes, divided by the cells per side (data bits plus the border)."""
    c = np.asarray(corners_px, dtype=np.float64).reshape(4, 2)
    a = 0.5 * (np.linalg.norm(c[1] - c[0]) + np.linalg.norm(c[2] - c[3]))
    b = 0.5 * (np.linalg.norm(c[3] - c[0]) + np.linalg.norm(c[2] - c[1]))
    return float(min(a, b)) / cells


def _merge(
    candidates: list[_Candidate], cells: int
) -> tuple[dict[int, tuple[np.ndarray, list[_Candidate]]], set[int]]:
    """Merge the candidates of each id: {id: (mean corners, agreeing candidates)}, ambiguous ids.

    Candidates of one id agree when every corner lies within 1.5 cells (+ 1 px) of the median
    corner set: passes place the unrefined corners of one marker up to about a cell apart,
    while a second marker with the same id, or a false detection, lies many cells away. The
    agreeing ones are averaged; an id whose candidates do not agree in majority is ambiguous.
    """
    by_id: dict[int, list[_Candidate]] = {}
    for cand in candidates:
        by_id.setdefault(cand.id, []).append(cand)
    merged, ambiguous = {}, set()
    for mid, cands in by_id.items():
        stack = np.stack([c.corners_px for c in cands])
        median = np.median(stack, axis=0)
        tol = 1.0 + 1.5 * marker_cell_px(median, cells)
        dist = np.linalg.norm(stack - median, axis=2).max(axis=1)
        keep = [c for c, d in zip(cands, dist, strict=True) if d <= tol]
        if 2 * len(keep) <= len(cands):
            ambiguous.add(mid)
            continue
        merged[mid] = (np.mean(np.stack([c.corners_px for c in keep]), axis=0), keep)
    return merged, ambiguous


def marker_crop(frame: RawFrame, corners: np.ndarray, margin: float) -> tuple[np.ndarray, int, int]:
    """A full-resolution float32 linear crop around a marker: (image, x0, y0 of its origin).

    Black levels are subtracted per CFA position, and each position is scaled so that the
    crop's bright pixels (the marker's white cells and quiet zone: paper, neutral) have the
    same mean at every position; no CFA pattern is left on the paper whatever the light's colour
    or the camera's channel gains. Each position's bright pixels are those above the midpoint
    of its own 5th and 95th percentiles: a threshold common to all positions would count the
    plate as bright in the channels of high gain and not in the others, and leave a pattern
    that moves the edges by half a pixel. A linear file gives the sum of its planes.
    """
    x0 = max(0, math.floor(corners[:, 0].min() - margin))
    y0 = max(0, math.floor(corners[:, 1].min() - margin))
    x1 = min(frame.width, math.ceil(corners[:, 0].max() + margin) + 1)
    y1 = min(frame.height, math.ceil(corners[:, 1].max() + margin) + 1)
    if frame.cfa is None:
        crop = frame.data[y0:y1, x0:x1].sum(axis=2, dtype=np.float32)
        return crop - np.float32(np.sum(frame.black)), x0, y0
    crop = frame.data[y0:y1, x0:x1].astype(np.float32)
    ph, pw = frame.cfa.shape
    means = {}
    for dy in range(ph):
        for dx in range(pw):
            py, px = (y0 + dy) % ph, (x0 + dx) % pw
            plane = crop[dy::ph, dx::pw]
            plane -= np.float32(frame.black[py, px])
            lo, hi = np.percentile(plane, (5, 95)) if plane.size else (0.0, 0.0)
            sel = plane[plane > 0.5 * (lo + hi)]
            means[dy, dx] = float(sel.mean()) if sel.size else 0.0
    target = float(np.mean(list(means.values())))
    for (dy, dx), m in means.items():
        if m > 0 and target > 0:
            crop[dy::ph, dx::pw] *= np.float32(target / m)
    return crop, x0, y0


def _edge_crossings(
    image: np.ndarray, a: np.ndarray, b: np.ndarray, outward: np.ndarray, half: float, step: float
) -> tuple[np.ndarray, np.ndarray]:
    """Where profiles across the marker side a -> b cross halfway from the ink to the outside.

    Profiles (bilinear samples every 0.2 px over +-`half` px along `outward`) start every
    0.5 px along the side, `step` px clear of its ends. Returns the crossing points (n, 2) and
    each profile's contrast (outside minus ink level; the ends of the profile give the levels).
    """
    length = float(np.linalg.norm(b - a))
    u = (b - a) / length
    s = np.arange(step, length - step, 0.5)
    o = np.arange(-half, half + 1e-9, 0.2)
    pts = a[None, None, :] + s[:, None, None] * u + o[None, :, None] * outward
    prof = cv2.remap(
        image, pts[..., 0].astype(np.float32), pts[..., 1].astype(np.float32), cv2.INTER_LINEAR
    )
    k = max(1, len(o) // 5)
    inner, outer = prof[:, :k].mean(axis=1), prof[:, -k:].mean(axis=1)
    mid = 0.5 * (inner + outer)
    above = prof > mid[:, None]
    idx = np.clip(np.argmax(above, axis=1), 1, len(o) - 1)
    rows = np.arange(len(s))
    p0, p1 = prof[rows, idx - 1], prof[rows, idx]
    rise = np.where(p1 > p0, p1 - p0, 1.0)
    off = o[idx - 1] + np.clip((mid - p0) / rise, 0.0, 1.0) * (o[1] - o[0])
    contrast = np.where(above.any(axis=1) & (np.abs(off) < half - 0.3), outer - inner, 0.0)
    return a + s[:, None] * u + off[:, None] * outward, contrast


def _fit_line(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Total-least-squares line (a point, a unit direction), refitted once without points
    more than 3 median distances (at least 0.5 px) off it."""
    for _ in range(2):
        centre = points.mean(axis=0)
        direction = np.linalg.svd(points - centre, full_matrices=False)[2][0]
        dist = np.abs((points - centre) @ np.array([-direction[1], direction[0]]))
        keep = dist <= max(0.5, 3.0 * float(np.median(dist)))
        if keep.sum() < 3 or keep.all():
            break
        points = points[keep]
    return centre, direction


def marker_bits(aruco_dict: cv2.aruco.Dictionary, marker_id: int) -> np.ndarray:
    """The marker's cells (1 white, 0 black) with its black border: (cells, cells)."""
    cells = int(aruco_dict.markerSize) + 2
    img = cv2.aruco.generateImageMarker(aruco_dict, marker_id, 10 * cells, borderBits=1)
    return (img[5::10, 5::10] > 127).astype(np.uint8)


def _cell_homography(corners: np.ndarray, cells: int) -> np.ndarray:
    """The homography from marker cell coordinates (u, v in [0, cells], u along the top side)
    to image pixels, through the 4 corners."""
    square = np.array([[0, 0], [cells, 0], [cells, cells], [0, cells]], dtype=np.float64)
    return cv2.getPerspectiveTransform(square.astype(np.float32), corners.astype(np.float32))


def _to_image(hom: np.ndarray, uv: np.ndarray) -> np.ndarray:
    q = np.c_[uv, np.ones(len(uv))] @ hom.T
    return q[:, :2] / q[:, 2:]


def _inner_edges(bits: np.ndarray) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, bool]]:
    """The boundaries between adjacent cells of different colour inside the outer border: (its
    start and end (u, v) in cells, half a cell across it, whether it goes from ink to paper)."""
    cells = bits.shape[0]
    out = []
    for i in range(cells):
        for j in range(1, cells):
            pairs = ((bits[i, j - 1], bits[i, j]), (bits[j - 1, i], bits[j, i]))
            for axis, (a, b) in enumerate(pairs):
                if a == b:
                    continue
                if axis == 0:  # between columns j - 1 and j of row i: the line u = j
                    ends = (np.array([j, i], float), np.array([j, i + 1], float))
                    across = np.array([0.5, 0.0])
                else:  # between rows j - 1 and j of column i: the line v = j
                    ends = (np.array([i, j], float), np.array([i + 1, j], float))
                    across = np.array([0.0, 0.5])
                out.append((ends[0], ends[1], across, bool(b > a)))
    return out


def _edge_offset(image: np.ndarray, hom: np.ndarray, edge: tuple) -> float | None:
    """Where the image shows one inner boundary, relative to where `hom` puts it (px, along
    the normal): profiles across it at 5 points of its middle 60%, averaged, crossing halfway
    between their two ends' levels. None when the boundary spans less than 2 px; half the
    profile's length when no edge of the expected polarity is in it."""
    start, end, across, rising = edge
    ts = np.linspace(0.2, 0.8, 5)
    mid_uv = start[None, :] + ts[:, None] * (end - start)[None, :]
    centre = _to_image(hom, mid_uv)
    inside = _to_image(hom, mid_uv - across)
    outside = _to_image(hom, mid_uv + across)
    normal = (outside - inside).mean(axis=0)
    half = float(np.linalg.norm(normal)) / 2
    if not 1.0 <= half <= 200.0:  # under 2 px across, or corners that make no square
        return None
    n = normal / (2 * half)
    o = np.arange(-half, half + 1e-9, 0.1)
    pts = (centre[:, None, :] + o[None, :, None] * n[None, None, :]).astype(np.float32)
    prof = cv2.remap(image, pts[..., 0], pts[..., 1], cv2.INTER_LINEAR).mean(axis=0)
    k = max(1, len(o) // 5)
    lo, hi = float(prof[:k].mean()), float(prof[-k:].mean())
    if rising != (hi > lo) or hi == lo:
        return half
    mid = 0.5 * (lo + hi)
    above = (prof - mid) * (1.0 if hi > lo else -1.0) > 0
    idx = int(np.argmax(above))
    if idx == 0:
        return half
    p0, p1 = float(prof[idx - 1]), float(prof[idx])
    frac = float(np.clip((mid - p0) / (p1 - p0), 0.0, 1.0)) if p1 != p0 else 0.5
    return float(o[idx - 1] + frac * (o[1] - o[0]))


def grid_error(image: np.ndarray, corners: np.ndarray, bits: np.ndarray) -> float:
    """How far (px) the marker's inner cell boundaries as the image shows them lie from where
    the homography through `corners` (in `image`'s pixels) puts them: the RMS over the
    boundaries, each located like the outer sides (profiles across it, half a cell each way,
    crossing halfway between ink and paper), its worst tenth left out; inf without any.
    Corners consistent with the marker's square place all of them; corners off by a fraction
    of a cell or more do not.
    """
    if not _convex(corners):
        return math.inf
    hom = _cell_homography(corners, bits.shape[0])
    offsets = [_edge_offset(image, hom, edge) for edge in _inner_edges(bits)]
    sq = np.sort(np.square([o for o in offsets if o is not None]))
    if sq.size == 0:
        return math.inf
    kept = sq[: max(1, math.ceil(0.9 * sq.size))]
    return math.sqrt(float(kept.mean()))


def _convex(corners: np.ndarray) -> bool:
    """Whether 4 corners make a convex quadrilateral, turning the same way at every corner."""
    d = np.roll(corners, -1, axis=0) - corners
    cross = d[:, 0] * np.roll(d, -1, axis=0)[:, 1] - d[:, 1] * np.roll(d, -1, axis=0)[:, 0]
    return bool(np.all(cross > 0) or np.all(cross < 0))


GRID_OK = 0.1
"""Corners whose inner grid is placed within this fraction of a cell need no wider search."""

GRID_FAR = 0.15
"""Corners more than half a cell from the detector's are kept only when they place the inner
grid within this fraction of a cell: a faint, noisy marker's best grid is no evidence."""

REFINE_PASSES = 3
"""With the marker's bits, the edges are located again from the refined corners up to this many
times, while the inner grid's error keeps falling (the first pass may start several pixels
off, with part of a side's profiles beside its edge)."""


def refine_corners(
    frame: RawFrame, corners: np.ndarray, cells: int, bits: np.ndarray | None = None
) -> np.ndarray:
    """Sub-pixel corners of one marker (full-resolution pixel coordinates) from its edges.

    Each of the 4 outer sides of the black border is located along its length in the linear
    full-resolution image around the marker (`marker_crop`): profiles across it, half a cell in
    and out, cross halfway from the ink to the paper (or plate) outside, which is where the
    edge is for any symmetric blur; a line is fitted through the crossings and the corners are
    the intersections of adjacent lines. Measured on synthetic markers (benchmarks/
    bench_markers.py): 0.03-0.2 px, where `cv2.cornerSubPix` in a window small enough to see
    only the corner's own edges gave 0.1-1.3 px. Profiles with less than half the median
    contrast (the side's edge is not inside them) are dropped; a side with fewer than 3 left
    keeps the corners it started from.

    Which corners are kept: with the marker's `bits` (`marker_bits`), those that place the
    marker's inner cell edges best (`grid_error`), also when they moved by more than half a
    cell from the detector's (whose corners can be several pixels off on small, foreshortened
    markers), provided they place that grid within GRID_FAR of a cell. When the detector's
    corners misplace the grid by more than GRID_OK of a cell, the sides are also looked for
    from the square moved by a cell either way, and the edges are located again from each
    better set (REFINE_PASSES). Otherwise (and without the bits) the refined corners are kept
    when they moved by at most half a cell.
    """
    c = np.asarray(corners, dtype=np.float64).reshape(4, 2)
    axes = _cell_axes(c, cells)
    margin = 4.0 + 3.0 * max(float(np.linalg.norm(v)) for v in axes)
    crop, x0, y0 = marker_crop(frame, c, margin)
    origin = np.array([x0, y0], dtype=np.float64)
    loc = c - origin
    smallest = min(float(np.linalg.norm(v)) for v in axes)
    near = _refine_once(crop, loc, cells)
    if near is not None and np.abs(near - loc).max() > 0.5 * smallest:
        near = None
    if bits is None:
        return c if near is None else near + origin
    best = _grid_search(crop, loc, cells, bits, axes)
    if best is not None and np.abs(best - loc).max() <= 0.5 * smallest:
        return best + origin
    if best is not None and grid_error(crop, best, bits) < GRID_FAR * smallest:
        return best + origin  # far from the detector's, but the marker's grid agrees with it
    return c if near is None else near + origin


def _grid_search(
    crop: np.ndarray, loc: np.ndarray, cells: int, bits: np.ndarray, axes: tuple
) -> np.ndarray | None:
    """The corners that place the marker's inner grid best, searched from `loc` (refine_corners);
    None when none places it better than `loc` does."""
    best, best_err = loc, grid_error(crop, loc, bits)
    start_err = best_err
    if not best_err < GRID_OK * min(float(np.linalg.norm(v)) for v in axes):
        # the detector's corners may be a cell or more off: start also from the square moved
        # by one cell along either side (the inner grid tells which start was right)
        starts = [loc + i * axes[0] + j * axes[1] for i in (-1, 0, 1) for j in (-1, 0, 1)]
        tries = [_refine_once(crop, s, cells, 0.6) for s in starts]
        scored = [(grid_error(crop, out, bits), out) for out in tries if out is not None]
        if scored:
            err, out = min(scored, key=lambda item: item[0])
            if err < best_err:
                best, best_err = out, err
    for _ in range(REFINE_PASSES):
        # profiles half a cell each way; a cell and a half when that finds no better corners
        # (a side more than half a cell off has part of its profiles beside its edge)
        tries = (_refine_once(crop, best, cells, reach) for reach in (0.6, 1.5))
        scored = [(grid_error(crop, out, bits), out) for out in tries if out is not None]
        better = [item for item in scored if item[0] < best_err]
        if not better:
            break
        best_err, best = min(better, key=lambda item: item[0])
    return best if best_err < start_err else None


def _cell_axes(c: np.ndarray, cells: int) -> tuple[np.ndarray, np.ndarray]:
    """The marker's mean cell vectors along its top side and down its left side (px)."""
    return (
        0.5 * ((c[1] - c[0]) + (c[2] - c[3])) / cells,
        0.5 * ((c[3] - c[0]) + (c[2] - c[1])) / cells,
    )


def _refine_once(
    crop: np.ndarray, loc: np.ndarray, cells: int, reach: float = 0.6
) -> np.ndarray | None:
    """The corners from the 4 outer sides located around `loc` (crop pixels), by profiles
    `reach` cells each way across each side; None when a side keeps fewer than 3 profiles with
    the edge in them, or the lines do not meet."""
    axes = _cell_axes(loc, cells)
    centre = loc.mean(axis=0)
    sides = []
    for k in range(4):
        a, b = loc[k], loc[(k + 1) % 4]
        u = (b - a) / np.linalg.norm(b - a)
        n = np.array([-u[1], u[0]])
        n = n if n @ (0.5 * (a + b) - centre) > 0 else -n
        across = abs(float(axes[(k + 1) % 2] @ n))  # the cell size across this side
        along = float(np.linalg.norm(axes[k % 2]))
        sides.append(_edge_crossings(crop, a, b, n, max(0.8, reach * across), 0.6 * along))
    contrasts = np.concatenate([con for _, con in sides])
    ref = float(np.median(contrasts[contrasts > 0])) if (contrasts > 0).any() else 0.0
    lines = []
    for pts, con in sides:
        good = pts[con >= 0.5 * ref] if ref > 0 else pts[:0]
        if len(good) < 3:
            return None
        lines.append(_fit_line(good))
    out = np.array([_intersect(lines[k - 1], lines[k]) for k in range(4)])
    return out if np.all(np.isfinite(out)) else None


def _intersect(l1: tuple[np.ndarray, np.ndarray], l2: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """The intersection of two lines given as (point, direction); NaN for parallel lines."""
    (p, d), (q, e) = l1, l2
    det = d[0] * -e[1] - d[1] * -e[0]
    if abs(det) < 1e-12:
        return np.full(2, np.nan)
    rhs = q - p
    t = (rhs[0] * -e[1] - rhs[1] * -e[0]) / det
    return p + t * d


def detect_markers(
    frame: RawFrame,
    dictionary: str = "DICT_4X4_50",
    settings: DetectorSettings | None = None,
    expected_ids: Iterable[int] = (),
) -> MarkerDetection:
    """Find ArUco markers of `dictionary` in a photo (docs/imaging.md §Markers).

    The 2 x 2 binned linear image is searched by each of `settings.passes` (a tone map and an
    ArUco threshold constant); when some of `expected_ids` (the layout's markers) were not
    found, the full-resolution image is searched by `settings.full_resolution_passes` too. The
    detections of each id are merged into one consistent set of corners, refined to sub-pixel
    precision on the full-resolution linear image and given in full-resolution pixel
    coordinates (docs/imaging.md §Pixels).
    """
    if dictionary not in ARUCO_DICTIONARIES:
        raise ImagingError(
            f"photo {frame.name!r}: unknown ArUco dictionary {dictionary!r}; use one of "
            f"{', '.join(ARUCO_DICTIONARIES)}"
        )
    settings = settings or DetectorSettings()
    aruco_dict = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    cells = int(aruco_dict.markerSize) + 2
    expected = set(expected_ids)
    linear, factor = binned_linear(frame)
    candidates, twice = _search(linear, factor, aruco_dict, settings.passes, settings, expected)
    small = {c.id for c in candidates if marker_cell_px(c.corners_px, cells) < SMALL_CELL_PX}
    again = (expected - {c.id for c in candidates}) | small
    if settings.full_resolution_passes and factor > 1 and again:
        full = full_linear(frame)
        passes = settings.full_resolution_passes
        more, twice_full = _search(full, 1, aruco_dict, passes, settings, again)
        found_full = {c.id for c in more}
        # a small marker found at full resolution keeps only those (finer) corners
        candidates = [c for c in candidates if not (c.id in small and c.id in found_full)]
        candidates += more
        twice |= twice_full
    merged, ambiguous = _merge([c for c in candidates if c.id not in twice], cells)
    ids, corners, found_by, cell_px = [], [], [], []
    for mid in sorted(merged):
        mean, keep = merged[mid]
        if settings.refine:  # at full resolution: 2-4 times closer than on the binned image
            mean = refine_corners(frame, mean, cells, marker_bits(aruco_dict, mid))
        ids.append(mid)
        corners.append(mean)
        found_by.append("+".join(sorted({c.source for c in keep})))
        cell_px.append(marker_cell_px(mean, cells))
    return MarkerDetection(
        ids=tuple(ids),
        corners_px=np.stack(corners) if corners else np.zeros((0, 4, 2)),
        dictionary=dictionary,
        dropped_ids=tuple(sorted(twice | ambiguous)),
        found_by=tuple(found_by),
        cell_px=tuple(cell_px),
    )


def matched_markers(
    detection: MarkerDetection,
    layout: MarkerLayout,
    *,
    photo: str,
    wedges: Iterable[str] = (),
    hint: str = "",
) -> tuple[tuple[int, ...], np.ndarray, np.ndarray]:
    """The detected markers that are in the layout: (ids, (4n, 2) base mm, (4n, 2) image px).

    Raises:
        ImagingError: fewer than `layout.min_markers` layout markers were detected; the message
            names the photo, the wedges that needed placement, what to check and `hint` (e.g.
            how foreshortened the markers are).
    """
    known = layout.corners_mm()
    used = sorted(
        ((i, c) for i, c in zip(detection.ids, detection.corners_px, strict=True) if i in known),
        key=lambda item: item[0],
    )
    if len(used) < layout.min_markers:
        wedge_list = sorted(wedges)
        need = f" to place the ROIs of {', '.join(map(repr, wedge_list))}" if wedge_list else ""
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
            f"{layout.min_markers} are needed{need}.{hint} Check that the markers are in the "
            f"photo, lit and in focus, that the dictionary ({layout.dictionary}) is the printed "
            "one, or give roi_px polygons for this photo"
        )
    src = np.concatenate([known[i] for i, _ in used]).astype(np.float64)
    dst = np.concatenate([c for _, c in used]).astype(np.float64)
    return tuple(i for i, _ in used), src, dst


def rms_px(a: np.ndarray, b: np.ndarray) -> float:
    """RMS distance between two (n, 2) point sets (px)."""
    return math.sqrt(float(np.mean(np.sum((np.asarray(a) - np.asarray(b)) ** 2, axis=1))))


def fit_placement(
    detection: MarkerDetection,
    layout: MarkerLayout,
    *,
    photo: str,
    wedges: Iterable[str] = (),
) -> Placement:
    """Fit the base-plane -> image homography from the detected markers that are in the layout.

    Exact for points on the base plane whatever the camera; faces that rise above the base are
    placed by `stairfit.imaging.fit_camera_pose` instead (docs/imaging.md §3-D placement).

    Raises:
        ImagingError: fewer than `layout.min_markers` layout markers were detected, or the RMS
            reprojection error exceeds `layout.max_reprojection_error_px`; the message names the
            photo, the wedges that needed placement and what to check.
    """
    ids, src, dst = matched_markers(detection, layout, photo=photo, wedges=wedges)
    wedge_list = sorted(wedges)
    need = f" to place the ROIs of {', '.join(map(repr, wedge_list))}" if wedge_list else ""
    hom, _ = cv2.findHomography(src, dst, 0)
    if hom is None or not np.all(np.isfinite(hom)):
        raise ImagingError(
            f"photo {photo!r}: no homography fits the markers {list(ids)}; "
            "check the markers' corners_mm (are they distinct and not all on one line?)"
        )
    rms = rms_px(cv2.perspectiveTransform(src.reshape(-1, 1, 2), hom).reshape(-1, 2), dst)
    if rms > layout.max_reprojection_error_px:
        raise ImagingError(
            f"photo {photo!r}: the marker homography misfits the detected corners by {rms:.2f} px "
            f"RMS (limit {layout.max_reprojection_error_px} px){need}. A marker's corners_mm may "
            "be wrong or in the wrong order (ArUco order: top-left, top-right, bottom-right, "
            "bottom-left of the printed marker), the base may not be flat, or the lens distorts "
            "strongly; fix the layout or give roi_px polygons for this photo"
        )
    return Placement(homography=hom, rms_error_px=rms, ids=ids)
