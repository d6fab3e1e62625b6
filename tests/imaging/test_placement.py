"""3-D placement of wedge faces from the markers (issue 12): geometry against cameras written
here (an orthographic camera with roll and a pinhole, plain NumPy, not the simulator's), and the
refusals of placements that are not consistent."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stairfit import imaging

# A base with four 20 mm markers around three wedges in a row along y (the simulator's plan).
MARKERS = {
    0: [(-30, -30), (-30, -10), (-10, -10), (-10, -30)],
    1: [(-30, 90), (-30, 110), (-10, 110), (-10, 90)],
    2: [(30, -30), (30, -10), (50, -10), (50, -30)],
    3: [(30, 90), (30, 110), (50, 110), (50, 90)],
}
LAYOUT = imaging.MarkerLayout(MARKERS)
WEDGES = {  # name -> (outline on the base, beta2 in deg)
    "w10": ([(0, 0), (20, 0), (20, 20), (0, 20)], 10.0),
    "w30": ([(0, 30), (20, 30), (20, 50), (0, 50)], 30.0),
    "w60": ([(0, 60), (20, 60), (20, 80), (0, 80)], 60.0),
}
SIZE = (1600, 1200)


def _rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def _camera_rotation(view_deg: float, roll_deg: float) -> np.ndarray:
    """World -> camera rotation of a camera above the base at view_deg about y, looking at the
    base (camera z forward, x right, y down), turned by roll_deg about its axis."""
    look_down = np.array([[0, 1, 0], [1, 0, 0], [0, 0, -1]], float)  # x_cam = y, y_cam = x
    return _rot_z(math.radians(roll_deg)) @ look_down @ _rot_y(-math.radians(view_deg))


def _ortho(view_deg: float, roll_deg: float = 7.0, px_per_mm: float = 8.0):
    rot = _camera_rotation(view_deg, roll_deg)
    centre = np.array([10.0, 40.0, 0.0])

    def project(p: np.ndarray) -> np.ndarray:
        cam = (np.asarray(p, float).reshape(-1, 3) - centre) @ rot.T
        return cam[:, :2] * px_per_mm + (SIZE[0] / 2, SIZE[1] / 2)

    return project


def _pinhole(view_deg: float, distance_mm: float, focal_px: float, roll_deg: float = 5.0):
    rot = _camera_rotation(view_deg, roll_deg)
    target = np.array([10.0, 40.0, 0.0])
    toward = np.array([math.sin(math.radians(view_deg)), 0.0, math.cos(math.radians(view_deg))])
    centre = target + distance_mm * toward
    k = np.array([[focal_px, 0, (SIZE[0] - 1) / 2], [0, focal_px, (SIZE[1] - 1) / 2], [0, 0, 1]])

    def project(p: np.ndarray) -> np.ndarray:
        cam = (np.asarray(p, float).reshape(-1, 3) - centre) @ rot.T
        img = cam @ k.T
        return img[:, :2] / img[:, 2:]

    project.centre, project.rot, project.k = centre, rot, k  # type: ignore[attr-defined]
    return project


def _face_hits(project, outline, beta2: float, pixels: np.ndarray) -> np.ndarray:
    """Where the test pinhole's rays through (n, 2) pixels meet a face's plane, z = (x - x_min)
    tan(beta2): plain ray casting, (n, 3)."""
    rays = np.column_stack([pixels, np.ones(len(pixels))]) @ np.linalg.inv(project.k).T
    d = rays @ project.rot  # camera -> world
    c = project.centre
    x0, slope = float(np.min(np.asarray(outline, float)[:, 0])), math.tan(math.radians(beta2))
    t = (slope * (c[0] - x0) - c[2]) / (d[:, 2] - slope * d[:, 0])
    return c + t[:, None] * d


def _lift(outline, beta2: float) -> np.ndarray:
    xy = np.asarray(outline, float)
    return np.column_stack([xy, (xy[:, 0] - xy[:, 0].min()) * math.tan(math.radians(beta2))])


def _detection(project) -> imaging.MarkerDetection:
    corners = np.stack([project(_lift(c, 0.0)) for c in MARKERS.values()])
    return imaging.MarkerDetection(tuple(MARKERS), corners, "DICT_4X4_50", cell_px=(9.0,) * 4)


def _pose(project, view_deg: float, camera=None, layout=LAYOUT) -> imaging.CameraPose:
    return imaging.fit_camera_pose(
        _detection(project), layout, photo="p.dng", image_size=SIZE, rising=True,
        view_deg=view_deg, camera=camera, wedges=list(WEDGES),
    )  # fmt: skip


def test_face_outline_rises_along_x_from_its_foot() -> None:
    pts = imaging.face_outline_3d([(5, 0), (25, 0), (25, 20), (5, 20)], 30.0)
    assert pts[:, 2] == pytest.approx([0, 20 * math.tan(math.radians(30)), 20 * 0.57735027, 0])
    assert imaging.face_outline_3d([(5, 0), (25, 0), (25, 20)], 0.0)[:, 2].tolist() == [0, 0, 0]


@pytest.mark.parametrize("view_deg", [-80.0, -45.0, -5.0, 0.0, 3.0, 20.0])
def test_affine_camera_is_exact_for_an_orthographic_view(view_deg: float) -> None:
    project = _ortho(view_deg)
    pose = _pose(project, view_deg)
    assert pose.model == "affine" and pose.rms_error_px < 1e-9
    assert pose.implied_view_deg == pytest.approx(abs(view_deg), abs=1e-3)
    for name, (outline, beta2) in WEDGES.items():
        placed = np.asarray(imaging.face_polygon(pose, outline, beta2))
        assert np.abs(placed - project(_lift(outline, beta2))).max() < 1e-8, name


def test_base_plane_homography_misplaces_rising_faces() -> None:
    """What issue 12 measured: the homography puts a face where its outline would be on the
    base; seen from 45 deg the 60-degree face is tens of pixels away."""
    project = _ortho(-45.0)
    flat = imaging.fit_placement(_detection(project), LAYOUT, photo="p.dng")
    outline, beta2 = WEDGES["w60"]
    error = np.abs(np.asarray(flat.polygon(outline)) - project(_lift(outline, beta2))).max()
    assert error > 100  # 34.6 mm high x sin(45 deg) x 8 px/mm = 196 px at the top edge


@pytest.mark.parametrize("view_deg", [-60.0, -20.0, 0.0, 15.0])
def test_pinhole_camera_places_faces_exactly(view_deg: float) -> None:
    project = _pinhole(view_deg, distance_mm=400.0, focal_px=2400.0)
    camera = imaging.PinholeCamera(2400.0)
    pose = _pose(project, view_deg, camera)
    assert pose.model == "pinhole" and pose.rms_error_px < 1e-6
    assert pose.implied_view_deg == pytest.approx(view_deg, abs=0.5)  # seen from the markers
    for name, (outline, beta2) in WEDGES.items():
        placed = np.asarray(imaging.face_polygon(pose, outline, beta2))
        assert np.abs(placed - project(_lift(outline, beta2))).max() < 1e-5, name


@pytest.mark.parametrize("view_deg", [-60.0, 0.0, 15.0])
def test_pixel_view_angles_are_the_rays_from_the_face_points(view_deg: float) -> None:
    """`pixel_view_deg` back-projects pixels onto the face and measures the view angle from
    there: against points on the face projected by the test's own pinhole (exact, 1e-6 deg)."""
    project = _pinhole(view_deg, distance_mm=400.0, focal_px=2400.0)
    pose = _pose(project, view_deg, imaging.PinholeCamera(2400.0))
    rng = np.random.default_rng(3)
    for name, (outline, beta2) in WEDGES.items():
        xy = np.asarray(outline, float)
        pts = _lift(rng.uniform(xy.min(axis=0), xy.max(axis=0), size=(50, 2)), beta2)
        pts[:, 2] = (pts[:, 0] - xy[:, 0].min()) * math.tan(math.radians(beta2))
        d = project.centre - pts
        want = np.degrees(np.arctan2(d[:, 0], d[:, 2]))
        got = imaging.pixel_view_deg(pose, outline, beta2, project(pts))
        assert np.abs(got - want).max() < 1e-6, name


def test_roi_view_angle_is_the_pixel_mean_not_the_face_centre() -> None:
    """Through a pinhole the near part of a tilted face covers more pixels: the view angle
    averaged over the face's pixels (what an ROI's mean measures) differs from the one at the
    outline's centre. `view_parallax_deg` with the pixels gives the brute-force pixel mean
    (every pixel centre inside the projected face, cast onto it by the test's rays) to 1e-6 deg,
    and that differs from the centre's by more than 0.05 deg here (60 deg face, 400 mm)."""
    view_deg = 0.0
    project = _pinhole(view_deg, distance_mm=400.0, focal_px=2400.0)
    pose = _pose(project, view_deg, imaging.PinholeCamera(2400.0))
    outline, beta2 = WEDGES["w60"]
    polygon = project(_lift(outline, beta2))
    lo, hi = np.floor(polygon.min(axis=0)), np.ceil(polygon.max(axis=0))
    gx, gy = np.meshgrid(np.arange(lo[0], hi[0] + 1), np.arange(lo[1], hi[1] + 1))
    grid = np.column_stack([gx.ravel(), gy.ravel()])
    edge = np.roll(polygon, -1, axis=0) - polygon  # a convex quadrilateral: one side of each
    side = edge[:, 0] * (grid[:, None, 1] - polygon[:, 1]) - edge[:, 1] * (
        grid[:, None, 0] - polygon[:, 0]
    )
    pixels = grid[(side > 0).all(axis=1) | (side < 0).all(axis=1)]
    hits = _face_hits(project, outline, beta2, pixels)
    d = project.centre - hits
    markers = np.array([c for c in MARKERS.values()], float).reshape(-1, 2).mean(axis=0)
    dm = project.centre - np.append(markers, 0.0)
    want = np.degrees(np.arctan2(d[:, 0], d[:, 2])).mean() - math.degrees(math.atan2(dm[0], dm[2]))
    got = imaging.view_parallax_deg(pose, LAYOUT, outline, beta2, pixels)
    at_centre = imaging.view_parallax_deg(pose, LAYOUT, outline, beta2)
    assert got == pytest.approx(want, abs=1e-6)
    assert abs(got - at_centre) > 0.05, (got, at_centre)


def test_close_perspective_camera_without_intrinsics_is_refused() -> None:
    project = _pinhole(-40.0, distance_mm=250.0, focal_px=1500.0)
    with pytest.raises(imaging.ImagingError) as err:
        _pose(project, -40.0)
    msg = str(err.value)
    assert "'p.dng'" in msg and "affine camera" in msg and "focal_length_px" in msg


def test_affine_camera_error_for_a_pinhole_is_parallax() -> None:
    """The affine camera's assumption, quantified (docs/imaging.md §3-D placement): for a
    pinhole at distance D looking straight down (the markers fit an affine map exactly, so
    nothing is refused) a point h above the base at distance L from the optical axis is
    misplaced by its parallax, px_per_mm x h x L / D; a 10 m camera is within about a pixel."""
    outline, beta2 = WEDGES["w60"]
    pts = _lift(outline, beta2)  # the top corners are 34.6 mm high, 22 and 41 mm off the axis
    parallax = np.hypot(pts[:, 0] - 10, pts[:, 1] - 40) * pts[:, 2]  # L x h (mm^2)
    for distance in (1000.0, 10000.0):
        project = _pinhole(0.0, distance_mm=distance, focal_px=8.0 * distance)  # 8 px/mm
        pose = _pose(project, 0.0)
        placed = np.asarray(imaging.face_polygon(pose, outline, beta2))
        error = np.linalg.norm(placed - project(pts), axis=1)
        assert error == pytest.approx(8.0 * parallax / distance, rel=0.1, abs=0.05), distance
    assert error.max() < 1.5  # at 10 m


def test_view_deg_of_the_wrong_sign_is_refused_with_a_pinhole() -> None:
    project = _pinhole(-35.0, distance_mm=400.0, focal_px=2400.0)
    with pytest.raises(imaging.ImagingError) as err:
        _pose(project, +35.0, imaging.PinholeCamera(2400.0))
    msg = str(err.value)
    assert "camera at -35" in msg and "view_deg = 35" in msg and "sign" in msg


def test_view_deg_that_disagrees_with_the_foreshortening_is_refused() -> None:
    with pytest.raises(imaging.ImagingError) as err:
        _pose(_ortho(-50.0), -20.0)
    msg = str(err.value)
    assert "foreshortened as seen from 50.0 deg" in msg and "view_deg = -20" in msg


def test_mirrored_layout_is_refused() -> None:
    mirrored = imaging.MarkerLayout({i: [(x, -y) for x, y in c] for i, c in MARKERS.items()})
    with pytest.raises(imaging.ImagingError, match=r"mirrored .*right-handed"):
        _pose(_ortho(-30.0), -30.0, layout=mirrored)
    with pytest.raises(imaging.ImagingError, match="below the base"):
        project = _pinhole(-30.0, distance_mm=400.0, focal_px=2400.0)
        _pose(project, -30.0, imaging.PinholeCamera(2400.0), layout=mirrored)


def test_faces_on_the_base_use_the_homography_of_any_camera() -> None:
    project = _pinhole(-50.0, distance_mm=200.0, focal_px=1200.0)  # strong perspective
    pose = imaging.fit_camera_pose(
        _detection(project), LAYOUT, photo="p.dng", image_size=SIZE, rising=False
    )
    assert pose.model == "homography"
    outline = [(0, 0), (20, 0), (20, 20)]
    placed = np.asarray(imaging.face_polygon(pose, outline))
    assert np.abs(placed - project(_lift(outline, 0))).max() < 1e-3  # findHomography's precision


def test_hidden_faces_are_found() -> None:
    """A low wedge behind a tall one (along x) is hidden from the downhill side."""
    front = ([(0, 0), (20, 0), (20, 20), (0, 20)], 60.0)  # its top edge is 34.6 mm high
    back = ([(25, 0), (45, 0), (45, 20), (25, 20)], 10.0)
    occluders = [("front", *front)]
    for view, expect_hidden in ((-45.0, True), (0.0, False), (20.0, False)):
        pose = _pose(_ortho(view), view)
        poly = imaging.face_polygon(pose, *back)
        roi = imaging.roi_mask(poly, SIZE[::-1], 2, photo="p", wedge="back")
        fraction, by = imaging._placement.hidden_fraction(pose, *back, occluders, roi)
        assert (fraction > 0.5) == expect_hidden and (by == "front") == expect_hidden, view


def _photo(project, faces: dict, tmp_path, name: str = "p.dng"):
    """A synthetic photo of `faces` (name -> (outline, beta2)) and the markers seen by
    `project`; returns the decoded frame and the true face polygons (px)."""
    import cv2

    from stairfit.imaging import synthetic

    base = np.array([c for m in MARKERS.values() for c in m], float)
    hom, _ = cv2.findHomography(base, project(_lift(base, 0.0)))
    true = {n: project(_lift(o, b)) for n, (o, b) in faces.items()}
    exposure = imaging.Exposure(1 / 100, 5.6, 100)
    photo = synthetic.render_photo(
        SIZE, {n: p.tolist() for n, p in true.items()}, {n: np.full(3, 4e6) for n in faces},
        exposure, background=np.full(3, 4e5), markers=LAYOUT, plane_to_image=hom,
        marker_white=np.full(3, 3e6), marker_black=np.full(3, 1e5), seed=2,
    )  # fmt: skip
    return imaging.decode_raw(photo.write_dng(tmp_path / name)), true


def _spec(frame, faces: dict, view_deg: float, camera=None) -> imaging.PhotoSpec:
    return imaging.PhotoSpec(
        frame.path, faces_mm={n: o for n, (o, _) in faces.items()}, markers=LAYOUT,
        face_angles_deg={n: b for n, (_, b) in faces.items()}, view_deg=view_deg, camera=camera,
    )  # fmt: skip


def test_pinhole_photo_places_faces_within_a_pixel(tmp_path) -> None:
    """Detected markers, a pinhole 400 mm away: within a pixel of the true faces; the same photo
    without the focal length is refused (too close for a parallel projection)."""
    project = _pinhole(-35.0, distance_mm=400.0, focal_px=2400.0)
    frame, true = _photo(project, WEDGES, tmp_path)
    spec = _spec(frame, WEDGES, -35.0, imaging.PinholeCamera(2400.0))
    result = imaging.measure_frame(frame, spec, imaging.ExtractionSettings(erode_px=3))
    assert result.placement is not None and result.placement.model == "pinhole"
    for name, poly in true.items():
        placed = np.asarray(result.rois[name].polygon)
        assert np.linalg.norm(placed - poly, axis=1).max() < 1.0, name
    assert {r.placement for r in result.rows} == {"pinhole"}
    with pytest.raises(imaging.ImagingError, match=r"affine camera .*focal_length_px"):
        imaging.measure_frame(frame, _spec(frame, WEDGES, -35.0), imaging.ExtractionSettings())


def test_hidden_face_is_refused_in_a_photo(tmp_path) -> None:
    faces = {
        "front": ([(0, 0), (20, 0), (20, 20), (0, 20)], 60.0),
        "back": ([(25, 0), (45, 0), (45, 20), (25, 20)], 10.0),
    }
    frame, _ = _photo(_ortho(-30.0), faces, tmp_path)
    with pytest.raises(imaging.ImagingError) as err:
        imaging.measure_frame(frame, _spec(frame, faces, -30.0), imaging.ExtractionSettings())
    msg = str(err.value)
    assert "'p.dng', wedge 'back'" in msg and "hidden behind wedge 'front'" in msg
    assert "roi_px" in msg


def test_a_face_too_thin_to_measure_is_not_checked_for_being_hidden(tmp_path) -> None:
    """The hidden-face check gets the measured faces' ROIs only (a face too thin to measure is
    a flagged row without one): it checks those and skips the rest, where it failed on the
    missing ROI before."""
    from stairfit.imaging._pipeline import _check_hidden, _eroded_rois, place_faces

    faces = {
        "front": ([(0, 0), (20, 0), (20, 20), (0, 20)], 60.0),
        "back": ([(25, 0), (45, 0), (45, 20), (25, 20)], 10.0),
    }
    frame, _ = _photo(_ortho(-30.0), faces, tmp_path)
    spec = _spec(frame, faces, -30.0)
    _, pose, placed = place_faces(frame, spec, None)
    polygons = {n: (p, "markers") for n, p in placed.items()}
    rois, _, _ = _eroded_rois(spec, polygons, (frame.height, frame.width),
                              imaging.ExtractionSettings())  # fmt: skip
    _check_hidden(spec, pose, {"front": rois["front"]})  # 'back' (hidden) not measured: no error
    with pytest.raises(imaging.ImagingError, match="hidden behind wedge 'front'"):
        _check_hidden(spec, pose, rois)
