"""Decoding RAW photographs with rawpy (LibRaw): the linear sensor values, never demosaiced.

`decode_raw` returns the visible part of the mosaic exactly as stored (no black subtraction, no
white balance, no gamma), the colour of every CFA position, the black and white levels and the
exposure tags. Pixel coordinates follow docs/imaging.md §Pixels: `data[y, x]`, x to the right,
y down, (0, 0) the centre of the top-left visible pixel, in the sensor's orientation (the EXIF
orientation flag is not applied).
"""

from __future__ import annotations

import hashlib
import io
import math
from dataclasses import dataclass
from pathlib import Path

import exifread
import numpy as np
import rawpy

from stairfit import fileio

from ._dng import DngHeaderError, check_dng
from ._errors import ImagingError

CHANNELS: tuple[str, str, str] = ("R", "G", "B")
"""Colour channels in the order used everywhere in `stairfit.imaging` (index 0, 1, 2)."""

_CHANNEL_INDEX = {"R": 0, "G": 1, "B": 2}

# exifread tag names for the exposure values and where each lives, in order of preference: the
# EXIF sub-IFD first, then IFD0 (where TIFF/EP and some DNG writers put them).
_EXIF_EXPOSURE_TIME = (("EXIF ExposureTime", "exif"), ("Image ExposureTime", "ifd0"))
_EXIF_F_NUMBER = (("EXIF FNumber", "exif"), ("Image FNumber", "ifd0"))
_EXIF_ISO = (
    ("EXIF ISOSpeedRatings", "exif"),
    ("EXIF PhotographicSensitivity", "exif"),
    ("Image ISOSpeedRatings", "ifd0"),
)
EXPOSURE_TAG_SOURCES: tuple[str, str] = ("exif", "ifd0")
"""Where `decode_raw` finds exposure tags: the EXIF sub-IFD ("exif") or IFD0 ("ifd0")."""
PLAUSIBLE_EXPOSURE_S = (1e-6, 3600.0)
"""An ExposureTime tag outside this open interval (seconds) is damaged or crafted: treated as
absent, so that the scene file's `exposure_time_s` must give the value."""
MAX_RAW_BYTES = 2 * 2**30
"""The largest photo file read (2 GiB): camera RAW files are tens to a few hundred MB, and the
whole file is held in memory while it is decoded. A larger file (a damaged or sparse copy) is
refused before it is read."""


@dataclass(frozen=True, eq=False)
class RawFrame:
    """One decoded RAW photograph: linear sensor values and the metadata needed to use them.

    Attributes:
        path: the file that was decoded.
        name: the photo's name in messages and tables (the file name by default).
        sha256: SHA-256 of the file's bytes (hex), as decoded.
        data: the visible image as stored, uint16 DN. A CFA (mosaic) file gives shape (H, W),
            one colour per pixel; a linear (already demosaiced) file gives (H, W, 3), the
            planes R, G, B.
        cfa: for a mosaic, the colour index (0 = R, 1 = G, 2 = B; both greens are 1) of each
            position of the repeating CFA tile, shape (ph, pw), so that pixel (y, x) has colour
            `cfa[y % ph, x % pw]` (already shifted for the sensor margins). None for a linear
            file.
        black: black level in DN, float32: per CFA tile position (shape (ph, pw)) for a mosaic,
            per plane (shape (3,)) for a linear file.
        white_level: the raw value at which the sensor saturates (DN).
        camera_whitebalance: the camera's as-shot (R, G, B) multipliers as LibRaw reports them;
            metadata only, never applied to the data.
        exif_exposure_time_s, exif_f_number, exif_iso: the exposure values from the file's
            tags, or None when the tag is absent or 0 (a missing value, as in files written by
            Magic Lantern). Each is read from the EXIF sub-IFD, or from IFD0 (TIFF/EP's place)
            when the EXIF IFD has no usable value.
        exposure_sources: where each of the three values came from, in the order (time,
            f-number, ISO): "exif", "ifd0", or "" when absent.
        make, model: camera make and model from EXIF ("" when absent).
        notes: facts worth knowing about the file that do not stop a measurement.
    """

    path: Path
    name: str
    sha256: str
    data: np.ndarray
    cfa: np.ndarray | None
    black: np.ndarray
    white_level: float
    camera_whitebalance: tuple[float, float, float]
    exif_exposure_time_s: float | None
    exif_f_number: float | None
    exif_iso: float | None
    make: str
    model: str
    notes: tuple[str, ...] = ()
    exposure_sources: tuple[str, str, str] = ("", "", "")

    @property
    def is_linear(self) -> bool:
        """True for a linear (already demosaiced, no CFA) file such as a LinearRaw DNG."""
        return self.cfa is None

    @property
    def height(self) -> int:
        """Visible height in pixels."""
        return int(self.data.shape[0])

    @property
    def width(self) -> int:
        """Visible width in pixels."""
        return int(self.data.shape[1])

    @property
    def cfa_string(self) -> str:
        """The CFA tile as letters row by row, e.g. "RGGB"; "" for a linear file."""
        if self.cfa is None:
            return ""
        return "".join(CHANNELS[c] for c in self.cfa.ravel())

    def black_level_per_channel(self) -> tuple[float, float, float]:
        """Mean black level (DN) of the R, G and B pixels (for reports)."""
        if self.cfa is None:
            return tuple(float(b) for b in self.black)  # type: ignore[return-value]
        return tuple(float(self.black[self.cfa == c].mean()) for c in range(3))  # type: ignore[return-value]

    @property
    def camera(self) -> str:
        """Make and model in one string ("" when EXIF has neither)."""
        return " ".join(s for s in (self.make, self.model) if s)


def file_sha256(path: str | Path, max_bytes: int | None = None) -> str:
    """SHA-256 (hex) of a regular file's bytes, read in 1 MiB chunks (`fileio.FileTypeError`
    for a pipe, a device or a loop of links; `fileio.FileTooLargeError` over `max_bytes`)."""
    h = hashlib.sha256()
    fd = fileio.open_regular(Path(path))
    with open(fd, "rb") as f:
        fileio.check_size(fd, Path(path), max_bytes)
        while chunk := f.read(1 << 20):
            h.update(chunk)
    return h.hexdigest()


def _read_blob(path: Path, name: str) -> bytes:
    """The file's bytes, or an `ImagingError` naming the photo, what the path is and the fix."""
    try:
        return fileio.read_bytes(path, MAX_RAW_BYTES)
    except fileio.FileTooLargeError as e:
        raise ImagingError(
            f"photo {name!r}: {path} {e.strerror} for a photo; a camera RAW file is far "
            "smaller, so this one is damaged (or a sparse copy): copy it from the camera again"
        ) from None
    except (fileio.FileTypeError, FileNotFoundError) as e:
        what = fileio.describe(path) or e.strerror
        raise ImagingError(
            f"photo {name!r}: {path} {what}; give the photo's RAW file (its name is relative to "
            "the scene file's folder)"
        ) from None
    except OSError as e:
        raise ImagingError(
            f"photo {name!r}: cannot read {path} ({e.strerror or e}); check its permissions"
        ) from e


def _libraw_parts(
    blob: bytes, path: Path, name: str
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray, float, tuple[float, float, float]]:
    """`_read_libraw` of the file's bytes; LibRaw's and rawpy's failures as one `ImagingError`
    with the fix (a RAW converter, or DNG)."""
    try:
        with rawpy.imread(io.BytesIO(blob)) as raw:
            return _read_libraw(raw, name)
    except rawpy.LibRawError as e:
        reason = (
            e.args[0].decode(errors="replace")
            if e.args and isinstance(e.args[0], bytes)
            else str(e)
        )
        raise ImagingError(
            f"photo {name!r}: LibRaw {'.'.join(map(str, rawpy.libraw_version))} cannot decode "
            f"{path} ({type(e).__name__}: {reason}); it is not a camera RAW file LibRaw supports, "
            "or it is truncated or corrupt. Check that it opens in a RAW converter, copy it from "
            "the camera again, or convert it to DNG with Adobe DNG Converter"
        ) from e
    except (NotImplementedError, RuntimeError, ValueError) as e:
        raise ImagingError(
            f"photo {name!r}: rawpy cannot give the raw mosaic of {path} ({e}); convert it to "
            "DNG with Adobe DNG Converter"
        ) from e


def _black_level_note(data: np.ndarray, black: np.ndarray) -> list[str]:
    """A note when the median raw value lies below the black level (a black level not in the
    data's units, seen in 8-bit lossy linear DNGs)."""
    median = float(
        np.median(data[:: max(1, data.shape[0] // 256), :: max(1, data.shape[1] // 256)])
    )
    if median >= float(black.min()):
        return []
    return [
        f"the median raw value ({median:g}) is below the black level ({float(black.min()):g}): "
        "the black level may not be in the data's units (seen in 8-bit lossy linear DNGs)"
    ]


def _exposure_tags(tags: dict) -> tuple[dict[str, float | None], list[str], list[str]]:
    """Exposure time, f-number and ISO from the EXIF tags (EXIF IFD or IFD0), with the source
    of each and the notes their reading gave."""
    values: dict[str, float | None] = {}
    sources: list[str] = []
    notes: list[str] = []
    for key, names in (
        ("exposure_time_s", _EXIF_EXPOSURE_TIME),
        ("f_number", _EXIF_F_NUMBER),
        ("iso", _EXIF_ISO),
    ):
        values[key], source, tag_notes = _exif_number(tags, names)
        sources.append(source)
        notes.extend(tag_notes)
    return values, sources, notes


def decode_raw(path: str | Path, name: str | None = None) -> RawFrame:
    """Decode a camera RAW file (anything LibRaw reads; DNG, CR2, NEF, ARW, ...) without demosaic.

    Args:
        path: the RAW file.
        name: the photo's name for messages and tables; defaults to the file name.

    Returns:
        The visible mosaic (or the R, G, B planes of a linear DNG) as stored, with its CFA
        pattern, black and white levels (DN), the camera white balance (metadata only) and the
        EXIF exposure tags. See `RawFrame`.

    Raises:
        ImagingError: the file is missing, unreadable, not a RAW file LibRaw supports, corrupt
            or truncated, or its colour filters are not R, G, B.
    """
    path = Path(path)
    name = name or path.name
    blob = _read_blob(path, name)
    try:
        check_dng(blob)
    except DngHeaderError as e:
        raise ImagingError(
            f"photo {name!r}: {path}: {e}; the file is damaged or was altered: copy it from "
            "the camera again, or convert the camera's RAW file with Adobe DNG Converter"
        ) from None
    data, cfa, black, white, wb = _libraw_parts(blob, path, name)
    tags, exif_note = _read_exif(blob)
    values, sources, tag_notes = _exposure_tags(tags)
    notes = ([exif_note] if exif_note else []) + _black_level_note(data, black) + tag_notes
    return RawFrame(
        path=path,
        name=name,
        sha256=hashlib.sha256(blob).hexdigest(),
        data=data,
        cfa=cfa,
        black=black,
        white_level=white,
        camera_whitebalance=wb,
        exif_exposure_time_s=values["exposure_time_s"],
        exif_f_number=values["f_number"],
        exif_iso=values["iso"],
        make=_exif_text(tags, "Image Make"),
        model=_exif_text(tags, "Image Model"),
        notes=tuple(notes),
        exposure_sources=(sources[0], sources[1], sources[2]),
    )


def _colour_indices(color_desc: bytes, n: int, name: str) -> list[int]:
    """Map LibRaw colour indices 0..n-1 (letters of color_desc) to 0 = R, 1 = G, 2 = B."""
    desc = color_desc.decode(errors="replace")
    out = []
    for k in range(n):
        letter = desc[k] if k < len(desc) else "?"
        if letter not in _CHANNEL_INDEX:
            raise ImagingError(
                f"photo {name!r}: colour filters {desc!r} are not R, G, B (e.g. a CMYG or "
                "monochrome sensor); stairfit measures R, G and B only"
            )
        out.append(_CHANNEL_INDEX[letter])
    return out


def _read_libraw(
    raw: rawpy.RawPy, name: str
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray, float, tuple[float, float, float]]:
    """(data, cfa, black, white, white balance) from an open rawpy object."""
    blpc = np.asarray(raw.black_level_per_channel, dtype=np.float32)
    white = float(raw.white_level)
    desc = raw.color_desc
    wb4 = list(raw.camera_whitebalance)
    pattern = raw.raw_pattern
    if pattern is None or raw.raw_type == rawpy.RawType.Stack:
        planes = np.asarray(raw.raw_image_visible)
        if planes.ndim != 3:
            raise ImagingError(f"photo {name!r}: unexpected linear image shape {planes.shape}")
        n = min(int(raw.num_colors), planes.shape[2])
        chans = _colour_indices(desc, n, name)
        if sorted(set(chans)) != [0, 1, 2]:
            raise ImagingError(
                f"photo {name!r}: the linear image's planes are {desc.decode()[:n]!r}; "
                "R, G and B planes are needed"
            )
        first = [chans.index(c) for c in range(3)]
        data = np.stack([planes[..., k] for k in first], axis=-1).astype(np.uint16, copy=False)
        black = blpc[first].astype(np.float32)
        wb = tuple(float(wb4[k]) for k in first)
        return np.ascontiguousarray(data), None, black, white, wb  # type: ignore[return-value]
    pattern = np.asarray(pattern)
    s = raw.sizes
    # raw_pattern is relative to the full sensor; shift it to the visible area's origin.
    visible = np.roll(pattern, (-int(s.top_margin), -int(s.left_margin)), axis=(0, 1))
    n_idx = int(pattern.max()) + 1
    chans = _colour_indices(desc, n_idx, name)
    cfa = np.asarray(chans, dtype=np.uint8)[visible]
    if sorted(set(cfa.ravel().tolist())) != [0, 1, 2]:
        raise ImagingError(f"photo {name!r}: the CFA pattern {visible.tolist()} lacks R, G or B")
    black = blpc[visible].astype(np.float32)
    data = np.array(raw.raw_image_visible, dtype=np.uint16, copy=True)
    idx = {c: chans.index(c) for c in range(3)}
    wb = tuple(float(wb4[idx[c]]) if idx[c] < len(wb4) else float("nan") for c in range(3))
    return data, cfa, black, white, wb  # type: ignore[return-value]


def _read_exif(blob: bytes) -> tuple[dict, str]:
    """exifread's tags of a file (an empty dict and a note when exifread cannot parse it)."""
    try:
        return exifread.process_file(io.BytesIO(blob), details=False), ""
    except Exception as e:  # exifread raises many types on formats it does not know
        return {}, f"exifread could not read EXIF ({type(e).__name__}: {e})"


def _exif_number(
    tags: dict, names: tuple[tuple[str, str], ...]
) -> tuple[float | None, str, list[str]]:
    """The first positive, finite value among the tags `names` ((tag, source) pairs).

    Returns (value, its source, notes): a tag that is present but 0 or unreadable is noted and
    the next place is tried (an EXIF IFD with ExposureTime 0 does not hide a good IFD0 value);
    (None, "", notes) when no place has a usable value.
    """
    notes = []
    for key, source in names:
        if key not in tags:
            continue
        values = getattr(tags[key], "values", None)
        try:
            v = float(values[0]) if values else float("nan")
        except (TypeError, ValueError, ZeroDivisionError, IndexError):
            v = float("nan")
        if math.isfinite(v) and v > 0 and _plausible(key, v):
            return v, source, notes
        notes.append(f"{key} is {tags[key]}{_implausible(key, v)} (treated as absent)")
    if not notes:
        notes.append(f"{names[0][0]} is absent (and {names[-1][0]} too)")
    return None, "", notes


def _plausible(key: str, value: float) -> bool:
    """Whether a positive exposure value can be real (only ExposureTime has a range here)."""
    lo, hi = PLAUSIBLE_EXPOSURE_S
    return not key.endswith("ExposureTime") or lo < value < hi


def _implausible(key: str, value: float) -> str:
    """The note's reason for a positive value that `_plausible` refuses ("" otherwise)."""
    if not (math.isfinite(value) and value > 0) or _plausible(key, value):
        return ""
    lo, hi = PLAUSIBLE_EXPOSURE_S
    return f" s, outside the plausible {lo:g} to {hi:g} s"


def _exif_text(tags: dict, key: str) -> str:
    """A string tag, stripped ("" when absent)."""
    return str(tags[key]).strip().strip("\x00") if key in tags else ""
