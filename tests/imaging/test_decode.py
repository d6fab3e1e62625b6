"""Decoding RAW files (issue 3): real camera files, synthetic DNGs, and bad input."""

from __future__ import annotations

import hashlib
import math
import shutil
from pathlib import Path

import exifread
import numpy as np
import pytest
import rawpy

from stairfit import imaging
from stairfit.imaging import synthetic

EXPOSURE = imaging.Exposure(exposure_time_s=1 / 250, f_number=5.6, iso=200)


def _mosaic(h: int = 64, w: int = 96, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 4096, size=(h, w)).astype(np.uint16)


# --- real camera files (../shared/data/raw, see its README) --------------------------------------


@pytest.mark.shared_data
def test_colorchart_decodes_as_rggb_with_rawpy_levels(shared_data: Path) -> None:
    path = shared_data / "raw" / "colorchart.dng"
    frame = imaging.decode_raw(path)
    assert not frame.is_linear
    assert frame.cfa_string == "RGGB"
    assert frame.data.shape == (1156, 1734)
    assert frame.data.dtype == np.uint16
    # The values rawpy itself reports (README "Decode check"), read here independently.
    with rawpy.imread(str(path)) as raw:
        assert np.array_equal(frame.data, raw.raw_image_visible)
        blpc = raw.black_level_per_channel
        assert frame.white_level == raw.white_level == 15000
    assert blpc == [2056, 2056, 2056, 2056]
    assert np.all(frame.black == 2056)
    assert frame.camera == "Canon Canon EOS Kiss X4"
    assert frame.sha256 == "592dba160b03770752667847f60ef07e9d96c17bf841e78e2b0cb5cbc5616edd"


@pytest.mark.shared_data
def test_colorchart_missing_exif_is_reported_clearly(shared_data: Path) -> None:
    frame = imaging.decode_raw(shared_data / "raw" / "colorchart.dng")
    # Magic Lantern wrote 0 for all three tags: absent, not "0 seconds".
    assert frame.exif_exposure_time_s is None
    assert frame.exif_f_number is None
    assert frame.exif_iso is None
    assert any("ExposureTime is 0" in n for n in frame.notes)
    with pytest.raises(imaging.ImagingError) as err:
        imaging.resolve_exposure(frame)
    msg = str(err.value)
    assert "colorchart.dng" in msg
    for field in ("exposure_time_s", "f_number", "iso"):
        assert field in msg
    # Overrides complete it; a partial override names only what is still missing.
    exp = imaging.resolve_exposure(frame, exposure_time_s=0.02, f_number=4.0, iso=100)
    assert exp.scale == pytest.approx(4.0**2 / (0.02 * 1.0))
    with pytest.raises(imaging.ImagingError, match=r"no usable ISO") as err:
        imaging.resolve_exposure(frame, exposure_time_s=0.02, f_number=4.0)
    assert "f_number" not in str(err.value)


@pytest.mark.shared_data
def test_linear_dng_takes_the_linear_path_and_reads_exif(shared_data: Path) -> None:
    path = shared_data / "raw" / "DSC8695.dng"
    frame = imaging.decode_raw(path)
    assert frame.is_linear
    assert frame.cfa is None and frame.cfa_string == ""
    assert frame.data.shape == (400, 600, 3)
    with rawpy.imread(str(path)) as raw:
        planes = raw.raw_image_visible
        assert raw.raw_pattern is None
        assert np.array_equal(frame.data, planes[..., :3])  # color_desc RGBG: planes R, G, B
    assert frame.black.tolist() == [51.0, 51.0, 51.0]
    assert frame.white_level == 65535
    assert frame.exif_exposure_time_s == pytest.approx(1 / 1600)
    assert frame.exif_f_number == pytest.approx(2.8)
    assert frame.exif_iso == 400
    assert frame.camera == "NIKON CORPORATION NIKON D500"
    exp = imaging.resolve_exposure(frame)
    assert exp.scale == pytest.approx(2.8**2 / (1 / 1600 * 4.0))


@pytest.mark.shared_data
def test_linear_dng_black_level_inconsistency_is_flagged(shared_data: Path) -> None:
    """LibRaw reports black 51 for this 8-bit lossy linear DNG, but its decoded values run 0..87
    with mean ~16 (the README's decode check): most pixels are below "black". That must show
    as a note on the frame and a `below_black` flag with NaN, never as a negative radiance."""
    frame = imaging.decode_raw(shared_data / "raw" / "DSC8695.dng")
    assert any("below the black level" in n for n in frame.notes)
    spec = imaging.PhotoSpec(frame.path, rois={"patch": [(100, 100), (300, 100), (300, 300)]})
    rows = imaging.measure_frame(frame, spec, imaging.ExtractionSettings()).rows
    assert len(rows) == 3
    for row in rows:
        assert math.isnan(row.value) and math.isnan(row.stderr)
        assert "below_black" in row.flag
    with pytest.warns(imaging.ImagingWarning, match=r"every ROI is below the black level \(51"):
        imaging.measure_photos([spec])


def _munsell_y(v: float) -> float:
    """Luminous reflectance Y (%) of Munsell value V (ASTM D1535 polynomial)."""
    return 1.1914 * v - 0.22533 * v**2 + 0.23352 * v**3 - 0.020484 * v**4 + 0.00081939 * v**5


@pytest.mark.shared_data
def test_colorchart_neutral_patches_are_linear(shared_data: Path) -> None:
    """Black subtraction and linearity on real data: the chart's neutral row.

    ROIs on the white (N9.5), N8, N6.5 and N5 patches of the ColorChecker's bottom row (centres
    read off the preview). Ratios to the white patch must match the Munsell values' reflectance
    (ASTM D1535) and be the same in R, G and B. Tolerances: the light is mixed and the lens
    flares (the darker patches N3.5 and N2 read 10-30% high, so they are left out); measured
    deviations are below 2% in G and 6% in R and B.
    """
    frame = imaging.decode_raw(shared_data / "raw" / "colorchart.dng")
    centres = {9.5: (705, 931), 8.0: (811, 927), 6.5: (917, 925), 5.0: (1027, 923)}
    rois = {f"N{v}": [(x - 30, y - 25), (x + 30, y - 25), (x + 30, y + 25), (x - 30, y + 25)]
            for v, (x, y) in centres.items()}  # fmt: skip
    spec = imaging.PhotoSpec(frame.path, rois=rois, exposure_time_s=1.0, f_number=1.0, iso=100)
    rows = imaging.measure_frame(frame, spec, imaging.ExtractionSettings(erode_px=4)).rows
    value = {(r.wedge, r.channel): r.value for r in rows}
    assert all(r.flag == "" for r in rows)
    for v in (8.0, 6.5, 5.0):
        expected = _munsell_y(v) / _munsell_y(9.5)
        ratios = [value[(f"N{v}", c)] / value[("N9.5", c)] for c in "RGB"]
        assert ratios[1] == pytest.approx(expected, rel=0.03)
        assert ratios == pytest.approx([expected] * 3, rel=0.08)


# --- synthetic DNGs written by write_dng --------------------------------------------------------


@pytest.mark.parametrize("cfa", ["RGGB", "BGGR", "GRBG", "GBRG"])
def test_write_dng_round_trips_through_rawpy(tmp_path: Path, cfa: str) -> None:
    mosaic = _mosaic()
    path = synthetic.write_dng(
        tmp_path / "m.dng", mosaic, cfa=cfa, black_level=256, white_level=4000, exposure=EXPOSURE
    )
    frame = imaging.decode_raw(path)
    assert frame.cfa_string == cfa
    assert np.array_equal(frame.data, mosaic)  # bit-exact
    assert np.all(frame.black == 256)
    assert frame.white_level == 4000
    assert frame.exif_exposure_time_s == pytest.approx(1 / 250)
    assert frame.exif_f_number == pytest.approx(5.6)
    assert frame.exif_iso == 200
    assert frame.make == "stairfit" and frame.model == "synthetic"
    with rawpy.imread(str(path)) as raw:  # what rawpy itself says about the file
        letters = raw.color_desc.decode()
        assert "".join(letters[i] for i in raw.raw_pattern.ravel()) == cfa
        assert raw.black_level_per_channel == [256] * 4
        assert raw.other.iso_speed == 200  # only read from an EXIF sub-IFD
        assert raw.other.shutter_speed == pytest.approx(1 / 250)
    with open(path, "rb") as f:
        tags = exifread.process_file(f, details=False)
    assert str(tags["EXIF ExposureTime"]) == "1/250"
    assert str(tags["EXIF FNumber"]) == "28/5"
    assert str(tags["EXIF ISOSpeedRatings"]) == "200"


def test_write_dng_without_exif_gives_the_missing_exposure_error(tmp_path: Path) -> None:
    path = synthetic.write_dng(tmp_path / "noexif.dng", _mosaic(), exposure=None)
    frame = imaging.decode_raw(path)
    assert frame.exif_exposure_time_s is None and frame.exif_iso is None
    with pytest.raises(imaging.ImagingError, match=r"noexif\.dng.*ExposureTime, FNumber, ISO"):
        imaging.resolve_exposure(frame)


def test_sha256_is_of_the_file_bytes(tmp_path: Path) -> None:
    path = synthetic.write_dng(tmp_path / "a.dng", _mosaic(), exposure=EXPOSURE)
    expected = hashlib.sha256(path.read_bytes()).hexdigest()
    assert imaging.decode_raw(path).sha256 == expected
    assert imaging.file_sha256(path) == expected


# --- bad input -----------------------------------------------------------------------------------


def test_truncated_file_is_a_clear_error(tmp_path: Path) -> None:
    good = synthetic.write_dng(tmp_path / "good.dng", _mosaic(256, 256), exposure=EXPOSURE)
    bad = tmp_path / "truncated.dng"
    bad.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(imaging.ImagingError) as err:
        imaging.decode_raw(bad)
    msg = str(err.value)
    assert "truncated.dng" in msg and "LibRaw" in msg and "corrupt" in msg


@pytest.mark.shared_data
def test_truncated_real_file_is_a_clear_error(shared_data: Path, tmp_path: Path) -> None:
    src = shared_data / "raw" / "colorchart.dng"
    bad = tmp_path / "cut.dng"
    bad.write_bytes(src.read_bytes()[:2_000_000])  # header intact, pixel data cut
    # the DNG header check (imaging/_dng.py) finds the cut strips before LibRaw reads them
    with pytest.raises(imaging.ImagingError, match=r"cut\.dng.*points past the end of the file"):
        imaging.decode_raw(bad)


def test_text_file_named_dng_is_unsupported(tmp_path: Path) -> None:
    bad = tmp_path / "notes.dng"
    bad.write_text("these are not pixels\n" * 20)
    with pytest.raises(imaging.ImagingError) as err:
        imaging.decode_raw(bad)
    msg = str(err.value)
    assert "notes.dng" in msg and "not a camera RAW file" in msg and "DNG" in msg


def test_missing_file_is_a_clear_error(tmp_path: Path) -> None:
    with pytest.raises(imaging.ImagingError, match=r"'gone\.dng'.*does not exist"):
        imaging.decode_raw(tmp_path / "gone.dng")


def test_photo_name_is_used_in_messages(tmp_path: Path) -> None:
    bad = tmp_path / "x.dng"
    shutil.copyfile(__file__, bad)  # a Python file is not a RAW file either
    with pytest.raises(imaging.ImagingError, match=r"photo 'front view'"):
        imaging.decode_raw(bad, name="front view")
