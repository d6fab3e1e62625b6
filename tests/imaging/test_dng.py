"""A DNG whose header contradicts its data is refused, naming the field (issue 42, case 3).

LibRaw decodes such files without a flag: ImageWidth one less than the strips hold shears the
image (a face's value 4796 -> 1091), Compression 7 over uncompressed data decodes noise, a
WhiteLevel of 0 becomes 65535. Each case here patches one field of a good synthetic DNG in
place (tifffile finds where it is stored) and checks that `decode_raw` refuses the file in one
line naming the file and the field; the good file and the real camera files still decode.
"""

from __future__ import annotations

import struct
from pathlib import Path

import exifread
import numpy as np
import pytest
import tifffile

from stairfit import imaging
from stairfit.imaging import synthetic

_FORMAT = {3: "<H", 4: "<I", 5: "<II"}  # SHORT, LONG, RATIONAL (little-endian, as written)


def _good(folder: Path) -> Path:
    mosaic = np.random.default_rng(1).integers(2000, 9000, size=(120, 160)).astype(np.uint16)
    exposure = imaging.Exposure(0.01, 4.0, 100)
    return synthetic.write_dng(folder / "a.dng", mosaic, exposure=exposure)


def _patch(path: Path, code: int, value: int) -> None:
    """Overwrite the (first) value of IFD0's tag `code` where it is stored."""
    with tifffile.TiffFile(path) as tif:
        tag = tif.pages.first.tags[code]
        at, dtype = tag.valueoffset, int(tag.dtype)
    data = bytearray(path.read_bytes())
    struct.pack_into(_FORMAT[dtype], data, at, value)
    path.write_bytes(bytes(data))


def _patch_exposure_time(path: Path, numerator: int, denominator: int) -> None:
    """Overwrite the EXIF IFD's ExposureTime (a RATIONAL) where it is stored."""
    with open(path, "rb") as fh:
        at = exifread.process_file(fh, details=False)["EXIF ExposureTime"].field_offset
    data = bytearray(path.read_bytes())
    struct.pack_into(_FORMAT[5], data, at, numerator, denominator)
    path.write_bytes(bytes(data))


@pytest.mark.parametrize(
    ("code", "value", "field"),
    [
        (256, 159, "ImageWidth"),  # one pixel less than each row holds
        (256, 161, "ImageWidth"),
        (259, 7, "Compression"),  # lossless JPEG said, uncompressed stored
        (259, 34892, "Compression"),
        (259, 8, "Compression"),  # deflate said
        (259, 5, "Compression"),  # LZW: not a DNG compression
        (279, 1000, "ImageWidth"),  # StripByteCounts: fewer bytes than the rows need
        (273, 10**9, "StripByteCounts"),  # StripOffsets past the end of the file
        (50717, 0, "WhiteLevel"),  # read as 65535 by LibRaw
        (50717, 70000, "WhiteLevel"),  # above the 16-bit range
        (50714, 20000, "BlackLevel"),  # above WhiteLevel 16383
    ],
    ids=["width-1", "width+1", "jpeg", "lossy", "deflate", "lzw", "short-strip", "offset",
         "white-0", "white-huge", "black-above-white"],
)  # fmt: skip
def test_a_header_field_that_contradicts_the_data_is_refused(
    tmp_path: Path, code: int, value: int, field: str
) -> None:
    path = _good(tmp_path)
    imaging.decode_raw(path)  # the good file decodes
    _patch(path, code, value)
    with pytest.raises(imaging.ImagingError) as err:
        imaging.decode_raw(path)
    message = str(err.value)
    assert "\n" not in message
    assert str(path) in message and f"DNG field {field}" in message, message


def test_an_implausible_exposure_time_is_not_used(tmp_path: Path) -> None:
    path = _good(tmp_path)
    _patch_exposure_time(path, 10**9, 1)  # 1e9 s
    frame = imaging.decode_raw(path)
    assert frame.exif_exposure_time_s is None
    assert any("outside the plausible" in n for n in frame.notes), frame.notes
    implausible = r"ExposureTime is 1000000000 s, outside the plausible .*exposure_time_s = "
    with pytest.raises(imaging.ImagingError, match=implausible):
        imaging.resolve_exposure(frame)
    assert imaging.resolve_exposure(frame, exposure_time_s=0.01).exposure_time_s == 0.01


def test_a_crafted_photo_stops_the_fit_in_one_line(tmp_path: Path, capsys) -> None:
    from stairfit.cli import main

    photos = tmp_path / "photos"
    argv = ["simulate", str(photos), "--megapixels", "0.3", "--views", "3", "--quiet"]
    assert main(argv) == 0
    target = photos / "IMG_0002.dng"
    with tifffile.TiffFile(target) as tif:
        width = int(tif.pages.first.imagewidth)
    _patch(target, 256, width - 1)
    capsys.readouterr()
    status = main(["fit", str(photos), "-o", str(tmp_path / "out"), "--quiet", "--no-posterior"])
    err = capsys.readouterr().err.strip().splitlines()
    assert status == 2 and len(err) == 1, err
    assert "IMG_0002.dng" in err[0] and "DNG field ImageWidth" in err[0], err[0]


@pytest.mark.shared_data
@pytest.mark.parametrize("name", ["colorchart.dng", "DSC8695.dng"])
def test_real_camera_files_pass_the_checks(shared_data: Path, name: str) -> None:
    frame = imaging.decode_raw(shared_data / "raw" / name)
    assert frame.width > 0
