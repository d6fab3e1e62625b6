"""Faces whose layer lines the camera resolves (issue 45), on photos of tests/striped_photos.py.

That renderer shares nothing with `stairfit.imaging`: its stripes are a Fourier series averaged
over each pixel's square and a lens blur, aliased by the pixel grid and the RGGB mosaic, and
its truths come from the continuous pattern (the layer-period average times the lamp's mean
over the ROI), never from pixels. The first tests check the renderer itself; the rest measure
its photos with the library (`measure_frame`, `roi_channel_stats`) or the command line
(`stairfit measure`) and compare with the truths over many faces, seeds and noise levels.

Bounds (the issue's "Done when", on this set): at least 90% of the faces' rows used;
measured / truth within 0.5% in the median and 2% at worst; pulls against the truth with a
standard deviation in [0.8, 1.25] and none beyond 4; a grey face's channel split below 0.5%;
markers placed within 0.2 px RMS. Larger grids: the slow tests and benchmarks/bench_striped.py.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from collections import Counter
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
import striped_photos as sp

from stairfit import imaging
from stairfit.imaging import _extract, _markers, _noise, _roi

EXPOSURE = {"exposure_time_s": 0.01, "f_number": 4.0, "iso": 100.0}
DN_PER_RADIANCE = 0.01 * 1.0 / 4.0**2  # t (ISO / 100) / N^2: relative radiance = DN / this


# --- the renderer, on its own ---------------------------------------------------------------------


def test_pixel_value_is_the_pattern_averaged_over_the_pixel() -> None:
    """The renderer's per-harmonic sinc average equals a brute-force average of the continuous
    pattern over each pixel's square (48 x 48 points), for periods 1-8 px at any angle."""
    rng = np.random.default_rng(0)
    for _ in range(6):
        face = sp.random_face(rng, (50.0, 50.0), 60.0)
        x = rng.uniform(35, 65, 8).round()
        y = rng.uniform(35, 65, 8).round()
        fast = sp.pixel_pattern(face, x, y, blur_px=0.0)
        o = (np.arange(48) + 0.5) / 48 - 0.5
        ox, oy = np.meshgrid(o, o)
        slow = np.empty_like(fast)
        for j in range(x.size):
            s, _, _, _ = sp.face_coordinates(face, x[j] + ox.ravel(), y[j] + oy.ravel())
            slow[:, j] = face.pattern.values(s / face.layer_mm + face.phase).mean(axis=1)
        scale = face.pattern.mean()[:, None]
        assert np.abs(fast - slow).max() / scale.max() < 2e-3, face.period_px


def test_sensor_noise_is_shot_plus_read() -> None:
    """An unstriped grey face: each channel's pixel variance is read^2 + level / gain."""
    rng = np.random.default_rng(1)
    flat = sp.Pattern(contrast=0.0, specular=0.0)
    face = dataclasses.replace(
        sp.random_face(rng, (150.0, 150.0), 150.0, graded=False), pattern=flat
    )
    sensor = sp.Sensor(level_dn=800.0, gain_e_per_dn=2.0, read_noise_dn=4.0, blur_px=0.0)
    r = sp.render(sp.PhotoSpec((300, 300), (face,), sensor), rng)
    roi = imaging.roi_mask(
        tuple(map(tuple, face.outline_px())), (300, 300), 4, photo="p", wedge="f"
    )
    rows, cols = roi.box()
    data = r.mosaic[rows, cols].astype(float) - sp.BLACK_DN
    yy, xx = np.mgrid[rows, cols]
    for c in range(3):
        sel = roi.mask & (sp.CFA[yy % 2, xx % 2] == c)
        level = face.light * sp.QE[c] * sensor.level_dn
        expected = sensor.read_noise_dn**2 + level / sensor.gain_e_per_dn + 1 / 12  # rounding
        assert data[sel].var() == pytest.approx(expected, rel=0.1)
        assert data[sel].mean() == pytest.approx(level, rel=0.01)


# --- measuring: helpers ---------------------------------------------------------------------------


def _measure(rendered: sp.Rendered, settings: imaging.ExtractionSettings | None = None) -> list:
    """measure_frame on a rendered photo, its faces as roi_px polygons (orientation unknown):
    per row (face, channel, row, truth in relative radiance)."""
    frame = sp.frame(rendered)
    rois = {f"f{k}": tuple(map(tuple, ft.outline_px)) for k, ft in enumerate(rendered.faces)}
    spec = imaging.PhotoSpec("striped.dng", rois=rois, **EXPOSURE)
    fm = imaging.measure_frame(frame, spec, settings or imaging.ExtractionSettings())
    out = []
    for row in fm.rows:
        k, c = int(row.wedge[1:]), "RGB".index(row.channel)
        roi = fm.rois[row.wedge]
        truth = (
            rendered.truth_dc(k, roi.mask, roi.y0, roi.x0)[c] / DN_PER_RADIANCE
            if roi.n_pixels
            else math.nan
        )
        out.append((k, c, row, truth))
    return out


def _photos(seeds: range, **kw) -> list:
    rows = []
    for seed in seeds:
        rng = np.random.default_rng(seed)
        rendered = sp.render(sp.random_photo(rng, **kw), rng)
        rows += [(seed, *item) for item in _measure(rendered)]
    return rows


def _check_bounds(rows: list, used: float = 0.9) -> dict[str, float]:
    """The issue's bounds over the rows (seed, face, channel, row, truth); the numbers."""
    ok = [r for r in rows if not r[3].flag]
    v = np.array([r[3].value for r in ok])
    t = np.array([r[4] for r in ok])
    se = np.array([r[3].stderr for r in ok])
    rel = np.abs(v / t - 1)
    pull = (v - t) / se
    got = {
        "used": len(ok) / len(rows),
        "rel_median": float(np.median(rel)),
        "rel_max": float(rel.max()),
        "pull_sd": float(np.std(pull, ddof=1)),
        "pull_max": float(np.abs(pull).max()),
    }
    assert got["used"] >= used, got
    assert got["rel_median"] <= 0.005 and got["rel_max"] <= 0.02, got
    assert 0.8 <= got["pull_sd"] <= 1.25 and got["pull_max"] <= 4.0, got
    return got


# --- measuring: values, errors, channels ----------------------------------------------------------


@pytest.fixture(scope="module")
def striped_rows() -> list:
    """12 photos x 4 grey faces (periods 1-8 px at any angle, a near lamp's gradient), the
    exposure drawn per photo (300-4000 DN: shot noise from 1.6% to 0.5% per pixel in G)."""
    return _photos(range(12), faces=4, extent_px=150)


def test_striped_faces_are_used_with_calibrated_errors(striped_rows: list) -> None:
    """144 rows (48 faces): >= 90% used, within 0.5% (median) and 2% (worst) of the truth,
    pulls with sd in [0.8, 1.25], none beyond 4. The faces' orientation is estimated from the
    pixels (roi_px); every face's stripes are found."""
    _check_bounds(striped_rows)
    assert all(r[3].stripe_period_px is not None for r in striped_rows)


def test_without_the_stripe_fit_the_same_rows_fail(striped_rows: list) -> None:
    """The bounds are not met by the plain block errors (`stripes = false`): today's pipeline
    flags most of these rows or misstates their errors, so the test above can fail."""
    rows = []
    for seed in range(12):
        rng = np.random.default_rng(seed)
        rendered = sp.render(sp.random_photo(rng, faces=4, extent_px=150), rng)
        plain = imaging.ExtractionSettings(stripes=False)
        rows += [(seed, *item) for item in _measure(rendered, plain)]
    with pytest.raises(AssertionError):
        _check_bounds(rows)


def test_known_orientation_gives_the_same_values(striped_rows: list) -> None:
    """With the direction across the layer lines given (as for a face placed from markers), the
    values agree with those of the estimated orientation within a tenth of their error."""
    seed = 3
    rng = np.random.default_rng(seed)
    rendered = sp.render(sp.random_photo(rng, faces=4, extent_px=150), rng)
    frame = sp.frame(rendered)
    settings = imaging.ExtractionSettings()
    for k, ft in enumerate(rendered.faces):
        erode = _roi.adaptive_erode_px(
            tuple(map(tuple, ft.outline_px)), frame.data.shape, settings.erode_px
        )
        roi = imaging.roi_mask(tuple(map(tuple, ft.outline_px)), frame.data.shape, erode,
                               photo="p", wedge=f"f{k}")  # fmt: skip
        known = imaging.roi_channel_stats(frame, roi, settings, across=ft.face.across_px())
        est = [r[3] for r in striped_rows if r[0] == seed and r[1] == k]
        for c, s in enumerate(known):
            assert s.mean_dn / DN_PER_RADIANCE == pytest.approx(
                est[c].value, abs=0.1 * est[c].stderr
            )


def test_sharp_stripes_square_to_the_pixels() -> None:
    """Grey faces whose layer lines run exactly along the pixel rows or columns (a camera
    squared to the specimen, as in the physically based set), with a narrow highlight and no
    lens blur, at periods where a harmonic shorter than 0.4 px falls near a Bayer Nyquist
    frequency (2.571 px: the 9th, 2.857: the 10th, 3.19: the 8th, 2.77: the 7th). After the
    pixel's square such a harmonic keeps a few percent of the mean, and on the R and B sites it
    is a near-constant of opposite sign. Fitting harmonics down to 0.4 px only, R and B came out
    up to 6% apart with pulls up to 66 (6 photos; 22 on these 3); with the harmonics that the
    residuals show fitted as well: within 1% (pulls sd 0.75 over 6 photos, max 2.3: the
    errors are a little conservative here)."""
    rows = []
    for seed in range(3):
        rng = np.random.default_rng(seed)
        spec = sp.random_photo(rng, faces=4, extent_px=150, square=True, sharp=True,
                               blur_px=0.0, periods=(2.5714, 2.8571, 3.19, 2.77))  # fmt: skip
        rows += [(seed, *item) for item in _measure(sp.render(spec, rng))]
    ok = [r for r in rows if not r[3].flag]
    pull = np.array([(r[3].value - r[4]) / r[3].stderr for r in ok])
    rel = np.array([r[3].value / r[4] - 1 for r in ok])
    assert len(ok) >= 0.9 * len(rows)
    assert np.median(np.abs(rel)) < 0.002 and np.abs(rel).max() < 0.01, rel
    assert np.std(pull, ddof=1) <= 1.25 and np.abs(pull).max() <= 4, pull
    split, split_pull = _split(rows)
    assert np.median(np.abs(split)) < 0.005 and np.abs(split_pull).max() <= 4


def test_what_the_stripes_leave_at_the_nyquist_frequency_is_in_r_and_b_errors() -> None:
    """A face whose rows (columns, for stripes along the columns) alternate by +-1% beyond its
    layer pattern, as a layer period under a pixel does under a strong perspective (the
    physically based set's 60-deg face seen at -20 deg: +-3.4%): not a function of the layer
    phase, so the stripes' fit leaves it (or takes up part of it, as a harmonic near the
    Nyquist frequency), and the channels' levels take up the rest: R and B up to 2% apart. The
    two greens, one on each half of the Bayer tile, show it, and R's and B's errors hold it:
    pulls within 4 (measured: at most 3.0; before, R's and B's pulls were 14-23)."""
    rows = []
    for seed in range(2):
        rng = np.random.default_rng(40 + seed)
        spec = sp.random_photo(rng, faces=4, extent_px=150, square=True, periods=(3.7,),
                               level_dn=3000.0)  # fmt: skip
        h, w = spec.size
        radiance = np.full((3, h, w), spec.background)
        for face in spec.faces:
            sp._draw_face(radiance, face, spec.sensor.blur_px, rng)
            y0, y1, x0, x1 = sp._face_box(face, (h, w))
            across = face.across_px()
            if abs(across[1]) > abs(across[0]):  # stripes along the rows
                radiance[:, y0:y1, x0:x1] *= 1 + 0.01 * (-1.0) ** np.arange(y0, y1)[:, None]
            else:
                radiance[:, y0:y1, x0:x1] *= 1 + 0.01 * (-1.0) ** np.arange(x0, x1)[None, :]
        truths = tuple(sp.FaceTruth(f.outline_px(), f) for f in spec.faces)
        rendered = sp.Rendered(sp._sensor(radiance, spec.sensor, rng), truths, spec)
        rows += [(seed, *item) for item in _measure(rendered)]
    ok = [r for r in rows if not r[3].flag and r[2] != 1]
    assert len(ok) >= 10
    rel = np.array([r[3].value / r[4] - 1 for r in ok])
    assert np.median(np.abs(rel)) > 0.004  # R and B carry the alternation ...
    pull = np.array([(r[3].value - r[4]) / r[3].stderr for r in ok])
    assert np.abs(pull).max() <= 4, pull  # ... and their errors say so


def _split(rows: list, flagged: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Per face: (R/G)/(B/G) of the measured values over that of the truths, minus 1, and that
    split over its standard error (the three channels' errors with their correlation); the
    flagged faces too with `flagged`."""
    faces: dict[tuple[int, int], dict[int, tuple]] = {}
    for seed, k, c, row, truth in rows:
        faces.setdefault((seed, k), {})[c] = (row, truth)
    split, pull = [], []
    for d in faces.values():
        if len(d) < 3 or (not flagged and any(d[c][0].flag for c in range(3))):
            continue
        (r, tr), (b, tb) = d[0], d[2]
        measured = math.log(r.value / b.value) - math.log(tr / tb)  # ln of (R/G)/(B/G)
        var = (r.stderr / r.value) ** 2 + (b.stderr / b.value) ** 2
        var -= 2 * r.corr_rb * (r.stderr / r.value) * (b.stderr / b.value)
        split.append(math.expm1(measured))
        pull.append(measured / math.sqrt(var) if var > 0 else math.inf)
    return np.array(split), np.array(pull)


@pytest.mark.slow  # a statistical check over 8 rendered photos (CI budget)
def test_grey_face_channels_agree() -> None:
    """Grey faces with stripes along the pixel rows or columns, periods near 2-4 px, where red
    and blue sites see different phases: (R/G)/(B/G) within 0.5% of the truth on every face
    (median a few 0.01%), and its pulls against the combined error have sd <= 1.25, none
    beyond 4. The plain channel means (stripes = false) split by up to 1.8% here."""
    rows, plain = [], []
    for seed in range(8):
        rng = np.random.default_rng(100 + seed)
        spec = sp.random_photo(rng, faces=4, extent_px=150, axis_aligned=True,
                               periods=(2.02, 2.6, 3.3, 4.05))  # fmt: skip
        rendered = sp.render(spec, rng)
        rows += [(seed, *item) for item in _measure(rendered)]
        off = imaging.ExtractionSettings(stripes=False)
        plain += [(seed, *item) for item in _measure(rendered, off)]
    split, pull = _split(rows)
    assert split.size >= 30
    assert np.abs(split).max() < 0.005 and np.median(np.abs(split)) < 0.002
    assert np.std(pull, ddof=1) <= 1.25 and np.abs(pull).max() <= 4
    old, _ = _split(plain, flagged=True)  # the plain means (most of them flagged few_blocks)
    assert np.abs(old).max() > 0.01 and np.sum(np.abs(old) > 0.005) >= 5


@pytest.mark.slow  # a statistical check over 8 rendered photos (CI budget)
def test_noise_part_is_what_changes_between_photos() -> None:
    """The same textured striped surface photographed twice (new sensor noise): the values
    differ by sqrt(stderr_noise_1^2 + stderr_noise_2^2), pulls sd in [0.8, 1.25] over 32
    faces x 3 channels; the surface's own structure is in stderr (larger), not in
    stderr_noise. (A texture finer than 2 px cannot be told from pixel noise in one photo and is
    counted as noise: docs/imaging.md §Standard errors.)"""
    pulls, ratio = [], []
    for seed in range(8):
        rng = np.random.default_rng(200 + seed)
        tex = sp.Texture(surface=0.01, ell_px=3.0, layers=0.003)
        spec = sp.random_photo(rng, faces=4, extent_px=150, texture=tex)
        a = _measure(
            sp.render(spec, np.random.default_rng(seed), noise_rng=np.random.default_rng(1))
        )
        b = _measure(
            sp.render(spec, np.random.default_rng(seed), noise_rng=np.random.default_rng(2))
        )
        for (_, _, ra, _), (_, _, rb, _) in zip(a, b, strict=True):
            pulls.append((ra.value - rb.value) / math.hypot(ra.stderr_noise, rb.stderr_noise))
            ratio.append(ra.stderr / ra.stderr_noise)
    assert 0.8 <= np.std(pulls, ddof=1) <= 1.25
    assert np.abs(pulls).max() <= 4.5
    assert np.median(ratio) > 1.2  # the texture's part is in stderr only


def test_photo_noise_model_matches_the_sensor_and_its_calibration_frames(tmp_path: Path) -> None:
    """The noise model fitted to a photo's ROIs (read + level / gain) against the sensor's
    truth and against what dark frames and a pair of flat fields of the same sensor say
    (their pixel scatter, computed here from the raw frames)."""
    sensor = sp.Sensor(level_dn=300.0, gain_e_per_dn=1.6, read_noise_dn=5.0, blur_px=0.3)
    rng = np.random.default_rng(7)
    spec = dataclasses.replace(sp.random_photo(rng, faces=4, extent_px=150), sensor=sensor)
    rendered = sp.render(spec, rng)
    frame = sp.frame(rendered)
    data = []
    for ft in rendered.faces:
        roi = imaging.roi_mask(tuple(map(tuple, ft.outline_px)), frame.data.shape, 8,
                               photo="p", wedge="f")  # fmt: skip
        data.append(_extract.roi_data(frame, roi, imaging.ExtractionSettings()))
    model = _noise.fit_noise_model([p for rd in data for p in _extract.noise_points(rd)])
    assert model is not None
    assert model.gain_e_per_dn == pytest.approx(sensor.gain_e_per_dn, rel=0.1)
    assert math.sqrt(model.read_var_dn2) == pytest.approx(sensor.read_noise_dn, abs=1.5)
    # the calibration frames: darks (read noise), two flats (shot noise: their difference)
    h, w = 200, 200
    dark = [
        sp.render(sp.PhotoSpec((h, w), (), sensor, background=0.0), rng).mosaic for _ in range(4)
    ]
    read_sd = float(np.std(np.stack(dark).astype(float), axis=0, ddof=1).mean())
    flats = [
        sp.render(sp.PhotoSpec((h, w), (), sensor, background=10.0), rng).mosaic for _ in range(2)
    ]
    diff = flats[0].astype(float) - flats[1].astype(float)
    g = sp.CFA[np.arange(h)[:, None] % 2, np.arange(w)[None, :] % 2] == 1
    level = float(flats[0][g].mean() - sp.BLACK_DN)
    gain = level / (float(diff[g].var()) / 2 - read_sd**2)
    assert model.gain_e_per_dn == pytest.approx(gain, rel=0.1)
    assert math.sqrt(model.read_var_dn2) == pytest.approx(read_sd, abs=1.5)


# --- thin faces -----------------------------------------------------------------------------------


def test_thin_faces_are_flagged_and_the_rest_measured(tmp_path: Path) -> None:
    """Faces 5, 12, 17 and 60 px across their layers (seen near grazing): the erosion adapts
    (8 px would empty the three thin ones), the 5-px face is flagged `thin` with NaN, the others
    are measured within their errors, and measuring the photo from its DNG does not fail."""
    rng = np.random.default_rng(11)
    spec = sp.random_photo(rng, faces=4, extent_px=150, thickness_px=(5.0, 12.0, 17.0, 60.0),
                           level_dn=3000.0)  # fmt: skip
    rendered = sp.render(spec, rng)
    path = tmp_path / "thin.dng"
    sp.write_dng(path, rendered.mosaic, **EXPOSURE)
    rois = {f"f{k}": tuple(map(tuple, ft.outline_px)) for k, ft in enumerate(rendered.faces)}
    table = imaging.measure_photos([imaging.PhotoSpec(path, rois=rois)], max_workers=1)
    by = {(r.wedge, r.channel): r for r in table}
    assert {by["f0", c].flag for c in "RGB"} == {"thin"}
    assert all(math.isnan(by["f0", c].value) for c in "RGB")
    # a quarter of each polygon's thickness (its filled pixels, a pixel or two more than the
    # face), at least 3 px, at most erode_px
    assert [by[f"f{k}", "G"].erode_px for k in (0, 1, 3)] == [3, 3, 8]
    assert by["f2", "G"].erode_px in (4, 5)
    for k, c, row, truth in _measure(rendered):
        if k == 0:
            continue
        assert row.flag in ("", "few_blocks"), row.flag
        assert abs(row.value - truth) < 4 * row.stderr, (k, c, row.value, truth, row.stderr)


# --- markers --------------------------------------------------------------------------------------


def _rms(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=1))))


def test_marker_corners_more_than_half_a_cell_off_are_refined() -> None:
    """40 markers of 3-6 px cells on their foreshortened side (the documented minimum is 3 px),
    foreshortened to 50-100%, the detector's corners all shifted by 0.6-1.0 of the smaller
    cell (1.8-6 px) and 0.3 px of noise each: the refined
    corners, kept because they place the marker's inner grid better, lie within 0.2 px RMS of
    the truth for at least 90% of the markers (median under 0.12 px); the old rule (refined
    corners kept only within half a cell of the detector's) left most of them off."""
    aruco = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    new, old = [], []
    for seed in range(40):
        rng = np.random.default_rng(300 + seed)
        fore = rng.uniform(0.5, 1.0)
        cell = rng.uniform(3.0, 6.0) / fore  # the unforeshortened side
        scale = cell / (sp.MARKER_MM / 6)
        rot = math.radians(rng.uniform(0, 360))
        lin = np.array([[math.cos(rot), -math.sin(rot)], [math.sin(rot), math.cos(rot)]])
        lin = lin @ np.diag([scale, scale * fore])
        hom = np.eye(3)
        hom[:2, :2] = lin
        hom[:2, 2] = np.array([150.0, 150.0]) - lin @ np.full(2, sp.MARKER_MM / 2)
        radiance = np.full((3, 300, 300), 0.1)
        mid = seed % 50
        truth = sp.draw_markers(radiance, hom, {mid: (0.0, 0.0)}, paper=1.6, ink=0.05)[mid]
        mosaic = sp._sensor(radiance, sp.Sensor(level_dn=3000.0, blur_px=0.4), rng)
        frame = sp.frame(sp.Rendered(mosaic, (), None))  # type: ignore[arg-type]
        shift = rng.normal(size=2)
        shift *= rng.uniform(0.6, 1.0) * cell * fore / np.hypot(*shift)
        start = truth + shift + rng.normal(0, 0.3, (4, 2))
        bits = _markers.marker_bits(aruco, mid)
        new.append(_rms(_markers.refine_corners(frame, start, 6, bits), truth))
        old.append(_rms(_markers.refine_corners(frame, start, 6), truth))
    new, old = np.array(new), np.array(old)
    assert np.mean(new <= 0.2) >= 0.9 and np.median(new) < 0.12, np.round(new, 3)
    assert np.mean(old > 0.5) > 0.7


# --- a photo folder through `stairfit measure` ----------------------------------------------------


def test_folder_through_stairfit_measure(tmp_path: Path) -> None:
    """A folder of 3 photos (faces flat on a base with four markers, periods 1.3-7.5 px, one
    coloured face): `stairfit measure` measures every face; the markers are placed within
    0.2 px RMS in every photo; the rows meet the bounds against the truths (computed over the
    ROIs that the same measurement used)."""
    from stairfit.cli import main

    folder = tmp_path / "photos"
    truth = sp.write_folder(folder, seed=5, photos=3)
    assert main(["measure", str(folder), "-o", str(tmp_path / "out"), "--quiet"]) == 0
    table = imaging.MeasurementTable.read_csv(tmp_path / "out" / "measurements.csv")
    scene = tomllib.loads((folder / "scene.toml").read_text())
    layout = imaging.MarkerLayout({m["id"]: m["corners_mm"] for m in scene["markers"]["marker"]})
    faces = {p["name"]: p["face_mm"] for p in scene["patches"]}
    rows = []
    for p, entry in enumerate(scene["photos"]):
        spec = imaging.PhotoSpec(folder / entry["file"], faces_mm=faces, markers=layout)
        fm = imaging.measure_frame(
            imaging.decode_raw(spec.path), spec, imaging.ExtractionSettings()
        )
        corners = truth["photos"][p]["marker_corners_px"]
        found = fm.detection.corners_px
        err = [
            np.sum((c - np.array(corners[str(i)])) ** 2, axis=1)
            for i, c in zip(fm.detection.ids, found, strict=True)
        ]
        assert math.sqrt(float(np.mean(err))) <= 0.2, (p, err)
        for row in fm.rows:
            roi = fm.rois[row.wedge]
            t = sp.folder_truth_dc(truth, p, int(row.wedge[1:]), roi.mask, roi.y0, roi.x0)
            rows.append((p, row.wedge, "RGB".index(row.channel), row, t["RGB".index(row.channel)]))
    cli = {(r.photo, r.wedge, r.channel): r.value for r in table}
    assert len(cli) == len(rows) == 3 * 4 * 3
    for p, wedge, c, row, _ in rows:
        assert cli[scene["photos"][p]["file"], wedge, "RGB"[c]] == row.value
    _check_bounds(rows)
    assert all(r[3].stripe_period_px is not None for r in rows)


# --- the message when nothing is usable -----------------------------------------------------------


def test_no_usable_measurement_names_the_cause_and_fixes_that_apply() -> None:
    """`few_blocks` on faces placed from markers with the default block_px: neither "enlarge
    the ROIs" nor "lower extraction.block_px" (neither applies); both when they do; `thin`
    names the grazing view."""
    from stairfit import _exclusions

    placed = [SimpleNamespace(flag="few_blocks", roi_source="markers")] * 3
    text = _exclusions.nothing_usable(3, Counter(few_blocks=3), placed, block_px=2)
    assert "texture" in text and "photograph the faces larger" in text
    assert "roi_px" not in text and "block_px" not in text
    drawn = [SimpleNamespace(flag="few_blocks", roi_source="polygon")]
    text = _exclusions.nothing_usable(1, Counter(few_blocks=1), drawn, block_px=8)
    assert "enlarge the roi_px polygons" in text and "lower extraction.block_px (now 8)" in text
    thin = [SimpleNamespace(flag="thin", roi_source="markers")]
    text = _exclusions.nothing_usable(1, Counter(thin=1), thin, block_px=2)
    assert "1 thin" in text and "too thin" in text and "nearer their normal" in text


# --- larger grids ---------------------------------------------------------------------------------


@pytest.mark.slow
def test_bounds_hold_over_the_calibration_grid() -> None:
    """40 photos (160 faces) per condition: grey and coloured faces, dim and bright exposures,
    stripes along the pixel axes, small and large faces, a fine surface texture."""
    conditions = {
        "grey": {},
        "coloured": {"grey": False},
        "dim (120 DN, 5 DN read noise)": {"level_dn": 120.0, "read_noise_dn": 5.0},
        "bright (6000 DN)": {"level_dn": 6000.0},
        "along the pixel axes": {"axis_aligned": True},
        "small faces (60 px)": {"extent_px": 60},
        "surface texture 2%, 3 px": {"texture": sp.Texture(surface=0.02, ell_px=3.0)},
    }
    for kw in conditions.values():
        _check_bounds(_photos(range(1000, 1040), **{"faces": 4, "extent_px": 150, **kw}))
