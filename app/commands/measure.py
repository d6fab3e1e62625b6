"""`stairfit measure DIR`: decode and measure only, for checking ROIs and for reference targets.

Writes the measurement table, the previews and a short report of flags and markers per photo
(`photos.csv`, `markers.csv`, `report.html`) into the output folder and prints the same on the
terminal; no model is fitted. A measure-only scene may name `[[patches]]` (a colour chart, a
grey card) beside or instead of `[specimen]` (docs/scene.md). Photos that cannot be measured
are reported with the others (their previews show the markers found); the command then exits
with status 2 and one line naming them.
"""

from __future__ import annotations

import argparse
import dataclasses
import html
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from .. import _ranges
from ..errors import UserError
from ..fileio import write_file
from ..imaging_specs import (
    CACHE_DIR,
    calibration_spec,
    extraction_settings,
    measurement_cache,
    photo_specs,
    radiometry_fields,
)
from ..photo_reports import (
    MARKER_COLUMNS,
    PHOTO_COLUMNS,
    PhotoReport,
    html_table,
    photo_reports,
    write_table,
)
from ..scene import Scene, load_scene

if TYPE_CHECKING:
    from stairfit import imaging


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register the `measure` command."""
    p = sub.add_parser(
        "measure",
        help="decode and measure the photos only (no fit): measurements, previews, a report",
        description=(
            "Decode the RAW photos listed in DIR/scene.toml and measure every wedge face and "
            "named patch: measurements.csv, previews, and a short report of flags and markers "
            "per photo (photos.csv, markers.csv, report.html). For checking ROIs before a long "
            "fit, and for reference targets such as a colour chart ([[patches]] in scene.toml)."
        ),
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("folder", type=Path, metavar="DIR", help="photo folder with scene.toml")
    p.add_argument(
        "-o", "--output", type=Path, default=None, help="output folder (default: DIR-measure)"
    )
    p.add_argument("--workers", type=int, default=1, help="processes decoding photos")
    p.add_argument("--no-cache", action="store_true", help="decode every photo again")
    p.add_argument("--force", action="store_true", help="replace an existing output folder")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def default_output(folder: Path) -> Path:
    """`DIR-measure` next to the photo folder."""
    from ..fileio import resolved

    folder = resolved(folder)
    return folder.with_name(f"{folder.name}-measure")


def run(args: argparse.Namespace) -> int:
    """`stairfit measure DIR`."""
    from ..outputs import staged_folder
    from ..pipeline import check_photos

    _ranges.check_workers(args.workers)
    scene = load_scene(args.folder, measure_only=True)
    out = args.output or default_output(args.folder)
    check_photos(scene)
    specs = measure_specs(scene)
    inputs = (scene.folder, *scene.input_files())
    reserved = (scene.folder / CACHE_DIR,)
    with staged_folder(out, args.force, command="measure", inputs=inputs, reserved=reserved) as tmp:
        table = measure_table(scene, specs, tmp, args)
        reports = photo_reports(scene, specs, table)
        write_outputs(scene, table, reports, tmp)
    print_summary(scene, reports, out)
    if table.failed:
        from stairfit.imaging import summarise_failures

        raise UserError(
            f"{scene.path}: {len(table.failed)} of {len(specs)} photos could not be measured "
            f"(see {out / 'report.html'}): {summarise_failures(list(table.failed))}"
        )
    return 0


def measure_specs(scene: Scene) -> list[imaging.PhotoSpec]:
    """One `imaging.PhotoSpec` per photo: its wedges (as `stairfit fit` measures them) and the
    scene's patches (pixel polygons, or outlines on the base placed by the markers)."""
    from stairfit import imaging

    from ..placement import marker_layout

    patches = scene.patches
    calibration = calibration_spec(scene) if scene.specimen is None else None
    specs = photo_specs(scene) if scene.specimen is not None else [None] * len(scene.photos)
    layout = marker_layout(scene)
    out = []
    for photo, spec in zip(scene.photos, specs, strict=True):
        per_photo = dict(photo.roi_px)
        rois = [(p.name, per_photo.get(p.name, p.roi_px)) for p in patches]
        rois = [(n, poly) for n, poly in rois if poly is not None]
        faces = [(p.name, p.face_mm) for p in patches if p.name not in dict(rois)]
        if spec is None:
            spec = imaging.PhotoSpec(
                path=scene.folder / photo.file, name=photo.file,
                exposure_time_s=photo.exposure_time_s, f_number=photo.f_number, iso=photo.iso,
                rois=tuple(rois), faces_mm=tuple(faces), markers=layout if faces else None,
                **radiometry_fields(scene, photo, calibration),
            )  # fmt: skip
        elif patches:
            spec = dataclasses.replace(
                spec,
                rois=spec.rois + tuple(rois),
                faces_mm=spec.faces_mm + tuple(faces),
                markers=spec.markers or (layout if faces else None),
            )
        out.append(spec)
    return out


def measure_table(
    scene: Scene, specs: Sequence[imaging.PhotoSpec], out: Path, args: argparse.Namespace
) -> imaging.MeasurementTable:
    """The measurement table of every photo that could be measured (failures in `.failed`)."""
    from stairfit import imaging

    cache, secret = measurement_cache(scene, not args.no_cache)
    try:
        return imaging.measure_photos(
            specs,
            extraction_settings(scene),
            cache=cache,
            cache_secret=secret,
            preview_dir=out / "previews",
            progress=not args.quiet,
            max_workers=args.workers,
            raise_on_failure=False,
        )
    except imaging.ImagingError as err:
        raise UserError(f"{scene.path}: {err}") from None


def write_outputs(
    scene: Scene, table: imaging.MeasurementTable, reports: Sequence[PhotoReport], out: Path
) -> None:
    """measurements.csv, photos.csv, markers.csv and report.html into `out`."""
    table.write_csv(out / "measurements.csv")
    write_table(out / "photos.csv", reports, PHOTO_COLUMNS)
    write_table(out / "markers.csv", reports, MARKER_COLUMNS)
    write_file(out / "report.html", report_html(scene, reports, out))


def report_html(scene: Scene, reports: Sequence[PhotoReport], out: Path) -> str:
    """A small page: the per-photo table and the previews."""
    from .. import __version__

    e = html.escape
    previews = sorted((out / "previews").glob("*.png")) if (out / "previews").exists() else []
    figs = "".join(
        f"<figure style='display:inline-block;width:30%'><img src='previews/{e(p.name)}' "
        f"style='width:100%'><figcaption>{e(p.stem)}</figcaption></figure>"
        for p in previews
    )
    n_failed = sum(r.status != "measured" for r in reports)
    return f"""<!doctype html><html><head><meta charset="utf-8"><title>stairfit measure</title>
<style>body{{font-family:sans-serif;max-width:1100px;margin:auto}}td,th{{padding:2px 8px}}
table{{border-collapse:collapse}}tr:nth-child(even){{background:#f3f3f3}}</style></head><body>
<h1>stairfit measure: {e(scene.folder.name)}</h1>
<p>{len(reports) - n_failed} of {len(reports)} photos measured; values in measurements.csv
(docs/imaging.md). Markers: the ids used, the layout's ids not found, the RMS reprojection
error (px) and the smallest marker cell (px).</p>
<h2>Photos</h2>{html_table(reports, PHOTO_COLUMNS)}
<h2>Regions of interest</h2>{figs}
<p style="color:#777">stairfit {e(__version__)}</p></body></html>
"""


def summary_line(r: PhotoReport) -> str:
    """One terminal line about a photo."""
    if r.status != "measured":
        return f"  {r.photo}: FAILED ({r.status.removeprefix('failed: ')})"
    flags = ", none flagged"
    if r.flagged:
        more = "; ..." if len(r.flagged) > 3 else ""
        flags = f", {len(r.flagged)} flagged ({'; '.join(r.flagged[:3])}{more})"
    text = f"  {r.photo}: {r.rois} ROIs{flags}; exposure from {r.exposure_source or '?'}"
    if r.marker_ids:
        text += (
            f"; markers {r.marker_ids} ({r.placement}, {r.rms_px:.2f} px RMS, cells "
            f"{r.cell_px:.1f} px)"
        )
        if r.missing_ids:
            text += f", not found: {r.missing_ids}"
    return text + (f"; note: {r.note}" if r.note and r.marker_ids else "")


def print_summary(scene: Scene, reports: Sequence[PhotoReport], out: Path) -> None:
    """The terminal summary of `measure`."""
    print(f"stairfit measure: {scene.folder}")
    for r in reports:
        print(summary_line(r))
    for note in scene.left_out:
        print(f"  note: {note}")
    print(f"  measurements: {out / 'measurements.csv'}; report: {out / 'report.html'}")
