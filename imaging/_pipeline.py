"""From photo specifications to the measurement table: ROIs, statistics, cache, parallelism.

`measure_photos` is the entry point for the command line: it takes one `PhotoSpec` per photo
(what the scene file says about it) and `ExtractionSettings`, reuses cached rows (and cached
preview PNGs) when neither the photo's bytes nor its ROI definition changed, measures the rest in
parallel worker processes and returns (and caches) the `MeasurementTable`. See docs/imaging.md.
"""

from __future__ import annotations

import hashlib
import json
import math
import multiprocessing
import os
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import Future, ProcessPoolExecutor, ThreadPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from dataclasses import asdict, dataclass
from functools import partial
from pathlib import Path

from tqdm import tqdm

from ._cache import prune_previews, read_cache, write_cache
from ._checks import low_signal_warnings, same_bytes_warnings
from ._decode import CHANNELS, RawFrame, decode_raw, file_sha256
from ._errors import ImagingError, PhotosFailedError
from ._exposure import Exposure, resolve_exposure
from ._extract import ChannelStats, ExtractionSettings, roi_channel_stats
from ._io import atomic_write_bytes
from ._markers import MarkerDetection, MarkerLayout, detect_markers
from ._placement import (
    CameraPose,
    PinholeCamera,
    check_in_image,
    face_polygon,
    fit_camera_pose,
    hidden_fraction,
)
from ._preview import PREVIEW_MAX_SIZE, PREVIEW_VERSION, preview_png
from ._roi import Polygon, RoiMask, as_polygon, roi_mask
from ._table import MeasurementRow, MeasurementTable

TABLE_VERSION = 4
"""Part of every cache key: bump it when a change to the code changes measured values.

3: the exposure_source, marker_ids, marker_cell_px and placement columns (3-D placement).
4: rows flagged below_black carry NaN (were negative values).
"""


def _named_polygons(
    items: Mapping[str, object] | Sequence[tuple[str, object]], what: str
) -> tuple[tuple[str, Polygon], ...]:
    pairs = list(items.items()) if isinstance(items, Mapping) else list(items)
    out = []
    for name, poly in pairs:
        out.append((str(name), as_polygon(poly, f"{what} {name!r}")))  # type: ignore[arg-type]
    names = [n for n, _ in out]
    if len(set(names)) != len(names):
        raise ImagingError(f"{what}: names repeat: {names}")
    return tuple(out)


@dataclass(frozen=True)
class PhotoSpec:
    """Everything the measurement of one photo depends on, apart from `ExtractionSettings`.

    Attributes:
        path: the RAW file.
        name: the photo's name in the table and in messages (default: the file name); unique.
        exposure_time_s, f_number, iso: overrides of the EXIF exposure (None = use EXIF).
        rois: ROI polygons in pixel coordinates (docs/imaging.md §Pixels), name -> polygon (a
            mapping or (name, polygon) pairs). These win over `faces_mm` for the same name.
        faces_mm: ROI outlines in base-plane millimetres, placed in the photo through the
            markers (needs `markers`), name -> polygon.
        markers: the marker layout, needed when some name is only in `faces_mm`.
        reference: the name (in `rois` or `faces_mm`) of a reference patch: every other ROI's
            value is divided by the reference's value in the same photo and channel.
        face_angles_deg: the wedge angle beta2 (deg) of faces in `faces_mm`, name -> angle: the
            face rises along +x from its outline's foot and is placed in 3-D (docs/imaging.md
            §3-D placement). A face without an angle lies on the base.
        view_deg: the camera's direction from the base normal, a rotation about the layer lines
            (y; positive: the uphill side), base frame; needed to place rising faces without
            `camera`.
        camera: pinhole intrinsics (`PinholeCamera`), or None for an affine camera.
        occluders_mm: (name, outline on the base, beta2) of every wedge that may hide a placed
            face from the camera (default: the placed faces themselves).
    """

    path: Path
    name: str = ""
    exposure_time_s: float | None = None
    f_number: float | None = None
    iso: float | None = None
    rois: tuple[tuple[str, Polygon], ...] = ()
    faces_mm: tuple[tuple[str, Polygon], ...] = ()
    markers: MarkerLayout | None = None
    reference: str | None = None
    face_angles_deg: tuple[tuple[str, float], ...] = ()
    view_deg: float | None = None
    camera: PinholeCamera | None = None
    occluders_mm: tuple[tuple[str, Polygon, float], ...] = ()

    def __post_init__(self) -> None:
        path = Path(self.path)
        name = self.name or path.name
        object.__setattr__(self, "path", path)
        object.__setattr__(self, "name", name)
        object.__setattr__(self, "rois", _named_polygons(self.rois, f"photo {name!r}, ROI"))
        object.__setattr__(
            self, "faces_mm", _named_polygons(self.faces_mm, f"photo {name!r}, face_mm")
        )
        _check_geometry_fields(self)
        names = self.roi_names()
        if not names:
            raise ImagingError(f"photo {name!r}: no ROIs; give pixel polygons or faces in mm")
        if self.placed_names() and self.markers is None:
            raise ImagingError(
                f"photo {name!r}: ROIs {list(self.placed_names())} are given in base-plane mm "
                "but there is no marker layout; add a [markers] table or give roi_px polygons"
            )
        if self.reference is not None and self.reference not in names:
            raise ImagingError(
                f"photo {name!r}: the reference patch {self.reference!r} is not among the ROIs "
                f"{list(names)}"
            )
        if self.reference is not None and len(names) < 2:
            raise ImagingError(f"photo {name!r}: a reference patch needs at least one other ROI")

    def roi_names(self) -> tuple[str, ...]:
        """ROI names in table order: pixel polygons first, then marker-placed faces."""
        px = [n for n, _ in self.rois]
        return tuple(px + [n for n, _ in self.faces_mm if n not in px])

    def placed_names(self) -> tuple[str, ...]:
        """Names placed through the markers (in `faces_mm` and not in `rois`)."""
        px = {n for n, _ in self.rois}
        return tuple(n for n, _ in self.faces_mm if n not in px)

    def occluders(self) -> tuple[tuple[str, Polygon, float], ...]:
        """The wedges that may hide a face: `occluders_mm`, else every face with an angle."""
        if self.occluders_mm:
            return self.occluders_mm
        angles = dict(self.face_angles_deg)
        return tuple((n, p, angles[n]) for n, p in self.faces_mm if n in angles)


def _check_geometry_fields(spec: PhotoSpec) -> None:
    """Normalise and check `face_angles_deg`, `view_deg` and `occluders_mm` of a PhotoSpec."""
    name = spec.name
    angles = tuple((str(n), float(a)) for n, a in dict(spec.face_angles_deg).items())
    faces = {n for n, _ in spec.faces_mm}
    for n, a in angles:
        if n not in faces:
            raise ImagingError(f"photo {name!r}: face_angles_deg names {n!r}, not in faces_mm")
        if not (math.isfinite(a) and 0 <= a < 90):
            raise ImagingError(f"photo {name!r}, face {n!r}: the wedge angle {a} is not in [0, 90)")
    view = spec.view_deg
    if view is not None and not (math.isfinite(float(view)) and abs(float(view)) < 89.9):
        raise ImagingError(f"photo {name!r}: view_deg = {view!r} must be in (-89.9, 89.9)")
    occ = tuple(
        (str(n), as_polygon(p, f"photo {name!r}, occluder {n!r}"), float(a))
        for n, p, a in spec.occluders_mm
    )
    object.__setattr__(spec, "face_angles_deg", angles)
    object.__setattr__(spec, "view_deg", None if view is None else float(view))
    object.__setattr__(spec, "occluders_mm", occ)


@dataclass(frozen=True, eq=False)
class FrameMeasurement:
    """The result of measuring one decoded photo (for callers that want more than the rows)."""

    rows: tuple[MeasurementRow, ...]
    rois: dict[str, RoiMask]
    exposure: Exposure
    detection: MarkerDetection | None
    placement: CameraPose | None


def cache_key(spec: PhotoSpec, settings: ExtractionSettings) -> str:
    """A hash of everything but the photo's bytes that the photo's rows depend on."""
    payload = {
        "version": TABLE_VERSION,
        "rois": spec.rois,
        "faces_mm": spec.faces_mm,
        "markers": asdict(spec.markers) if spec.markers and spec.placed_names() else None,
        "geometry": [
            spec.face_angles_deg,
            spec.view_deg,
            asdict(spec.camera) if spec.camera else None,
            spec.occluders_mm,
        ]
        if spec.placed_names()
        else None,
        "reference": spec.reference,
        "exposure": [spec.exposure_time_s, spec.f_number, spec.iso],
        "settings": asdict(settings),
    }
    text = json.dumps(payload, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _check_overlaps(rois: dict[str, RoiMask], photo: str) -> None:
    """ImagingError if two eroded ROIs share pixels (their errors would not be independent)."""
    items = list(rois.values())
    for i, a in enumerate(items):
        for b in items[i + 1 :]:
            y0, x0 = max(a.y0, b.y0), max(a.x0, b.x0)
            y1 = min(a.y0 + a.mask.shape[0], b.y0 + b.mask.shape[0])
            x1 = min(a.x0 + a.mask.shape[1], b.x0 + b.mask.shape[1])
            if y0 >= y1 or x0 >= x1:
                continue
            ma = a.mask[y0 - a.y0 : y1 - a.y0, x0 - a.x0 : x1 - a.x0]
            mb = b.mask[y0 - b.y0 : y1 - b.y0, x0 - b.x0 : x1 - b.x0]
            n = int((ma & mb).sum())
            if n:
                raise ImagingError(
                    f"photo {photo!r}, wedges {a.name!r} and {b.name!r}: the ROIs overlap by "
                    f"{n} px after erosion; fix the polygons so that each pixel belongs to one ROI"
                )


def _flags(s: ChannelStats, settings: ExtractionSettings) -> list[str]:
    flags = []
    if s.n_in_roi == 0:
        flags.append("no_pixels")
    elif s.saturated_fraction > settings.max_saturated_fraction or s.n_pixels == 0:
        flags.append("saturated")
    if s.n_pixels > 0 and s.n_blocks < settings.min_blocks:
        flags.append("few_blocks")
    if s.mean_dn < -5 * s.stderr_dn:
        # E[raw - black] >= 0 with a correct black level; 5 sigma below is a wrong black level
        flags.append("below_black")
    return flags


def _radiance(s: ChannelStats, scale: float, flags: list[str]) -> tuple[float, float]:
    """(value, stderr) in relative radiance; NaN when below black (never a negative value)."""
    if "below_black" in flags:
        return math.nan, math.nan
    return s.mean_dn * scale, s.stderr_dn * scale


def measure_frame(
    frame: RawFrame, spec: PhotoSpec, settings: ExtractionSettings
) -> FrameMeasurement:
    """Measure every ROI of `spec` in a decoded photo.

    Places marker-based ROIs (when there are any), rasterises and erodes every ROI, resolves the
    exposure, computes the per-channel statistics, flags, and the optional reference
    normalisation.

    Raises:
        ImagingError: exposure unknown, ROI outside the image or empty after erosion, ROIs
            overlapping, too few markers or a poor marker fit; the message names photo and wedge.
    """
    photo = spec.name
    exposure = resolve_exposure(frame, spec.exposure_time_s, spec.f_number, spec.iso)
    polygons: dict[str, tuple[Polygon, str]] = {n: (p, "polygon") for n, p in spec.rois}
    detection, placement, placed_polygons = place_faces(frame, spec)
    polygons |= {n: (p, "markers") for n, p in placed_polygons.items()}
    rois = {
        n: roi_mask(
            polygons[n][0],
            (frame.height, frame.width),
            settings.erode_px,
            photo=photo,
            wedge=n,
            source=polygons[n][1],
        )
        for n in spec.roi_names()
    }
    if placement is not None:  # before the overlap check: a hidden face overlaps its hider
        _check_hidden(spec, placement, rois)
    _check_overlaps(rois, photo)
    key = cache_key(spec, settings)
    black = frame.black_level_per_channel()
    stats = {n: roi_channel_stats(frame, roi, settings) for n, roi in rois.items()}
    ref = stats[spec.reference] if spec.reference else None
    ref_flags = [_flags(s, settings) for s in ref] if ref else None
    rows = []
    for n, roi in rois.items():
        by_marker = roi.source == "markers" and placement is not None
        for c, s in enumerate(stats[n]):
            flags = _flags(s, settings)
            value, stderr = _radiance(s, exposure.scale, flags)
            normalised_by = ""
            if ref is not None and ref_flags is not None and n != spec.reference:
                r = ref[c]
                normalised_by = spec.reference or ""
                flags += [f"reference-{f}" for f in ref_flags[c]]
                if "below_black" in flags:
                    pass  # no ratio of a value below black: NaN, flagged
                elif r.mean_dn > 0:
                    ratio = s.mean_dn / r.mean_dn
                    stderr = math.hypot(s.stderr_dn / r.mean_dn, ratio * r.stderr_dn / r.mean_dn)
                    value = ratio
                else:
                    flags.append("reference-nonpositive")
                    value = stderr = math.nan
            rows.append(
                MeasurementRow(
                    photo=photo,
                    photo_sha256=frame.sha256,
                    settings_key=key,
                    wedge=n,
                    channel=CHANNELS[c],
                    value=float(value),
                    stderr=float(stderr),
                    n_pixels=s.n_pixels,
                    n_blocks=s.n_blocks,
                    saturated_fraction=float(s.saturated_fraction),
                    channel_corr=float(s.channel_corr),
                    flag=";".join(flags),
                    normalised_by=normalised_by,
                    exposure_time_s=exposure.exposure_time_s,
                    f_number=exposure.f_number,
                    iso=exposure.iso,
                    exposure_source=exposure.source,
                    black_level=black[c],
                    white_level=frame.white_level,
                    roi_source=roi.source,
                    reprojection_error_px=placement.rms_error_px if by_marker else None,  # type: ignore[union-attr]
                    n_markers=len(placement.ids) if by_marker else None,  # type: ignore[union-attr]
                    camera=frame.camera,
                    **_marker_columns(placement if by_marker else None, detection),
                )
            )
    return FrameMeasurement(tuple(rows), rois, exposure, detection, placement)


def place_faces(
    frame: RawFrame, spec: PhotoSpec
) -> tuple[MarkerDetection | None, CameraPose | None, dict[str, Polygon]]:
    """Detect the markers and place the faces of `spec.placed_names()`: (detection, camera,
    image polygons by name); (None, None, {}) when nothing is placed from markers.

    Faces with a wedge angle are placed in 3-D (docs/imaging.md §3-D placement).

    Raises:
        ImagingError: too few markers, an inconsistent camera, or a face outside the image.
    """
    placed = spec.placed_names()
    if not placed:
        return None, None, {}
    layout = spec.markers
    assert layout is not None  # checked by PhotoSpec
    ids = [m for m, _ in layout.markers]
    detection = detect_markers(frame, layout.dictionary, layout.detector, expected_ids=ids)
    angles = dict(spec.face_angles_deg)
    size = (frame.width, frame.height)
    pose = fit_camera_pose(
        detection,
        layout,
        photo=spec.name,
        image_size=size,
        rising=any(angles.get(n, 0.0) > 0 for n in placed),
        view_deg=spec.view_deg,
        camera=spec.camera,
        wedges=placed,
    )
    faces = dict(spec.faces_mm)
    polygons = {}
    for n in placed:
        polygons[n] = face_polygon(pose, faces[n], angles.get(n, 0.0))
        check_in_image(polygons[n], size, photo=spec.name, wedge=n)
    return detection, pose, polygons


def _check_hidden(spec: PhotoSpec, pose: CameraPose, rois: dict[str, RoiMask]) -> None:
    """ImagingError when another wedge hides part of a placed face's eroded ROI."""
    faces, angles = dict(spec.faces_mm), dict(spec.face_angles_deg)
    occluders = spec.occluders()
    for n in spec.placed_names():
        others = [o for o in occluders if o[0] != n]
        if not others:
            continue
        fraction, by = hidden_fraction(pose, faces[n], angles.get(n, 0.0), others, rois[n])
        if fraction > 0:
            raise ImagingError(
                f"photo {spec.name!r}, wedge {n!r}: {100 * fraction:.0f}% of the face's ROI is "
                f"hidden behind wedge {by!r} from this view; give a roi_px polygon for {n!r} in "
                "this photo that keeps to the visible part, or leave the photo out"
            )


def _marker_columns(pose: CameraPose | None, detection: MarkerDetection | None) -> dict:
    """The marker columns of a row: ids used, their smallest cell (px) and the camera model."""
    if pose is None or detection is None:
        return {"marker_ids": "", "marker_cell_px": None, "placement": ""}
    cells = dict(zip(detection.ids, detection.cell_px, strict=True))
    return {
        "marker_ids": " ".join(str(i) for i in pose.ids),
        "marker_cell_px": min(cells[i] for i in pose.ids),
        "placement": pose.model,
    }


def measure_photo(
    spec: PhotoSpec,
    settings: ExtractionSettings,
    preview: str | Path | None = None,
    *,
    preview_cache: str | Path | None = None,
) -> tuple[MeasurementRow, ...]:
    """Decode one photo, measure it, and optionally write its preview PNG.

    When the measurement fails after decoding, the preview is still written (with the markers
    found, if a layout was given) so that the failure can be looked at; then the error is raised.

    Args:
        spec, settings: what to measure and how.
        preview: the preview PNG to write, or None for none.
        preview_cache: a folder (`preview_cache_dir` of a measurement cache) where a copy of
            the preview of a successful measurement is kept under `cached_preview_name`, so
            that `measure_photos` can reuse it with the cached rows. Only used with `preview`.
    """
    frame = decode_raw(spec.path, spec.name)
    outcome, write = _measure_decoded(frame, spec, settings, preview, preview_cache)
    if write is not None:
        write()
    if isinstance(outcome, ImagingError):
        raise outcome
    return outcome


_PreviewJob = Callable[[], None]


def _measure_decoded(
    frame: RawFrame,
    spec: PhotoSpec,
    settings: ExtractionSettings,
    preview: str | Path | None,
    preview_cache: str | Path | None,
) -> tuple[tuple[MeasurementRow, ...] | ImagingError, _PreviewJob | None]:
    """`measure_photo` of a decoded photo, the preview left to the caller: (rows or error, job).

    The job (None without `preview`) renders the preview and writes it (and its cached copy
    after a success); it holds the frame until it has run.
    """
    try:
        result = measure_frame(frame, spec, settings)
    except ImagingError as e:
        if preview is None:
            raise
        det = (
            detect_markers(
                frame,
                spec.markers.dictionary,
                spec.markers.detector,
                expected_ids=[m for m, _ in spec.markers.markers],
            )
            if spec.markers
            else None
        )
        # for drawing roi_px by hand: the markers found, the given polygons, a pixel grid
        job = partial(_write_previews, frame, {}, det, settings, [Path(preview)], dict(spec.rois))
        return e, job
    if preview is None:
        return result.rows, None
    paths = [Path(preview)]
    if preview_cache is not None:
        name = cached_preview_name(frame.sha256, cache_key(spec, settings))
        paths.append(Path(preview_cache) / name)
    job = partial(_write_previews, frame, result.rois, result.detection, settings, paths)
    return result.rows, job


def _write_previews(
    frame: RawFrame,
    rois: dict[str, RoiMask],
    detection: MarkerDetection | None,
    settings: ExtractionSettings,
    paths: Sequence[Path],
    failed: dict[str, Polygon] | None = None,
) -> None:
    """Render a photo's preview once and write it (atomically) to each of `paths`.

    Only the first path is required; the others are cached copies, skipped when they cannot be
    written (a read-only photo folder: the next run renders the preview again). `failed` (the
    pixel polygons of a photo that could not be measured) draws those and a pixel grid.
    """
    level = settings.saturation_level
    png = preview_png(
        frame,
        rois,
        detection,
        saturation_level=level,
        max_size=PREVIEW_MAX_SIZE,
        grid=failed is not None,
        outlines=failed,
    )
    for k, path in enumerate(paths):
        try:
            atomic_write_bytes(path, png)
        except OSError:
            if k == 0:
                raise


def _measure_in_process(
    todo: Sequence[PhotoSpec],
    settings: ExtractionSettings,
    pdir: Path | None,
    pcache: Path | None,
    bar: tqdm,
) -> tuple[dict[str, tuple[MeasurementRow, ...]], dict[str, str]]:
    """Measure photos one after the other in this process: (rows by photo, errors by photo).

    Two helper threads keep a second core busy: one decodes the next photo while this one is
    measured, the other renders and writes the previous photo's preview (LibRaw, SHA-256,
    OpenCV, most of NumPy and file writes release the GIL). Each keeps at most one photo, so at
    most three photos are in memory.
    """
    done: dict[str, tuple[MeasurementRow, ...]] = {}
    errors: dict[str, str] = {}
    pending: tuple[str, Future] | None = None

    def finish(item: tuple[str, Future]) -> None:
        name, future = item
        try:
            future.result()
        except ImagingError as e:  # the preview failed: so does the photo, as in measure_photo
            done.pop(name, None)
            errors.setdefault(name, str(e))

    with (
        ThreadPoolExecutor(max_workers=1, thread_name_prefix="stairfit-decode") as reader,
        ThreadPoolExecutor(max_workers=1, thread_name_prefix="stairfit-preview") as writer,
    ):
        upcoming = [reader.submit(decode_raw, todo[0].path, todo[0].name)] if todo else []
        for k, spec in enumerate(todo):
            if k + 1 < len(todo):
                upcoming.append(reader.submit(decode_raw, todo[k + 1].path, todo[k + 1].name))
            pv = preview_path(pdir, spec) if pdir else None
            try:
                frame = upcoming.pop(0).result()
                outcome, job = _measure_decoded(frame, spec, settings, pv, pcache)
            except ImagingError as e:
                outcome, job = e, None
            frame = None  # the preview job holds it if it needs it
            if isinstance(outcome, ImagingError):
                errors[spec.name] = str(outcome)
            else:
                done[spec.name] = outcome
            if pending is not None:
                finish(pending)
            pending = (spec.name, writer.submit(job)) if job is not None else None
            bar.update(1)
        if pending is not None:
            finish(pending)
    return done, errors


def preview_path(preview_dir: str | Path, spec: PhotoSpec) -> Path:
    """Where `measure_photos` writes a photo's preview: `<preview_dir>/<name>.png`.

    Always directly inside `preview_dir`: a name with folders (`raw/IMG_1.dng`) is flattened
    to `raw__IMG_1.dng.png`, and `.`/`..` parts are dropped, so a photo's name can never place
    its preview elsewhere.
    """
    parts = [p for p in spec.name.replace("\\", "/").split("/") if p not in ("", ".", "..")]
    return Path(preview_dir) / f"{'__'.join(parts) or 'photo'}.png"


def preview_cache_dir(cache: str | Path) -> Path:
    """The folder of cached previews that goes with the measurement cache `cache`.

    It sits beside the cache file and is named after it: `out/measurements.csv` keeps its
    previews in `out/measurements.previews/`.
    """
    cache = Path(cache)
    return cache.with_name(f"{cache.stem}.previews")


def cached_preview_name(photo_sha256: str, settings_key: str) -> str:
    """The file name of a cached preview: everything the PNG depends on, in the name.

    The photo's bytes (SHA-256), its `cache_key` (ROIs, marker layout, settings, including the
    saturation level that colours pixels magenta), the preview code's `PREVIEW_VERSION` and the
    preview size. A preview cached under another name is stale and never read.
    """
    return f"{photo_sha256[:32]}-{settings_key}-v{PREVIEW_VERSION}-{PREVIEW_MAX_SIZE}px.png"


_PNG_START = b"\x89PNG\r\n\x1a\n"
_PNG_END = b"IEND\xaeB`\x82"


def _cached_preview(folder: Path, rows: Sequence[MeasurementRow]) -> bytes | None:
    """The cached preview PNG of a photo's (already validated) cached rows, or None.

    None when it is missing, unreadable, or not a whole PNG file (it is then made again).
    """
    path = folder / cached_preview_name(rows[0].photo_sha256, rows[0].settings_key)
    try:
        png = path.read_bytes()
    except OSError:
        return None
    return png if png.startswith(_PNG_START) and png.endswith(_PNG_END) else None


def _load_cache(cache: Path | None) -> dict[str, tuple[MeasurementRow, ...]]:
    table = read_cache(cache, TABLE_VERSION)
    if table is None:
        return {}
    return {p: table.for_photo(p) for p in table.photos()}


def _cached_rows(
    spec: PhotoSpec,
    settings: ExtractionSettings,
    cached: dict[str, tuple[MeasurementRow, ...]],
) -> tuple[MeasurementRow, ...] | None:
    """A photo's cached rows if the photo's SHA-256 and its `cache_key` both match, else None."""
    rows = cached.get(spec.name)
    if not rows or not spec.path.is_file():
        return None
    key = cache_key(spec, settings)
    if any(r.settings_key != key for r in rows):
        return None
    sha = file_sha256(spec.path)
    if any(r.photo_sha256 != sha for r in rows):
        return None
    return rows


def measure_photos(
    specs: Sequence[PhotoSpec],
    settings: ExtractionSettings | None = None,
    *,
    cache: str | Path | None = None,
    preview_dir: str | Path | None = None,
    progress: bool = False,
    max_workers: int | None = None,
    raise_on_failure: bool = True,
) -> MeasurementTable:
    """Measure a set of photos: the measurement table, one row per photo x ROI x channel.

    Args:
        specs: one `PhotoSpec` per photo (names must be unique).
        settings: extraction settings (defaults: `ExtractionSettings()`).
        cache: a CSV file. Rows found there are reused for a photo when the photo file's SHA-256
            and its `cache_key` (ROIs, marker layout, reference, exposure overrides, settings,
            table version) both match, so the photo is not decoded again. The file is then
            rewritten (atomically) with exactly the rows returned. With `preview_dir`, previews
            are cached too, in `preview_cache_dir(cache)`; cached previews of rows no longer in
            the file are deleted.
        preview_dir: if given, a preview PNG `<name>.png` is written there for every photo:
            rendered when the photo is decoded, copied from the cache when its rows are reused
            (a photo whose cached preview is missing or stale is decoded again).
        progress: show a tqdm progress bar (on stderr).
        max_workers: worker processes; default min(2, CPU count, photos to decode). With 1,
            photos are measured in this process. Each worker holds one photo at a time, so
            memory stays bounded by a few photos.
        raise_on_failure: False returns the rows of the photos that succeeded, with the
            failures in the table's `failed` ((photo, one-line reason) pairs), instead of
            raising (`stairfit measure` reports them).

    Returns:
        The table, rows in the order of `specs`.

    Raises:
        PhotosFailedError: one or more photos failed (an ImagingError; `failed_photos` names them);
            the message, one line, lists each (photo, wedge, fix), photos that failed alike
            together. Rows of the photos that succeeded are written to the cache first, and the
            failed photos' previews (with `preview_dir`) show the markers found, their pixel
            ROIs and a pixel grid.
    """
    settings = settings or ExtractionSettings()
    names = [s.name for s in specs]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ImagingError(f"photo names must be unique; repeated: {dup} (give each a name)")
    cache_path = Path(cache) if cache is not None else None
    pdir = Path(preview_dir) if preview_dir is not None else None
    pcache = preview_cache_dir(cache_path) if cache_path is not None and pdir is not None else None
    cached = _load_cache(cache_path)
    done: dict[str, tuple[MeasurementRow, ...]] = {}
    errors: dict[str, str] = {}
    bar = tqdm(total=len(specs), unit="photo", desc="photos", disable=not progress)
    todo = []
    for spec in specs:
        rows = _cached_rows(spec, settings, cached)
        if rows is not None and pdir is not None:
            png = _cached_preview(pcache, rows) if pcache is not None else None
            if png is None:
                rows = None  # decode again to make the preview
            else:
                atomic_write_bytes(preview_path(pdir, spec), png)
        if rows is None:
            todo.append(spec)
        else:
            done[spec.name] = rows
            bar.update(1)
    workers = max_workers or min(2, os.cpu_count() or 1)
    workers = max(1, min(workers, len(todo)))
    try:
        if workers == 1:
            serial_done, serial_errors = _measure_in_process(todo, settings, pdir, pcache, bar)
            done |= serial_done
            errors |= serial_errors
        else:
            # "spawn": never fork a parent that may be running JAX threads.
            ctx = multiprocessing.get_context("spawn")
            with ProcessPoolExecutor(max_workers=workers, mp_context=ctx) as pool:
                futures: dict[Future, PhotoSpec] = {
                    pool.submit(
                        measure_photo,
                        spec,
                        settings,
                        preview_path(pdir, spec) if pdir else None,
                        preview_cache=pcache,
                    ): spec
                    for spec in todo
                }
                try:
                    _collect(futures, done, errors, bar)
                except BaseException:  # an interruption: do not start the photos still queued
                    pool.shutdown(wait=False, cancel_futures=True)
                    raise
    finally:
        bar.close()
    table = MeasurementTable(tuple(r for s in specs if s.name in done for r in done[s.name]))
    if cache_path is not None and write_cache(cache_path, table, TABLE_VERSION):
        keep = {cached_preview_name(r.photo_sha256, r.settings_key) for r in table.rows}
        prune_previews(preview_cache_dir(cache_path), keep)
    same_bytes_warnings(table)
    low_signal_warnings(table)
    return _with_failures(table, [(n, errors[n]) for n in names if n in errors], raise_on_failure)


def _with_failures(
    table: MeasurementTable, failures: list[tuple[str, str]], raise_on_failure: bool
) -> MeasurementTable:
    """`measure_photos`'s result: the table, or a `PhotosFailedError` listing the failures (one
    line), or with `raise_on_failure=False` the table with the failures in `failed`."""
    if failures and raise_on_failure:
        raise PhotosFailedError(
            f"{len(failures)} of {len(table.photos()) + len(failures)} photos could not be "
            f"measured: {summarise_failures(failures)}",
            tuple(n for n, _ in failures),
        )
    if not failures:
        return table
    return MeasurementTable(table.rows, tuple((n, " ".join(m.split())) for n, m in failures))


def _collect(
    futures: dict[Future, PhotoSpec],
    done: dict[str, tuple[MeasurementRow, ...]],
    errors: dict[str, str],
    bar: tqdm,
) -> None:
    """Gather the worker processes' results into `done` and `errors` as they complete."""
    for fut in as_completed(futures):
        spec = futures[fut]
        try:
            done[spec.name] = fut.result()
        except ImagingError as e:
            errors[spec.name] = str(e)
        except BrokenProcessPool as e:
            raise ImagingError(
                f"photo {spec.name!r}: a worker process died ({e}); it may have run "
                "out of memory, or measure_photos was called while a script was "
                "being imported (put the call under `if __name__ == '__main__':`). "
                "Retry with max_workers=1"
            ) from e
        bar.update(1)


def summarise_failures(failures: Sequence[tuple[str, str]]) -> str:
    """The failures of several photos on one line, photos that failed alike named together.

    Each message starts with `photo '<name>'` (the convention of every ImagingError about one
    photo); messages that are the same apart from that prefix are merged, e.g. three photos
    without EXIF give `photos 'a.dng', 'b.dng', 'c.dng': EXIF has no usable ...`. Groups are
    separated by " | ". Any line breaks inside a message are flattened, so the command line can
    print the whole error as one line.
    """
    groups: dict[str, list[str]] = {}
    for name, message in failures:
        text = " ".join(message.split())
        prefix = f"photo {name!r}"
        rest = text[len(prefix) :] if text.startswith(prefix) else f": {text}"
        groups.setdefault(rest, []).append(name)
    parts = []
    for rest, group in groups.items():
        who = f"photo {group[0]!r}" if len(group) == 1 else "photos " + ", ".join(map(repr, group))
        parts.append(who + rest)
    return " | ".join(parts)
