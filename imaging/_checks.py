"""Checks of a finished measurement table that warn without stopping (docs/imaging.md).

* the same bytes under two photo names (a copied file listed as a second view);
* very low signal: a photo whose brightest usable ROI averages less than `LOW_SIGNAL_FRACTION`
  of the raw range above black (quantisation and read noise dominate, and any black-level error
  is a large fraction of the value), or whose every ROI is below its black level. An HDR
  bracket is not checked for low signal: its values are expressed at its shortest exposure, and
  the merge has taken the longer ones where the shortest is near black.

Each gives one `ImagingWarning` naming the photos. They work on the table alone, so they run
for cached rows as well as for photos decoded now.
"""

from __future__ import annotations

import math
import warnings

from ._errors import ImagingWarning
from ._table import MeasurementRow, MeasurementTable

LOW_SIGNAL_FRACTION = 0.01
"""A photo's brightest usable ROI mean below this fraction of (white - black) is 'low signal'."""


def same_bytes_warnings(table: MeasurementTable) -> list[str]:
    """Warn once per group of photo names whose files have the same SHA-256."""
    by_hash: dict[str, list[str]] = {}
    for name in table.photos():
        by_hash.setdefault(table.for_photo(name)[0].photo_sha256, []).append(name)
    messages = []
    for names in by_hash.values():
        if len(names) > 1:
            messages.append(
                f"photos {', '.join(map(repr, names))} are the same file content (SHA-256): one "
                "photo listed under several names is measured and fitted as several views; "
                "remove the extra [[photos]] entries unless the views really are identical"
            )
    for m in messages:
        warnings.warn(m, ImagingWarning, stacklevel=2)
    return messages


def _dn_above_black(row: MeasurementRow) -> float:
    """The row's mean raw value above black (DN): the value without the exposure scaling."""
    return row.value * row.exposure_time_s * (row.iso / 100.0) / row.f_number**2


def low_signal_warnings(table: MeasurementTable) -> list[str]:
    """Warn for each photo whose ROIs are all below black, or all at very low signal."""
    messages = []
    for name in table.photos():
        rows = [r for r in table.for_photo(name) if not r.normalised_by]
        if not rows:
            continue
        if all("below_black" in r.flag for r in rows):
            messages.append(
                f"photo {name!r}: every ROI is below the black level ({rows[0].black_level:g} DN, "
                "flag below_black): the file's black level is not in its data's units (e.g. a "
                "lossy 8-bit linear DNG); use the camera's original RAW file"
            )
            continue
        usable = [r for r in rows if not r.flag and math.isfinite(r.value)]
        if not usable or "bracket(" in usable[0].radiometry:
            continue  # a bracket's values are at its shortest exposure, the longer ones merged
        best = max(usable, key=_dn_above_black)
        span = best.white_level - best.black_level
        dn = _dn_above_black(best)
        if span > 0 and dn < LOW_SIGNAL_FRACTION * span:
            messages.append(
                f"photo {name!r}: very low signal: its brightest ROI ({best.wedge!r}, "
                f"{best.channel}) averages {dn:.3g} DN above black, {100 * dn / span:.2g}% of the "
                f"raw range ({span:g} DN); expose longer (or bracket) so that the faces reach "
                "at least a few percent of the range"
            )
    for m in messages:
        warnings.warn(m, ImagingWarning, stacklevel=2)
    return messages
