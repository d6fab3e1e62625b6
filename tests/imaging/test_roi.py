"""ROIs (issue 3): pixel convention, erosion, bad polygons, and placement from ArUco markers."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from stairfit import imaging
from stairfit.imaging import synthetic

EXPOSURE = imaging.Exposure(exposure_time_s=1 / 100, f_number=8.0, iso=200)
SHAPE = (400, 600)  # (height, width)

# A specimen base 140 x 80 mm with four 20 mm markers in its corners and three wedge faces.
LAYOUT = imaging.MarkerLayout(
    {
        0: [(0, 0), (20, 0), (20, 20), (0, 20)],
        1: [(120, 0), (140, 0), (140, 20), (120, 20)],
        2: [(0, 60), (20, 60), (20, 80), (0, 80)],
        3: [(120, 60), (140, 60), (140, 80), (120, 80)],
    }
)
FACES_MM = {
    "w10": [(27, 5), (52, 5), (52, 35), (27, 35)],
    "w30": [(57, 5), (82, 5), (82, 35), (57, 35)],
    "w60": [(87, 5), (112, 5), (112, 35), (87, 35)],
}
# base plane (mm) -> image (px): a mild perspective view
PLANE_TO_IMAGE = cv2.getPerspectiveTransform(
    np.float32([[0, 0], [140, 0], [140, 80], [0, 80]]),
    np.float32([[25, 40], [575, 55], [560, 370], [40, 380]]),
)


def _to_px(poly_mm: list, hom: np.ndarray = PLANE_TO_IMAGE) -> list:
    pts = cv2.perspectiveTransform(np.asarray(poly_mm, float).reshape(-1, 1, 2), hom)
    return [tuple(p) for p in pts.reshape(-1, 2)]


def _marker_photo(tmp_path, layout=LAYOUT, seed=3, name="markers.dng"):
    faces_px = {n: _to_px(p) for n, p in FACES_MM.items()}
    radiance = {n: np.array([800.0, 1500.0, 1100.0]) * EXPOSURE.scale for n in faces_px}
    photo = synthetic.render_photo(
        (SHAPE[1], SHAPE[0]),
        faces_px,
        radiance,
        EXPOSURE,
        background=np.full(3, 3000.0) * EXPOSURE.scale,
        markers=layout,
        plane_to_image=PLANE_TO_IMAGE,
        seed=seed,
    )
    return photo, photo.write_dng(tmp_path / name)


# --- rasterisation and erosion -------------------------------------------------------------------


def test_pixel_centres_are_integer_coordinates() -> None:
    # cv2.fillPoly includes the pixels the outline passes through: an axis-aligned rectangle
    # with integer corners covers (x1 - x0 + 1) x (y1 - y0 + 1) pixels, starting at (x0, y0).
    roi = imaging.roi_mask([(10, 10), (40, 10), (40, 30), (10, 30)], SHAPE, 0, photo="p", wedge="w")
    assert (roi.y0, roi.x0, roi.mask.shape) == (10, 10, (21, 31))
    assert roi.n_pixels == roi.n_before_erosion == 21 * 31


def test_erosion_removes_erode_px_on_every_side() -> None:
    roi = imaging.roi_mask([(10, 10), (40, 10), (40, 30), (10, 30)], SHAPE, 3, photo="p", wedge="w")
    assert (roi.y0, roi.x0, roi.mask.shape) == (13, 13, (15, 25))
    assert roi.mask.all()
    assert roi.n_before_erosion == 21 * 31


def test_image_border_is_not_a_face_edge() -> None:
    # A polygon reaching the image border (-0.5) is not eroded from that side.
    poly = [(-0.5, -0.5), (40, -0.5), (40, 30), (-0.5, 30)]
    roi = imaging.roi_mask(poly, SHAPE, 3, photo="p", wedge="w")
    assert (roi.y0, roi.x0, roi.mask.shape) == (0, 0, (28, 38))


def test_roi_outside_the_image_names_photo_and_wedge() -> None:
    poly = [(500, 300), (650, 300), (650, 390), (500, 390)]
    with pytest.raises(imaging.ImagingError) as err:
        imaging.roi_mask(poly, SHAPE, 8, photo="side.dng", wedge="w45")
    msg = str(err.value)
    assert "'side.dng'" in msg and "'w45'" in msg and "(650.0, 300.0)" in msg
    assert "outside the image (600 x 400 px" in msg


def test_roi_empty_after_erosion_names_photo_and_wedge() -> None:
    poly = [(100, 100), (110, 100), (110, 110), (100, 110)]  # 11 x 11 px
    imaging.roi_mask(poly, SHAPE, 5, photo="a.dng", wedge="w10")  # 1 px survives
    with pytest.raises(imaging.ImagingError) as err:
        imaging.roi_mask(poly, SHAPE, 6, photo="a.dng", wedge="w10")
    msg = str(err.value)
    assert "'a.dng'" in msg and "'w10'" in msg and "empty after eroding it by 6 px" in msg
    assert "121 px before erosion" in msg and "erode_px" in msg


def test_bad_polygon_is_rejected() -> None:
    with pytest.raises(imaging.ImagingError, match="at least 3 finite"):
        imaging.PhotoSpec("a.dng", rois={"w": [(0, 0), (1, 1)]})
    with pytest.raises(imaging.ImagingError, match="at least 3 finite"):
        imaging.PhotoSpec("a.dng", rois={"w": [(0, 0), (1, float("nan")), (2, 2)]})


def test_overlapping_rois_are_refused(tmp_path) -> None:
    path = synthetic.write_dng(tmp_path / "o.dng", np.full((100, 100), 2000, np.uint16))
    frame = imaging.decode_raw(path)
    spec = imaging.PhotoSpec(
        path,
        rois={"a": [(0, 0), (60, 0), (60, 60), (0, 60)], "b": [(30, 30), (99, 30), (99, 99)]},
        exposure_time_s=1.0,
        f_number=1.0,
        iso=100,
    )
    with pytest.raises(imaging.ImagingError, match=r"'o\.dng', wedges 'a' and 'b'.*overlap"):
        imaging.measure_frame(frame, spec, imaging.ExtractionSettings(erode_px=2))


# --- markers -------------------------------------------------------------------------------------


def test_markers_are_detected_at_their_true_corners(tmp_path) -> None:
    photo, path = _marker_photo(tmp_path)
    det = imaging.detect_markers(imaging.decode_raw(path), "DICT_4X4_50")
    assert sorted(det.ids) == [0, 1, 2, 3]
    err = np.stack(
        [c - photo.marker_corners_px[i] for i, c in zip(det.ids, det.corners_px, strict=True)]
    )
    # Markers are ~80 px (cells ~13 px) and detected on the half-resolution image with OpenCV's
    # sub-pixel refinement; single corners scatter by about 1 px, without a systematic offset.
    assert np.sqrt(np.mean(np.sum(err**2, axis=-1))) < 1.5
    assert np.all(np.abs(err.reshape(-1, 2).mean(axis=0)) < 0.3)


def test_marker_placement_recovers_the_true_rois(tmp_path) -> None:
    photo, path = _marker_photo(tmp_path)
    frame = imaging.decode_raw(path)
    spec = imaging.PhotoSpec(path, faces_mm=FACES_MM, markers=LAYOUT)
    result = imaging.measure_frame(frame, spec, imaging.ExtractionSettings())
    assert result.placement is not None
    assert result.placement.ids == (0, 1, 2, 3)
    assert result.placement.rms_error_px < 1.5
    for name, poly_mm in FACES_MM.items():
        placed = np.asarray(result.rois[name].polygon)
        true = np.asarray(_to_px(poly_mm))
        # the homography averages 16 corners: every face vertex lands within a pixel
        assert np.max(np.linalg.norm(placed - true, axis=1)) < 1.0, name
        assert result.rois[name].source == "markers"
    rows = result.rows
    assert {r.roi_source for r in rows} == {"markers"}
    assert all(r.n_markers == 4 and r.reprojection_error_px < 1.5 for r in rows)
    # and the measured values are the rendered ones (errors are checked in the pull tests)
    for r in rows:
        expected = photo.expected[r.wedge][imaging.CHANNELS.index(r.channel)]
        assert r.value == pytest.approx(expected, rel=0.01)


def test_too_few_markers_is_a_clear_error(tmp_path) -> None:
    only_one = imaging.MarkerLayout({0: LAYOUT.corners_mm()[0].tolist()})
    _, path = _marker_photo(tmp_path, layout=only_one, name="one_marker.dng")
    frame = imaging.decode_raw(path)
    spec = imaging.PhotoSpec(path, faces_mm=FACES_MM, markers=LAYOUT)
    with pytest.raises(imaging.ImagingError) as err:
        imaging.measure_frame(frame, spec, imaging.ExtractionSettings())
    msg = str(err.value)
    assert "'one_marker.dng'" in msg and "found 1 of the layout's 4" in msg
    assert "at least 2" in msg and "'w10', 'w30', 'w60'" in msg and "roi_px" in msg


def test_wrong_dictionary_finds_no_markers(tmp_path) -> None:
    _, path = _marker_photo(tmp_path)
    layout = imaging.MarkerLayout(LAYOUT.markers, dictionary="DICT_6X6_250")
    spec = imaging.PhotoSpec(path, faces_mm=FACES_MM, markers=layout)
    with pytest.raises(imaging.ImagingError, match=r"found 0 of .*DICT_6X6_250"):
        imaging.measure_frame(imaging.decode_raw(path), spec, imaging.ExtractionSettings())


def test_misplaced_marker_in_the_layout_is_refused(tmp_path) -> None:
    _, path = _marker_photo(tmp_path)
    corners = LAYOUT.corners_mm()
    corners[3] = corners[3] + (8.0, 0.0)  # the layout puts marker 3 8 mm too far right
    layout = imaging.MarkerLayout({k: v.tolist() for k, v in corners.items()})
    spec = imaging.PhotoSpec(path, faces_mm=FACES_MM, markers=layout)
    with pytest.raises(imaging.ImagingError) as err:
        imaging.measure_frame(imaging.decode_raw(path), spec, imaging.ExtractionSettings())
    msg = str(err.value)
    assert "misfits the detected corners" in msg and "px RMS (limit 3.0 px)" in msg


def test_pixel_rois_win_over_faces_and_need_no_markers(tmp_path) -> None:
    _, path = _marker_photo(tmp_path)
    rois = {n: _to_px(p) for n, p in FACES_MM.items()}
    spec = imaging.PhotoSpec(path, rois=rois, faces_mm=FACES_MM, markers=LAYOUT)
    assert spec.placed_names() == ()
    result = imaging.measure_frame(imaging.decode_raw(path), spec, imaging.ExtractionSettings())
    assert result.detection is None and result.placement is None
    assert {r.roi_source for r in result.rows} == {"polygon"}
    assert all(r.reprojection_error_px is None for r in result.rows)


def test_layout_validation() -> None:
    with pytest.raises(imaging.ImagingError, match="exactly 4 corners"):
        imaging.MarkerLayout({0: [(0, 0), (1, 0), (1, 1)]})
    with pytest.raises(imaging.ImagingError, match="unknown ArUco dictionary 'DICT_4X4_5'"):
        imaging.MarkerLayout({0: [(0, 0), (1, 0), (1, 1), (0, 1)]}, dictionary="DICT_4X4_5")
    with pytest.raises(imaging.ImagingError, match="no marker layout"):
        imaging.PhotoSpec("a.dng", faces_mm=FACES_MM)
