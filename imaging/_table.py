"""The measurement table: one row per photo x ROI x channel, written to and read from CSV."""

from __future__ import annotations

import csv
import io
import math
import types
import typing
from collections.abc import Iterator
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from stairfit.fileio import atomic_bytes, read_bytes

from ._errors import ImagingError


@dataclass(frozen=True)
class MeasurementRow:
    """One measured value: a colour channel of one ROI in one photo (docs/imaging.md §Table).

    Attributes:
        photo: the photo's name (its file name by default).
        photo_sha256: SHA-256 of the photo file that was decoded.
        settings_key: hash of everything else the value depends on (ROIs, marker layout,
            reference, exposure overrides, extraction settings, table version); the cache key.
        wedge: the ROI's name (a wedge, or the reference patch).
        channel: "R", "G" or "B".
        value: mean relative radiance (DN x N^2 / (t x ISO/100)), or, when `normalised_by` is
            set, the ratio to that reference patch's mean (dimensionless). NaN if no pixels or
            when flagged `below_black` (with `stderr`): never a negative radiance.
        stderr: standard error of `value` (block scatter; docs/imaging.md §Standard errors).
        n_pixels: unsaturated pixels averaged.
        n_blocks: non-empty blocks behind the standard error.
        saturated_fraction: fraction of the channel's ROI pixels that were saturated.
        channel_corr: mean correlation of the errors of this ROI's R, G and B values, from the
            cross-covariance of their block residuals (docs/imaging.md §Channel correlation);
            the same on the ROI's three rows; NaN when undefined.
        stderr_noise: the part of `stderr` due to white pixel noise (shot, read,
            quantisation), which differs between photos; the rest (`sqrt(stderr^2 -
            stderr_noise^2)`) is texture, the same in every photo of a face
            (docs/imaging.md §Standard errors). NaN when undefined.
        stderr_dof: degrees of freedom of the standard error (its estimate's own precision);
            0 when the ROI is too small to estimate it.
        block_px: side (raw pixels) of the blocks the standard error was computed from.
        corr_rg, corr_rb, corr_gb: correlations of the errors of this ROI's (R, G), (R, B) and
            (G, B) means; the same on the ROI's three rows; NaN when undefined.
        flag: "" when usable, else ";"-separated reasons ("saturated", "few_blocks",
            "below_black", "no_pixels", "thin", "reference-..."). Flagged rows must not be
            fitted. "thin": the face is too thin in this photo to measure (seen near grazing;
            `thickness_px` after the erosion `erode_px`); its value is NaN.
        normalised_by: the reference patch `value` is divided by ("" if none).
        exposure_time_s, f_number, iso: the exposure used (EXIF or override).
        exposure_source: where it came from: "exif" (EXIF IFD), "ifd0" (IFD0), "scene"
            (scene-file override), or per value "exposure_time_s=scene;f_number=exif;..." when
            the three differ (`imaging.Exposure.source`).
        black_level: mean black level of the channel (DN).
        white_level: the white (saturation) level (DN).
        roi_source: "polygon" (pixel polygon given) or "markers" (placed from ArUco markers).
        reprojection_error_px: RMS marker reprojection error (px) for marker-placed ROIs.
        n_markers: markers used for the placement, for marker-placed ROIs.
        camera: camera make and model from EXIF ("" when absent).
        marker_ids: the markers used, space-separated ids ("" unless placed from markers).
        marker_cell_px: the smallest cell of those markers (full-resolution px, its
            foreshortened side; docs/imaging.md §Markers).
        placement: the camera model that placed the ROI: "homography" (a face on the base),
            "affine" or "pinhole" (docs/imaging.md §3-D placement); "" for pixel polygons.
        radiometry: the corrections applied, e.g. "dark(8)+flat(2)+bracket(3)" ("" for none:
            the black level subtracted, no flat field, one file); docs/imaging.md.
        face_view_deg: for a face placed through a pinhole camera, its own view angle (deg,
            about y, base frame): the photo's view_deg (seen from the markers' centre) plus the
            parallax from the pose (`view_parallax_deg`); `stairfit fit` takes theta_o from it.
            None otherwise (docs/imaging.md §3-D placement).
        view_spread: the eroded ROI's share of its face polygon's spread along the face's
            in-plane direction (ratio of standard deviations, <= 1); the fit narrows the
            scene's `angular_extent_deg` by it for this ROI (docs/imaging.md §Viewing spread).
        view_half_width_deg: for a face placed through a pinhole camera, the half-width (deg)
            of the uniform spread of viewing angles with the standard deviation of its eroded
            ROI's pixels' own view angles (`imaging.roi_view_half_width_deg`): the ROI's own
            spread, which follows the face's length along its slope and its distance; `stairfit
            fit` uses it in place of `angular_extent_deg x view_spread`. None otherwise.
        face_points_mm: for a face placed from the markers, the face points its eroded ROI's
            pixels see, as a quadrature (`imaging.roi_face_points`): "x y z w" per point
            (base-frame mm, weight), points separated by ";"; the lab model's 3-D directions
            come from them (docs/imaging.md §3-D placement). "" otherwise.
        camera_mm: for a face placed through a pinhole, the camera's centre in the base frame
            (mm, "x y z"); "" otherwise (an affine camera is at infinity along view_deg).
        stripe_period_px: when the ROI shows its layer lines as stripes and they were fitted
            and removed (docs/imaging.md §Layer stripes): their period in the image (px);
            None otherwise.
        stripe_angle_deg: the image direction across the stripes (deg from +x towards +y).
        stripe_amplitude: the stripes' relative amplitude (their fundamental's).
        stripe_offset: the ROI's own mean (incomplete periods at its edges) relative to
            `value`, the period average: `value x (1 + stripe_offset)` is the ROI's mean
            radiance as its pixels show it (before the normalisation by a reference).
        erode_px: the erosion applied (px): `extraction.erode_px`, or less for a thin face
            (docs/imaging.md §Pixels).
        thickness_px: the eroded ROI's thickness (px: the diameter of its largest inscribed
            disk); 0 when nothing is left.
    """

    photo: str
    photo_sha256: str
    settings_key: str
    wedge: str
    channel: str
    value: float
    stderr: float
    n_pixels: int
    n_blocks: int
    saturated_fraction: float
    channel_corr: float
    stderr_noise: float
    stderr_dof: float
    block_px: int
    corr_rg: float
    corr_rb: float
    corr_gb: float
    flag: str
    normalised_by: str
    exposure_time_s: float
    f_number: float
    iso: float
    exposure_source: str
    black_level: float
    white_level: float
    roi_source: str
    reprojection_error_px: float | None
    n_markers: int | None
    camera: str
    marker_ids: str
    marker_cell_px: float | None
    placement: str
    radiometry: str = ""
    face_view_deg: float | None = None
    view_spread: float = 1.0
    view_half_width_deg: float | None = None
    face_points_mm: str = ""
    camera_mm: str = ""
    stripe_period_px: float | None = None
    stripe_angle_deg: float | None = None
    stripe_amplitude: float | None = None
    stripe_offset: float | None = None
    erode_px: int = 0
    thickness_px: float = 0.0


COLUMNS: tuple[str, ...] = tuple(f.name for f in fields(MeasurementRow))
"""The CSV header, in order."""

_HINTS = typing.get_type_hints(MeasurementRow)


def _base_type(hint: object) -> type:
    """The non-None type of a hint such as `float | None`."""
    if isinstance(hint, types.UnionType):
        return next(a for a in typing.get_args(hint) if a is not type(None))
    return hint  # type: ignore[return-value]


_TYPES = {name: _base_type(_HINTS[name]) for name in COLUMNS}
_OPTIONAL = {name for name in COLUMNS if isinstance(_HINTS[name], types.UnionType)}


def _format(v: object) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return repr(v) if math.isfinite(v) else str(v)
    return str(v)


def _parse(name: str, text: str) -> object:
    if text == "" and name in _OPTIONAL:
        return None
    return _TYPES[name](text)


@dataclass(frozen=True)
class MeasurementTable:
    """The measurements of a set of photos: an immutable sequence of `MeasurementRow`s.

    `failed` lists (photo, one-line reason) of photos that could not be measured, when
    `measure_photos` was asked not to raise; `from_cache` the photos whose rows were read from
    a verified measurement cache instead of being measured now. Neither is written to CSV.
    """

    rows: tuple[MeasurementRow, ...] = ()
    failed: tuple[tuple[str, str], ...] = ()
    from_cache: tuple[str, ...] = ()

    def __len__(self) -> int:
        return len(self.rows)

    def __iter__(self) -> Iterator[MeasurementRow]:
        return iter(self.rows)

    def photos(self) -> tuple[str, ...]:
        """Photo names, in order of first appearance."""
        return tuple(dict.fromkeys(r.photo for r in self.rows))

    def for_photo(self, photo: str) -> tuple[MeasurementRow, ...]:
        """The rows of one photo."""
        return tuple(r for r in self.rows if r.photo == photo)

    def column(self, name: str) -> np.ndarray:
        """One column as an array (float for numeric columns, None -> NaN; object for text)."""
        if name not in _TYPES:
            raise KeyError(f"no column {name!r}; columns are {', '.join(COLUMNS)}")
        values = [getattr(r, name) for r in self.rows]
        if _TYPES[name] in (int, float):
            return np.array([np.nan if v is None else v for v in values], dtype=np.float64)
        return np.array(values, dtype=object)

    def to_csv(self) -> str:
        """The table as CSV text with a header line (floats at full precision)."""
        buf = io.StringIO()
        writer = csv.writer(buf, lineterminator="\n")
        writer.writerow(COLUMNS)
        for r in self.rows:
            writer.writerow([_format(getattr(r, c)) for c in COLUMNS])
        return buf.getvalue()

    def write_csv(self, path: str | Path) -> Path:
        """Write the table as CSV, atomically (temporary file + os.replace)."""
        return atomic_bytes(path, self.to_csv().encode())

    @classmethod
    def read_csv(cls, path: str | Path) -> MeasurementTable:
        """Read a table written by `write_csv`.

        Raises:
            ImagingError: the file is missing or is not a measurement table of this version.
        """
        path = Path(path)
        try:
            text = read_bytes(path).decode("utf-8")
        except (OSError, UnicodeDecodeError) as e:
            raise ImagingError(f"measurement table {path}: cannot read it ({e})") from e
        return cls.from_csv_text(text, path)

    @classmethod
    def from_csv_text(cls, text: str, path: str | Path) -> MeasurementTable:
        """The table of CSV `text` (as `to_csv` writes it); `path` names it in errors."""
        reader = csv.reader(io.StringIO(text))
        header = next(reader, None)
        if header is None or tuple(header) != COLUMNS:
            raise ImagingError(
                f"measurement table {path}: the header is not {','.join(COLUMNS)}; it was "
                "written by another version or is not a measurement table; delete it"
            )
        rows = []
        for k, line in enumerate(reader, start=2):
            if len(line) != len(COLUMNS):
                raise ImagingError(
                    f"measurement table {path}, line {k}: expected {len(COLUMNS)} fields"
                )
            try:
                values = {c: _parse(c, t) for c, t in zip(COLUMNS, line, strict=True)}
            except ValueError as e:
                raise ImagingError(f"measurement table {path}, line {k}: {e}") from e
            rows.append(MeasurementRow(**values))  # type: ignore[arg-type]
        return cls(tuple(rows))
