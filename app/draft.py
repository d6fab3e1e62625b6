"""From a folder of photos to a scene file: what `stairfit init DIR` drafts.

`draft_scene` reads every camera RAW file of the folder (size, camera, exposure tags, focal
length, capture time), tells photographs from flat fields and dark frames, groups the
photographs into views (an HDR bracket is one view at several exposures), finds each view's
markers and, from them and the wedges' faces, its camera and view angle (app/_draft_pose.py),
and writes a commented scene file that validates: every estimate with its source as a comment,
every value it cannot know as a TODO string that `stairfit fit` and `measure` refuse until it
is filled (`scene.TODO_PREFIX`). What the photos cannot tell comes from the user: the lamp's
angles (`--light-deg`, or a CSV of `file,light_deg[,view_deg]`), and the plate's and the
setup's tables, written once in a layout file and reused (`--layout`: the scene file's own
`[specimen]`, `[markers]`, `[light]` and `[camera]`). docs/first-photo-set.md walks through it.

Nothing is overwritten (`write_draft`): the draft goes to `scene.toml`, or to
`scene.draft.toml` beside an existing one; when both exist, init refuses.
"""

from __future__ import annotations

import csv
import difflib
import io
import math
import os
import tomllib
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from . import _draft_pose as pose
from . import _draft_survey as survey
from ._draft_toml import Entry, Table, Todo, collect_todos, from_raw, render, stand_ins
from .errors import UserError
from .fileio import FileTooLargeError, describe, read_bytes
from .scene import (
    SCENE_FILE,
    SCENE_VERSION,
    Layout,
    RawTable,
    parse_layout,
    parse_scene,
    todo_fields,
)

if TYPE_CHECKING:
    from stairfit import imaging

DRAFT_FILE = "scene.draft.toml"
"""Where the draft goes when the folder already has a scene.toml."""
MAX_SMALL_FILE = 16 * 2**20
"""The largest layout or angles file read (16 MiB; either is a few kB)."""
ANGLE_COLUMNS = ("file", "light_deg", "view_deg")
"""The columns of an angles file: `file` and `light_deg` required, `view_deg` optional."""

LIGHT_TODO = (
    "the lamp's angle from the base normal in degrees (positive: on the downhill side of the "
    "wedges; docs/scene.md), e.g. 20"
)
VIEW_TODO = (
    "the camera's angle from the base normal in degrees (positive: on the uphill side), e.g. -40"
)


@dataclass(frozen=True)
class AngleRow:
    """One row of an angles file: its line number, file name, lamp and (optional) view angle."""

    line: int
    file: str
    light_deg: float
    view_deg: float | None


@dataclass(frozen=True)
class DraftedView:
    """What init wrote for one view (for its summary): files, angles and where they came
    from, the marker estimate and the TODO fields."""

    files: tuple[str, ...]
    light_deg: float | None
    light_source: str
    view_deg: float | None
    view_source: str
    """"markers" for an estimate, else the angles file's line, or why there is none."""
    estimate: pose.ViewEstimate | None


@dataclass(frozen=True)
class Draft:
    """A drafted scene file: its text, the views, the calibration frames, the camera's focal
    length (None: not estimated) and the fields still holding a TODO."""

    text: str
    views: tuple[DraftedView, ...]
    flat_field: tuple[str, ...]
    dark_frames: tuple[str, ...]
    focal: pose.Focal | None
    todos: tuple[str, ...]


# --- the user's inputs ---------------------------------------------------------------------


def _read_text(path: Path, what: str) -> str:
    """A small UTF-8 text file, or one line saying what is wrong with it."""
    problem = describe(path)
    if problem is not None:
        raise UserError(f"{path}: {problem}; give the {what}")
    try:
        return read_bytes(path, MAX_SMALL_FILE).decode("utf-8-sig")
    except UnicodeDecodeError:
        raise UserError(f"{path}: not a UTF-8 text file; save the {what} as UTF-8") from None
    except FileTooLargeError as e:
        raise UserError(f"{path}: {e.strerror} for a {what}") from None
    except OSError as e:
        raise UserError(
            f"{path}: cannot read it ({e.strerror or e}); check its permissions"
        ) from None


def read_layout(path: Path) -> tuple[RawTable, Layout]:
    """A layout file's tables as written (for the draft) and validated (`scene.parse_layout`)."""
    text = _read_text(path, "layout file (TOML: [specimen], [markers], [light], [camera])")
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise UserError(f"{path}: not valid TOML ({e}); fix the syntax at that line") from None
    except RecursionError:
        raise UserError(f"{path}: its tables are nested too deeply to read") from None
    return raw, parse_layout(raw, path)


def _number(text: str, path: Path, line: int, column: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise UserError(
            f"{path}: line {line}: {column} {text!r} is not a number; give degrees, e.g. 20"
        ) from None
    if not (math.isfinite(value) and -90.0 <= value <= 90.0):
        raise UserError(f"{path}: line {line}: {column} {text} is outside [-90, 90] degrees")
    return value


def read_angles(path: Path) -> tuple[AngleRow, ...]:
    """The rows of an angles file: a CSV whose first line names the columns `file`,
    `light_deg` and optionally `view_deg` (degrees, base frame; docs/first-photo-set.md)."""
    text = _read_text(path, "angles file (CSV: file,light_deg[,view_deg])")
    reader = csv.reader(io.StringIO(text))
    try:
        header = [h.strip() for h in next(reader, [])]
        rows = list(reader)
    except csv.Error as e:
        raise UserError(
            f"{path}: not a CSV file ({e}); write file,light_deg[,view_deg] rows"
        ) from None
    missing = [c for c in ANGLE_COLUMNS[:2] if c not in header]
    unknown = [h for h in header if h not in ANGLE_COLUMNS]
    if unknown:
        near = difflib.get_close_matches(unknown[0], ANGLE_COLUMNS, n=1)
        hint = f"did you mean {near[0]!r}?" if near else "the columns are file, light_deg, view_deg"
        raise UserError(f"{path}: line 1: unknown column {unknown[0]!r}; {hint}")
    if missing:
        raise UserError(
            f"{path}: line 1: no column {' or '.join(map(repr, missing))}; the first line must "
            "name the columns, e.g. file,light_deg,view_deg"
        )
    out, seen = [], {}
    for line, row in enumerate(rows, start=2):
        if not any(c.strip() for c in row):
            continue
        if len(row) != len(header):
            raise UserError(f"{path}: line {line}: {len(row)} values for {len(header)} columns")
        cell = {h: c.strip() for h, c in zip(header, row, strict=True)}
        if not cell["file"]:
            raise UserError(f"{path}: line {line}: file is empty; give the photo's file name")
        if cell["file"] in seen:
            raise UserError(
                f"{path}: line {line}: {cell['file']!r} is also on line "
                f"{seen[cell['file']]}; give each photo once"
            )
        seen[cell["file"]] = line
        view = cell.get("view_deg", "")
        out.append(
            AngleRow(
                line,
                cell["file"],
                _number(cell["light_deg"], path, line, "light_deg"),
                _number(view, path, line, "view_deg") if view else None,
            )
        )
    if not out:
        raise UserError(f"{path}: no rows after the header; give one row per photo")
    return tuple(out)


def check_light_deg(values: Sequence[float]) -> None:
    """`--light-deg` values must be finite angles in [-90, 90] degrees."""
    for v in values:
        if not (math.isfinite(v) and -90.0 <= v <= 90.0):
            raise UserError(f"--light-deg: {v:g} is outside [-90, 90] degrees")


# --- the folder ----------------------------------------------------------------------------


def survey_folder(folder: Path, progress: bool = False) -> tuple[survey.RawFile, ...]:
    """Every RAW file of the folder, surveyed (`_draft_survey.survey`); one line naming the
    file when one cannot be read."""
    from tqdm import tqdm

    from stairfit import imaging

    if not folder.is_dir():
        what = describe(folder) or "is not a folder"
        raise UserError(f"{folder}: {what}; give the folder that holds the photos")
    try:
        paths = survey.raw_files(folder)
    except OSError as e:
        raise UserError(
            f"{folder}: cannot list it ({e.strerror or e}); check its permissions"
        ) from None
    if not paths:
        kinds = ", ".join(sorted(survey.RAW_EXTENSIONS)[:8])
        raise UserError(
            f"{folder}: no camera RAW files ({kinds}, ...); give the folder that holds the photos"
        )
    out = []
    for path in tqdm(paths, desc="reading photos", unit="file", disable=not progress):
        try:
            out.append(survey.survey(path))
        except imaging.ImagingError as e:
            text = str(e).split(": ", 1)[-1] if str(e).startswith("photo ") else str(e)
            raise UserError(
                f"{path}: cannot be read as a photo ({text}); move it out of the "
                "folder (init reads every RAW file in it)"
            ) from None
    return tuple(out)


def sort_files(
    files: Sequence[survey.RawFile], folder: Path
) -> tuple[
    tuple[survey.View, ...], list[tuple[survey.RawFile, str]], list[tuple[survey.RawFile, str]]
]:
    """(views, flat fields, dark frames) of the surveyed files, each frame with why it is one.
    One image size for all: one camera's photo set per folder."""
    sizes: dict[tuple[int, int], list[str]] = {}
    for f in files:
        sizes.setdefault((f.width, f.height), []).append(f.name)
    if len(sizes) > 1:
        listed = "; ".join(f"{w} x {h} px: {', '.join(n[:3])}{', ...' * (len(n) > 3)}"
                           for (w, h), n in sizes.items())  # fmt: skip
        raise UserError(
            f"{folder}: the RAW files differ in size ({listed}); keep one camera's photo set "
            "(photos, flat fields, dark frames at one image size) per folder"
        )
    kinds = [(f, *survey.kind(f)) for f in files]
    photos = [f for f, k, _ in kinds if k == "photo"]
    flats = [(f, why) for f, k, why in kinds if k == "flat"]
    darks = [(f, why) for f, k, why in kinds if k == "dark"]
    if not photos:
        raise UserError(
            f"{folder}: no photograph among the {len(files)} RAW files ({len(flats)} look like "
            f"flat fields, {len(darks)} like dark frames); init needs photos of the wedges"
        )
    return survey.group_views(photos), flats, darks


# --- the lamp's angles ---------------------------------------------------------------------


def _angles_per_view(
    views: Sequence[survey.View],
    light_deg: Sequence[float],
    rows: Sequence[AngleRow],
    angles_path: Path | None,
    frames: set[str],
) -> list[tuple[float | None, str, float | None, str]]:
    """Per view: (light_deg, its source, view_deg given, its source)."""
    if light_deg and len(light_deg) not in (1, len(views)):
        raise UserError(
            f"--light-deg: {len(light_deg)} values for {len(views)} views; give one for every "
            "photo, one per view in the order init lists them, or an --angles file"
        )
    if light_deg:
        values = list(light_deg) * (len(views) if len(light_deg) == 1 else 1)
        return [(v, "--light-deg", None, "") for v in values]
    owner = {name: k for k, v in enumerate(views) for name in v.names}
    given: dict[int, AngleRow] = {}
    for row in rows:
        if row.file in frames:
            raise UserError(
                f"{angles_path}: line {row.line}: {row.file!r} is a flat field or "
                "dark frame, not a photograph; remove the row"
            )
        if row.file not in owner:
            near = difflib.get_close_matches(row.file, list(owner), n=1)
            hint = f"did you mean {near[0]!r}?" if near else "give a RAW file of the folder"
            raise UserError(
                f"{angles_path}: line {row.line}: {row.file!r} is not a photo in the folder; {hint}"
            )
        k = owner[row.file]
        if k in given and (given[k].light_deg, given[k].view_deg) != (row.light_deg, row.view_deg):
            raise UserError(
                f"{angles_path}: line {row.line}: {row.file!r} is in one bracket with "
                f"{given[k].file!r} (line {given[k].line}) but has other angles"
            )
        given[k] = row
    name = angles_path.name if angles_path else ""
    return [
        (
            given[k].light_deg,
            f"{name} line {given[k].line}",
            given[k].view_deg,
            f"{name} line {given[k].line}",
        )
        if k in given
        else (None, "", None, "")
        for k in range(len(views))
    ]


# --- markers and view angles ---------------------------------------------------------------


def _marker_layout(layout: Layout) -> imaging.MarkerLayout:
    from stairfit import imaging

    m = layout.markers
    assert m is not None
    return imaging.MarkerLayout(
        {x.id: x.corners_mm for x in m.markers}, m.dictionary, m.min_markers
    )


def _detect(
    folder: Path, view: survey.View, layout: imaging.MarkerLayout
) -> tuple[imaging.MarkerDetection, str]:
    """The markers of a view: of its exposures, the detection with most layout markers."""
    from stairfit import imaging

    ids = [m for m, _ in layout.markers]
    best = None
    for f in view.files:
        det = imaging.detect_markers(
            imaging.decode_raw(folder / f.name),
            layout.dictionary,
            layout.detector,
            expected_ids=ids,
        )
        found = len(set(det.ids) & set(ids))
        if best is None or found > best[0]:
            best = (found, det, f.name)
    assert best is not None
    return best[1], best[2]


def _edges(folder: Path, view: survey.View) -> Callable[[], list[pose.EdgeImage]]:
    """A callable giving a view's edge images (decoded only when called)."""
    from stairfit import imaging

    def make() -> list[pose.EdgeImage]:
        frames = [imaging.decode_raw(folder / f.name) for f in view.files]
        return pose.edge_images(frames, [f.exposure for f in view.files])

    return make


def _focal(
    layout: Layout,
    views: Sequence[survey.View],
    detections: Sequence[imaging.MarkerDetection],
    marker_layout: imaging.MarkerLayout,
) -> pose.Focal:
    """The focal length: the layout's, the tags', or the markers' (`_draft_pose`)."""
    if layout.camera.focal_length_px is not None:
        return pose.Focal(layout.camera.focal_length_px, "the layout", from_layout=True)
    tags = pose.focal_from_tags([f.tags for v in views for f in v.files])
    if tags is not None:
        return tags
    size = (views[0].files[0].width, views[0].files[0].height)
    return pose.focal_from_markers(detections, marker_layout, size)


def estimate_views(
    folder: Path, views: Sequence[survey.View], layout: Layout, progress: bool = False
) -> tuple[pose.Focal, list[tuple[pose.ViewEstimate, str]]]:
    """The focal length and, per view, its view-angle estimate and the file whose markers
    were used."""
    from tqdm import tqdm

    marker_layout = _marker_layout(layout)
    found = [
        _detect(folder, v, marker_layout)
        for v in tqdm(views, desc="finding markers", unit="view", disable=not progress)
    ]
    focal = _focal(layout, views, [d for d, _ in found], marker_layout)
    faces = [
        (w.face_mm, w.angle_deg)
        for w in (layout.specimen.wedges if layout.specimen else ())
        if w.face_mm is not None
    ]
    out = []
    for view, (det, member) in zip(views, found, strict=True):
        size = (view.files[0].width, view.files[0].height)
        photo = pose.PhotoMarkers(det, marker_layout, size, tuple(faces), _edges(folder, view))
        est = pose.estimate_view(photo, focal)
        out.append((est, member))
    return focal, out


# --- the document --------------------------------------------------------------------------


def _skeleton(name: str) -> Table:
    """A table the layout did not give, with TODOs for what a scene needs from it."""
    if name == "specimen":
        wedge = Table(
            "specimen.wedges",
            (
                Entry("name", "w1", "one [[specimen.wedges]] table per wedge, each name unique"),
                Entry("angle_deg", Todo("the wedge angle in degrees, e.g. 30", 30.0)),
                Entry(
                    "roi_px",
                    Todo(
                        "the face in pixels, [[x, y], ...], the same in every photo "
                        "(or face_mm and [markers] in a layout: docs/scene.md)",
                        [[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]],
                    ),
                ),
            ),
            array=True,
        )
        return Table(
            "specimen",
            (
                Entry("layer_um", Todo("the layer thickness in micrometres, e.g. 150", 150.0)),
                Entry("material", "pla", 'a named material (README "Materials") or an index table'),
            ),
            children=(wedge,),
            notes=("no layout gave [specimen]: docs/scene.md",),
        )
    if name == "light":
        return Table(
            "light",
            (
                Entry(
                    "illuminant",
                    Todo("the lamp's spectrum, a CIE illuminant such as D65 or A", "D65"),
                ),
                Entry(
                    "angular_diameter_deg",
                    Todo(
                        "the lamp's angular size seen from the specimen in degrees, e.g. 1.0", 1.0
                    ),
                ),
            ),
            notes=("no layout gave [light]: docs/scene.md",),
        )
    return Table(
        "camera",
        (
            Entry(
                "sensitivity",
                Todo(
                    "the camera's channel sensitivities, one of Nikon 5100 (NPL), "
                    "Sigma SDMerill (NPL) or ideal (docs/scene.md)",
                    "ideal",
                ),
            ),
            Entry(
                "angular_extent_deg",
                Todo(
                    "the spread of viewing angles across one face in "
                    "degrees (face length / distance), e.g. 1.0",
                    1.0,
                ),
            ),
        ),
        notes=("no layout gave [camera]: docs/scene.md",),
    )


def _camera_table(raw: RawTable, focal: pose.Focal | None) -> Table:
    """The layout's [camera] (or a skeleton), with the estimated focal length added."""
    table = from_raw("camera", raw["camera"]) if "camera" in raw else _skeleton("camera")
    if focal is None or focal.from_layout:
        return table
    if focal.focal_length_px is None:
        return Table(
            table.path,
            table.entries,
            notes=(*table.notes, f"no focal_length_px: {focal.source}"),
            children=table.children,
        )
    entry = Entry(
        "focal_length_px", round(focal.focal_length_px, 2), f"estimated from {focal.source}"
    )
    return Table(table.path, (*table.entries, entry), notes=table.notes, children=table.children)


def _calibration_table(
    flats: Sequence[tuple[survey.RawFile, str]], darks: Sequence[tuple[survey.RawFile, str]]
) -> Table | None:
    entries = []
    for key, frames, what in (
        ("flat_field", flats, "flat fields"),
        ("dark_frames", darks, "dark frames"),
    ):
        if frames:
            why = "; ".join(f"{f.name}: {w}" for f, w in frames[:3])
            more = f"; and {len(frames) - 3} more" if len(frames) > 3 else ""
            entries.append(
                Entry(key, [f.name for f, _ in frames], f"recognised as {what} ({why}{more})")
            )
    return Table("calibration", tuple(entries)) if entries else None


def _exposure_entries(view: survey.View) -> list[Entry]:
    """Exposure overrides for files whose tags lack one: TODO where no tag gives it."""
    if all(f.exposure is not None for f in view.files):
        return []
    out = []
    keys = ("exposure_time_s", "f_number", "iso")
    texts = (
        "the exposure time in seconds, e.g. 0.125",
        "the f-number, e.g. 8",
        "the ISO, e.g. 100",
    )
    stand = (1.0, 8.0, 100.0)
    for j, (key, text, s) in enumerate(zip(keys, texts, stand, strict=True)):
        values = [
            f.tag_exposure[j] if f.tag_exposure[j] is not None else Todo(text, s)
            for f in view.files
        ]
        if all(not isinstance(v, Todo) for v in values):
            continue
        value = values[0] if len(values) == 1 else values
        out.append(Entry(key, value, "the file has no such tag"))
    return out


def _view_entry(
    given: float | None, given_source: str, est: pose.ViewEstimate | None, no_markers: str
) -> tuple[Entry, float | None, str]:
    """The view_deg line, the value written (None: a TODO) and its source in words: the
    angle given (`--angles`), else the markers' estimate, else a TODO saying why."""
    if given is not None:
        said = f" (the markers say {est.view_deg:.4g})" if est and est.view_deg is not None else ""
        return Entry("view_deg", given, f"given by {given_source}{said}"), given, given_source
    if est is not None and est.view_deg is not None:
        value = round(est.view_deg, 3)
        return Entry("view_deg", value, f"estimated from {est.source}"), value, "markers"
    why = est.problem if est is not None else no_markers
    return Entry("view_deg", Todo(f"{VIEW_TODO}; {why}", 0.0)), None, why


def _photo_table(
    view: survey.View,
    member: str,
    angles: tuple[float | None, str, float | None, str],
    est: pose.ViewEstimate | None,
    no_markers: str,
) -> tuple[Table, DraftedView]:
    """One [[photos]] table (files, light_deg, view_deg, exposure overrides where a tag is
    missing) with its notes, and its summary."""
    light, light_src, view_given, view_src = angles
    names = list(view.names)
    bracket = f": one view at {len(names)} exposures (an HDR bracket, the shortest first)"
    notes = [", ".join(names) + (bracket if len(names) > 1 else "")]
    taken = [f.tags.taken for f in view.files if f.tags.taken]
    notes += [f"taken {taken[0]}"] if taken else []
    if est is not None and est.ids:
        notes.append(f"markers {' '.join(map(str, est.ids))} of {member} used")
    light_entry = (
        Entry("light_deg", light, f"given by {light_src}")
        if light is not None
        else Entry("light_deg", Todo(LIGHT_TODO, 0.0))
    )
    view_entry, view_value, source = _view_entry(view_given, view_src, est, no_markers)
    file_value = names[0] if len(names) == 1 else names
    entries = (Entry("file", file_value), light_entry, view_entry, *_exposure_entries(view))
    table = Table("photos", entries, array=True, notes=tuple(notes))
    return table, DraftedView(tuple(names), light, light_src, view_value, source, est)


def _header(
    files: Sequence[survey.RawFile],
    views: Sequence[survey.View],
    n_flat: int,
    n_dark: int,
    layout_path: Path | None,
) -> list[str]:
    """The comment lines at the top of the draft."""
    cameras = sorted({f.camera or "unknown camera" for f in files})
    sizes = sorted({f"{f.width} x {f.height} px" for f in files})
    brackets = sum(len(v.files) > 1 for v in views)
    return [
        f"stairfit scene file drafted by `stairfit init` from the {len(files)} RAW files of this",
        "folder (docs/first-photo-set.md, every field: docs/scene.md). Check every value: each",
        'estimate says where it came from. A value that is a string starting with "TODO:" is',
        "one init could not know: replace the string with the value; `stairfit fit` and",
        "`stairfit measure` refuse the file until none is left.",
        f"Camera: {', '.join(cameras)}; {', '.join(sizes)}.",
        f"{len(views)} views ({brackets} of them HDR brackets), {n_flat} flat "
        f"field{'s' * (n_flat != 1)}, {n_dark} dark frame{'s' * (n_dark != 1)}.",
        f"[specimen], [light], [camera] and [markers] from the layout {layout_path.name}."
        if layout_path
        else "No layout given (--layout): [specimen], [light] and [camera] are to be filled in.",
    ]


def _target(folder: Path) -> Path:
    """scene.toml, or scene.draft.toml beside an existing one; refused when both exist."""
    for name in (SCENE_FILE, DRAFT_FILE):
        if not os.path.lexists(folder / name):
            return folder / name
    raise UserError(
        f"{folder}: both {SCENE_FILE} and {DRAFT_FILE} exist; init never replaces a file: move "
        f"or delete {DRAFT_FILE} to draft again"
    )


def _validate(text: str, tables: Sequence[Table], target: Path) -> None:
    """The draft must validate once every TODO holds its stand-in (a bug or a layout that
    cannot describe these photos otherwise: one line saying which)."""
    raw = stand_ins(tomllib.loads(text), collect_todos(tables))
    try:
        parse_scene(raw, target)
    except UserError as e:
        raise UserError(
            f"the drafted scene would not validate: {e}; check the layout and the angles given"
        ) from None


def draft_scene(
    folder: Path,
    layout_path: Path | None = None,
    light_deg: Sequence[float] = (),
    angles_path: Path | None = None,
    progress: bool = False,
) -> Draft:
    """Draft the scene file of a folder of photos (module docstring). `layout_path`: the
    layout file; `light_deg`: one lamp angle for every photo or one per view; `angles_path`:
    a CSV of `file,light_deg[,view_deg]` instead. User mistakes raise `UserError`."""
    check_light_deg(light_deg)
    raw, layout = read_layout(layout_path) if layout_path else ({}, None)
    rows = read_angles(angles_path) if angles_path else ()
    files = survey_folder(folder, progress)
    views, flats, darks = sort_files(files, folder)
    frames = {f.name for f, _ in (*flats, *darks)}
    angles = _angles_per_view(views, light_deg, rows, angles_path, frames)
    focal, estimates = None, [(None, "")] * len(views)
    no_markers = (
        "no layout (--layout) with [markers] to estimate it from"
        if layout is None
        else "the layout has no [markers] to estimate it from"
    )
    if layout is not None and layout.markers is not None:
        focal, estimates = estimate_views(folder, views, layout, progress)
    tables = [
        Table(
            "",
            (
                Entry("version", SCENE_VERSION),
                Entry(
                    "angles_relative_to",
                    "base",
                    "light_deg and view_deg below are measured from the base normal "
                    "(docs/scene.md)",
                ),
            ),
        )
    ]
    for name in ("specimen", "light"):
        tables.append(from_raw(name, raw[name]) if name in raw else _skeleton(name))
    tables.append(_camera_table(raw, focal))
    if "markers" in raw:
        tables.append(from_raw("markers", raw["markers"]))
    calibration = _calibration_table(flats, darks)
    tables += [calibration] if calibration else []
    drafted = []
    for view, angle, (est, member) in zip(views, angles, estimates, strict=True):
        table, summary = _photo_table(view, member, angle, est, no_markers)
        tables.append(table)
        drafted.append(summary)
    text = render(tables, _header(files, views, len(flats), len(darks), layout_path))
    target = folder / SCENE_FILE
    _validate(text, tables, target)
    todos = tuple(w for w, _ in todo_fields(tomllib.loads(text)))
    return Draft(
        text,
        tuple(drafted),
        tuple(f.name for f, _ in flats),
        tuple(f.name for f, _ in darks),
        focal,
        todos,
    )


def write_draft(folder: Path, draft: Draft) -> Path:
    """Write the draft to scene.toml, or to scene.draft.toml beside an existing scene.toml;
    never over an existing file (created by a hard link of a finished temporary file, which
    fails if the name exists: `fileio.create_text`)."""
    from .fileio import create_text

    target = _target(folder)
    try:
        create_text(target, draft.text)
    except FileExistsError:
        raise UserError(
            f"{target}: appeared while init ran; init never replaces a file, run it again"
        ) from None
    except OSError as e:
        raise UserError(
            f"{folder}: cannot write {target.name} ({e.strerror or e}); check the "
            "folder's permissions"
        ) from None
    return target
