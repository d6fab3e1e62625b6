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
from typing import Any

ADVICE: dict[str, str] = {
    "saturated": "shorten the exposures (or bracket them)",
    "some saturated pixels": "shorten the exposures (or bracket them)",
    "below_black": (
        "the raw values lie below the file's black level, so the file's black level is not in "
        "its data's units (e.g. a lossy 8-bit linear DNG): use the camera's original RAW files"
    ),
    "few_blocks": "enlarge the ROIs or lower extraction.block_px",
    "no_pixels": "move the ROIs onto the faces",
    "reference": "check the reference patch's ROI and exposure",
    "not finite": "check the photos' exposure values",
}
"""The fix for each reason a row is not fitted."""


def reasons(row: Any) -> list[str]:
    """The reasons one measurement row is not fitted (empty when it is used)."""
    if row.flag:
        return sorted(
            {"reference" if f.startswith("reference-") else f for f in row.flag.split(";")}
        )
    if row.saturated_fraction > 0:
        return ["some saturated pixels"]
    ok = row.value == row.value and row.stderr == row.stderr and 0 < row.stderr < float("inf")
    return [] if ok else ["not finite"]


def count_reasons(rows: Iterable[Any]) -> Counter[str]:
    """How many rows each reason excludes (a row may have several)."""
    counts: Counter[str] = Counter()
    for row in rows:
        counts.update(reasons(row))
    return counts


def describe(counts: Counter[str]) -> str:
    """`12 saturated, 3 below_black`, most frequent first."""
    return ", ".join(f"{n} {reason}" for reason, n in counts.most_common())


def advice(counts: Counter[str]) -> str:
    """The fixes for the reasons present, each once, most frequent reason first."""
    fixes = dict.fromkeys(ADVICE.get(reason, "see docs/imaging.md") for reason in counts)
    return "; ".join(fixes)


def nothing_usable(n_rows: int, counts: Counter[str]) -> str:
    """The error when no row can be fitted."""
    return (
        f"no usable measurement: of {n_rows} measurements, {describe(counts)} (the flag "
        f"column of measurements.csv, docs/imaging.md); {advice(counts)}"
    )
