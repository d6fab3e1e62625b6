"""Exposure tags (issue 12): read from the EXIF IFD or IFD0, and the source recorded per value."""

from __future__ import annotations

from pathlib import Path

import exifread
import numpy as np
import pytest

from stairfit import imaging
from stairfit.imaging import synthetic

EXPOSURE = imaging.Exposure(exposure_time_s=1 / 250, f_number=5.6, iso=200)
OTHER = imaging.Exposure(exposure_time_s=1 / 30, f_number=2.0, iso=1600)
ROI = {"patch": [(8, 8), (87, 8), (87, 55), (8, 55)]}


def _mosaic() -> np.ndarray:
    return np.random.default_rng(4).integers(3000, 5000, size=(64, 96)).astype(np.uint16)


def _tags(path: Path) -> dict[str, str]:
    with open(path, "rb") as f:
        return {k: str(v) for k, v in exifread.process_file(f, details=False).items()}


def test_ifd0_tags_are_read_where_tiff_ep_puts_them(tmp_path: Path) -> None:
    path = synthetic.write_dng(tmp_path / "ifd0.dng", _mosaic(), ifd0_exposure=EXPOSURE)
    tags = _tags(path)  # exifread itself sees them in IFD0 only
    assert tags["Image ExposureTime"] == "1/250" and tags["Image ISOSpeedRatings"] == "200"
    assert "EXIF ExposureTime" not in tags
    frame = imaging.decode_raw(path)
    assert frame.exif_exposure_time_s == pytest.approx(1 / 250)
    assert frame.exif_f_number == pytest.approx(5.6)
    assert frame.exif_iso == 200
    assert frame.exposure_sources == ("ifd0", "ifd0", "ifd0")
    exposure = imaging.resolve_exposure(frame)
    assert exposure.source == "ifd0"
    assert exposure.scale == pytest.approx(EXPOSURE.scale)


def test_exif_ifd_wins_over_ifd0(tmp_path: Path) -> None:
    path = synthetic.write_dng(
        tmp_path / "both.dng", _mosaic(), exposure=EXPOSURE, ifd0_exposure=OTHER
    )
    tags = _tags(path)
    assert tags["Image ExposureTime"] == "1/30" and tags["EXIF ExposureTime"] == "1/250"
    frame = imaging.decode_raw(path)
    assert (frame.exif_exposure_time_s, frame.exif_f_number, frame.exif_iso) == pytest.approx(
        (1 / 250, 5.6, 200)
    )
    assert imaging.resolve_exposure(frame).source == "exif"


def test_no_tags_anywhere_names_both_places_and_the_fix(tmp_path: Path) -> None:
    frame = imaging.decode_raw(synthetic.write_dng(tmp_path / "none.dng", _mosaic()))
    assert frame.exposure_sources == ("", "", "")
    assert any("Image ExposureTime" in n for n in frame.notes)
    with pytest.raises(imaging.ImagingError) as err:
        imaging.resolve_exposure(frame)
    msg = str(err.value)
    assert "'none.dng'" in msg and "IFD0" in msg and "exposure_time_s = ..." in msg


def test_measurement_rows_say_where_each_value_came_from(tmp_path: Path) -> None:
    mosaic = _mosaic()
    settings = imaging.ExtractionSettings(erode_px=2)
    rows = {}
    for where, kw in (("exif", {"exposure": EXPOSURE}), ("ifd0", {"ifd0_exposure": EXPOSURE})):
        path = synthetic.write_dng(tmp_path / f"{where}.dng", mosaic, **kw)
        spec = imaging.PhotoSpec(path, rois=ROI)
        rows[where] = imaging.measure_frame(imaging.decode_raw(path), spec, settings).rows
        assert {r.exposure_source for r in rows[where]} == {where}
    # the same pixels and exposure give the same values wherever the tags are
    assert [r.value for r in rows["exif"]] == [r.value for r in rows["ifd0"]]
    path = tmp_path / "ifd0.dng"
    spec = imaging.PhotoSpec(path, rois=ROI, iso=400)  # one value overridden by the scene
    partial = imaging.measure_frame(imaging.decode_raw(path), spec, settings).rows
    assert {r.exposure_source for r in partial} == {"exposure_time_s=ifd0;f_number=ifd0;iso=scene"}
    assert partial[0].value == pytest.approx(rows["ifd0"][0].value / 2)
    table = imaging.MeasurementTable(partial)
    again = imaging.MeasurementTable.read_csv(table.write_csv(tmp_path / "m.csv"))
    assert again.rows == table.rows


@pytest.mark.parametrize("where", synthetic.EXPOSURE_TAG_PLACES)
def test_synthetic_photo_writes_the_tags_where_asked(tmp_path: Path, where: str) -> None:
    photo = synthetic.render_photo(
        (64, 48),
        {"f": [(4, 4), (60, 4), (60, 44), (4, 44)]},
        {"f": np.full(3, 2000.0) * EXPOSURE.scale},
        EXPOSURE,
        background=np.full(3, 100.0),
    )
    frame = imaging.decode_raw(photo.write_dng(tmp_path / "p.dng", exposure_tags=where))
    expected = {"exif": "exif", "ifd0": "ifd0", "both": "exif", "none": ""}[where]
    assert frame.exposure_sources == (expected,) * 3
    with pytest.raises(imaging.ImagingError, match="exposure_tags"):
        photo.write_dng(tmp_path / "q.dng", exposure_tags="exif-ifd")


@pytest.mark.parametrize("where", ["none"])  # "ifd0": tests/app/test_measure.py's folder
def test_simulate_writes_the_tags_where_asked(where: str, tmp_path: Path) -> None:
    """`stairfit simulate --exposure-tags none`: no tags, the scene file gives the exposure."""
    import tomllib

    from stairfit.cli import main

    folder = tmp_path / "photos"
    argv = ["simulate", str(folder), "--megapixels", "0.5", "--views", "3", "--quiet"]
    assert main([*argv, "--exposure-tags", where]) == 0
    photos = tomllib.loads((folder / "scene.toml").read_text())["photos"]
    frame = imaging.decode_raw(folder / photos[0]["file"])
    expected = {"ifd0": ("ifd0",) * 3, "none": ("",) * 3}[where]
    assert frame.exposure_sources == expected
    assert ("exposure_time_s" in photos[0]) == (where == "none")
    exposure = imaging.resolve_exposure(
        frame, photos[0].get("exposure_time_s"), photos[0].get("f_number"), photos[0].get("iso")
    )
    assert exposure.source == {"ifd0": "ifd0", "none": "scene"}[where]
