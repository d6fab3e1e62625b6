"""Each view's camera from the markers, for `stairfit init` (app/draft.py): the focal length,
then the view angle.

The pose itself is imaging's (`imaging.fit_camera_pose`, the code that places the faces when a
scene is measured); this module decides which camera model the photos support and reads the
view angle off the pose:

* **the focal length**: the layout's `[camera] focal_length_px`, else the tags (FocalLength x
  FocalPlaneXResolution, when every photo has them and they agree), else the markers of all
  views (`cv2.calibrateCamera`: one focal length, the principal point at the image centre, no
  distortion), used when a perspective camera fits the corners clearly better than a parallel
  projection does; otherwise the camera is affine (no focal length).
* **a pinhole's view angle** is the direction of its centre seen from the centre of the
  layout's markers (docs/scene.md). When the markers fit a mirrored pose about as well (planar
  targets seen through a long lens), the faces' edges decide between the two.
* **an affine camera** gives only the magnitude of the view angle (the foreshortening of the
  markers, `arccos` of the ratio of the affine map's singular values); its sign, and near the
  base normal, where the foreshortening hardly changes, its value, come from the wedges' faces:
  the view angle that puts the faces' projected outlines on the strongest edges of the image,
  searched within the range the markers allow.

The standard deviation of each marker estimate comes from refitting with the corners perturbed
by their own RMS misfit (`BOOTSTRAP_DRAWS`, a fixed seed).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from stairfit.imaging import (
        CameraPose,
        CameraTags,
        Exposure,
        MarkerDetection,
        MarkerLayout,
        PinholeCamera,
        RawFrame,
    )

Face = tuple[tuple[tuple[float, float], ...], float]
"""A wedge face for the edge search: its outline on the base (mm) and its angle (deg)."""
EdgeImage = tuple[np.ndarray, np.ndarray, int]
"""A view's image gradients (x, y) and its binning factor (`edge_images`)."""

BOOTSTRAP_DRAWS = 48
"""Refits with perturbed corners behind each view angle's standard deviation."""

AFFINE_FOCAL_FACTOR = 200.0
"""A focal length from the markers longer than this many image widths (a field of view under
0.3 deg) is a parallel projection: the camera is affine."""

PERSPECTIVE_GAIN = 1.5
"""A pinhole is used when the affine camera's RMS corner misfit is more than this many times
the pinhole's (plus `CORNER_NOISE_PX`): the perspective is seen in the corners."""

CORNER_NOISE_PX = 0.05
"""Corner misfit (px) below which the two cameras are not told apart."""

TAGS_AGREE = 0.005
"""The tags give the focal length only when every photo's value is within this fraction."""

MARKER_ONLY_SD_DEG = 0.1
"""An affine view angle keeps the markers' magnitude when its standard deviation is below this
(the faces then only give the sign); otherwise the faces' edges give the value."""

SEARCH_STEP_DEG = 0.05
"""Step of the search over view angles along the faces' edges (refined by a parabola)."""

SEARCH_MARGIN_DEG = 0.2
"""The search covers the markers' magnitude +- 3 standard deviations and this margin."""

SIGN_FREE_DEG = 0.3
"""A view angle whose magnitude is certainly below this needs no sign."""

AMBIGUOUS_SCORE = 0.95
"""When the best edge score of the other sign is above this fraction of the best, the sign is
left to the user."""


@dataclass(frozen=True)
class Focal:
    """The focal length the views are posed with (None: an affine camera) and where it came
    from, in words for the scene file's comment."""

    focal_length_px: float | None
    source: str
    from_layout: bool = False


@dataclass(frozen=True)
class ViewEstimate:
    """One view's angle from its markers (and faces), or why there is none.

    Attributes:
        view_deg: the signed view angle (deg, base frame), or None.
        sd_deg: its standard deviation from the markers' corner misfit, or None.
        source: how it was found, for the scene file's comment.
        problem: why there is no (signed) estimate ("" when there is one).
        magnitude_deg: the unsigned angle when only the sign is unknown.
        model: "pinhole" or "affine" ("" when the markers gave no pose).
        rms_px: the pose's RMS corner misfit.
        ids: the markers used.
    """

    view_deg: float | None
    sd_deg: float | None = None
    source: str = ""
    problem: str = ""
    magnitude_deg: float | None = None
    model: str = ""
    rms_px: float = math.nan
    ids: tuple[int, ...] = ()


def markers_centre(layout: MarkerLayout) -> np.ndarray:
    """The centre of the layout's marker corners on the base (x, y, 0), mm: where a view angle
    is seen from (docs/scene.md)."""
    corners = np.array([c for _, c in layout.markers], float).reshape(-1, 2)
    return np.append(corners.mean(axis=0), 0.0)


def view_of(pose: CameraPose, layout: MarkerLayout) -> float:
    """The view angle (deg, about y) of a pinhole's centre seen from the markers' centre."""
    d = pose.camera_centre_mm() - markers_centre(layout)
    return math.degrees(math.atan2(d[0], d[2]))


def _relaxed(layout: MarkerLayout) -> MarkerLayout:
    """The layout with the view-angle check off (init finds the angle, there is none to check)."""
    return dataclasses.replace(layout, max_view_error_deg=90.0)


def _pose(
    det: MarkerDetection,
    layout: MarkerLayout,
    size: tuple[int, int],
    camera: PinholeCamera | None,
    view: float | None,
) -> CameraPose:
    from stairfit import imaging

    return imaging.fit_camera_pose(
        det,
        _relaxed(layout),
        photo="",
        image_size=size,
        rising=True,
        view_deg=view,
        camera=camera,
    )


# --- the focal length ----------------------------------------------------------------------


def focal_from_tags(tags: Sequence[CameraTags]) -> Focal | None:
    """The focal length from every photo's FocalLength and FocalPlaneXResolution tags, when
    all have them and they agree within `TAGS_AGREE`; else None."""
    found = [t.focal_length_px() for t in tags]
    values = [v for v in found if v is not None]
    if not values or len(values) < len(found):
        return None
    if max(values) > min(values) * (1 + TAGS_AGREE):
        return None
    t = tags[0]
    return Focal(
        float(np.median(values)),
        f"the tags: FocalLength {t.focal_length_mm:g} mm x FocalPlaneXResolution "
        f"{t.pixels_per_mm:.6g} px/mm",
    )


def _corner_sets(
    detections: Sequence[MarkerDetection], layout: MarkerLayout
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """(base-frame points (n, 3), image points (n, 2)) of the layout's markers per detection
    with at least `min_markers` of them."""
    known = layout.corners_mm()
    obj, img = [], []
    for det in detections:
        pairs = [(i, c) for i, c in zip(det.ids, det.corners_px, strict=True) if i in known]
        if len(pairs) < layout.min_markers:
            continue
        xy = np.concatenate([known[i] for i, _ in pairs])
        obj.append(np.column_stack([xy, np.zeros(len(xy))]).astype(np.float32))
        img.append(np.concatenate([c for _, c in pairs]).astype(np.float32))
    return obj, img


def focal_from_markers(
    detections: Sequence[MarkerDetection], layout: MarkerLayout, size: tuple[int, int]
) -> Focal:
    """The focal length the markers of all views support (see the module docstring): a
    pinhole's, or None (affine) when the perspective is not seen in the corners."""
    import cv2

    obj, img = _corner_sets(detections, layout)
    if not obj:
        return Focal(None, "no photo shows enough markers to tell a focal length")
    affine = _affine_rms(detections, layout, size)
    w, h = size
    try:
        k0 = cv2.initCameraMatrix2D(obj, img, size)
        f0 = float(k0[0, 0]) if np.isfinite(k0[0, 0]) and k0[0, 0] > 0 else 10.0 * w
        k0 = np.array([[f0, 0.0, (w - 1) / 2], [0.0, f0, (h - 1) / 2], [0.0, 0.0, 1.0]])
        flags = (
            cv2.CALIB_USE_INTRINSIC_GUESS
            | cv2.CALIB_FIX_PRINCIPAL_POINT
            | cv2.CALIB_FIX_ASPECT_RATIO
            | cv2.CALIB_ZERO_TANGENT_DIST
            | cv2.CALIB_FIX_K1
            | cv2.CALIB_FIX_K2
            | cv2.CALIB_FIX_K3
        )
        out = cv2.calibrateCameraExtended(obj, img, size, k0, None, flags=flags)
        rms, f, sd = float(out[0]), float(out[1][0, 0]), float(out[5][1, 0])
    except cv2.error:
        rms, f, sd = math.inf, math.inf, math.inf
    affine_text = f"a parallel projection misfits them by {affine:.2g} px RMS"
    if not (math.isfinite(f) and 0 < f < AFFINE_FOCAL_FACTOR * w) or (
        affine <= PERSPECTIVE_GAIN * rms + CORNER_NOISE_PX
    ):
        return Focal(
            None,
            f"the markers of {len(obj)} photos show no perspective ({affine_text}"
            f"): an affine camera, no focal length",
        )
    return Focal(
        f,
        f"the markers of {len(obj)} photos (one focal length, the principal point at the image "
        f"centre, no distortion: {rms:.2g} px RMS, where {affine_text}): {f:.6g} +- "
        f"{sd:.2g} px",
    )


def _affine_rms(
    detections: Sequence[MarkerDetection], layout: MarkerLayout, size: tuple[int, int]
) -> float:
    """RMS corner misfit of the affine camera over every view it fits (inf for none)."""
    from stairfit import imaging

    loose = dataclasses.replace(_relaxed(layout), max_reprojection_error_px=1e9)
    squares, count = 0.0, 0
    for det in detections:
        try:
            pose = _pose(det, loose, size, None, 45.0)
        except imaging.ImagingError:
            continue
        n = 4 * len(pose.ids)
        squares += n * pose.rms_error_px**2
        count += n
    return math.sqrt(squares / count) if count else math.inf


# --- the view angle ------------------------------------------------------------------------


def _perturbed(det: MarkerDetection, sd_px: float, rng: np.random.Generator) -> MarkerDetection:
    """The detection with its corners moved by Gaussian noise of `sd_px` per coordinate."""
    noise = rng.normal(0.0, sd_px, np.shape(det.corners_px))
    return dataclasses.replace(det, corners_px=det.corners_px + noise)


def _spread(values: Sequence[float]) -> float:
    return float(np.std(values, ddof=1)) if len(values) > 1 else math.inf


def _bootstrap(
    det: MarkerDetection, pose: CameraPose, angle: Callable[[MarkerDetection], float]
) -> list[float]:
    """`angle(detection)` of refits with the corners perturbed by the pose's own misfit (per
    coordinate: RMS / sqrt(2), for the 6 or so parameters fitted)."""
    from stairfit import imaging

    n = 4 * len(pose.ids)
    sd = pose.rms_error_px / math.sqrt(2) * math.sqrt(n / max(n - 3, 1))
    rng = np.random.default_rng(0)
    values = []
    for _ in range(BOOTSTRAP_DRAWS):
        try:
            values.append(angle(_perturbed(det, sd, rng)))
        except imaging.ImagingError:
            continue
    return values


@dataclass(frozen=True)
class PhotoMarkers:
    """What the view angle of one photo is found from: its markers (`det`), the layout, the
    image size (w, h), the wedges' faces (with outlines on the base) and a callable giving the
    photo's edge images (`edge_images`; decoded only when the faces are needed)."""

    det: MarkerDetection
    layout: MarkerLayout
    size: tuple[int, int]
    faces: tuple[Face, ...]
    edges: Callable[[], list[EdgeImage]]

    def pose(
        self, camera: PinholeCamera | None, view: float | None, det: MarkerDetection | None = None
    ) -> CameraPose:
        """imaging's camera fitted to the markers (or to `det`), `view` choosing among poses."""
        return _pose(det or self.det, self.layout, self.size, camera, view)


def estimate_view(photo: PhotoMarkers, focal: Focal) -> ViewEstimate:
    """The view angle of one photo from its markers and, where they leave its sign or value
    open, its faces' edges (module docstring)."""
    from stairfit import imaging

    camera = None
    if focal.focal_length_px is not None:
        camera = imaging.PinholeCamera(focal.focal_length_px)
    try:
        pose = photo.pose(camera, None if camera else 45.0)
    except imaging.ImagingError as e:
        return ViewEstimate(None, problem=_without_photo(str(e)))
    if camera is not None:
        return _pinhole_view(photo, camera, pose)
    return _affine_view(photo, pose)


def _without_photo(message: str) -> str:
    """An imaging message about the photo without its leading "photo '': "."""
    return message.removeprefix("photo '': ")


def _pinhole_view(photo: PhotoMarkers, camera: PinholeCamera, pose: CameraPose) -> ViewEstimate:
    """A pinhole's view angle, the mirrored pose decided by the faces' edges (module docs)."""
    from stairfit import imaging

    layout = photo.layout
    view = view_of(pose, layout)
    draws = _bootstrap(photo.det, pose, lambda d: view_of(photo.pose(camera, view, d), layout))
    sd = _spread(draws)
    common = {"model": "pinhole", "rms_px": pose.rms_error_px, "ids": pose.ids, "sd_deg": sd}
    text = (
        f"the markers' pinhole pose ({len(pose.ids)} markers, {pose.rms_error_px:.2g} px "
        f"RMS) seen from their centre: +- {sd:.2g} deg"
    )
    try:
        other = photo.pose(camera, -view)
        other_view = view_of(other, layout)
    except imaging.ImagingError:
        other_view = view
    if abs(other_view - view) <= SIGN_FREE_DEG:
        return ViewEstimate(view, source=text, **common)
    both = f"the markers fit {view:.3g} and {other_view:.3g} deg about equally"
    if not photo.faces:
        return ViewEstimate(
            None,
            problem=f"{both}; give view_deg (a layout with face_mm outlines lets init decide)",
            magnitude_deg=abs(view),
            **common,
        )
    images = photo.edges()
    per_pose = [face_edge_scores(images, p, photo.faces) for p in (pose, other)]
    s_best, s_other = combined_scores(np.stack(per_pose), photo.faces)
    top, low = max(s_best, s_other), min(s_best, s_other)
    if top <= 0 or low > AMBIGUOUS_SCORE * top:
        return ViewEstimate(
            None,
            problem=f"{both}, and the faces' edges do not tell them apart; give view_deg",
            magnitude_deg=abs(view),
            **common,
        )
    chosen = view if s_best >= s_other else other_view
    return ViewEstimate(
        chosen,
        source=f"{text}; {both}: the faces' edges chose this one "
        f"(edge scores {top:.3g} and {low:.3g})",
        **common,
    )


def _affine_view(photo: PhotoMarkers, pose: CameraPose) -> ViewEstimate:
    """An affine camera's view angle: magnitude from the markers, sign (and near the base
    normal the value) from the faces' edges (module docstring)."""
    tilt = float(pose.implied_view_deg)
    draws = _bootstrap(photo.det, pose, lambda d: float(photo.pose(None, 45.0, d).implied_view_deg))
    lo, hi = _magnitude_range(tilt, draws)
    sd = _spread(draws)
    common = {"model": "affine", "rms_px": pose.rms_error_px, "ids": pose.ids, "sd_deg": sd}
    marker_text = (
        f"the markers' foreshortening (affine camera, {len(pose.ids)} markers, "
        f"{pose.rms_error_px:.2g} px RMS): |view| {tilt:.4g} +- {sd:.2g} deg"
    )
    if hi < SIGN_FREE_DEG:
        return ViewEstimate(
            tilt, source=f"{marker_text}; no sign needed so near the normal", **common
        )
    unsigned = "the sign is not shown (positive: the camera on the uphill side); give view_deg"
    if not photo.faces:
        return ViewEstimate(
            None,
            problem=f"{marker_text}; with an affine camera {unsigned} "
            "(a layout with face_mm outlines lets init decide)",
            magnitude_deg=tilt,
            **common,
        )
    search = _edge_search(photo, photo.edges(), lo, hi)
    if search is None:
        return ViewEstimate(
            None,
            problem=f"{marker_text}; by the faces' edges {unsigned}",
            magnitude_deg=tilt,
            **common,
        )
    best, best_score, other_score = search
    if sd <= MARKER_ONLY_SD_DEG and lo > 0:
        return ViewEstimate(
            math.copysign(tilt, best),
            source=f"{marker_text}; the sign from the "
            f"faces' edges (edge score {best_score:.3g}, the other sign's best "
            f"{other_score:.3g})",
            **common,
        )
    return ViewEstimate(
        best,
        source=f"{marker_text}; the value from the faces' edges within "
        f"+-[{lo:.3g}, {hi:.3g}] deg (edge score {best_score:.3g})",
        **common,
    )


def _magnitude_range(tilt: float, draws: Sequence[float]) -> tuple[float, float]:
    """The magnitudes of the view angle the markers allow: their foreshortening `cos(tilt)`
    +- 3 standard deviations of the refits' (about linear in the noise, where the angle is not:
    near the normal noise only ever adds tilt), widened by `SEARCH_MARGIN_DEG`."""
    c = math.cos(math.radians(tilt))
    sd = _spread([math.cos(math.radians(t)) for t in draws])
    if not math.isfinite(sd):
        return 0.0, 90.0
    lo = math.degrees(math.acos(min(1.0, c + 3.0 * sd))) - SEARCH_MARGIN_DEG
    hi = math.degrees(math.acos(max(0.0, c - 3.0 * sd))) + SEARCH_MARGIN_DEG
    return max(0.0, lo), min(90.0, hi)


def _edge_search(
    photo: PhotoMarkers, images: list[EdgeImage], lo: float, hi: float
) -> tuple[float, float, float] | None:
    """(view angle, its edge score, the other sign's best score) of the best placement of the
    faces' outlines over view angles of magnitude in [lo, hi]; None when the sign is
    ambiguous (`AMBIGUOUS_SCORE`) or no edge is seen."""
    from stairfit import imaging

    steps = max(2, math.ceil((hi - lo) / SEARCH_STEP_DEG) + 1)
    grid = np.unique(np.concatenate([-np.linspace(lo, hi, steps), np.linspace(lo, hi, steps)]))
    scores = []
    for v in grid:
        try:
            pose = photo.pose(None, float(v))
            scores.append(face_edge_scores(images, pose, photo.faces))
        except imaging.ImagingError:
            scores.append(np.zeros(len(photo.faces)))
    s = combined_scores(np.stack(scores), photo.faces)
    k = int(np.argmax(s))
    if s[k] <= 0:
        return None
    best = float(grid[k])
    if 0 < k < len(grid) - 1 and np.isclose(grid[k + 1] - grid[k], grid[k] - grid[k - 1]):
        curve = s[k - 1] - 2 * s[k] + s[k + 1]  # a parabola through the peak and neighbours
        if curve < 0:
            best += 0.5 * (s[k - 1] - s[k + 1]) / curve * (grid[k + 1] - grid[k])
    other = s[np.sign(grid) == -np.sign(best)] if abs(best) > SIGN_FREE_DEG else s[:0]
    other_best = float(other.max()) if other.size else 0.0
    if lo > 0 and other_best > AMBIGUOUS_SCORE * s[k]:
        return None
    return best, float(s[k]), other_best


# --- the faces' edges ----------------------------------------------------------------------


def edge_images(
    frames: Sequence[RawFrame], exposures: Sequence[Exposure | None]
) -> list[EdgeImage]:
    """The gradients (x, y) of a view's linear image, binned 2 x 2 (`imaging.binned_linear`)
    and lightly smoothed, with the binning factor: [(gx, gy, factor)]. An HDR bracket's
    exposures are merged first (`imaging.prepare_radiometry`), so that neither clipped nor
    black faces hide their edges. Linear, not logarithmic: the slope of a blurred step peaks
    at the edge itself in linear units, in logarithmic ones on its dark side."""
    import cv2

    from stairfit import imaging

    frame = frames[0]
    if len(frames) > 1 and all(e is not None for e in exposures):
        merged = imaging.prepare_radiometry(
            frames,
            exposures,
            None,
            imaging.ExtractionSettings(),
            frame.name,
        ).frame
        top = float(np.nanmax(merged.data)) if np.isfinite(merged.data).any() else 0.0
        frame = dataclasses.replace(merged, data=np.nan_to_num(merged.data, nan=top))
    linear, factor = imaging.binned_linear(frame)
    image = cv2.GaussianBlur(linear, (0, 0), 0.7)
    gx = cv2.Sobel(image, cv2.CV_32F, 1, 0, ksize=3) / np.float32(8.0)
    gy = cv2.Sobel(image, cv2.CV_32F, 0, 1, ksize=3) / np.float32(8.0)
    return [(gx, gy, factor)]


def _outline_samples(
    pose: CameraPose, outline: tuple[tuple[float, float], ...], angle: float
) -> tuple[np.ndarray, np.ndarray]:
    """Points along the middle 70% of every edge of a face's projected outline (full-res px)
    and the unit normal of their edge."""
    from stairfit import imaging

    poly = pose.project(imaging.face_outline_3d(outline, angle))
    points, normals = [np.zeros((0, 2))], [np.zeros((0, 2))]
    for a, b in zip(poly, np.roll(poly, -1, axis=0), strict=True):
        length = float(np.hypot(*(b - a)))
        if length < 1.0:
            continue
        t = np.linspace(0.15, 0.85, max(4, int(length / 2)))[:, None]
        points.append(a + t * (b - a))
        normals.append(np.broadcast_to(np.array([a[1] - b[1], b[0] - a[0]]) / length, (len(t), 2)))
    return np.concatenate(points), np.concatenate(normals)


def face_edge_scores(
    images: Sequence[EdgeImage], pose: CameraPose, faces: Sequence[Face]
) -> np.ndarray:
    """Per face, the mean strength of the image's edges across its projected outline
    (`edge_images`): largest when the outline lies on the face's edges in the photo; 0 where no
    outline point falls inside the image. Compare a face's scores between poses, not faces."""
    import cv2

    out = np.zeros(len(faces))
    for k, (outline, angle) in enumerate(faces):
        points, normals = _outline_samples(pose, outline, angle)
        for gx, gy, factor in images:
            b = (points - (factor - 1) / 2.0) / factor
            h, w = gx.shape
            inside = (b[:, 0] >= 1) & (b[:, 0] <= w - 2) & (b[:, 1] >= 1) & (b[:, 1] <= h - 2)
            if not inside.any():
                continue
            mx = b[inside, 0].astype(np.float32)[None, :]
            my = b[inside, 1].astype(np.float32)[None, :]
            sx = cv2.remap(gx, mx, my, cv2.INTER_LINEAR)[0]
            sy = cv2.remap(gy, mx, my, cv2.INTER_LINEAR)[0]
            n = normals[inside]
            out[k] += float(np.mean(np.abs(sx * n[:, 0] + sy * n[:, 1]))) / len(images)
    return out


def face_heights_mm(faces: Sequence[Face]) -> np.ndarray:
    """How high each face rises above the base (mm): how far its top edge moves in the image
    when the view angle changes, relative to the other faces."""
    from stairfit import imaging

    return np.array([float(np.ptp(imaging.face_outline_3d(o, a)[:, 2])) for o, a in faces])


def combined_scores(per_pose: np.ndarray, faces: Sequence[Face]) -> np.ndarray:
    """(n_poses,) from (n_poses, n_faces) face scores: each face's scores divided by its best
    (a dim face's edges count as much as a bright one's) and weighted by its height (a low
    face's edges hardly move with the view angle), summed over the faces."""
    best = per_pose.max(axis=0)
    weight = face_heights_mm(faces)
    used = (best > 0) & (weight > 0)
    if not used.any():
        return np.zeros(per_pose.shape[0])
    return (per_pose[:, used] / best[used]) @ (weight[used] / weight[used].sum())
