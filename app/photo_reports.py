"""What `stairfit measure` and the fit's marker table say about each photo: `PhotoReport`s
(measured or why not, ROIs, flagged rows, markers used and missed, reprojection error, the
smallest marker cell) and their CSV and HTML tables (photos.csv, markers.csv, report.html).
"""

from __future__ import annotations

import csv
import html
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from .fileio import writing
from .scene import Scene

if TYPE_CHECKING:
    from stairfit import imaging

NEAR_LIMIT = 1.5
"""Markers with cells under this many times the detection limit get a note."""


@dataclass(frozen=True)
class PhotoReport:
    """What `measure` (and the fit's marker table) says about one photo."""

    photo: str
    status: str  # "measured" or "failed: <reason>"
    rois: int
    flagged: tuple[str, ...]  # "<roi> <channel>: <flags>"
    exposure_source: str
    marker_ids: str  # the markers used ("" without marker placement)
    missing_ids: str  # layout markers not found
    rms_px: float | None
    cell_px: float | None
    placement: str
    note: str


def photo_reports(
    scene: Scene, specs: Sequence[imaging.PhotoSpec], table: imaging.MeasurementTable
) -> list[PhotoReport]:
    """One `PhotoReport` per photo, in scene order (failed photos included)."""
    failed = dict(table.failed)
    layout_ids = [m.id for m in scene.markers.markers] if scene.markers else []
    reports = []
    for spec in specs:
        rows = table.for_photo(spec.name)
        if spec.name in failed or not rows:
            reason = failed.get(spec.name, "not measured")
            reports.append(PhotoReport(spec.name, f"failed: {reason}", 0, (), "", "", "", None,
                                       None, "", ""))  # fmt: skip
            continue
        reports.append(_report(spec.name, rows, layout_ids))
    return reports


def _report(
    photo: str, rows: Sequence[imaging.MeasurementRow], layout_ids: list[int]
) -> PhotoReport:
    from stairfit import imaging

    placed = next((r for r in rows if r.roi_source == "markers"), None)
    flagged = tuple(f"{r.wedge} {r.channel}: {r.flag}" for r in rows if r.flag)
    note = "" if placed is not None else "pixel ROIs only (markers not used)"
    found = placed.marker_ids.split() if placed is not None else []
    missing = [str(i) for i in layout_ids if placed is not None and str(i) not in found]
    cell = placed.marker_cell_px if placed is not None else None
    limit = imaging.MIN_DETECTABLE_CELL_PX
    if cell is not None and cell < NEAR_LIMIT * limit:
        note = (
            f"markers at {cell:.1f} px per cell, near the detection limit (about {limit:g} px "
            "per cell); larger markers or a closer camera would be safer"
        )
    return PhotoReport(
        photo=photo,
        status="measured",
        rois=len({r.wedge for r in rows}),
        flagged=flagged,
        exposure_source=rows[0].exposure_source,
        marker_ids=" ".join(found),
        missing_ids=" ".join(missing),
        rms_px=placed.reprojection_error_px if placed is not None else None,
        cell_px=cell,
        placement=placed.placement if placed is not None else "",
        note=note,
    )


MARKER_COLUMNS = ("photo", "placement", "marker_ids", "missing_ids", "rms_px", "cell_px", "note")

PHOTO_COLUMNS = ("photo", "status", "rois", "flagged", "exposure_source", *MARKER_COLUMNS[1:])


def _cells(report: PhotoReport, columns: Sequence[str]) -> list[str]:
    def text(v: object) -> str:
        if v is None:
            return ""
        if isinstance(v, float):
            return f"{v:.3g}"
        return "; ".join(v) if isinstance(v, tuple) else str(v)

    return [text(getattr(report, c)) for c in columns]


def write_table(path: Path, reports: Sequence[PhotoReport], columns: Sequence[str]) -> None:
    """A CSV of the reports' `columns` (markers.csv, photos.csv)."""
    with writing(path) as fh:
        writer = csv.writer(fh)
        writer.writerow(columns)
        writer.writerows(_cells(r, columns) for r in reports)


def html_table(reports: Sequence[PhotoReport], columns: Sequence[str]) -> str:
    """The reports as an HTML table (for report.html of `measure` and of `fit`)."""
    e = html.escape
    head = "".join(f"<th>{e(c)}</th>" for c in columns)
    body = "".join(
        "<tr>" + "".join(f"<td>{e(c)}</td>" for c in _cells(r, columns)) + "</tr>" for r in reports
    )
    return f"<table><tr>{head}</tr>{body}</table>"


def fit_marker_reports(
    scene: Scene, specs: Sequence[imaging.PhotoSpec], table: imaging.MeasurementTable
) -> list[PhotoReport]:
    """The per-photo reports of a fit's measurement table (for its markers.csv and report),
    from the photo specs the fit measured with."""
    return photo_reports(scene, specs, table)
