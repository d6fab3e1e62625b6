"""Flat fields and dark frames (imaging/_calibration.py, issue 12): each checked against the
known truth (HDR brackets: tests/imaging/test_hdr.py).

Synthetic photos (`stairfit.imaging.synthetic`) with 15% vignetting and a sensor whose true dark
level differs from its black-level tag; every check compares the measured ROI means with the
radiance the photos were rendered from, in units of the reported standard errors, with and
without the correction.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from stairfit import imaging
from stairfit.imaging import _pipeline, synthetic

EXPOSURE = imaging.Exposure(exposure_time_s=1 / 100, f_number=8.0, iso=200)
SIZE = (800, 600)  # (width, height)
SETTINGS = imaging.ExtractionSettings()


def _faces() -> dict[str, list]:
    """Six 150 px faces, two rows of three, reaching into the corners (strong vignetting)."""
    faces = {}
    for i, y0 in enumerate((10, 440)):
        for j, x0 in enumerate((10, 325, 640)):
            faces[f"f{3 * i + j}"] = [
                (x0, y0),
                (x0 + 150, y0),
                (x0 + 150, y0 + 150),
                (x0, y0 + 150),
            ]
    return faces


FACES = _faces()


def _write_flats(folder: Path, n: int, vignetting: float, level_dn: float = 6000.0) -> list:
    """`n` flat-field photos of a uniform target; (label, path) pairs."""
    out = []
    for k in range(n):
        photo = synthetic.render_photo(
            SIZE, {}, {}, EXPOSURE, background=np.full(3, level_dn * EXPOSURE.scale),
            texture_amplitude=0.0, vignetting=vignetting, seed=900 + k,
        )  # fmt: skip
        out.append((f"calibration.flat_field[{k}]", photo.write_dng(folder / f"flat{k}.dng")))
    return out


def _measure(paths: list[Path], calibration: imaging.CalibrationSpec | None) -> list:
    specs = [imaging.PhotoSpec(p, rois=FACES, calibration=calibration) for p in paths]
    return list(imaging.measure_photos(specs, SETTINGS, max_workers=1))


def _pulls(rows: list, truth: dict[str, dict[str, np.ndarray]]) -> np.ndarray:
    return np.array(
        [(r.value - truth[r.photo][r.wedge][imaging.CHANNELS.index(r.channel)]) / r.stderr
         for r in rows]
    )  # fmt: skip


# --- flat fields ---------------------------------------------------------------------------------


def test_flat_field_gain_follows_the_lens_vignetting(tmp_path: Path) -> None:
    """The fitted gain equals the rendered vignetting (1 at the centre), within its own error."""
    spec = imaging.calibration_spec(flat_field=_write_flats(tmp_path, 2, 0.15))
    cal = imaging.build_calibration(spec)
    assert cal.flat is not None and cal.dark is None
    gain = cal.flat.gain()
    h, w = SIZE[1], SIZE[0]
    cy, cx = (h - 1) / 2, (w - 1) / 2
    f2 = (cx**2 + cy**2) / (0.85**-0.5 - 1)
    y, x = np.mgrid[0:h, 0:w]
    truth = 1.0 / (1.0 + ((x - cx) ** 2 + (y - cy) ** 2) / f2) ** 2  # synthetic's cos^4 law
    assert gain[0, 0] == pytest.approx(0.85, abs=0.003)
    err = gain - truth
    rms = float(np.sqrt(np.mean(err**2)))
    # the reported error of the fitted gain describes its actual error (within a factor of 2)
    assert 0.5 * cal.flat.rel_stderr.mean() < rms < 2.0 * cal.flat.rel_stderr.mean()
    # a polynomial fit is least certain at the image's edges; inside them the error is small
    # everywhere, and even in the extreme corners it is a small fraction of the 15% fall-off
    inner = err[30:-30, 40:-40]
    assert np.abs(inner).max() < 1.2e-3
    assert np.abs(err).max() < 5e-3
    # the polynomial follows the flat: its residuals are the cells' noise, not misfit
    assert np.all(cal.flat.fit_rms < 1.3 * cal.flat.cell_noise)
    # 1 at the exact image centre: each CFA position's level is off by no more than its
    # stated error (normalising to a central window's mean instead was 1.4e-4 off at 15%)
    for dy in range(2):
        for dx in range(2):
            offset = float(err[dy::2, dx::2].mean())
            assert abs(offset) < 3.5 * cal.flat.centre_stderr[dy, dx], (dy, dx, offset)


def _vignetted_photos(folder: Path, n: int, seed: int, **sensor: float) -> tuple[list, dict]:
    rng = np.random.default_rng(seed)
    paths, truth = [], {}
    for k in range(n):
        radiance = {f: rng.uniform(400, 3000, 3) * EXPOSURE.scale for f in FACES}
        photo = synthetic.render_photo(
            SIZE, FACES, radiance, EXPOSURE, background=np.full(3, 200 * EXPOSURE.scale),
            sensor=synthetic.SensorModel(**sensor), texture_amplitude=0.02, texture_sigma_px=1.0,
            vignetting=0.15, seed=seed * 100 + k,
        )  # fmt: skip
        name = f"p{k}.dng"
        paths.append(photo.write_dng(folder / name))
        truth[name] = radiance  # the surface itself: no vignetting, untextured
    return paths, truth


def test_flat_field_removes_the_vignetting_bias(tmp_path: Path) -> None:
    """15% vignetting: uncorrected corner faces read about 10% low; flat-fielded, they are
    unbiased and their pulls have unit width."""
    paths, truth = _vignetted_photos(tmp_path, 4, seed=3)
    plain = _measure(paths, None)
    rel = np.array([r.value / truth[r.photo][r.wedge][imaging.CHANNELS.index(r.channel)] - 1
                    for r in plain if r.wedge in ("f0", "f2", "f3", "f5")])  # fmt: skip
    assert -0.13 < rel.mean() < -0.07  # the corner faces see most of the fall-off
    spec = imaging.calibration_spec(flat_field=_write_flats(tmp_path, 2, 0.15))
    corrected = _measure(paths, spec)
    assert all(r.flag == "" and r.radiometry == "flat(2)" for r in corrected)
    pulls = _pulls(corrected, truth)
    assert pulls.size == 72
    # 72 pulls: the sd is known to about 8.5% (1 sigma), the mean to 0.12; bounds ~3 sigma
    assert 0.75 < pulls.std(ddof=1) < 1.3
    assert abs(pulls.mean()) < 0.4


def test_flat_field_must_match_the_photos(tmp_path: Path) -> None:
    """A flat of another image size is refused with one line naming the photo and the field."""
    paths, _ = _vignetted_photos(tmp_path, 1, seed=4)
    small = synthetic.render_photo(
        (400, 300), {}, {}, EXPOSURE, background=np.full(3, 6000 * EXPOSURE.scale), seed=1
    )
    flat = small.write_dng(tmp_path / "small_flat.dng")
    spec = imaging.calibration_spec(flat_field=[("calibration.flat_field[0]", flat)])
    with pytest.raises(imaging.ImagingError) as err:
        _measure(paths, spec)
    text = str(err.value)
    assert "'p0.dng'" in text and "calibration.flat_field[0]" in text and "800 x 600" in text


@pytest.mark.parametrize(
    ("level_dn", "what"),
    [(20000.0, "saturated"), (100.0, "too dark")],
)
def test_badly_exposed_flat_is_refused(tmp_path: Path, level_dn: float, what: str) -> None:
    flats = _write_flats(tmp_path, 1, 0.1, level_dn=level_dn)
    with pytest.raises(imaging.ImagingError) as err:
        imaging.build_calibration(imaging.calibration_spec(flat_field=flats))
    text = str(err.value)
    assert text.startswith("calibration.flat_field[0] 'flat0.dng': ") and what in text


def test_flat_fields_of_different_sizes_are_refused(tmp_path: Path) -> None:
    flats = _write_flats(tmp_path, 1, 0.1)
    other = synthetic.render_photo(
        (400, 300), {}, {}, EXPOSURE, background=np.full(3, 6000 * EXPOSURE.scale), seed=1
    ).write_dng(tmp_path / "other.dng")
    flats.append(("calibration.flat_field[1]", other))
    with pytest.raises(imaging.ImagingError, match=r"calibration.flat_field\[1\] 'other.dng'"):
        imaging.build_calibration(imaging.calibration_spec(flat_field=flats))


def test_missing_calibration_file_names_the_field(tmp_path: Path) -> None:
    with pytest.raises(imaging.ImagingError, match=r"^calibration.dark_frames\[0\] 'nope.dng'"):
        imaging.calibration_spec(
            dark_frames=[("calibration.dark_frames[0]", tmp_path / "nope.dng")]
        )


# --- dark frames ---------------------------------------------------------------------------------

# A sensor whose true dark level is 6 DN above its black-level tag, with a 3 DN fixed pattern.
DARK_SENSOR = {"bias_dn": 6.0, "fixed_pattern_dn": 3.0, "read_noise_dn": 2.0}


def _write_darks(folder: Path, n: int, **sensor: float) -> list:
    out = []
    for k in range(n):
        photo = synthetic.render_photo(
            SIZE, {}, {}, EXPOSURE, background=np.zeros(3), sensor=synthetic.SensorModel(**sensor),
            texture_amplitude=0.0, vignetting=0.0, seed=500 + k,
        )  # fmt: skip
        out.append((f"calibration.dark_frames[{k}]", photo.write_dng(folder / f"dark{k}.dng")))
    return out


def _dim_photos(folder: Path, n: int, seed: int) -> tuple[list, dict]:
    """Faces only 15-60 DN above black: a 6 DN dark-level error is a 10-40% bias."""
    rng = np.random.default_rng(seed)
    paths, truth = [], {}
    for k in range(n):
        radiance = {f: rng.uniform(15, 60, 3) * EXPOSURE.scale for f in FACES}
        photo = synthetic.render_photo(
            SIZE, FACES, radiance, EXPOSURE, background=np.full(3, 5 * EXPOSURE.scale),
            sensor=synthetic.SensorModel(**DARK_SENSOR), texture_amplitude=0.02,
            texture_sigma_px=1.0, vignetting=0.0, seed=seed * 100 + k,
        )  # fmt: skip
        name = f"p{k}.dng"
        paths.append(photo.write_dng(folder / name))
        truth[name] = radiance
    return paths, truth


def test_dark_frames_replace_a_wrong_black_level(tmp_path: Path) -> None:
    paths, truth = _dim_photos(tmp_path, 3, seed=5)
    plain = _pulls(_measure(paths, None), truth)
    assert plain.mean() > 5  # 6 DN too high everywhere: many standard errors
    spec = imaging.calibration_spec(dark_frames=_write_darks(tmp_path, 8, **DARK_SENSOR))
    rows = _measure(paths, spec)
    assert all(r.radiometry == "dark(8)" for r in rows)
    assert all(r.black_level == pytest.approx(1024 + 6, abs=0.3) for r in rows)
    pulls = _pulls(rows, truth)
    # 54 pulls: the sd is known to about 10%, the mean to 0.14; bounds about 3 sigma
    assert 0.7 < pulls.std(ddof=1) < 1.35
    assert abs(pulls.mean()) < 0.45


def test_dark_frame_noise_enters_the_standard_errors(tmp_path: Path) -> None:
    """Two dark frames: each master pixel carries read noise 2 DN / sqrt(2), common to every
    photo; an ROI mean of n pixels gets sqrt(2^2 / 2 / n) DN added in quadrature."""
    paths, _ = _dim_photos(tmp_path, 1, seed=6)
    spec = imaging.calibration_spec(dark_frames=_write_darks(tmp_path, 2, **DARK_SENSOR))
    cal = imaging.build_calibration(spec)
    assert cal.dark is not None
    # two frames: the between-frame scatter of a pixel is the read noise (2 DN); 4 positions
    # of ~120 000 pixels each give it to about 0.5%
    assert cal.dark.pixel_sd == pytest.approx(np.full((2, 2), 2.0), rel=0.03)
    photo = imaging.PhotoSpec(paths[0], rois=FACES, calibration=spec)
    frames = imaging.decode_view(photo)
    radiometry = _pipeline.view_radiometry(frames, photo, SETTINGS, cal)
    result = imaging.measure_frame(frames[0], photo, SETTINGS, radiometry)
    for name, roi in result.rois.items():
        stats = imaging.roi_channel_stats(radiometry.frame, roi, SETTINGS)
        common = radiometry.common_stderr_dn(roi, stats)
        for c, s in enumerate(stats):
            assert common[c] == pytest.approx(np.sqrt(4.0 / 2 / s.n_pixels), rel=0.03)
            row = next(r for r in result.rows if r.wedge == name and r.channel == "RGB"[c])
            total = np.hypot(s.stderr_dn, common[c]) * EXPOSURE.scale
            assert row.stderr == pytest.approx(total, rel=1e-9)


def test_a_bright_dark_frame_is_refused(tmp_path: Path) -> None:
    flats = _write_flats(tmp_path, 1, 0.0)
    with pytest.raises(imaging.ImagingError, match="not a dark frame"):
        imaging.build_calibration(
            imaging.calibration_spec(dark_frames=[("calibration.dark_frames[0]", flats[0][1])])
        )
