"""Why measurements were not fitted, in words that name the flags and the right fix.

`fit` leaves out rows that imaging flagged (docs/imaging.md §The measurement table) and rows
with some saturated pixels (their mean is biased low). The note in the summary and the error
when nothing is left name each reason with its count, and the advice fits the reason: "shorten
the exposures" is right for saturation and wrong for a linear DNG whose values sit below its
black level.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from stairfit.imaging import MeasurementRow

ADVICE: dict[str, str] = {
    "saturated": "shorten the exposures (or bracket them)",
    "some saturated pixels": "shorten the exposures (or bracket them)",
    "below_black": (
        "the raw values lie below the file's black level, so the file's black level is not in "
        "its data's units (e.g. a lossy 8-bit linear DNG): use the camera's original RAW files"
    ),
    "few_blocks": (
        "the faces' texture is correlated over too much of each ROI for its own pixels to "
        "give its error: photograph the faces larger (more pixels across each face)"
    ),
    "thin": (
        "the faces are too thin in these photos to measure (seen near grazing; the "
        "thickness_px column): photograph them from views nearer their normal"
    ),
    "no_pixels": "move the ROIs onto the faces",
    "reference": "check the reference patch's ROI and exposure",
    "not finite": "check the photos' exposure values",
}
"""The fix for each reason a row is not fitted."""


def reasons(row: MeasurementRow) -> list[str]:
    """The reasons one measurement row is not fitted (empty when it is used)."""
    if row.flag:
        return sorted(
            {"reference" if f.startswith("reference-") else f for f in row.flag.split(";")}
        )
    if row.saturated_fraction > 0:
        return ["some saturated pixels"]
    ok = row.value == row.value and row.stderr == row.stderr and 0 < row.stderr < float("inf")
    return [] if ok else ["not finite"]


def count_reasons(rows: Iterable[MeasurementRow]) -> Counter[str]:
    """How many rows each reason excludes (a row may have several)."""
    counts: Counter[str] = Counter()
    for row in rows:
        counts.update(reasons(row))
    return counts


def describe(counts: Counter[str]) -> str:
    """`12 saturated, 3 below_black`, most frequent first."""
    return ", ".join(f"{n} {reason}" for reason, n in counts.most_common())


def advice(
    counts: Counter[str], rows: Iterable[MeasurementRow] = (), block_px: int | None = None
) -> str:
    """The fixes for the reasons present, each once, most frequent reason first.

    With the rows and the scene's `extraction.block_px`, the fix for `few_blocks` names only
    what applies: enlarging the ROIs only when some are pixel polygons (a face placed from the
    markers is measured whole), lowering block_px only when it was raised above the default.
    """
    fixes = dict.fromkeys(
        _few_blocks_fix(rows, block_px) if reason == "few_blocks" else ADVICE.get(reason)
        for reason, _ in counts.most_common()
    )
    return "; ".join(f or "see docs/imaging.md" for f in fixes)


DEFAULT_BLOCK_PX = 2
"""`extraction.block_px` by default (one Bayer tile), the smallest it can be."""


def _few_blocks_fix(rows: Iterable[MeasurementRow], block_px: int | None) -> str:
    """The cause and the fixes of `few_blocks` that apply to these rows."""
    flagged = [r for r in rows if "few_blocks" in r.flag.split(";")]
    text = ADVICE["few_blocks"]
    if any(r.roi_source == "polygon" for r in flagged):
        text += ", or enlarge the roi_px polygons that are smaller than their faces"
    if block_px is not None and block_px > DEFAULT_BLOCK_PX:
        text += f", or lower extraction.block_px (now {block_px})"
    return text


def nothing_usable(
    n_rows: int,
    counts: Counter[str],
    rows: Iterable[MeasurementRow] = (),
    block_px: int | None = None,
) -> str:
    """The error when no row can be fitted: each reason with its count, its cause and the fix
    that applies (`advice`)."""
    rows = list(rows)
    return (
        f"no usable measurement: of {n_rows} measurements, {describe(counts)} (the flag "
        f"column of measurements.csv, docs/imaging.md); {advice(counts, rows, block_px)}"
    )
