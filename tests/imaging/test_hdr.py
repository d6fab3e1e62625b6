"""HDR brackets (imaging/_hdr.py, issue 12): several exposures of one view merged, checked
against the known truth.

Synthetic photos (`stairfit.imaging.synthetic`) of one view in three exposures that share their
texture, from a few DN to far above the clip level; the merged ROI means are compared with the
radiance the photos were rendered from, in units of the reported standard errors. The bracket's
markers come from the exposure that shows them; the cache follows every member. The photos'
layout and helpers are tests/imaging/test_calibration.py's.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from test_calibration import EXPOSURE, FACES, SETTINGS, SIZE, _measure, _pulls, _write_flats

from stairfit import imaging
from stairfit.imaging import synthetic

BRACKET = (1.0, 4.0, 16.0)  # exposure times relative to the reference (the first file)


def _bracket(folder: Path, view: int, radiance: dict, texture: float = 0.03) -> tuple[list, dict]:
    """One view in three exposures that share their texture; paths and the untextured ROI
    means (the standard errors cover noise and texture)."""
    paths, expected = [], None
    for k, f in enumerate(BRACKET):
        exposure = imaging.Exposure(EXPOSURE.exposure_time_s * f, EXPOSURE.f_number, EXPOSURE.iso)
        photo = synthetic.render_photo(
            SIZE, FACES, radiance, exposure, background=np.full(3, 20 * EXPOSURE.scale),
            texture_amplitude=texture, texture_sigma_px=1.0, vignetting=0.04,
            seed=1000 * view + k, texture_seed=view,
        )  # fmt: skip
        paths.append(photo.write_dng(folder / f"v{view}_{k}.dng"))
        expected = photo.expected_untextured if expected is None else expected
    return paths, expected


def test_bracket_merge_gives_honest_errors_across_clipping(tmp_path: Path) -> None:
    """Faces from 3 DN to far above the clip level of the longest exposure: the merged means
    agree with the truth within their block standard errors, none is flagged."""
    rng = np.random.default_rng(11)
    specs, truth = [], {}
    # reference DN above black: the longest exposure (x16) clips above about 1000 DN here;
    # f3 sits right at its HDR_HIGH threshold, so its pixels mix exposures
    levels = {"f0": 3.0, "f1": 40.0, "f2": 400.0, "f3": 930.0, "f4": 2000.0, "f5": 10000.0}
    for view in range(3):
        radiance = {f: levels[f] * rng.uniform(0.9, 1.1, 3) * EXPOSURE.scale for f in FACES}
        paths, expected = _bracket(tmp_path, view, radiance)
        specs.append(imaging.PhotoSpec(paths[0], rois=FACES, bracket=tuple(paths[1:])))
        truth[paths[0].name] = expected
    rows = list(imaging.measure_photos(specs, SETTINGS, max_workers=1))
    assert all(r.flag == "" and r.saturated_fraction == 0 for r in rows)
    assert all(r.radiometry == "bracket(3)" for r in rows)
    assert all(r.exposure_time_s == EXPOSURE.exposure_time_s for r in rows)  # the reference
    pulls = _pulls(rows, truth)
    # 54 pulls against the untextured means
    assert 0.7 < pulls.std(ddof=1) < 1.35
    assert abs(pulls.mean()) < 0.45
    for face in ("f0", "f3", "f5"):  # near black, mixed, clipped in the longer exposures
        p = np.array([(r.value - truth[r.photo][r.wedge][imaging.CHANNELS.index(r.channel)])
                      / r.stderr for r in rows if r.wedge == face])  # fmt: skip
        assert np.abs(p).max() < 4, (face, p)


def test_bracket_is_more_precise_than_its_reference_exposure(tmp_path: Path) -> None:
    radiance = {f: np.full(3, 60.0) * EXPOSURE.scale for f in FACES}
    paths, _ = _bracket(tmp_path, 0, radiance, texture=0.0)
    single = _measure(paths[:1], None)
    merged = list(
        imaging.measure_photos(
            [imaging.PhotoSpec(paths[0], rois=FACES, bracket=tuple(paths[1:]))], SETTINGS,
            max_workers=1,
        )
    )  # fmt: skip
    ratio = np.array([m.stderr / s.stderr for m, s in zip(merged, single, strict=True)])
    # 21x the exposure in all: shot and read noise of the sum fall by about sqrt(21) or more
    assert np.all(ratio < 0.35), ratio


def test_bracket_members_must_match(tmp_path: Path) -> None:
    radiance = {f: np.full(3, 60.0) * EXPOSURE.scale for f in FACES}
    paths, _ = _bracket(tmp_path, 0, radiance)
    other = synthetic.render_photo(
        (400, 300), {}, {}, EXPOSURE, background=np.full(3, 50 * EXPOSURE.scale), seed=1
    ).write_dng(tmp_path / "other.dng")
    spec = imaging.PhotoSpec(paths[0], rois=FACES, bracket=(other,))
    with pytest.raises(imaging.ImagingError, match=r"photo 'v0_0.dng': bracket member 'other.dng'"):
        imaging.measure_photos([spec], SETTINGS, max_workers=1)


def test_bracket_member_without_exposure_names_the_file(tmp_path: Path) -> None:
    radiance = {f: np.full(3, 60.0) * EXPOSURE.scale for f in FACES}
    paths, _ = _bracket(tmp_path, 0, radiance)
    mosaic = imaging.decode_raw(paths[1]).data
    bare = synthetic.write_dng(tmp_path / "bare.dng", mosaic, black_level=1024, white_level=16383)
    spec = imaging.PhotoSpec(paths[0], rois=FACES, bracket=(bare,))
    with pytest.raises(imaging.ImagingError) as err:
        imaging.measure_photos([spec], SETTINGS, max_workers=1)
    text = str(err.value)
    assert "photo 'v0_0.dng', bracket file 'bare.dng'" in text and "one value per file" in text


def test_bracket_markers_come_from_the_exposure_that_shows_them(tmp_path: Path) -> None:
    """Dark markers beside bright faces: too faint in the short reference exposure to place the
    faces (3 DN of contrast: not found, or found with corners too noisy for a consistent
    camera), clear in the long one; placement succeeds from those, to well under a pixel."""
    layout = imaging.MarkerLayout(
        {0: [(0, 0), (20, 0), (20, 20), (0, 20)], 1: [(120, 0), (140, 0), (140, 20), (120, 20)],
         2: [(0, 60), (20, 60), (20, 80), (0, 80)], 3: [(120, 60), (140, 60), (140, 80), (120, 80)]}
    )  # fmt: skip
    hom = cv2.getPerspectiveTransform(
        np.float32([[0, 0], [140, 0], [140, 80], [0, 80]]),
        np.float32([[25, 40], [775, 55], [760, 570], [40, 580]]),
    )
    face_mm = {"w": [(40, 20), (100, 20), (100, 60), (40, 60)]}
    face_px = {
        "w": [tuple(p) for p in cv2.perspectiveTransform(
            np.float32(face_mm["w"]).reshape(-1, 1, 2), hom).reshape(-1, 2)]
    }  # fmt: skip
    paths = []
    for k, f in enumerate((1.0, 64.0)):
        exposure = imaging.Exposure(EXPOSURE.exposure_time_s * f, EXPOSURE.f_number, EXPOSURE.iso)
        photo = synthetic.render_photo(
            SIZE, face_px, {"w": np.full(3, 4000 * EXPOSURE.scale)}, exposure,
            background=np.full(3, 1.0 * EXPOSURE.scale), markers=layout, plane_to_image=hom,
            marker_white=np.full(3, 3 * EXPOSURE.scale),
            marker_black=np.full(3, 0.1 * EXPOSURE.scale),
            seed=70 + k, texture_seed=70,
        )  # fmt: skip
        paths.append(photo.write_dng(tmp_path / f"m{k}.dng"))
    single = imaging.PhotoSpec(paths[0], faces_mm=face_mm, markers=layout)
    with pytest.raises(imaging.ImagingError, match=r"ArUco markers|misfits the detected corners"):
        imaging.measure_photos([single], SETTINGS, max_workers=1)
    spec = imaging.PhotoSpec(paths[0], faces_mm=face_mm, markers=layout, bracket=(paths[1],))
    rows = list(imaging.measure_photos([spec], SETTINGS, max_workers=1))
    assert rows[0].roi_source == "markers" and rows[0].n_markers == 4
    assert rows[0].reprojection_error_px < 0.5
    assert rows[0].value == pytest.approx(4000 * EXPOSURE.scale, rel=0.02)


def test_the_cache_follows_bracket_members_and_calibration_frames(tmp_path: Path) -> None:
    """A changed bracket member or calibration frame measures the photo again; nothing
    changed, the cached rows come back."""
    radiance = {f: np.full(3, 300.0) * EXPOSURE.scale for f in FACES}
    paths, _ = _bracket(tmp_path, 0, radiance)
    flats = _write_flats(tmp_path, 1, 0.1)

    def measure() -> list:
        spec = imaging.PhotoSpec(
            paths[0], rois=FACES, bracket=tuple(paths[1:]),
            calibration=imaging.calibration_spec(flat_field=flats),
        )  # fmt: skip
        return list(imaging.measure_photos([spec], SETTINGS, cache=tmp_path / "m.csv"))

    first = measure()
    assert measure() == first  # reused from the cache, bit for bit
    synthetic.render_photo(
        SIZE, FACES, radiance, EXPOSURE, background=np.full(3, 20 * EXPOSURE.scale), seed=99
    ).write_dng(paths[2])  # another exposure of the bracket
    second = measure()
    assert second[0].photo_sha256 != first[0].photo_sha256
    assert second[0].settings_key == first[0].settings_key
    _write_flats(tmp_path, 1, 0.12)  # the flat-field photo is taken again
    third = measure()
    assert third[0].settings_key != second[0].settings_key
    assert third[0].value != second[0].value


def test_a_brackets_markers_come_from_its_best_consistent_exposure() -> None:
    """`_best_exposure_pose`: of the exposures whose markers give a camera, most markers used
    wins, then the smaller RMS error; when none gives one, the error of the exposure that found
    the most markers is raised (the earlier on a tie)."""
    from stairfit.imaging._pipeline import _best_exposure_pose

    def det(n: int, tag: float) -> imaging.MarkerDetection:
        return imaging.MarkerDetection(tuple(range(n)), np.full((n, 4, 2), tag), "DICT_4X4_50")

    def pose(d: imaging.MarkerDetection, used: int, rms: float) -> imaging.CameraPose:
        return imaging.CameraPose("homography", np.eye(3), rms, d.ids[:used], (rms,) * used)

    rules = {0.0: None, 1.0: (3, 0.1), 2.0: (4, 0.4), 3.0: (4, 0.2)}  # by tag: (used, rms)

    def fit(d: imaging.MarkerDetection) -> imaging.CameraPose:
        rule = rules[float(d.corners_px[0, 0, 0])]
        if rule is None:
            raise imaging.ImagingError(f"misfit of {len(d.ids)} markers")
        return pose(d, *rule)

    dets = [det(6, 0.0), det(3, 1.0), det(4, 2.0), det(4, 3.0)]
    chosen, camera = _best_exposure_pose(dets, fit)
    assert chosen is dets[3] and camera.rms_error_px == 0.2
    rules.update({1.0: None, 2.0: None, 3.0: None})
    with pytest.raises(imaging.ImagingError, match="misfit of 6 markers"):
        _best_exposure_pose(dets, fit)
    with pytest.raises(imaging.ImagingError, match="misfit of 4 markers"):
        _best_exposure_pose(dets[1:], fit)
