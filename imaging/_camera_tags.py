"""The tags of a RAW file beyond the exposure: focal length, the sensor's pixel pitch and the
capture time (for `stairfit init`, which drafts a scene file from a folder of photos).

exifread names a tag of the EXIF sub-IFD `EXIF FocalLength` and the same tag in IFD0 (where
TIFF/EP and some DNG writers put it) `Image FocalLength`; both places are read, the EXIF IFD
first, as `decode_raw` reads the exposure tags.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

from stairfit import fileio

from ._decode import MAX_RAW_BYTES, _exif_number, _read_exif

_FOCAL_LENGTH = (("EXIF FocalLength", "exif"), ("Image FocalLength", "ifd0"))
_FOCAL_35MM = (("EXIF FocalLengthIn35mmFilm", "exif"), ("Image FocalLengthIn35mmFilm", "ifd0"))
_PLANE_X_RESOLUTION = (
    ("EXIF FocalPlaneXResolution", "exif"),
    ("Image FocalPlaneXResolution", "ifd0"),
)
_PLANE_UNIT = ("EXIF FocalPlaneResolutionUnit", "Image FocalPlaneResolutionUnit")
_TAKEN = ("EXIF DateTimeOriginal", "Image DateTimeOriginal", "Image DateTime")

RESOLUTION_UNIT_MM: dict[int, float] = {2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}
"""Millimetres per unit of the EXIF FocalPlaneResolutionUnit codes (EXIF 2.32 and the DNG
specification: 2 inch, the default; 3 centimetre; 4 millimetre; 5 micrometre)."""

FULL_FRAME_DIAGONAL_MM = math.hypot(36.0, 24.0)
"""The diagonal of a 36 x 24 mm frame, to which FocalLengthIn35mmFilm refers (EXIF 2.32)."""


@dataclass(frozen=True)
class CameraTags:
    """What a RAW file's tags say about its lens and time (None or "" where a tag is absent).

    Attributes:
        focal_length_mm: the lens's focal length (FocalLength).
        pixels_per_mm: the sensor's pixels per millimetre (FocalPlaneXResolution in its
            FocalPlaneResolutionUnit): 1 / pixel pitch.
        focal_length_35mm: the 35-mm equivalent focal length (FocalLengthIn35mmFilm).
        taken: the capture time as written (DateTimeOriginal, else DateTime).
    """

    focal_length_mm: float | None = None
    pixels_per_mm: float | None = None
    focal_length_35mm: float | None = None
    taken: str = ""

    def focal_length_px(self) -> float | None:
        """The focal length in pixels (focal length x pixels per mm), or None when either tag
        is missing."""
        if self.focal_length_mm is None or self.pixels_per_mm is None:
            return None
        return self.focal_length_mm * self.pixels_per_mm


def read_camera_tags(path: str | Path) -> CameraTags:
    """The focal length, pixel pitch and capture time of a RAW file's tags (see `CameraTags`).

    A file whose tags exifread cannot parse, or that cannot be read, gives empty tags: they are
    hints for drafting a scene, never needed to measure.
    """
    try:
        blob = fileio.read_bytes(Path(path), MAX_RAW_BYTES)
    except OSError:
        return CameraTags()
    tags, _note = _read_exif(blob)
    focal = _exif_number(tags, _FOCAL_LENGTH)[0]
    equivalent = _exif_number(tags, _FOCAL_35MM)[0]
    resolution = _exif_number(tags, _PLANE_X_RESOLUTION)[0]
    return CameraTags(
        focal_length_mm=focal,
        pixels_per_mm=_per_mm(tags, resolution),
        focal_length_35mm=equivalent,
        taken=next((str(tags[k]).strip() for k in _TAKEN if k in tags), ""),
    )


def _per_mm(tags: dict, resolution: float | None) -> float | None:
    """FocalPlaneXResolution in pixels per millimetre (its unit defaults to the inch)."""
    if resolution is None:
        return None
    unit = 2
    for key in _PLANE_UNIT:
        values = getattr(tags.get(key), "values", None)
        if values:
            try:
                unit = int(values[0])
            except (TypeError, ValueError):
                return None
            break
    mm = RESOLUTION_UNIT_MM.get(unit)
    return None if mm is None else resolution / mm
