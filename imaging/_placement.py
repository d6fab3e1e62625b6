"""3-D placement of wedge faces from the ArUco markers on the specimen base.

A wedge face is not on the base plane: the scene gives its outline on the base (`face_mm`,
base-frame millimetres, x uphill), and the face rises along +x at its wedge angle beta2, so the
point (x, y) of the outline lies at height z = (x - x_min) tan(beta2), x_min being the outline's
smallest x (the foot). Seen from an oblique camera it appears displaced from where the
base-plane homography would put it. This module fits a camera to the marker corners and
projects the faces' 3-D outlines (docs/imaging.md §3-D placement):

* **pinhole** (the scene's `[camera] focal_length_px` is given): the camera pose from the
  markers (`cv2.solvePnPGeneric`, IPPE for the planar target, then Levenberg-Marquardt); lens
  distortion is not modelled.
* **affine** (no intrinsics): a parallel projection along the photo's view direction
  `(sin V, 0, cos V)` (`view_deg` = V, a rotation about the layer lines y): a point is moved
  along the view direction onto the base plane and mapped by the affine map the marker corners
  fit. Exact for an orthographic camera (stairfit's simulator), of any scale and roll.
* **homography**: when every face to place lies on the base (no wedge angle), the
  homography, exact for any camera.

Placements that are not consistent are refused with a message naming photo, wedge and fix:
markers that misfit the camera, a view_deg that disagrees with the markers, a base seen from
below (a mirrored layout), a face outside the image or hidden behind another wedge.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from ._errors import ImagingError
from ._markers import MarkerDetection, MarkerLayout, matched_markers, rms_px
from ._roi import Polygon, RoiMask

PLACEMENT_MODELS: tuple[str, ...] = ("homography", "affine", "pinhole")
"""How a photo's faces were placed: the `placement` column of the measurement table."""


@dataclass(frozen=True)
class PinholeCamera:
    """Intrinsics of a pinhole camera, in pixels of the full-resolution visible raw image.

    Attributes:
        focal_length_px: focal length in pixels (focal length / pixel pitch; e.g. 50 mm on a
            4.3 um pixel is 11600 px).
        principal_point_px: (cx, cy) in the pixel convention of docs/imaging.md §Pixels; None:
            the image centre ((W - 1) / 2, (H - 1) / 2).
    """

    focal_length_px: float
    principal_point_px: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        f = float(self.focal_length_px)
        if not (math.isfinite(f) and f > 0):
            raise ImagingError(f"camera: focal_length_px = {self.focal_length_px!r} must be > 0")
        object.__setattr__(self, "focal_length_px", f)
        if self.principal_point_px is not None:
            cx, cy = (float(v) for v in self.principal_point_px)
            if not (math.isfinite(cx) and math.isfinite(cy)):
                raise ImagingError("camera: principal_point_px must be two finite numbers")
            object.__setattr__(self, "principal_point_px", (cx, cy))

    def matrix(self, width: int, height: int) -> np.ndarray:
        """The 3 x 3 camera matrix K for an image of `width` x `height` pixels."""
        cx, cy = self.principal_point_px or ((width - 1) / 2.0, (height - 1) / 2.0)
        f = self.focal_length_px
        return np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])


def face_outline_3d(outline_mm: Polygon | np.ndarray, beta2_deg: float = 0.0) -> np.ndarray:
    """(n, 3) base-frame points of a face from its outline on the base and its wedge angle.

    z = (x - x_min) tan(beta2): the face rises along +x from its foot (the shared base-frame
    convention, docs/imaging.md §3-D placement). beta2 = 0 is a patch lying on the base.
    """
    xy = np.asarray(outline_mm, dtype=np.float64).reshape(-1, 2)
    z = (xy[:, 0] - xy[:, 0].min()) * math.tan(math.radians(beta2_deg))
    return np.column_stack([xy, z])


def toward_camera(view_deg: float) -> np.ndarray:
    """Unit vector from the specimen towards a camera at `view_deg` (rotation about y, base
    frame): (sin V, 0, cos V); positive V is the uphill (+x) side [conventions §1]."""
    v = math.radians(view_deg)
    return np.array([math.sin(v), 0.0, math.cos(v)])


@dataclass(frozen=True, eq=False)
class CameraPose:
    """A camera fitted to the marker corners: maps base-frame points (mm) to pixels.

    Attributes:
        model: "homography", "affine" or "pinhole" (`PLACEMENT_MODELS`).
        base_to_image: 3 x 3 homography of the base plane (z = 0) to the image; affine (last
            row 0, 0, 1) for the affine model, K [r1 r2 t] for the pinhole.
        rms_error_px: RMS reprojection error of the marker corners used.
        ids: the markers used.
        marker_errors_px: RMS reprojection error of each marker in `ids`.
        direction: the affine model's unit vector towards the camera (base frame).
        camera_matrix, rvec, tvec: the pinhole's K and pose (OpenCV's convention).
        implied_view_deg: the view angle the markers imply (the affine model: its magnitude
            only, from the foreshortening; the pinhole: signed, about y); None for a homography.
    """

    model: str
    base_to_image: np.ndarray
    rms_error_px: float
    ids: tuple[int, ...]
    marker_errors_px: tuple[float, ...]
    direction: np.ndarray | None = None
    camera_matrix: np.ndarray | None = None
    rvec: np.ndarray | None = None
    tvec: np.ndarray | None = None
    implied_view_deg: float | None = None

    def project(self, points_mm: np.ndarray) -> np.ndarray:
        """(n, 3) base-frame points (or (n, 2) points on the base) to (n, 2) pixels."""
        pts = np.asarray(points_mm, dtype=np.float64)
        if pts.shape[-1] == 2:
            pts = np.column_stack([pts.reshape(-1, 2), np.zeros(pts.size // 2)])
        pts = pts.reshape(-1, 3)
        if self.model == "pinhole":
            img, _ = cv2.projectPoints(pts, self.rvec, self.tvec, self.camera_matrix, None)
            return img.reshape(-1, 2)
        base = pts[:, :2]
        if self.direction is not None:  # slide along the view direction onto the base
            base = base - np.outer(pts[:, 2] / self.direction[2], self.direction[:2])
        elif np.any(pts[:, 2] != 0):
            raise ImagingError("a homography places points on the base plane only")
        return cv2.perspectiveTransform(base.reshape(-1, 1, 2), self.base_to_image).reshape(-1, 2)

    def camera_centre_mm(self) -> np.ndarray | None:
        """The pinhole's centre in the base frame (mm); None for the other models."""
        if self.model != "pinhole":
            return None
        rot, _ = cv2.Rodrigues(self.rvec)
        return (-rot.T @ self.tvec.reshape(3)).reshape(3)

    def rays_to_camera(self, points_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For (n, 3) points: unit directions towards the camera and the distance to it (mm;
        infinite for a parallel projection)."""
        pts = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
        centre = self.camera_centre_mm()
        if centre is None:
            d = self.direction if self.direction is not None else np.array([0.0, 0.0, 1.0])
            return np.broadcast_to(d, pts.shape).copy(), np.full(len(pts), np.inf)
        diff = centre - pts
        dist = np.linalg.norm(diff, axis=1)
        return diff / dist[:, None], dist


def _marker_errors(pose_project: np.ndarray, dst: np.ndarray) -> tuple[float, ...]:
    """RMS error of each marker (4 consecutive corners)."""
    n = len(dst) // 4
    return tuple(rms_px(pose_project[4 * k : 4 * k + 4], dst[4 * k : 4 * k + 4]) for k in range(n))


def _need(wedges: Sequence[str]) -> str:
    return f" to place the ROIs of {', '.join(map(repr, sorted(wedges)))}" if wedges else ""


def _misfit(photo: str, what: str, rms: float, layout: MarkerLayout, wedges: Sequence[str]) -> str:
    return (
        f"photo {photo!r}: the {what} misfits the detected corners by {rms:.2f} px RMS "
        f"(limit {layout.max_reprojection_error_px} px){_need(wedges)}"
    )


def affine_tilt_deg(linear: np.ndarray) -> float:
    """The tilt of the base plane (deg from the view direction) that a 2 x 2 affine map of
    it implies for a scaled orthographic camera: arccos(smaller / larger singular value)."""
    s = np.linalg.svd(np.asarray(linear, dtype=np.float64), compute_uv=False)
    return math.degrees(math.acos(min(1.0, float(s[1] / s[0])))) if s[0] > 0 else 90.0


def fit_affine_pose(
    src: np.ndarray,
    dst: np.ndarray,
    ids: tuple[int, ...],
    layout: MarkerLayout,
    *,
    photo: str,
    view_deg: float,
    wedges: Sequence[str] = (),
) -> CameraPose:
    """The affine camera: the marker corners' least-squares affine map of the base and a
    parallel projection along `toward_camera(view_deg)`.

    Raises:
        ImagingError: the corners do not fit an affine map (a perspective camera: give its
            focal length), the base is seen mirrored, or the markers' foreshortening disagrees
            with `view_deg` by more than `layout.max_view_error_deg`.
    """
    design = np.column_stack([src, np.ones(len(src))])
    coef, *_ = np.linalg.lstsq(design, dst, rcond=None)
    hom = np.vstack([coef.T, [0.0, 0.0, 1.0]])
    proj = design @ coef
    rms = rms_px(proj, dst)
    if rms > layout.max_reprojection_error_px:
        raise ImagingError(
            _misfit(photo, "affine camera (no [camera] focal_length_px)", rms, layout, wedges)
            + ". The camera is too close for a parallel projection (perspective): give "
            "[camera] focal_length_px; or a marker's corners_mm are wrong or in the wrong order"
        )
    linear = hom[:2, :2]
    if np.linalg.det(linear) > 0:
        raise ImagingError(
            f"photo {photo!r}: the markers show the base mirrored (seen from below){_need(wedges)}"
            "; the layout's corners_mm must be in a right-handed frame (x uphill, y along the "
            "layer lines, z up) with each marker's corners in ArUco order"
        )
    tilt = affine_tilt_deg(linear)
    if abs(tilt - abs(view_deg)) > layout.max_view_error_deg:
        raise ImagingError(
            f"photo {photo!r}: the markers are foreshortened as seen from {tilt:.1f} deg off the "
            f"base normal, but view_deg = {view_deg:g}{_need(wedges)}; fix view_deg (and "
            "angles_relative_to), or give [camera] focal_length_px for a perspective camera"
        )
    return CameraPose(
        model="affine",
        base_to_image=hom,
        rms_error_px=rms,
        ids=ids,
        marker_errors_px=_marker_errors(proj, dst),
        direction=toward_camera(view_deg),
        implied_view_deg=tilt,
    )


def _pinhole_solutions(
    src: np.ndarray, dst: np.ndarray, k: np.ndarray
) -> list[tuple[float, np.ndarray, np.ndarray]]:
    """(RMS error, rvec, tvec) of each IPPE solution, refined by Levenberg-Marquardt."""
    obj = np.column_stack([src, np.zeros(len(src))]).astype(np.float64)
    img = dst.astype(np.float64)
    _n, rvecs, tvecs, _err = cv2.solvePnPGeneric(obj, img, k, None, flags=cv2.SOLVEPNP_IPPE)
    out = []
    for rvec, tvec in zip(rvecs, tvecs, strict=True):
        rvec, tvec = cv2.solvePnPRefineLM(obj, img, k, None, rvec.copy(), tvec.copy())
        proj, _ = cv2.projectPoints(obj, rvec, tvec, k, None)
        out.append((rms_px(proj.reshape(-1, 2), img), rvec, tvec))
    return sorted(out, key=lambda item: item[0])


def _view_of(centre: np.ndarray, target: np.ndarray) -> float:
    """The signed view angle (deg, about y) of a camera at `centre` seen from `target`."""
    d = centre - target
    return math.degrees(math.atan2(d[0], d[2]))


def fit_pinhole_pose(
    src: np.ndarray,
    dst: np.ndarray,
    ids: tuple[int, ...],
    layout: MarkerLayout,
    *,
    photo: str,
    camera: PinholeCamera,
    image_size: tuple[int, int],
    view_deg: float | None,
    wedges: Sequence[str] = (),
) -> CameraPose:
    """The pinhole camera's pose from the marker corners (`cv2.solvePnPGeneric`, IPPE + LM).

    Of IPPE's two solutions for a planar target the better-fitting is kept, or, when both fit
    within 20%, the one nearer `view_deg`.

    Raises:
        ImagingError: no pose fits within `layout.max_reprojection_error_px`, the camera is
            below the base, or its direction disagrees with `view_deg` by more than
            `layout.max_view_error_deg`.
    """
    k = camera.matrix(*image_size)
    sols = _pinhole_solutions(src, dst, k)
    if not sols or not math.isfinite(sols[0][0]):
        raise ImagingError(f"photo {photo!r}: no camera pose fits the markers {list(ids)}")
    target = np.append(src.mean(axis=0), 0.0)

    def view(sol: tuple[float, np.ndarray, np.ndarray]) -> float:
        rot, _ = cv2.Rodrigues(sol[1])
        return _view_of(-rot.T @ sol[2].reshape(3), target)

    near = [s for s in sols if s[0] <= 1.2 * sols[0][0] + 1e-9]
    if view_deg is not None and len(near) > 1:
        near.sort(key=lambda s: abs(view(s) - view_deg))
    rms, rvec, tvec = near[0]
    if rms > layout.max_reprojection_error_px:
        raise ImagingError(
            _misfit(photo, f"pinhole camera (focal length {camera.focal_length_px:g} px)", rms,
                    layout, wedges)
            + "; check [camera] focal_length_px and principal_point_px, and the markers' "
            "corners_mm (ArUco order: top-left, top-right, bottom-right, bottom-left)"
        )  # fmt: skip
    pose = CameraPose(
        model="pinhole",
        base_to_image=k @ np.column_stack([cv2.Rodrigues(rvec)[0][:, :2], tvec.reshape(3)]),
        rms_error_px=rms,
        ids=ids,
        marker_errors_px=_marker_errors(
            cv2.projectPoints(np.column_stack([src, np.zeros(len(src))]), rvec, tvec, k, None)[
                0
            ].reshape(-1, 2),
            dst,
        ),
        camera_matrix=k,
        rvec=rvec,
        tvec=tvec,
    )
    return _checked_pinhole(pose, target, layout, photo=photo, view_deg=view_deg, wedges=wedges)


def _checked_pinhole(
    pose: CameraPose,
    target: np.ndarray,
    layout: MarkerLayout,
    *,
    photo: str,
    view_deg: float | None,
    wedges: Sequence[str],
) -> CameraPose:
    """The pinhole pose with its implied view angle, refused when the camera is below the base
    or disagrees with `view_deg`."""
    centre = pose.camera_centre_mm()
    assert centre is not None
    if centre[2] <= 0:
        raise ImagingError(
            f"photo {photo!r}: the markers put the camera below the base (z = {centre[2]:.0f} "
            f"mm){_need(wedges)}; the layout's corners_mm must be in a right-handed frame (x "
            "uphill, y along the layer lines, z up) with each marker's corners in ArUco order"
        )
    implied = _view_of(centre, target)
    if view_deg is not None and abs(implied - view_deg) > layout.max_view_error_deg:
        raise ImagingError(
            f"photo {photo!r}: the markers put the camera at {implied:.1f} deg from the base "
            f"normal (about the layer lines), but view_deg = {view_deg:g}{_need(wedges)}; fix "
            "view_deg (its sign: positive is the uphill side) or [camera] focal_length_px"
        )
    return CameraPose(
        model=pose.model,
        base_to_image=pose.base_to_image,
        rms_error_px=pose.rms_error_px,
        ids=pose.ids,
        marker_errors_px=pose.marker_errors_px,
        camera_matrix=pose.camera_matrix,
        rvec=pose.rvec,
        tvec=pose.tvec,
        implied_view_deg=implied,
    )


def fit_homography_pose(
    src: np.ndarray,
    dst: np.ndarray,
    ids: tuple[int, ...],
    layout: MarkerLayout,
    *,
    photo: str,
    wedges: Sequence[str] = (),
) -> CameraPose:
    """The base-plane homography (for faces that lie on the base), as a `CameraPose`."""
    hom, _ = cv2.findHomography(src, dst, 0)
    if hom is None or not np.all(np.isfinite(hom)):
        raise ImagingError(
            f"photo {photo!r}: no homography fits the markers {list(ids)}; check the markers' "
            "corners_mm (are they distinct and not all on one line?)"
        )
    proj = cv2.perspectiveTransform(src.reshape(-1, 1, 2), hom).reshape(-1, 2)
    rms = rms_px(proj, dst)
    if rms > layout.max_reprojection_error_px:
        raise ImagingError(
            _misfit(photo, "marker homography", rms, layout, wedges)
            + ". A marker's corners_mm may be wrong or in the wrong order (ArUco order: "
            "top-left, top-right, bottom-right, bottom-left of the printed marker), the base "
            "may not be flat, or the lens distorts strongly; fix the layout or give roi_px "
            "polygons for this photo"
        )
    return CameraPose("homography", hom, rms, ids, _marker_errors(proj, dst))


def foreshortening_hint(detection: MarkerDetection, view_deg: float | None) -> str:
    """A sentence on how small the markers are, for the too-few-markers message."""
    parts = []
    if detection.cell_px:
        parts.append(
            f" The markers found are {min(detection.cell_px):.1f} px per cell (detection needs "
            f"about {MIN_DETECTABLE_CELL_PX:g}; docs/imaging.md §Markers)."
        )
    if view_deg is not None and abs(view_deg) >= 60:
        parts.append(
            f" At view_deg = {view_deg:g} the markers are foreshortened to "
            f"{math.cos(math.radians(view_deg)):.2f} of their size along the view; larger "
            "markers, a closer camera, or roi_px polygons for this photo help."
        )
    return "".join(parts)


MIN_DETECTABLE_CELL_PX = 3.0
"""About the smallest marker cell (full-resolution px, the foreshortened side) the detector
finds: measured by benchmarks/bench_markers.py (docs/imaging.md §Markers)."""


def fit_camera_pose(
    detection: MarkerDetection,
    layout: MarkerLayout,
    *,
    photo: str,
    image_size: tuple[int, int],
    rising: bool,
    view_deg: float | None = None,
    camera: PinholeCamera | None = None,
    wedges: Sequence[str] = (),
) -> CameraPose:
    """The camera that places a photo's faces: homography (every face on the base), pinhole
    (`camera` given) or affine (neither; needs `view_deg`). See the module docstring.

    Args:
        detection, layout: the markers found and where they are on the base.
        photo, wedges: names for messages.
        image_size: (width, height) of the visible raw image.
        rising: whether any face to place rises above the base (has a wedge angle).
        view_deg: the camera's direction from the base normal, rotation about y (base frame).
        camera: pinhole intrinsics, or None.
    """
    hint = foreshortening_hint(detection, view_deg)
    ids, src, dst = matched_markers(detection, layout, photo=photo, wedges=wedges, hint=hint)
    if not rising:
        return fit_homography_pose(src, dst, ids, layout, photo=photo, wedges=wedges)
    if camera is not None:
        return fit_pinhole_pose(
            src, dst, ids, layout, photo=photo, camera=camera, image_size=image_size,
            view_deg=view_deg, wedges=wedges,
        )  # fmt: skip
    if view_deg is None:
        raise ImagingError(
            f"photo {photo!r}: placing wedge faces in 3-D needs the photo's view_deg or "
            f"[camera] focal_length_px{_need(wedges)}"
        )
    return fit_affine_pose(src, dst, ids, layout, photo=photo, view_deg=view_deg, wedges=wedges)


def face_polygon(pose: CameraPose, outline_mm: Polygon, beta2_deg: float = 0.0) -> Polygon:
    """A face's image polygon (px): its 3-D outline (`face_outline_3d`) projected by `pose`."""
    img = pose.project(face_outline_3d(outline_mm, beta2_deg))
    return tuple((float(x), float(y)) for x, y in img)


def face_axis_px(pose: CameraPose, outline_mm: Polygon, beta2_deg: float = 0.0) -> np.ndarray:
    """Unit image vector (px) of a placed face's in-plane direction: the image of the face's
    uphill direction `(cos beta2, 0, sin beta2)` at its centre, along which its viewing angle
    varies (docs/imaging.md §Viewing spread)."""
    face = face_outline_3d(outline_mm, beta2_deg)
    centre = face.mean(axis=0)
    b = math.radians(beta2_deg)
    step = 0.05 * float(np.ptp(face[:, 0]) or 1.0)
    uphill = step * np.array([math.cos(b), 0.0, math.sin(b)])
    ends = pose.project(np.stack([centre - uphill, centre + uphill]))
    d = ends[1] - ends[0]
    norm = float(np.hypot(*d))
    return d / norm if norm > 0 else np.array([0.0, 1.0])


def face_view_deg(pose: CameraPose, outline_mm: Polygon, beta2_deg: float = 0.0) -> float | None:
    """The view angle (deg, about y, base frame) from a face's centre to a pinhole's centre:
    the face's own `view_deg` through a camera at finite distance (a raised or off-centre face
    is seen at another angle than the photo's nominal one); None for the other camera models
    (at infinity, every face is seen along one direction). docs/imaging.md §3-D placement."""
    centre = pose.camera_centre_mm()
    if centre is None:
        return None
    return _view_of(centre, face_outline_3d(outline_mm, beta2_deg).mean(axis=0))


def pixels_on_face(
    pose: CameraPose, outline_mm: Polygon, beta2_deg: float, pixels_px: np.ndarray
) -> np.ndarray:
    """The base-frame points (n, 3; mm) of a face that (n, 2) pixel centres (x, y) see: each
    pixel back-projected onto the face's plane by the plane-to-image homography of its 3-D
    outline through `pose` (exact for a pinhole and for an affine camera). docs/imaging.md
    §3-D placement."""
    face = face_outline_3d(outline_mm, beta2_deg)
    pts = np.concatenate([face, 0.5 * (face + np.roll(face, -1, axis=0))])  # >= 4, not collinear
    h, _ = cv2.findHomography(pose.project(pts), pts[:, :2], 0)
    px = np.asarray(pixels_px, dtype=np.float64).reshape(-1, 2)
    xy = cv2.perspectiveTransform(px.reshape(-1, 1, 2), h).reshape(-1, 2)
    z = (xy[:, 0] - face[:, 0].min()) * math.tan(math.radians(beta2_deg))
    return np.column_stack([xy, z])


def pixel_view_deg(
    pose: CameraPose, outline_mm: Polygon, beta2_deg: float, pixels_px: np.ndarray
) -> np.ndarray | None:
    """The view angle (deg, about y, base frame) from the face point each pixel sees to a
    pinhole's centre (`pixels_on_face`). None for the other camera models.
    docs/imaging.md §3-D placement."""
    centre = pose.camera_centre_mm()
    if centre is None:
        return None
    xyz = pixels_on_face(pose, outline_mm, beta2_deg, pixels_px)
    return np.degrees(np.arctan2(centre[0] - xyz[:, 0], centre[2] - xyz[:, 2]))


FACE_POINT_GRID = 4
"""`roi_face_points` bins an ROI's pixels into this many cells along each of the face's two
axes (up the slope, along the layer lines)."""


def roi_face_points(
    pose: CameraPose, outline_mm: Polygon, beta2_deg: float, pixels_px: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """A quadrature of an ROI's pixels over its face: (points (m, 3) in base-frame mm, weights
    (m,) summing to 1). The pixels' face points (`pixels_on_face`) are binned into a
    `FACE_POINT_GRID` x `FACE_POINT_GRID` grid along the face's axes; each non-empty cell gives
    its points' mean, weighted by its share of the pixels. The ROI's mean value is the mean
    over its pixels, so a function of the face point averaged with these weights is that mean
    up to the variation within a cell. docs/imaging.md §3-D placement."""
    xyz = pixels_on_face(pose, outline_mm, beta2_deg, pixels_px)
    if xyz.shape[0] == 0:
        return np.zeros((0, 3)), np.zeros(0)
    b = math.radians(beta2_deg)
    up = xyz[:, 0] * math.cos(b) + xyz[:, 2] * math.sin(b)  # along the slope
    cells = []
    for coord in (up, xyz[:, 1]):
        lo, hi = float(coord.min()), float(coord.max())
        k = np.floor((coord - lo) / max(hi - lo, 1e-12) * FACE_POINT_GRID).astype(int)
        cells.append(np.clip(k, 0, FACE_POINT_GRID - 1))
    cell = cells[0] * FACE_POINT_GRID + cells[1]
    counts = np.bincount(cell, minlength=FACE_POINT_GRID**2)
    sums = np.stack([np.bincount(cell, xyz[:, j], FACE_POINT_GRID**2) for j in range(3)], 1)
    keep = counts > 0
    return sums[keep] / counts[keep, None], counts[keep] / counts.sum()


def roi_view_half_width_deg(
    pose: CameraPose, outline_mm: Polygon, beta2_deg: float, pixels_px: np.ndarray
) -> float | None:
    """The half-width (deg) of the uniform spread of viewing angles with the same standard
    deviation as `pixel_view_deg` over an ROI's (n, 2) pixel centres: `sqrt(3) sd`, the row's
    own `h_o cos(theta_o) view_spread` [conventions §9]. Unlike the scene's one
    `angular_extent_deg` it follows each face's own length along its slope (a standing
    60-deg face on a 20 mm footprint is 40 mm long) and its distance. None for the other
    camera models or fewer than 2 pixels. docs/imaging.md §Viewing spread."""
    angles = pixel_view_deg(pose, outline_mm, beta2_deg, pixels_px)
    if angles is None or angles.size < 2:
        return None
    return float(math.sqrt(3.0) * angles.std())


def view_parallax_deg(
    pose: CameraPose,
    layout: MarkerLayout,
    outline_mm: Polygon,
    beta2_deg: float = 0.0,
    pixels_px: np.ndarray | None = None,
) -> float | None:
    """How much farther (deg, about y) a pinhole camera is turned as seen from a face than as
    seen from the centre of the layout's markers. A photo's `view_deg` is the camera seen from
    the markers' centre; each face is seen at `view_deg + view_parallax_deg`. The difference is
    what the pose determines well: a pose from coplanar markers through a long lens may be
    tilted by a few tenths of a degree, the same for every point. None for the other camera
    models.

    The face is seen from its outline's centre (`face_view_deg`), or, with `pixels_px` (the
    (n, 2) centres of the ROI's pixels), as the mean over those pixels of `pixel_view_deg`:
    what the ROI's mean measures. Through a pinhole the near part of a tilted face covers more
    pixels per mm^2, so the two differ (up to 0.019 deg on the standing 60-deg face at 900 mm,
    0.5% of the radiance on a steep lobe flank; docs/imaging.md §3-D placement)."""
    if pixels_px is None:
        face = face_view_deg(pose, outline_mm, beta2_deg)
    else:
        angles = pixel_view_deg(pose, outline_mm, beta2_deg, pixels_px)
        face = None if angles is None or angles.size == 0 else float(angles.mean())
    if face is None:
        return None
    corners = np.array([c for _, c in layout.markers], float).reshape(-1, 2)
    mid = np.append(corners.mean(axis=0), 0.0)
    return face - _view_of(pose.camera_centre_mm(), mid)  # type: ignore[arg-type]


def check_in_image(
    polygon: Polygon, image_size: tuple[int, int], *, photo: str, wedge: str
) -> None:
    """ImagingError when a placed face reaches outside the image (names photo, wedge, fix)."""
    pts = np.asarray(polygon)
    w, h = image_size
    out = (pts[:, 0] < -0.5) | (pts[:, 0] > w - 0.5) | (pts[:, 1] < -0.5) | (pts[:, 1] > h - 0.5)
    if out.any():
        x, y = pts[int(np.argmax(out))]
        raise ImagingError(
            f"photo {photo!r}, wedge {wedge!r}: the face placed from the markers reaches "
            f"outside the image (a corner at ({x:.0f}, {y:.0f}) px, image {w} x {h}); check "
            "the wedge's face_mm and angle_deg and the photo's view_deg, or give a roi_px "
            "polygon for this wedge in this photo"
        )


def inside_polygon(polygon: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Boolean mask of (n, 2) points inside a polygon (even-odd rule)."""
    poly = np.asarray(polygon, dtype=np.float64).reshape(-1, 2)
    x, y = points[:, 0], points[:, 1]
    inside = np.zeros(len(points), dtype=bool)
    for (x0, y0), (x1, y1) in zip(poly, np.roll(poly, -1, axis=0), strict=True):
        crosses = (y0 > y) != (y1 > y)
        with np.errstate(divide="ignore", invalid="ignore"):
            xc = x0 + (y - y0) * (x1 - x0) / (y1 - y0)
        inside ^= crosses & (x < xc)
    return inside


def wedge_planes(outline_mm: Polygon, beta2_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """The half-spaces n . p <= c bounding a wedge's solid: (normals (m, 3), offsets (m,)).

    The solid lies above the base (z >= 0), below its face (z <= (x - x_min) tan beta2) and
    inside the vertical prism over the convex hull of its outline (a concave outline is
    treated as its hull: conservative for hiding).
    """
    xy = np.asarray(outline_mm, dtype=np.float64).reshape(-1, 2)
    hull = cv2.convexHull(xy.astype(np.float32)).reshape(-1, 2).astype(np.float64)
    if _signed_area(hull) < 0:
        hull = hull[::-1]
    t = math.tan(math.radians(beta2_deg))
    normals = [(0.0, 0.0, -1.0), (-t, 0.0, 1.0)]
    offsets = [0.0, -xy[:, 0].min() * t]
    for a, b in zip(hull, np.roll(hull, -1, axis=0), strict=True):
        n = np.array([b[1] - a[1], -(b[0] - a[0]), 0.0])  # outward for a counter-clockwise hull
        normals.append(tuple(n))
        offsets.append(float(n[:2] @ a))
    return np.asarray(normals), np.asarray(offsets)


def _signed_area(poly: np.ndarray) -> float:
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def ray_hits_solid(
    points: np.ndarray, directions: np.ndarray, reach: np.ndarray, planes: tuple[np.ndarray, ...]
) -> np.ndarray:
    """Whether each ray p + t d, 0 < t < reach, passes through a convex solid n . p <= c by
    more than 1e-3 mm (Cyrus-Beck clipping; grazing contacts do not count)."""
    normals, offsets = planes
    num = offsets[None, :] - points @ normals.T  # (n, m)
    den = directions @ normals.T
    with np.errstate(divide="ignore", invalid="ignore"):
        t = num / den
    enter = np.where(den < 0, t, -np.inf).max(axis=1)
    leave = np.where(den > 0, t, np.inf).min(axis=1)
    parallel_out = ((den == 0) & (num < 0)).any(axis=1)
    enter = np.maximum(enter, 0.0)
    leave = np.minimum(leave, reach)
    return ~parallel_out & (leave - enter > 1e-3)


def hidden_fraction(
    pose: CameraPose,
    outline_mm: Polygon,
    beta2_deg: float,
    occluders: Sequence[tuple[str, Polygon, float]],
    roi: RoiMask,
    samples: int = 48,
) -> tuple[float, str]:
    """The fraction of a placed face's ROI hidden from the camera by other wedges, and the
    wedge that hides most of it ("" if none).

    Points on a `samples` x `samples` grid over the face (base frame, lifted onto the face) that
    project into the eroded ROI are traced towards the camera through every other wedge's solid
    (`wedge_planes`).
    """
    xy = np.asarray(outline_mm, dtype=np.float64).reshape(-1, 2)
    gx = np.linspace(xy[:, 0].min(), xy[:, 0].max(), samples)
    gy = np.linspace(xy[:, 1].min(), xy[:, 1].max(), samples)
    grid = np.stack(np.meshgrid(gx, gy), axis=-1).reshape(-1, 2)
    grid = grid[inside_polygon(xy, grid)]
    pts = face_outline_3d(np.vstack([xy, grid]), beta2_deg)[len(xy) :]  # same foot as the face
    px = np.rint(pose.project(pts)).astype(int)
    r, c = px[:, 1] - roi.y0, px[:, 0] - roi.x0
    h, w = roi.mask.shape
    ok = (r >= 0) & (r < h) & (c >= 0) & (c < w)
    ok[ok] = roi.mask[r[ok], c[ok]]
    pts = pts[ok]
    if len(pts) == 0:
        return 0.0, ""
    dirs, reach = pose.rays_to_camera(pts)
    hidden = np.zeros(len(pts), dtype=bool)
    worst, worst_n = "", 0
    for name, other, beta2 in occluders:
        hit = ray_hits_solid(pts + 1e-6 * dirs, dirs, reach, wedge_planes(other, beta2))
        hidden |= hit
        if int(hit.sum()) > worst_n:
            worst, worst_n = name, int(hit.sum())
    return float(hidden.mean()), worst
