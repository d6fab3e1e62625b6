"""Exposure normalisation: from raw DN to relative radiance.

relative radiance = (DN - black) * N^2 / (t * ISO / 100)   [docs/imaging.md §Units]

with the exposure time t (s), the f-number N and the ISO setting. Its unit is "DN per second at
f/1 and ISO 100": photos taken with different exposures of the same scene give the same values.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from ._decode import RawFrame
from ._errors import ImagingError


@dataclass(frozen=True)
class Exposure:
    """The exposure of one photo: time (s), f-number and ISO setting (all positive, finite)."""

    exposure_time_s: float
    f_number: float
    iso: float

    def __post_init__(self) -> None:
        for field in ("exposure_time_s", "f_number", "iso"):
            v = getattr(self, field)
            try:
                x = float(v)
            except (TypeError, ValueError):
                x = float("nan")
            if not (math.isfinite(x) and x > 0):
                raise ImagingError(f"exposure {field} = {v!r} must be a positive number")
            object.__setattr__(self, field, x)

    @property
    def scale(self) -> float:
        """Relative radiance per DN above black: N^2 / (t * ISO / 100)."""
        return self.f_number**2 / (self.exposure_time_s * self.iso / 100.0)


def resolve_exposure(
    frame: RawFrame,
    exposure_time_s: float | None = None,
    f_number: float | None = None,
    iso: float | None = None,
) -> Exposure:
    """The photo's exposure: each value from the override when given, else from EXIF.

    Overrides come from the scene file (per photo) and win over EXIF: they exist to fix files
    whose EXIF is missing or wrong.

    Raises:
        ImagingError: a value is neither in EXIF (absent or 0) nor overridden; the message names
            the photo, the missing fields and the scene-file fields that fix it.
    """
    chosen = {
        "exposure_time_s": exposure_time_s
        if exposure_time_s is not None
        else frame.exif_exposure_time_s,
        "f_number": f_number if f_number is not None else frame.exif_f_number,
        "iso": iso if iso is not None else frame.exif_iso,
    }
    missing = [k for k, v in chosen.items() if v is None]
    if missing:
        exif_name = {"exposure_time_s": "ExposureTime", "f_number": "FNumber", "iso": "ISO"}
        raise ImagingError(
            f"photo {frame.name!r}: EXIF has no usable "
            f"{', '.join(exif_name[k] for k in missing)} (absent or 0) and the scene file gives "
            f"no override; add {', '.join(f'{k} = ...' for k in missing)} to this photo's "
            "[[photos]] entry"
        )
    try:
        return Exposure(**chosen)  # type: ignore[arg-type]
    except ImagingError as e:
        raise ImagingError(f"photo {frame.name!r}: {e}") from e
