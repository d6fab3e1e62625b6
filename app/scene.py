"""The scene file: what was photographed, how, and where the wedges are in each photo.

A TOML file (`scene.toml`) in the photo folder. TOML because Python reads it without an extra
dependency (`tomllib`), it allows comments (the annotated example in docs/scene.md), and its
types are unambiguous (no YAML "Norway problem": `no` stays a string). Every table is
validated: unknown fields are errors with a suggestion, missing fields name the fix, values are
range-checked. Angles are in degrees here (an edge of the program) [conventions §1].
"""

from __future__ import annotations

import difflib
import math
import os
import tomllib
from dataclasses import dataclass, field, replace
from pathlib import Path
from types import EllipsisType
from typing import TYPE_CHECKING, TypeVar, overload

from .errors import UserError
from .fileio import FileTooLargeError, describe, read_bytes, resolved

if TYPE_CHECKING:
    from stairfit.model.materials import Dispersion, PerChannel

SCENE_FILE = "scene.toml"
SCENE_VERSION = 1
Polygon = tuple[tuple[float, float], ...]
MetadataValue = str | int | float
IndexParam = float | tuple[float, ...]
RawTable = dict[str, object]
"""A table of a scene file as read from TOML, before validation (values of any TOML type)."""
T = TypeVar("T")
D = TypeVar("D")
CHANNELS = ("R", "G", "B")
"""The camera channels, in the order of per-channel fields: `imaging.CHANNELS`, restated so that
reading a scene file does not import the imaging stack (cv2, rawpy)."""


@dataclass(frozen=True)
class IndexSpec:
    """The dispersion model: a named material, or explicit parameters [conventions §7]."""

    model: str  # "named", "constant", "cauchy", "sellmeier", "tabulated", "per_channel"
    name: str = "pla"
    params: tuple[tuple[str, IndexParam], ...] = ()

    def build(self) -> Dispersion | PerChannel:
        """The `stairfit.model.materials` object this spec describes."""
        from stairfit.model import materials

        p = dict(self.params)
        if self.model == "named":
            return materials.get_material(self.name)
        if self.model == "constant":
            return materials.ConstantIndex(n=p["n"], k=p.get("k", 0.0))
        if self.model == "cauchy":
            return materials.Cauchy(
                a=p["a"], b_um2=p.get("b_um2", 0.0), c_um4=p.get("c_um4", 0.0), k=p.get("k", 0.0)
            )
        if self.model == "sellmeier":
            return materials.Sellmeier(c0=p.get("c0", 0.0), b=tuple(p["b"]), c_um=tuple(p["c_um"]))
        if self.model == "per_channel":  # not a dispersion model: one index per channel
            return materials.PerChannel(n=tuple(p["n"]), k=tuple(p["k"]) if any(p["k"]) else ())
        return materials.Tabulated(
            wavelength_nm=tuple(p["wavelength_nm"]),
            n=tuple(p["n"]),
            k=tuple(p["k"]) if "k" in p else None,
        )


@dataclass(frozen=True)
class Wedge:
    """One printed wedge: its angle and where its face is (pixels, or base-plane mm)."""

    name: str
    angle_deg: float
    roi_px: Polygon | None = None
    face_mm: Polygon | None = None


@dataclass(frozen=True)
class Specimen:
    """The printed specimen: layer thickness, material and wedges [conventions §2]."""

    layer_um: float
    index: IndexSpec
    wedges: tuple[Wedge, ...]
    metadata: tuple[tuple[str, MetadataValue], ...] = ()
    """Free `[specimen.metadata]` (printer, nozzle temperature, ...): key = string or number."""
    plate_albedo: float = 0.0
    """Lambertian reflectance of the plate the wedges stand on: the lab model adds the plate's
    light that the risers reflect into a downhill view (0: not modelled)."""


@dataclass(frozen=True)
class Light:
    """The light source: spectrum by name, angular diameter and shape [conventions §8, §9]:
    "uniform" (every in-plane offset across the diameter alike) or "disk" (a round light).

    A near lamp (docs/scene.md "A near lamp") has a position in the base frame (mm):
    `position_mm`, one point for every photo, or `distance_mm` from the base frame's origin,
    placed by each photo's `light_deg`; a photo's own `light_position_mm` wins over both.
    `diameter_mm` is its physical size; `angular_diameter_deg` is then the size seen from the
    origin. All None: a distant light, the same direction at every face.
    """

    illuminant: str = "D65"
    angular_diameter_deg: float = 0.0
    shape: str = "uniform"
    diameter_mm: float | None = None
    distance_mm: float | None = None
    position_mm: tuple[float, float, float] | None = None

    @property
    def near(self) -> bool:
        """Whether the lamp has a position (a near lamp) rather than only a direction."""
        return self.distance_mm is not None or self.position_mm is not None


@dataclass(frozen=True)
class Camera:
    """The camera: channel sensitivities by name, and the spread of viewing angles over a face.

    `focal_length_px` and `principal_point_px` (optional, pixels of the full-resolution raw
    image) make it a pinhole for placing wedge faces in 3-D from the markers; without them an
    affine camera is assumed (docs/imaging.md §3-D placement). `plane_of_incidence`: the image
    direction of the plane of incidence for roi_px polygons, "vertical" or "horizontal"
    (docs/imaging.md §Viewing spread).
    """

    sensitivity: str = "ideal"
    angular_extent_deg: float = 0.0
    focal_length_px: float | None = None
    principal_point_px: tuple[float, float] | None = None
    plane_of_incidence: str = "vertical"


@dataclass(frozen=True)
class Marker:
    """One ArUco marker on the base: its id and its corners in base-plane millimetres."""

    id: int
    corners_mm: Polygon


@dataclass(frozen=True)
class Markers:
    """The marker layout used to place ROIs automatically."""

    dictionary: str
    markers: tuple[Marker, ...]
    min_markers: int = 2


@dataclass(frozen=True)
class Reference:
    """An optional reference patch (grey card or flat plate) measured in every photo."""

    name: str
    roi_px: Polygon | None = None
    face_mm: Polygon | None = None


@dataclass(frozen=True)
class BracketFile:
    """A further exposure of a photo's view (an HDR bracket), with its own exposure overrides."""

    file: str
    exposure_time_s: float | None = None
    f_number: float | None = None
    iso: float | None = None


@dataclass(frozen=True)
class Photo:
    """One photograph: its file, geometry and optional overrides.

    `file` is the photo's (first) file and its name in the results; an HDR bracket (`file` a
    list in the scene file) has its further exposures in `bracket`. The overrides here are the
    first file's. `light_deg` and `view_deg` are always set in a scene for `fit`; a
    measure-only scene of patches alone (no [specimen]) may leave them out (None).
    """

    file: str
    light_deg: float | None
    view_deg: float | None
    exposure_time_s: float | None = None
    f_number: float | None = None
    iso: float | None = None
    roi_px: tuple[tuple[str, Polygon], ...] = ()
    bracket: tuple[BracketFile, ...] = ()
    light_position_mm: tuple[float, float, float] | None = None
    """This photo's lamp position in the base frame (mm), overriding `[light]`'s."""

    @property
    def files(self) -> tuple[str, ...]:
        """Every file of this view: the photo's file, then the bracket's further exposures."""
        return (self.file, *(b.file for b in self.bracket))


@dataclass(frozen=True)
class CalibrationFrames:
    """Flat-field photos and dark frames (file names in the scene's folder); docs/scene.md."""

    flat_field: tuple[str, ...] = ()
    dark_frames: tuple[str, ...] = ()
    flat_degree: int = 8


@dataclass(frozen=True)
class Patch:
    """A named patch measured by `stairfit measure` (a colour-chart patch, a grey card): its
    pixel polygon in every photo, or its outline on the base (flat, placed by the markers)."""

    name: str
    roi_px: Polygon | None = None
    face_mm: Polygon | None = None


GEOMETRIES: dict[str, str] = {
    "auto": "the lab model when the lamp is near (its position given), else in the plane",
    "lab": "the lab model: each face's own 3-D light and view directions",
    "in_plane": "one plane of incidence and a distant light for every face",
}
"""`[fit] geometry`: which directions the fit models (docs/scene.md "Which model of the
directions")."""


@dataclass(frozen=True)
class FitSettings:
    """The optional `[fit]` table: `geometry`, one of `GEOMETRIES`."""

    geometry: str = "auto"


@dataclass(frozen=True)
class Extraction:
    """Settings for turning pixels into measurements (see docs/imaging.md)."""

    erode_px: int = 8
    block_px: int = 2
    saturation_level: float = 0.98
    max_saturated_fraction: float = 0.5


TRUTH_FIELDS: tuple[str, ...] = (
    "sigma_deg",
    "delta_n",
    "edge_radius_um",
    "fillet_radius_um",
    "scale",
    "floor",
)
"""The fields of `[truth]`: the physical parameters `stairfit simulate` renders from, named and
in the units of truth.json and results.json (`sigma_deg` in degrees, radii in micrometres)."""


@dataclass(frozen=True)
class SceneTruth:
    """Known values of the physical parameters (the optional `[truth]` table; docs/scene.md).

    The truth of a synthetic scene (`stairfit simulate` writes it) or values measured
    independently (a micrograph's tip and fillet radii). The fit does not use them; the report
    and results.json show them beside the fitted values. None where not given.
    """

    sigma_deg: float | None = None
    delta_n: float | None = None
    edge_radius_um: float | None = None
    fillet_radius_um: float | None = None
    scale: float | None = None
    floor: float | None = None

    def items(self) -> tuple[tuple[str, float], ...]:
        """The given values as (field, value), in `TRUTH_FIELDS` order."""
        return tuple((k, v) for k in TRUTH_FIELDS if (v := getattr(self, k)) is not None)


@dataclass(frozen=True)
class Scene:
    """A validated scene file. `angles_relative_to` says how photo angles are given."""

    path: Path
    angles_relative_to: str
    specimen: Specimen | None  # None only in a measure-only scene of patches
    light: Light
    camera: Camera
    photos: tuple[Photo, ...]
    markers: Markers | None = None
    reference: Reference | None = None
    extraction: Extraction = field(default_factory=Extraction)
    patches: tuple[Patch, ...] = ()
    calibration: CalibrationFrames | None = None
    truth: SceneTruth | None = None
    fit: FitSettings = field(default_factory=FitSettings)
    left_out: tuple[str, ...] = ()
    """Why each photo listed in the file but not in `photos` was left out (`load_scene`)."""

    @property
    def folder(self) -> Path:
        """The photo folder (the scene file's folder)."""
        return self.path.parent

    def input_fields(self) -> tuple[tuple[str, str, Path], ...]:
        """Every file the scene lists: (scene field, name as written, absolute resolved path).

        Photos and their bracket members (`photos[k].file`, `photos[k].file[j]`), then the
        calibration frames (`calibration.flat_field[j]`, `calibration.dark_frames[j]`).
        """
        out = []
        for k, photo in enumerate(self.photos):
            if not photo.bracket:
                out.append((f"photos[{k}].file", photo.file))
            else:
                out += [(f"photos[{k}].file[{j}]", f) for j, f in enumerate(photo.files)]
        if self.calibration is not None:
            c = self.calibration
            out += [(f"calibration.flat_field[{j}]", f) for j, f in enumerate(c.flat_field)]
            out += [(f"calibration.dark_frames[{j}]", f) for j, f in enumerate(c.dark_frames)]
        return tuple((where, name, resolved(self.folder / name)) for where, name in out)

    def input_files(self) -> tuple[Path, ...]:
        """Every file this scene makes a run read, as absolute resolved paths, without repeats.

        The scene file, then each photo's file (every member of a bracket), then the flat-field
        photos and dark frames (`input_fields`). Whoever adds a new kind of input file adds it
        there: outputs are refused when they would replace any of these (app/outputs.py).
        """
        files = [resolved(self.path), *(path for _, _, path in self.input_fields())]
        return tuple(dict.fromkeys(files))

    def lamp_position_mm(self, photo: Photo) -> tuple[float, float, float] | None:
        """The lamp's centre in the base frame (mm) for this photo, or None for a distant light.

        The photo's `light_position_mm`, else `[light] position_mm`, else the point at
        `[light] distance_mm` from the origin in the direction of the photo's `light_deg`:
        `distance_mm * (-sin L, 0, cos L)` (a positive `light_deg` is on the downhill side,
        [conventions §1]; docs/scene.md "A near lamp").
        """
        if photo.light_position_mm is not None:
            return photo.light_position_mm
        if self.light.position_mm is not None:
            return self.light.position_mm
        if self.light.distance_mm is None or photo.light_deg is None:
            return None
        a, d = math.radians(photo.light_deg), self.light.distance_mm
        return (-d * math.sin(a), 0.0, d * math.cos(a))

    def face_angles_deg(self, photo: Photo, wedge: Wedge) -> tuple[float, float]:
        """(theta_i, theta_o) of this photo in this wedge's face frame, degrees.

        With `angles_relative_to = "base"` the photo's angles are measured from the normal of
        the specimen base, with the same sign rules as the face frame [conventions §1]: a
        positive `light_deg` puts the light on the downhill side, a positive `view_deg` the
        camera on the uphill side. The face is the base tilted by `beta2` towards downhill, so
        `theta_i = light_deg - beta2` and `theta_o = view_deg + beta2`. With
        `angles_relative_to = "face"` they are used as they are (same for every wedge).
        """
        if self.angles_relative_to == "face":
            return photo.light_deg, photo.view_deg
        return photo.light_deg - wedge.angle_deg, photo.view_deg + wedge.angle_deg


# --- loading and validation -----------------------------------------------------------------


MAX_NAME = 100
"""The longest name of a wedge, patch or reference patch."""
TODO_PREFIX = "TODO:"
"""How `stairfit init` marks a value it could not know: a string starting with this in place
of the value (docs/first-photo-set.md). A scene that still holds one is refused."""
MAX_SCENE_BYTES = 16 * 2**20
"""The largest scene file read (16 MiB; a scene of a thousand photos is well under 1 MiB)."""


def load_scene(path: Path, measure_only: bool = False) -> Scene:
    """Read and validate a scene file (or the `scene.toml` inside a folder).

    `measure_only` (for `stairfit measure`) also allows `[[patches]]`, beside or instead of
    `[specimen]`, and photos without angles when there is no specimen.
    """
    path = Path(path)
    problem = describe(path)
    if problem == "does not exist":
        raise UserError(
            f"{path}: no such folder or file; give the photo folder that holds {SCENE_FILE}"
        )
    if path.is_dir():
        path = path / SCENE_FILE
        problem = describe(path)
    if problem == "does not exist":
        raise UserError(
            f"{path}: no scene file; write one (annotated example: docs/scene.md, or run "
            "'stairfit simulate OUT' to see a complete one)"
        )
    if problem is not None:
        raise UserError(f"{path}: {problem}, not a scene file; make it a UTF-8 TOML text file")
    try:
        text = read_bytes(path, MAX_SCENE_BYTES).decode("utf-8-sig")  # a BOM (Notepad) is fine
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise UserError(f"{path}: not valid TOML ({e}); fix the syntax at that line") from None
    except RecursionError:
        raise UserError(
            f"{path}: its tables or arrays are nested too deeply to read; a scene file needs a "
            "few levels (docs/scene.md)"
        ) from None
    except UnicodeDecodeError:
        raise UserError(f"{path}: not a UTF-8 text file; save it as UTF-8 TOML") from None
    except FileTooLargeError as e:
        raise UserError(f"{path}: {e.strerror} for a scene file; give the scene's TOML") from None
    except OSError as e:
        raise UserError(
            f"{path}: cannot read the scene file ({e.strerror or e}); check its permissions"
        ) from None
    return parse_scene(raw, path, measure_only)


def todo_fields(raw: object, where: str = "") -> list[tuple[str, str]]:
    """Every (field, text) of a scene (or layout) dict whose value is still a TODO string that
    `stairfit init` wrote (`TODO_PREFIX`), in the file's order."""
    if isinstance(raw, str):
        return [(where, raw)] if raw.startswith(TODO_PREFIX) else []
    if isinstance(raw, dict):
        return [t for k, v in raw.items() for t in todo_fields(v, _join(where, str(k)))]
    if isinstance(raw, list):
        return [t for k, v in enumerate(raw) for t in todo_fields(v, f"{where}[{k}]")]
    return []


def _refuse_todos(raw: object, path: Path) -> None:
    """A one-line error naming the first TODO left in the file (and how many more)."""
    todos = todo_fields(raw)
    if not todos:
        return
    where, text = todos[0]
    more = ""
    if len(todos) > 1:
        listed = ", ".join(w for w, _ in todos[1:4]) + (", ..." if len(todos) > 4 else "")
        more = f" ({len(todos) - 1} more TODOs: {listed})"
    what = text.removeprefix(TODO_PREFIX).strip()
    raise UserError(
        f"{path}: {where}: still a TODO left by 'stairfit init' ({what}); replace the string "
        f"with the value{more}"
    )


def parse_scene(raw: RawTable, path: Path, measure_only: bool = False) -> Scene:
    """Validate a scene given as a dict (as read from TOML); see `load_scene`. A value still
    marked as a TODO by `stairfit init` is refused first."""
    _refuse_todos(raw, path)
    r = _Reader(path)
    top = r.table(
        raw,
        "",
        [
            "version",
            "angles_relative_to",
            "specimen",
            "light",
            "camera",
            "photos",
            "markers",
            "reference",
            "extraction",
            "fit",
            "patches",
            "calibration",
            "truth",
        ],
    )
    version = r.get(top, "version", int, "", default=SCENE_VERSION)
    if version != SCENE_VERSION:
        r.fail("version", f"is {version}; this stairfit reads version {SCENE_VERSION}")
    relative = r.get(top, "angles_relative_to", str, "", default="base")
    if relative not in ("base", "face"):
        r.fail("angles_relative_to", f'is {relative!r}; use "base" or "face"')
    if "patches" in top and not measure_only:
        r.fail("patches", "named patches are measured by 'stairfit measure' only; remove them")
    patch_only = measure_only and "patches" in top and "specimen" not in top
    specimen = None if patch_only else _specimen(r, r.need_table(top, "specimen", ""))
    light = _light(r, r.opt_table(top, "light", ""))
    camera = _camera(r, r.opt_table(top, "camera", ""))
    markers = _markers(r, top["markers"], "markers") if "markers" in top else None
    reference = _reference(r, top["reference"], "reference") if "reference" in top else None
    extraction = _extraction(r, r.opt_table(top, "extraction", ""))
    fit = _fit_settings(r, r.opt_table(top, "fit", ""))
    patches = _patches(r, top, specimen, reference, markers) if "patches" in top else ()
    photos = _photos(r, top, specimen, tuple(x.name for x in patches))
    calibration = _calibration(r, top["calibration"]) if "calibration" in top else None
    truth = _truth(r, top["truth"], specimen) if "truth" in top else None
    scene = Scene(
        path, relative, specimen, light, camera, photos, markers, reference, extraction, patches,
        calibration, truth, fit,
    )  # fmt: skip
    _check_input_paths(r, scene)
    if specimen is not None:
        _check_geometry(r, scene)
        _check_rois(r, scene)
        scene = _without_blind_photos(scene)
    return scene


def _without_blind_photos(scene: Scene) -> Scene:
    """`scene` without the photos in which no wedge face is both lit and seen (each named in
    `left_out`): such a photo holds no measurement, and the others are still worth fitting."""
    assert scene.specimen is not None
    keep, left = [], []
    for photo in scene.photos:
        if any(visible(scene, photo, w) for w in scene.specimen.wedges) or photo.roi_px:
            keep.append(photo)
        else:
            left.append(
                f"photo {photo.file!r} left out: no wedge face is both lit and seen in it "
                f"(light_deg {photo.light_deg}, view_deg {photo.view_deg}: every face is "
                f"lit or seen more than {VISIBILITY_LIMIT_DEG:g} deg from its normal)"
            )
    return replace(scene, photos=tuple(keep), left_out=tuple(left)) if left else scene


LAYOUT_TABLES: tuple[str, ...] = ("specimen", "markers", "light", "camera")
"""The tables of a layout file (`stairfit init --layout`): the scene file's own, nothing else."""


@dataclass(frozen=True)
class Layout:
    """A validated layout file: a plate's and a setup's tables, written once and reused by
    `stairfit init` for every photo set of them (docs/first-photo-set.md). None where the file
    has no such table (`light` and `camera` then take the scene file's defaults)."""

    specimen: Specimen | None
    light: Light
    camera: Camera
    markers: Markers | None


def parse_layout(raw: RawTable, path: Path) -> Layout:
    """Validate a layout given as a dict (as read from TOML): its tables are checked as in a
    scene file, and every wedge needs roi_px, or face_mm and a [markers] table."""
    _refuse_todos(raw, path)
    r = _Reader(path)
    if not isinstance(raw, dict):
        r.fail("top level", "must be a table")
    for key in raw:
        if key not in LAYOUT_TABLES:
            r.fail(key, "a layout holds only the [specimen], [markers], [light] and "
                   "[camera] tables of a scene file; remove it (init writes the rest)")  # fmt: skip
    specimen = _specimen(r, raw["specimen"]) if "specimen" in raw else None
    light = _light(r, raw.get("light", {}))
    camera = _camera(r, raw.get("camera", {}))
    markers = _markers(r, raw["markers"], "markers") if "markers" in raw else None
    for k, w in enumerate(specimen.wedges if specimen else ()):
        if w.roi_px is None and (w.face_mm is None or markers is None):
            r.fail(
                f"specimen.wedges[{k}]",
                f"wedge {w.name!r} needs roi_px (pixels, the same in every photo), or face_mm "
                "(its outline on the base) and a [markers] table",
            )
    return Layout(specimen, light, camera, markers)


class _Reader:
    """Reads fields with messages naming the file and the field path."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def fail(self, where: str, what: str) -> None:
        raise UserError(f"{self.path}: {where}: {what}")

    def table(self, d: object, where: str, allowed: list[str]) -> RawTable:
        if not isinstance(d, dict):
            self.fail(where or "top level", "must be a table")
        for key in d:
            if key not in allowed:
                near = difflib.get_close_matches(key, allowed, n=1)
                hint = (
                    f"; did you mean {near[0]!r}?" if near else f"; allowed: {', '.join(allowed)}"
                )
                self.fail(_join(where, key), f"unknown field{hint}")
        return d

    def need_table(self, d: RawTable, key: str, where: str) -> RawTable:
        if key not in d:
            self.fail(_join(where, key), "missing; add this table (see docs/scene.md)")
        return d[key]

    def opt_table(self, d: RawTable, key: str, where: str) -> RawTable:
        return d.get(key, {})

    @overload
    def get(
        self, d: RawTable, key: str, kind: type[T], where: str, default: EllipsisType = ...,
        lo: float | None = None, hi: float | None = None,
    ) -> T: ...  # fmt: skip

    @overload
    def get(
        self, d: RawTable, key: str, kind: type[T], where: str, default: D,
        lo: float | None = None, hi: float | None = None,
    ) -> T | D: ...  # fmt: skip

    def get(
        self,
        d: RawTable,
        key: str,
        kind: type[T],
        where: str,
        default: object = ...,
        lo: float | None = None,
        hi: float | None = None,
    ) -> object:
        """Field `key` of `d`, of type `kind` (an int is taken as a float) within [lo, hi];
        `default` when absent (missing is an error without one)."""
        name = _join(where, key)
        if key not in d:
            if default is ...:
                self.fail(name, f"missing; add {key} = ... (see docs/scene.md)")
            return default
        v = d[key]
        if kind is float and isinstance(v, int) and not isinstance(v, bool):
            v = float(v)
        if not isinstance(v, kind) or (isinstance(v, bool) and kind is not bool):
            self.fail(name, f"must be {_kind_name(kind)}, not {v!r}")
        if kind is float and not math.isfinite(v):
            self.fail(name, f"must be a finite number, not {v!r}")
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            self.fail(name, f"{v!r} is outside [{lo}, {hi}]; fix the value")
        return v

    def name(self, d: RawTable, where: str, default: str | EllipsisType = ...) -> str:
        """A `name` field (of a wedge, a patch, the reference): a non-empty string, at most
        `MAX_NAME` characters (it names columns, files and lines of a report)."""
        v = self.get(d, "name", str, where, default=default)
        if not v.strip():
            self.fail(_join(where, "name"), f'{v!r} is empty; give a name such as "w30"')
        if len(v) > MAX_NAME:
            self.fail(_join(where, "name"), f"has {len(v)} characters; keep it to {MAX_NAME}")
        return v

    def choice(self, d: RawTable, key: str, where: str, choices: dict[str, str]) -> str:
        """A string field that must be one of `choices` (value -> meaning; the first is the
        default); the error lists each with its meaning."""
        v = self.get(d, key, str, where, default=next(iter(choices)))
        if v not in choices:
            listed = "; ".join(f'"{c}" ({m})' for c, m in choices.items())
            self.fail(_join(where, key), f"{v!r} is not one of: {listed}")
        return v

    def polygon(self, d: RawTable, key: str, where: str) -> Polygon | None:
        if key not in d:
            return None
        name = _join(where, key)
        v = d[key]
        ok = (
            isinstance(v, list)
            and len(v) >= 3
            and all(isinstance(p, list) and len(p) == 2 and all(_is_real(c) for c in p) for p in v)
        )
        if not ok:
            self.fail(
                name,
                "must be a list of at least 3 [x, y] points, e.g. [[10, 10], "
                "[200, 10], [200, 150], [10, 150]]",
            )
        _check_polygon(self, name, v)
        return tuple((float(p[0]), float(p[1])) for p in v)


def _specimen(r: _Reader, d: RawTable) -> Specimen:
    w = "specimen"
    r.table(d, w, ["layer_um", "material", "index", "wedges", "metadata", "plate_albedo"])
    layer = r.get(d, "layer_um", float, w, lo=1.0, hi=10_000.0)
    plate_albedo = r.get(d, "plate_albedo", float, w, default=0.0, lo=0.0, hi=1.0)
    if "index" in d and "material" in d:
        r.fail(f"{w}.index", "give either 'material' (a name) or an 'index' table, not both")
    if "index" in d:
        index = _index(r, d["index"], f"{w}.index")
    else:
        name = r.get(d, "material", str, w, default="pla")
        from stairfit.model import materials

        if name.lower() not in materials.MATERIALS:
            near = difflib.get_close_matches(name.lower(), list(materials.MATERIALS), n=1)
            hint = (
                f"did you mean {near[0]!r}?" if near else f"known: {', '.join(materials.MATERIALS)}"
            )
            r.fail(f"{w}.material", f"unknown material {name!r}; {hint}")
        index = IndexSpec("named", name=name.lower())
    wedges_raw = d.get("wedges")
    if not isinstance(wedges_raw, list) or not wedges_raw:
        r.fail(
            f"{w}.wedges",
            "missing or empty; add [[specimen.wedges]] tables with name and angle_deg",
        )
    wedges = []
    for k, wd in enumerate(wedges_raw):
        where = f"{w}.wedges[{k}]"
        r.table(wd, where, ["name", "angle_deg", "roi_px", "face_mm"])
        wedges.append(
            Wedge(
                name=r.name(wd, where),
                angle_deg=r.get(wd, "angle_deg", float, where, lo=0.01, hi=89.99),
                roi_px=r.polygon(wd, "roi_px", where),
                face_mm=r.polygon(wd, "face_mm", where),
            )
        )
    names = [x.name for x in wedges]
    dup = {x for x in names if names.count(x) > 1}
    if dup:
        r.fail(f"{w}.wedges", f"duplicate wedge name(s) {sorted(dup)}; names must be unique")
    metadata = _metadata(r, d.get("metadata", {}), f"{w}.metadata")
    return Specimen(layer, index, tuple(wedges), metadata, plate_albedo)


def _truth(r: _Reader, d: object, specimen: Specimen | None) -> SceneTruth:
    """`[truth]`: known parameter values, each optional and checked like the simulator's
    options; the radii must fit every wedge of the specimen (docs/rounded.md §1)."""
    w = "truth"
    if specimen is None:
        r.fail(w, "the truth describes a specimen; add [specimen] or remove [truth]")
    r.table(d, w, list(TRUTH_FIELDS))
    v = {k: r.get(d, k, float, w, default=None) for k in TRUTH_FIELDS}
    if v["sigma_deg"] is not None and not 0.0 < v["sigma_deg"] <= 90.0:
        r.fail(f"{w}.sigma_deg", f"{v['sigma_deg']!r} is outside (0, 90] deg; fix the value")
    if v["scale"] is not None and not v["scale"] > 0.0:
        r.fail(f"{w}.scale", f"{v['scale']!r} must be > 0; fix the value")
    for key, meaning in (
        ("floor", "0 = no diffuse floor"),
        ("edge_radius_um", "0 = sharp layer edges"),
        ("fillet_radius_um", "0 = sharp concave corners"),
    ):
        if v[key] is not None and v[key] < 0.0:
            r.fail(f"{w}.{key}", f"{v[key]!r} is negative; give a value >= 0 ({meaning})")
    _check_truth_radii(r, specimen, v["edge_radius_um"] or 0.0, v["fillet_radius_um"] or 0.0)
    return SceneTruth(**v)


def _check_truth_radii(r: _Reader, specimen: Specimen, tip_um: float, fillet_um: float) -> None:
    """Tip arcs and fillets must fit the cell of every wedge: `r <= min(l1, l2)` and
    `r_f <= min(l1, l2) - r`, `l2 = l1 cot beta2` [conventions §2] (`model.max_edge_radius`,
    `model.max_fillet_radius`), with the model's relative slack of 1e-12."""
    if tip_um == 0.0 and fillet_um == 0.0:
        return
    import numpy as np

    from stairfit import model

    beta2 = np.deg2rad([x.angle_deg for x in specimen.wedges])
    room = np.asarray(model.max_edge_radius(beta2, specimen.layer_um), float)
    k = int(np.argmin(room))  # the finest cell limits both radii
    wedge, cap = specimen.wedges[k], float(room[k])
    cell = (
        f"wedge {wedge.name!r} ({wedge.angle_deg:g} deg, layer_um {specimen.layer_um:g}), "
        f"whose min(l1, l2) = {cap:.6g} um"
    )
    if tip_um > cap * (1 + 1e-12):
        r.fail("truth.edge_radius_um", f"{tip_um:g} um does not fit {cell}; give at most {cap:.6g}")
    rf_max = float(np.asarray(model.max_fillet_radius(beta2, specimen.layer_um, tip_um))[k])
    if fillet_um > rf_max + cap * 1e-12:
        r.fail(
            "truth.fillet_radius_um",
            f"{fillet_um:g} um does not fit beside truth.edge_radius_um = {tip_um:g} um on "
            f"{cell}: r + r_f must not exceed it; give at most {rf_max:.6g} um (or a smaller "
            "edge_radius_um)",
        )


def _metadata(r: _Reader, d: object, w: str) -> tuple[tuple[str, MetadataValue], ...]:
    """`[specimen.metadata]`: free key = value pairs, each a string or a finite number."""
    if not isinstance(d, dict):
        r.fail(w, 'must be a table of key = value, e.g. printer = "MK4", nozzle_c = 215')
    items = []
    for key, v in d.items():
        if isinstance(v, float) and not math.isfinite(v):
            r.fail(f"{w}.{key}", f"must be a finite number, not {v!r}")
        if isinstance(v, dict | list):
            r.fail(
                f"{w}.{key}",
                f"is a {'table' if isinstance(v, dict) else 'list'}; metadata values are single "
                f'strings or numbers, e.g. {key} = "..."',
            )
        if isinstance(v, bool) or not isinstance(v, str | int | float):
            r.fail(f"{w}.{key}", f'must be a string or a number, not {v!r}; quote it: "{v}"')
        items.append((str(key), v))
    return tuple(items)


def _index(r: _Reader, d: RawTable, w: str) -> IndexSpec:
    models = {
        "constant": (["n"], ["k"]),
        "cauchy": (["a"], ["b_um2", "c_um4", "k"]),
        "sellmeier": (["b", "c_um"], ["c0"]),
        "tabulated": (["wavelength_nm", "n"], ["k"]),
        "per_channel": (["n"], ["k"]),
    }
    if not isinstance(d, dict):
        r.fail(w, 'must be a table such as { model = "constant", n = 1.46 }')
    model = r.get(d, "model", str, w)
    if model not in models:
        r.fail(f"{w}.model", f"is {model!r}; use one of {', '.join(models)}")
    need, optional = models[model]
    r.table(d, w, ["model", *need, *optional])
    params: dict[str, IndexParam] = {}
    for key in need + optional:
        if key not in d:
            if key in need:
                r.fail(f"{w}.{key}", f"missing; the {model} model needs {', '.join(need)}")
            continue
        v = d[key]
        if isinstance(v, list):
            if not v or not all(_is_num(x) for x in v):
                r.fail(f"{w}.{key}", "must be a non-empty list of numbers")
            params[key] = tuple(float(x) for x in v)
        elif _is_num(v):
            params[key] = float(v)
        else:
            r.fail(f"{w}.{key}", f"must be a number or list of numbers, not {v!r}")
    if model == "tabulated":
        lens = {len(params[k]) for k in ("wavelength_nm", "n", "k") if k in params}
        if len(lens) != 1:
            r.fail(w, "wavelength_nm, n (and k) must have the same length")
    if model == "sellmeier" and len(params["b"]) != len(params["c_um"]):
        r.fail(w, "b and c_um must have the same length")
    if model == "per_channel":
        return _per_channel_index(r, params, w)
    spec = IndexSpec(model, params=tuple(sorted(params.items())))
    _check_physical_index(r, spec, w)
    return spec


def _check_physical_index(r: _Reader, spec: IndexSpec, where: str) -> None:
    """The index must be physical over the whole spectral grid a fit can use [conventions §8]."""
    from stairfit.model import materials, spectral

    problem = materials.index_problem(spec.build(), spectral.VISIBLE_NM)
    if problem is not None:
        r.fail(where, f"{problem}; fix the {spec.model} coefficients")


def _per_channel_index(r: _Reader, params: dict[str, IndexParam], w: str) -> IndexSpec:
    """One index per camera channel, in R, G, B order; `k` one for all or one per channel
    [conventions §6, §7]."""
    n, k = params["n"], params.get("k", 0.0)
    if not isinstance(n, tuple) or len(n) != len(CHANNELS):
        r.fail(
            f"{w}.n",
            "must list one index per camera channel, in R, G, B order, e.g. n = [1.47, 1.46, 1.45]",
        )
    k = k if isinstance(k, tuple) else (k,) * len(CHANNELS)
    if len(k) != len(CHANNELS):
        r.fail(f"{w}.k", "must be one number for every channel, or 3 numbers in R, G, B order")
    for name, n_c, k_c in zip(CHANNELS, n, k, strict=True):
        if not (math.isfinite(n_c) and n_c > 1.0):
            r.fail(f"{w}.n", f"{n_c:g} for channel {name}; each index must be > 1 (e.g. 1.46)")
        if not (math.isfinite(k_c) and k_c >= 0.0):
            r.fail(f"{w}.k", f"{k_c:g} for channel {name}; the extinction k must be >= 0")
    return IndexSpec("per_channel", params=(("k", k), ("n", n)))


def _light(r: _Reader, d: RawTable) -> Light:
    r.table(d, "light", ["illuminant", "angular_diameter_deg", "shape", "diameter_mm",
                         "distance_mm", "position_mm"])  # fmt: skip
    ill = r.get(d, "illuminant", str, "light", default="D65")
    from stairfit.model import spectral

    try:
        spectral.illuminant_spd(ill)
    except ValueError as e:
        r.fail("light.illuminant", str(e))
    shape = r.choice(d, "shape", "light", {
        "uniform": "a bar across the plane of incidence: every in-plane offset alike",
        "disk": "a round light",
    })  # fmt: skip
    distance = r.get(d, "distance_mm", float, "light", default=None, lo=1.0, hi=1e6)
    position = _point_mm(r, d, "position_mm", "light")
    if distance is not None and position is not None:
        r.fail("light.position_mm", "give either distance_mm or position_mm, not both")
    size = r.get(d, "diameter_mm", float, "light", default=None, lo=0.0, hi=1e4)
    if size is not None and "angular_diameter_deg" in d:
        r.fail("light.diameter_mm", "give either diameter_mm or angular_diameter_deg, not both")
    if size is None:
        diameter = r.get(d, "angular_diameter_deg", float, "light", default=0.0, lo=0, hi=30)
    else:
        reach = distance if distance is not None else _norm(position)
        if reach is None:
            r.fail("light.diameter_mm", "needs the lamp's distance_mm or position_mm as well "
                   "(or give angular_diameter_deg instead)")  # fmt: skip
        if size >= reach:
            r.fail("light.diameter_mm", f"{size:g} mm is not smaller than the lamp's distance "
                   f"({reach:g} mm); check the units (millimetres)")  # fmt: skip
        diameter = math.degrees(2.0 * math.atan(0.5 * size / reach))
        if diameter > 30:
            r.fail("light.diameter_mm", f"the lamp would span {diameter:.3g} deg; at most 30")
    return Light(ill, diameter, shape, size, distance, position)


def _point_mm(r: _Reader, d: RawTable, key: str, where: str) -> tuple[float, float, float] | None:
    """An optional [x, y, z] point in base-frame millimetres, above the base (z > 0)."""
    if key not in d:
        return None
    v = d[key]
    if not (isinstance(v, list) and len(v) == 3 and all(_is_real(c) for c in v)):
        r.fail(_join(where, key), "must be [x, y, z] in millimetres of the base frame, "
               "e.g. [0, 0, 500]")  # fmt: skip
    x, y, z = (float(c) for c in v)
    if not all(math.isfinite(c) and abs(c) <= 1e6 for c in (x, y, z)):
        r.fail(_join(where, key), "must be finite, at most 1e6 mm from the origin")
    if z <= 0:
        r.fail(_join(where, key), f"z = {z:g} mm: the lamp must be above the base (z > 0)")
    return (x, y, z)


def _norm(p: tuple[float, float, float] | None) -> float | None:
    return None if p is None else math.sqrt(sum(c * c for c in p))


def _camera(r: _Reader, d: RawTable) -> Camera:
    fields = ["sensitivity", "angular_extent_deg", "focal_length_px", "principal_point_px",
              "plane_of_incidence"]  # fmt: skip
    r.table(d, "camera", fields)
    sens = r.get(d, "sensitivity", str, "camera", default="ideal")
    from stairfit.model import spectral

    if sens not in spectral.CAMERAS:
        r.fail(
            "camera.sensitivity", f"unknown camera {sens!r}; known: {', '.join(spectral.CAMERAS)}"
        )
    ext = r.get(d, "angular_extent_deg", float, "camera", default=0.0, lo=0, hi=30)
    focal = r.get(d, "focal_length_px", float, "camera", default=None, lo=1.0, hi=1e6)
    centre = d.get("principal_point_px")
    if centre is not None:
        if not (isinstance(centre, list) and len(centre) == 2 and all(map(_is_num, centre))):
            r.fail("camera.principal_point_px", "must be [cx, cy] in pixels, e.g. [2999.5, 1999.5]")
        if focal is None:
            r.fail("camera.principal_point_px", "needs camera.focal_length_px as well")
        centre = (float(centre[0]), float(centre[1]))
    plane = r.choice(d, "plane_of_incidence", "camera", {
        "vertical": "the light and the camera move up and down the image, the layer lines "
        "run across it",
        "horizontal": "they move across the image",
    })  # fmt: skip
    return Camera(sens, ext, focal, centre, plane)


def _markers(r: _Reader, d: object, w: str) -> Markers:
    r.table(d, w, ["dictionary", "min_markers", "marker"])
    items = d.get("marker")
    if not isinstance(items, list) or not items:
        r.fail(f"{w}.marker", "missing; add [[markers.marker]] tables with id and corners_mm")
    dictionary = r.get(d, "dictionary", str, w, default="DICT_4X4_50")
    size = _dictionary_size(r, dictionary, f"{w}.dictionary")
    markers: list[Marker] = []
    for k, m in enumerate(items):
        where = f"{w}.marker[{k}]"
        r.table(m, where, ["id", "corners_mm"])
        corners = r.polygon(m, "corners_mm", where)
        if corners is None or len(corners) != 4:
            r.fail(f"{where}.corners_mm", "must list the marker's 4 corners in mm")
        marker_id = r.get(m, "id", int, where, lo=0, hi=size - 1)
        same = [j for j, other in enumerate(markers) if other.id == marker_id]
        if same:
            r.fail(f"{where}.id", f"{marker_id} is also {w}.marker[{same[0]}].id; give each "
                   "marker its own id, as printed on the base")  # fmt: skip
        markers.append(Marker(marker_id, corners))
    least = r.get(d, "min_markers", int, w, default=2, lo=1, hi=1000)
    if "min_markers" in d and least > len(markers):
        r.fail(f"{w}.min_markers", f"{least} is more than the {len(markers)} markers listed; "
               f"give at most {len(markers)}")  # fmt: skip
    return Markers(dictionary=dictionary, markers=tuple(markers), min_markers=least)


def _dictionary_size(r: _Reader, name: str, where: str) -> int:
    """How many markers the ArUco dictionary `name` has (an unknown name is refused)."""
    import cv2

    code = getattr(cv2.aruco, name, None) if name.startswith("DICT_") else None
    if not isinstance(code, int):
        from stairfit.imaging import ARUCO_DICTIONARIES

        near = difflib.get_close_matches(name, ARUCO_DICTIONARIES, n=1)
        hint = f"did you mean {near[0]!r}?" if near else 'e.g. "DICT_4X4_50"'
        r.fail(where, f"{name!r} is not an OpenCV ArUco dictionary; {hint}")
    return int(cv2.aruco.getPredefinedDictionary(code).bytesList.shape[0])


def _reference(r: _Reader, d: object, w: str) -> Reference:
    r.table(d, w, ["name", "roi_px", "face_mm"])
    ref = Reference(
        r.name(d, w, default="reference"),
        r.polygon(d, "roi_px", w),
        r.polygon(d, "face_mm", w),
    )
    if ref.roi_px is None and ref.face_mm is None:
        r.fail(w, "give roi_px (pixels) or face_mm (base-plane mm, needs [markers])")
    return ref


def _fit_settings(r: _Reader, d: RawTable) -> FitSettings:
    r.table(d, "fit", ["geometry"])
    return FitSettings(r.choice(d, "geometry", "fit", GEOMETRIES))


def _extraction(r: _Reader, d: RawTable) -> Extraction:
    w = "extraction"
    r.table(d, w, ["erode_px", "block_px", "saturation_level", "max_saturated_fraction"])
    from stairfit.imaging import MAX_ERODE_PX  # erosion time grows as radius^2 x ROI area

    return Extraction(
        erode_px=r.get(d, "erode_px", int, w, default=8, lo=0, hi=MAX_ERODE_PX),
        block_px=r.get(d, "block_px", int, w, default=2, lo=2, hi=512),
        saturation_level=r.get(d, "saturation_level", float, w, default=0.98, lo=0.5, hi=1.0),
        max_saturated_fraction=r.get(
            d, "max_saturated_fraction", float, w, default=0.5, lo=0.0, hi=1.0
        ),
    )


def _patches(
    r: _Reader,
    top: RawTable,
    specimen: Specimen | None,
    reference: Reference | None,
    markers: Markers | None,
) -> tuple[Patch, ...]:
    """The `[[patches]]` of a measure-only scene: unique names, one polygon each."""
    items = top["patches"]
    if not isinstance(items, list) or not items:
        r.fail("patches", "must be [[patches]] tables with name and roi_px (or face_mm)")
    taken = {w.name for w in specimen.wedges} if specimen else set()
    taken |= {reference.name} if reference else set()
    patches = []
    for k, d in enumerate(items):
        w = f"patches[{k}]"
        r.table(d, w, ["name", "roi_px", "face_mm"])
        name = r.name(d, w)
        patch = Patch(name, r.polygon(d, "roi_px", w), r.polygon(d, "face_mm", w))
        if (patch.roi_px is None) == (patch.face_mm is None):
            r.fail(w, "give either roi_px (pixels) or face_mm (base-plane mm), one of them")
        if patch.face_mm is not None and markers is None:
            r.fail(f"{w}.face_mm", "needs a [markers] layout to be placed; or give roi_px")
        if patch.name in taken:
            r.fail(f"{w}.name", f"{patch.name!r} is already a wedge, patch or reference name")
        taken.add(patch.name)
        patches.append(patch)
    return tuple(patches)


def _photos(
    r: _Reader, top: RawTable, specimen: Specimen | None, patches: tuple[str, ...] = ()
) -> tuple[Photo, ...]:
    items = top.get("photos")
    if not isinstance(items, list) or not items:
        r.fail("photos", "missing or empty; add one [[photos]] table per photograph")
    names = {w.name for w in specimen.wedges} if specimen is not None else set()
    names |= set(patches)
    angle = ... if specimen is not None else None  # required unless there are no wedges
    photos = []
    for k, p in enumerate(items):
        w = f"photos[{k}]"
        r.table(
            p, w, ["file", "light_deg", "view_deg", "exposure_time_s", "f_number", "iso", "roi_px",
                   "light_position_mm"],
        )  # fmt: skip
        rois = p.get("roi_px", {})
        if not isinstance(rois, dict):
            r.fail(f"{w}.roi_px", "must be a table of wedge name = polygon")
        roi_items = []
        for name in rois:
            if name not in names:
                near = difflib.get_close_matches(name, sorted(names), n=1)
                hint = (
                    f"did you mean {near[0]!r}?" if near else f"wedges: {', '.join(sorted(names))}"
                )
                r.fail(f"{w}.roi_px.{name}", f"no such wedge; {hint}")
            roi_items.append((name, r.polygon(rois, name, f"{w}.roi_px")))
        files = _file_list(r, p, "file", w)
        overrides = _exposure_overrides(r, p, w, len(files))
        lamp = _point_mm(r, p, "light_position_mm", w)
        if lamp is not None and "light_deg" in p:
            r.fail(f"{w}.light_position_mm", "give either light_deg or light_position_mm, not both")
        light_deg = (
            r.get(p, "light_deg", float, w, default=angle, lo=-90, hi=90)
            if lamp is None
            else math.degrees(math.atan2(-lamp[0], lamp[2]))  # about y [conventions §1]
        )
        photos.append(
            Photo(
                file=files[0],
                light_deg=light_deg,
                view_deg=r.get(p, "view_deg", float, w, default=angle, lo=-90, hi=90),
                exposure_time_s=overrides[0][0],
                f_number=overrides[0][1],
                iso=overrides[0][2],
                roi_px=tuple(roi_items),
                bracket=tuple(
                    BracketFile(f, *o) for f, o in zip(files[1:], overrides[1:], strict=True)
                ),
                light_position_mm=lamp,
            )
        )
    return tuple(photos)


_OVERRIDES = (("exposure_time_s", 1e-6, 3600.0), ("f_number", 0.5, 256.0), ("iso", 1.0, 1e7))


def _file_list(r: _Reader, d: RawTable, key: str, where: str) -> tuple[str, ...]:
    """A file name, or a non-empty list of them (an HDR bracket of one view)."""
    name = _join(where, key)
    if key not in d:
        r.fail(name, f'missing; add {key} = "IMG_0001.dng" (or a list of files for a bracket)')
    v = d[key]
    items = v if isinstance(v, list) else [v]
    if not items or not all(isinstance(x, str) for x in items):
        r.fail(
            name, f'must be a file name or a list of file names, e.g. ["a.dng", "b.dng"], not {v!r}'
        )
    return tuple(items)


def _exposure_overrides(
    r: _Reader, d: RawTable, where: str, n_files: int
) -> list[tuple[float | None, float | None, float | None]]:
    """Per file (exposure_time_s, f_number, iso) overrides: a number applies to every file of
    a bracket, a list gives one value per file."""
    per_key = []
    for key, lo, hi in _OVERRIDES:
        v = d.get(key)
        if isinstance(v, list):
            if len(v) != n_files:
                r.fail(
                    _join(where, key),
                    f"lists {len(v)} values for {n_files} files; give one per file in 'file'",
                )
            vals = [r.get({key: x}, key, float, where, lo=lo, hi=hi) for x in v]
        else:
            vals = [r.get(d, key, float, where, default=None, lo=lo, hi=hi)] * n_files
        per_key.append(vals)
    return list(zip(*per_key, strict=True))


def _calibration(r: _Reader, d: object) -> CalibrationFrames:
    w = "calibration"
    r.table(d, w, ["flat_field", "dark_frames", "flat_degree"])
    flat = _file_list(r, d, "flat_field", w) if "flat_field" in d else ()
    dark = _file_list(r, d, "dark_frames", w) if "dark_frames" in d else ()
    if not flat and not dark:
        r.fail(w, "give flat_field (flat-field photos) and/or dark_frames (see docs/scene.md)")
    degree = r.get(d, "flat_degree", int, w, default=8, lo=2, hi=16)
    return CalibrationFrames(flat, dark, degree)


def _check_input_paths(r: _Reader, scene: Scene) -> None:
    """Every listed file (photos, bracket members, calibration frames) lies in the scene's
    folder (by its name) and is listed once (by path).

    `../x.dng` or an absolute path elsewhere is refused: results must not depend on files
    outside the folder, and a preview is never written outside the output. A link inside the
    folder may point anywhere (that is how to use photos kept elsewhere). Two names of one file
    (`./a.dng` and `a.dng`, or two links to it) are refused by comparing resolved paths.
    """
    folder = Path(os.path.abspath(r.path.parent))
    seen: dict[Path, tuple[str, str]] = {}
    for where, name, _ in scene.input_fields():
        lexical = Path(os.path.normpath(folder / name))
        if lexical == folder:
            r.fail(where, f"{name!r} names the photo folder, not a photo file")
        if folder not in lexical.parents:
            r.fail(
                where,
                f"{name!r} is outside the photo folder {folder}; copy the file (or a link to "
                "it) into the folder and give its name relative to the folder",
            )
        real = resolved(lexical)
        if real in seen:
            other_where, other = seen[real]
            what = (
                f"is listed twice (also as {other_where})"
                if other == name
                else f"is the same file as {other_where} {other!r}"
            )
            r.fail(where, f"{name!r} {what}; list every file once")
        seen[real] = (where, name)


VISIBILITY_LIMIT_DEG = 89.0
"""A wedge whose face is lit or seen at more than this from its normal is left out of a photo."""


def visible(scene: Scene, photo: Photo, wedge: Wedge) -> bool:
    """Whether the face of `wedge` is both lit and seen in `photo` (face angles below 89 deg).

    With angles relative to the base, steep wedges turn their faces away from some views
    (e.g. a 60-degree face is seen from behind once the camera is more than 30 degrees uphill);
    such a wedge is simply not measured in that photo [conventions §1].
    """
    ti, to = scene.face_angles_deg(photo, wedge)
    return abs(ti) < VISIBILITY_LIMIT_DEG and abs(to) < VISIBILITY_LIMIT_DEG


def _check_geometry(r: _Reader, scene: Scene) -> None:
    assert scene.specimen is not None
    patches = {p.name for p in scene.patches}
    for k, photo in enumerate(scene.photos):
        seen = [w for w in scene.specimen.wedges if visible(scene, photo, w)]
        for name, _ in photo.roi_px:
            if name in patches:
                continue
            wedge = next(w for w in scene.specimen.wedges if w.name == name)
            if wedge not in seen:
                ti, to = scene.face_angles_deg(photo, wedge)
                r.fail(
                    f"photos[{k}].roi_px.{name}",
                    f"this photo cannot see wedge {name!r}'s face lit (face-frame theta_i = "
                    f"{ti:g} deg, theta_o = {to:g} deg); fix light_deg/view_deg or drop the ROI",
                )
    blind = [
        k for k, p in enumerate(scene.photos)
        if not p.roi_px and not any(visible(scene, p, w) for w in scene.specimen.wedges)
    ]  # fmt: skip
    if blind and len(blind) == len(scene.photos) and not patches:
        r.fail(
            f"photos[{blind[0]}]",
            "no wedge face is both lit and visible in this photo, nor in any other; fix "
            "light_deg/view_deg or angles_relative_to",
        )


def _check_rois(r: _Reader, scene: Scene) -> None:
    assert scene.specimen is not None
    for k, photo in enumerate(scene.photos):
        per_photo = dict(photo.roi_px)
        for wedge in scene.specimen.wedges:
            placed = wedge.name in per_photo or wedge.roi_px is not None
            markers = wedge.face_mm is not None and scene.markers is not None
            if visible(scene, photo, wedge) and not placed and not markers:
                r.fail(
                    f"photos[{k}]",
                    f"no ROI for wedge {wedge.name!r}: give specimen.wedges roi_px, a per-photo "
                    "roi_px, or face_mm together with a [markers] layout",
                )


MAX_COORDINATE = 1e6
"""The largest |coordinate| of a polygon (pixels or millimetres): 1e300 overflowed OpenCV."""


def _check_polygon(r: _Reader, name: str, points: list[list[float]]) -> None:
    """Finite coordinates, and a simple outline (corners in order, not crossing)."""
    from ._polygons import polygon_problem

    for k, p in enumerate(points):
        if not all(math.isfinite(c) for c in p):
            r.fail(name, f"point {k} is {p!r}; every coordinate must be a finite number")
        if not all(abs(c) <= MAX_COORDINATE for c in p):
            r.fail(
                name,
                f"point {k} is {p!r}, beyond +-{MAX_COORDINATE:g}: no photo has such pixels and "
                "no base such millimetres; fix the coordinate",
            )
    problem = polygon_problem([(float(x), float(y)) for x, y in points])
    if problem is not None:
        r.fail(name, f"the polygon {problem}")


def _join(where: str, key: str) -> str:
    return f"{where}.{key}" if where else key


def _is_real(x: object) -> bool:
    """A number (finite or not; `_check_polygon` says which coordinate is not finite)."""
    return isinstance(x, int | float) and not isinstance(x, bool)


def _is_num(x: object) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)


def _kind_name(kind: type) -> str:
    return {float: "a number", int: "an integer", str: "a string", bool: "true or false"}.get(
        kind, kind.__name__
    )
