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

EXPOSURE_FIELDS: tuple[str, str, str] = ("exposure_time_s", "f_number", "iso")
"""The three exposure values, in the order used by `RawFrame.exposure_sources`."""

SCENE_OVERRIDE = "scene"
"""The source name of a value given by the scene file (a per-photo override)."""


@dataclass(frozen=True)
class Exposure:
    """The exposure of one photo: time (s), f-number and ISO setting (all positive, finite).

    `source` says where the values came from (docs/imaging.md §Units): "exif" (the EXIF
    sub-IFD), "ifd0" (IFD0, where TIFF/EP puts them), "scene" (overrides in the scene file), or,
    when the three differ, one `field=source` per value joined by ";", e.g.
    "exposure_time_s=scene;f_number=exif;iso=exif". Empty for an exposure made by hand.
    """

    exposure_time_s: float
    f_number: float
    iso: float
    source: str = ""

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


def exposure_source(sources: tuple[str, str, str]) -> str:
    """The `Exposure.source` text of per-value sources (time, f-number, ISO)."""
    if len(set(sources)) == 1:
        return sources[0]
    return ";".join(f"{k}={v}" for k, v in zip(EXPOSURE_FIELDS, sources, strict=True))


def resolve_exposure(
    frame: RawFrame,
    exposure_time_s: float | None = None,
    f_number: float | None = None,
    iso: float | None = None,
) -> Exposure:
    """The photo's exposure: each value from the override when given, else from the file's tags.

    Overrides come from the scene file (per photo) and win over the tags: they exist to fix
    files whose tags are missing or wrong. The tags are read from the EXIF IFD or, failing
    that, IFD0 (`decode_raw`). The result's `source` records which, per value.

    Raises:
        ImagingError: a value is neither in the tags (absent or 0) nor overridden; the message
            names the photo, the missing fields and the scene-file fields that fix it.
    """
    overrides = (exposure_time_s, f_number, iso)
    from_file = (frame.exif_exposure_time_s, frame.exif_f_number, frame.exif_iso)
    chosen = {
        k: o if o is not None else f
        for k, o, f in zip(EXPOSURE_FIELDS, overrides, from_file, strict=True)
    }
    sources = tuple(
        SCENE_OVERRIDE if o is not None else s
        for o, s in zip(overrides, frame.exposure_sources, strict=True)
    )
    missing = [k for k, v in chosen.items() if v is None]
    if missing:
        exif_name = {"exposure_time_s": "ExposureTime", "f_number": "FNumber", "iso": "ISO"}
        implausible = [n for n in frame.notes if "outside the plausible" in n]
        why = f"{'; '.join(implausible)}, " if implausible else ""
        raise ImagingError(
            f"photo {frame.name!r}: EXIF has no usable "
            f"{', '.join(exif_name[k] for k in missing)} ({why}absent or 0, in the EXIF IFD and "
            f"in IFD0) and the scene file gives no override; add "
            f"{', '.join(f'{k} = ...' for k in missing)} to this photo's [[photos]] entry"
        )
    try:
        return Exposure(**chosen, source=exposure_source(sources))  # type: ignore[arg-type]
    except ImagingError as e:
        raise ImagingError(f"photo {frame.name!r}: {e}") from e
