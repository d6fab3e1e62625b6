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
from collections.abc import Callable, Iterable, Mapping, Sequence
from concurrent.futures import Future, ProcessPoolExecutor, ThreadPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from dataclasses import asdict, dataclass
from functools import partial
from pathlib import Path

import numpy as np
from tqdm import tqdm

from stairfit.fileio import atomic_bytes

from ._cache import VerifiedCache, preview_digests, prune_previews, read_cache, write_cache
from ._calibration import Calibration, CalibrationSpec, build_calibration, combined_sha256
from ._checks import low_signal_warnings, same_bytes_warnings
from ._decode import CHANNELS, MAX_RAW_BYTES, RawFrame, decode_raw, file_sha256
from ._errors import ImagingError, PhotosFailedError
from ._exposure import Exposure, resolve_exposure
from ._extract import (
    ChannelStats,
    ExtractionSettings,
    RoiData,
    finish_stats,
    noise_points,
    roi_data,
)
from ._hdr import BracketMember, Radiometry, prepare_radiometry
from ._markers import MarkerDetection, MarkerLayout, detect_markers
from ._noise import NoiseModel, fit_noise_model
from ._placement import (
    CameraPose,
    PinholeCamera,
    check_in_image,
    face_axis_px,
    face_outline_3d,
    face_polygon,
    fit_camera_pose,
    hidden_fraction,
    roi_face_points,
    roi_view_half_width_deg,
    view_parallax_deg,
)
from ._preview import PREVIEW_MAX_SIZE, PREVIEW_VERSION, preview_png
from ._roi import (
    INCIDENCE_AXES,
    Polygon,
    RoiMask,
    adaptive_erode_px,
    as_polygon,
    roi_mask,
    thickness_px,
    too_thin,
    view_spread,
)
from ._table import MeasurementRow, MeasurementTable

TABLE_VERSION = 16
"""Part of every cache key: bump it when a change to the code changes measured values.

3: the exposure_source, marker_ids, marker_cell_px and placement columns (3-D placement).
4: rows flagged below_black carry NaN (were negative values).
5: standard errors from the 1-dependent block covariance at a block size chosen from the data;
   the stderr_noise, stderr_dof, block_px, corr_rg, corr_rb and corr_gb columns (issue 13).
5 (radiometry branch): the radiometry column (dark frames, flat fields, HDR brackets).
6 (radiometry branch): the face_view_deg column (a pinhole-placed face's own view angle).
7: both of the above together (the two branches' tables 5 and 6 are stale).
8: the view_spread column (the eroded ROI's share of its face's viewing-angle spread).
9: each channel's value moved by its plane to the ROI's centroid (docs/imaging.md §Channel sites).
10: face_view_deg is the mean view angle over the eroded ROI's pixels (was: at the face's centre).
11: the view_half_width_deg column (a pinhole-placed ROI's own spread of viewing angles).
12: the face_points_mm and camera_mm columns (the lab model's 3-D geometry of each ROI).
13: resolved layer stripes fitted and removed, the photo's noise model, the erosion adapted to
    a face's thickness, thin ROIs flagged; the stripe_* and erode_px columns (issue 45).
14: the stripes' harmonics shorter than 0.4 px that the residuals show are fitted too; what the
    stripes leave at the mosaic's Nyquist frequency (the two greens' difference) is in R's and
    B's errors (issue 45).
15: block means detrended by a quadratic, then a cubic surface where a plane leaves the
    correlation unresolved (a near lamp's highlight across a face).
16: an ROI thinner than THIN_SITES_PX moves its channels by green's profile across it
    instead of by their planes (docs/imaging.md §Channel sites).
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
        bracket: further exposures of the same view (an HDR bracket; `path` is the first and
            the reference: values are expressed at its exposure). docs/imaging.md §HDR brackets.
        calibration: flat-field photos and dark frames to correct with (docs/imaging.md §Flat
            fields and dark frames), or None.
        plane_of_incidence: the image direction of the plane of incidence for pixel polygons,
            "vertical" (the layer lines run across the image, as `stairfit simulate` shoots)
            or "horizontal"; marker-placed faces take it from the camera pose
            (docs/imaging.md §Viewing spread).
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
    bracket: tuple[BracketMember, ...] = ()
    calibration: CalibrationSpec | None = None
    plane_of_incidence: str = "vertical"

    def __post_init__(self) -> None:
        path = Path(self.path)
        object.__setattr__(
            self, "bracket", tuple(m if isinstance(m, BracketMember) else BracketMember(m)
                                   for m in self.bracket)
        )  # fmt: skip
        name = self.name or path.name
        object.__setattr__(self, "path", path)
        object.__setattr__(self, "name", name)
        object.__setattr__(self, "rois", _named_polygons(self.rois, f"photo {name!r}, ROI"))
        object.__setattr__(
            self, "faces_mm", _named_polygons(self.faces_mm, f"photo {name!r}, face_mm")
        )
        _check_geometry_fields(self)
        if self.plane_of_incidence not in INCIDENCE_AXES:
            raise ImagingError(
                f"photo {name!r}: plane_of_incidence = {self.plane_of_incidence!r} must be one "
                f"of {', '.join(map(repr, INCIDENCE_AXES))}"
            )
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
        "plane_of_incidence": spec.plane_of_incidence,
        "exposure": [spec.exposure_time_s, spec.f_number, spec.iso],
        "settings": asdict(settings),
    }
    if spec.bracket:  # added only when used, so that other photos keep their cache keys
        payload["bracket"] = [
            [m.path.name, m.exposure_time_s, m.f_number, m.iso] for m in spec.bracket
        ]
    if spec.calibration is not None:
        payload["calibration"] = spec.calibration.key()
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


def _flags(s: ChannelStats, settings: ExtractionSettings, thin: bool = False) -> list[str]:
    if thin:  # too thin to measure in this photo (docs/imaging.md §Pixels): nothing else applies
        return ["thin"]
    flags = []
    if s.n_in_roi == 0:
        flags.append("no_pixels")
    elif s.saturated_fraction > settings.max_saturated_fraction or s.n_pixels == 0:
        flags.append("saturated")
    if s.n_pixels > 0 and not s.dof >= settings.min_blocks:  # also when dof is NaN
        flags.append("few_blocks")
    if s.mean_dn < -5 * s.stderr_dn:
        # E[raw - black] >= 0 with a correct black level; 5 sigma below is a wrong black level
        flags.append("below_black")
    return flags


def _scaled(
    s: ChannelStats,
    r: ChannelStats | None,
    scale: float,
    below_black: bool,
    common: tuple[float, float] = (0.0, 0.0),
) -> tuple[float, float, float, float]:
    """A row's value, stderr, stderr_noise and dof: exposure-scaled, or the ratio to `r`.

    `common` is the calibration frames' part of the standard error (DN) of the ROI and of the
    reference (`_common_stderr`): added in quadrature to the total error, not to the noise
    part, since the same dark and flat frames enter every photo that uses them. The ROIs do not
    overlap, so the ratio's error adds the two relative errors in quadrature; its dof is the
    smaller of the two (docs/imaging.md §Reference patch). NaN below black (never a negative
    value) and for a reference mean <= 0.
    """
    if below_black or (r is not None and not r.mean_dn > 0):
        return math.nan, math.nan, math.nan, s.dof
    se = math.hypot(s.stderr_dn, common[0])
    if r is None:
        return s.mean_dn * scale, se * scale, s.stderr_noise_dn * scale, s.dof
    ratio = s.mean_dn / r.mean_dn

    def err(se: float, se_ref: float) -> float:
        return math.hypot(se / r.mean_dn, ratio * se_ref / r.mean_dn)

    noise = err(s.stderr_noise_dn, r.stderr_noise_dn)
    total = err(se, math.hypot(r.stderr_dn, common[1]))
    return ratio, total, noise, min(s.dof, r.dof)


def measure_frame(
    frame: RawFrame,
    spec: PhotoSpec,
    settings: ExtractionSettings,
    radiometry: Radiometry | None = None,
) -> FrameMeasurement:
    """Measure every ROI of `spec` in a decoded photo.

    Places marker-based ROIs (when there are any), rasterises and erodes every ROI, resolves the
    exposure, computes the per-channel statistics, flags, and the optional reference
    normalisation. With `radiometry` (dark, flat, bracket: `view_radiometry`), the statistics
    come from its corrected image, plus the calibration frames' noise (docs/imaging.md).

    Raises:
        ImagingError: exposure unknown, ROI outside the image or empty after erosion, ROIs
            overlapping, too few markers or a poor marker fit; the message names photo and wedge.
    """
    photo = spec.name
    exposure = resolve_exposure(frame, spec.exposure_time_s, spec.f_number, spec.iso)
    polygons: dict[str, tuple[Polygon, str]] = {n: (p, "polygon") for n, p in spec.rois}
    detection, placement, placed_polygons = place_faces(frame, spec, radiometry)
    polygons |= {n: (p, "markers") for n, p in placed_polygons.items()}
    rois, erosion, thin = _eroded_rois(spec, polygons, (frame.height, frame.width), settings)
    if placement is not None:  # before the overlap check: a hidden face overlaps its hider
        _check_hidden(spec, placement, {n: r for n, r in rois.items() if n not in thin})
    _check_overlaps(rois, photo)
    key = cache_key(spec, settings)
    stats_frame, black = _stats_source(frame, radiometry)
    data = {
        n: roi_data(stats_frame, roi, settings, across=_layer_normal(spec, placement, n))
        for n, roi in rois.items()
        if n not in thin
    }
    noise = _photo_noise(data.values(), radiometry)
    stats = {n: finish_stats(rd, noise) for n, rd in data.items()}
    stats |= {n: _empty_stats(rois[n]) for n in thin}
    spreads = {n: view_spread(roi, _in_plane_axis(spec, placement, n)) for n, roi in rois.items()}
    common = {n: _common_stderr(radiometry, roi, stats[n]) for n, roi in rois.items()}
    ref = stats[spec.reference] if spec.reference else None
    ref_thin = spec.reference in thin
    ref_flags = [_flags(s, settings, ref_thin) for s in ref] if ref else None
    rows = []
    for n, roi in rois.items():
        by_marker = roi.source == "markers" and placement is not None
        for c, s in enumerate(stats[n]):
            flags = _flags(s, settings, n in thin)
            normalised_by, r, r_common = "", None, 0.0
            if ref is not None and ref_flags is not None and n != spec.reference:
                r = ref[c]
                normalised_by = spec.reference or ""
                r_common = common[normalised_by][c]
                flags += [f"reference-{f}" for f in ref_flags[c]]
                if "below_black" not in flags and not r.mean_dn > 0:
                    flags.append("reference-nonpositive")
            value, stderr, noise_se, dof = _scaled(
                s, r, exposure.scale, "below_black" in flags or n in thin,
                (common[n][c], r_common),
            )  # fmt: skip
            rows.append(
                MeasurementRow(
                    photo=photo,
                    photo_sha256=stats_frame.sha256,
                    settings_key=key,
                    wedge=n,
                    channel=CHANNELS[c],
                    value=float(value),
                    stderr=float(stderr),
                    n_pixels=s.n_pixels,
                    n_blocks=s.n_blocks,
                    saturated_fraction=float(s.saturated_fraction),
                    channel_corr=float(s.channel_corr),
                    stderr_noise=float(noise_se),
                    stderr_dof=float(dof),
                    block_px=int(s.block_px),
                    corr_rg=float(s.channel_corrs[0]),
                    corr_rb=float(s.channel_corrs[1]),
                    corr_gb=float(s.channel_corrs[2]),
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
                    **_marker_columns(placement if by_marker else None, detection, spec, roi),
                    radiometry=radiometry.description if radiometry is not None else "",
                    view_spread=spreads[n],
                    **_stripe_columns(s),
                    erode_px=erosion[n],
                    thickness_px=round(thickness_px(roi.mask), 1),
                )
            )
    return FrameMeasurement(tuple(rows), rois, exposure, detection, placement)


def _eroded_rois(
    spec: PhotoSpec,
    polygons: Mapping[str, tuple[Polygon, str]],
    shape: tuple[int, int],
    settings: ExtractionSettings,
) -> tuple[dict[str, RoiMask], dict[str, int], set[str]]:
    """Each ROI rasterised and eroded by its adapted erosion (docs/imaging.md §Pixels): the
    masks (in the order of `spec.roi_names()`), the erosion applied, and the names of those too
    thin to measure."""
    erosion, rois = {}, {}
    for n in spec.roi_names():
        poly, source = polygons[n]
        where = {"photo": spec.name, "wedge": n, "source": source}
        erosion[n] = adaptive_erode_px(poly, shape, settings.erode_px, **where)
        rois[n] = roi_mask(poly, shape, erosion[n], **where, empty_ok=True)
    return rois, erosion, {n for n, roi in rois.items() if too_thin(roi)}


def _empty_stats(roi: RoiMask) -> tuple[ChannelStats, ChannelStats, ChannelStats]:
    """The statistics of an ROI too thin to measure: no pixels used (flagged `thin`)."""
    n = roi.n_pixels
    return tuple(ChannelStats(math.nan, math.nan, 0, 0, n, math.nan) for _ in range(3))  # type: ignore[return-value]


def _stripe_columns(s: ChannelStats) -> dict[str, float | None]:
    """The stripe_* columns of a row: None where no stripes were fitted."""

    def value(v: float) -> float | None:
        return float(v) if math.isfinite(v) else None

    return {
        "stripe_period_px": value(s.stripe_period_px),
        "stripe_angle_deg": value(s.stripe_angle_deg),
        "stripe_amplitude": value(s.stripe_amplitude),
        "stripe_offset": value(s.stripe_offset),
    }


def _photo_noise(data: Iterable[RoiData], radiometry: Radiometry | None) -> NoiseModel | None:
    """The photo's noise model from all its ROIs (docs/imaging.md §Pixel noise), or None for
    an image whose noise is not `read + x / gain`: one divided by a flat field or merged from
    a bracket (each ROI then keeps its own neighbour-difference estimate)."""
    if radiometry is not None and (
        radiometry.flat_rel_stderr is not None or len(radiometry.members) > 1
    ):
        return None
    return fit_noise_model([p for rd in data for p in noise_points(rd)])


def _layer_normal(spec: PhotoSpec, pose: CameraPose | None, name: str) -> np.ndarray | None:
    """The image direction across the layer lines of a face placed from the markers (its
    layer lines run along the base's y axis: the normal to their image at the face's centre),
    None for a pixel polygon (the stripes' orientation is then estimated from the image)."""
    if pose is None or name not in spec.placed_names():
        return None
    angle = dict(spec.face_angles_deg).get(name, 0.0)
    face = face_outline_3d(dict(spec.faces_mm)[name], angle)
    centre = face.mean(axis=0)
    step = 0.05 * float(np.ptp(face[:, 1]) or 1.0)
    along = np.array([0.0, step, 0.0])
    ends = pose.project(np.stack([centre - along, centre + along]))
    d = ends[1] - ends[0]
    norm = float(np.hypot(*d))
    return np.array([-d[1], d[0]]) / norm if norm > 0 else None


def _in_plane_axis(spec: PhotoSpec, pose: CameraPose | None, name: str) -> np.ndarray:
    """The image direction along which ROI `name`'s viewing angle varies: from the camera pose
    for a marker-placed face, else the scene's `plane_of_incidence`."""
    if pose is not None and name in spec.placed_names():
        angle = dict(spec.face_angles_deg).get(name, 0.0)
        return face_axis_px(pose, dict(spec.faces_mm)[name], angle)
    return np.asarray(INCIDENCE_AXES[spec.plane_of_incidence])


def place_faces(
    frame: RawFrame, spec: PhotoSpec, radiometry: Radiometry | None = None
) -> tuple[MarkerDetection | None, CameraPose | None, dict[str, Polygon]]:
    """Detect the markers and place the faces of `spec.placed_names()`: (detection, camera,
    image polygons by name); (None, None, {}) when nothing is placed from markers.

    Faces with a wedge angle are placed in 3-D (docs/imaging.md §3-D placement). With
    `radiometry` of an HDR bracket, the markers are those of the exposure that places the
    camera best (`_best_exposure_pose`).

    Raises:
        ImagingError: too few markers, an inconsistent camera, or a face outside the image.
    """
    placed = spec.placed_names()
    if not placed:
        return None, None, {}
    layout = spec.markers
    assert layout is not None  # checked by PhotoSpec
    angles = dict(spec.face_angles_deg)
    size = (frame.width, frame.height)

    def fit(detection: MarkerDetection) -> CameraPose:
        return fit_camera_pose(
            detection,
            layout,
            photo=spec.name,
            image_size=size,
            rising=any(angles.get(n, 0.0) > 0 for n in placed),
            view_deg=spec.view_deg,
            camera=spec.camera,
            wedges=placed,
        )

    members = radiometry.members if radiometry is not None else (frame,)
    detection, pose = _best_exposure_pose([_detect_layout(m, layout) for m in members], fit)
    faces = dict(spec.faces_mm)
    polygons = {}
    for n in placed:
        polygons[n] = face_polygon(pose, faces[n], angles.get(n, 0.0))
        check_in_image(polygons[n], size, photo=spec.name, wedge=n)
    return detection, pose, polygons


def _check_hidden(spec: PhotoSpec, pose: CameraPose, rois: dict[str, RoiMask]) -> None:
    """ImagingError when another wedge hides part of a placed face's eroded ROI (`rois`: the
    faces measured; one too thin to measure is not in it and not checked)."""
    faces, angles = dict(spec.faces_mm), dict(spec.face_angles_deg)
    occluders = spec.occluders()
    for n in spec.placed_names():
        others = [o for o in occluders if o[0] != n]
        if not others or n not in rois:
            continue
        fraction, by = hidden_fraction(pose, faces[n], angles.get(n, 0.0), others, rois[n])
        if fraction > 0:
            raise ImagingError(
                f"photo {spec.name!r}, wedge {n!r}: {100 * fraction:.0f}% of the face's ROI is "
                f"hidden behind wedge {by!r} from this view; give a roi_px polygon for {n!r} in "
                "this photo that keeps to the visible part, or leave the photo out"
            )


def _marker_columns(
    pose: CameraPose | None, detection: MarkerDetection | None, spec: PhotoSpec, roi: RoiMask
) -> dict:
    """The marker columns of an ROI's rows: ids used, their smallest cell (px), the camera
    model and, through a pinhole, the face's own view angle (`face_view_deg`: the mean over
    the eroded ROI's pixels, what its mean measures) and the ROI's own spread of viewing
    angles (`view_half_width_deg`, `roi_view_half_width_deg`)."""
    if pose is None or detection is None:
        return {"marker_ids": "", "marker_cell_px": None, "placement": ""}
    cells = dict(zip(detection.ids, detection.cell_px, strict=True))
    name = roi.name
    angle = dict(spec.face_angles_deg).get(name, 0.0)
    assert spec.markers is not None  # a pose comes from markers
    ys, xs = np.nonzero(roi.mask)
    if ys.size == 0:  # a thin ROI: no pixels to take the view from
        ids = " ".join(str(i) for i in pose.ids)
        cell = min(cells[i] for i in pose.ids)
        return {"marker_ids": ids, "marker_cell_px": cell, "placement": pose.model}
    pixels = np.column_stack([xs + roi.x0, ys + roi.y0])  # pixel centres (docs §Pixels)
    outline = dict(spec.faces_mm)[name]
    parallax = view_parallax_deg(pose, spec.markers, outline, angle, pixels)
    own = None if parallax is None or spec.view_deg is None else spec.view_deg + parallax
    points, weights = roi_face_points(pose, outline, angle, pixels)
    centre = pose.camera_centre_mm()
    return {
        "face_points_mm": ";".join(
            " ".join(f"{v:.6g}" for v in (*p, w)) for p, w in zip(points, weights, strict=True)
        ),
        "camera_mm": "" if centre is None else " ".join(f"{v:.8g}" for v in centre),
        "marker_ids": " ".join(str(i) for i in pose.ids),
        "marker_cell_px": min(cells[i] for i in pose.ids),
        "placement": pose.model,
        "face_view_deg": own,
        "view_half_width_deg": roi_view_half_width_deg(pose, outline, angle, pixels),
    }


def _detect_layout(frame: RawFrame, layout: MarkerLayout) -> MarkerDetection:
    """The markers of `layout` in one exposure (its dictionary, detector settings and ids)."""
    ids = [m for m, _ in layout.markers]
    return detect_markers(frame, layout.dictionary, layout.detector, expected_ids=ids)


def _best_exposure_pose(
    detections: Sequence[MarkerDetection], fit: Callable[[MarkerDetection], CameraPose]
) -> tuple[MarkerDetection, CameraPose]:
    """The (detection, camera) of the exposure that shows the markers best: of the exposures
    whose markers give a consistent camera, the one using most markers, then the smallest RMS
    reprojection error (docs/imaging.md §HDR brackets). One photo: its own.

    Raises:
        ImagingError: no exposure gives a consistent camera: the error of the exposure with
            most markers found (ties: the earlier file).
    """
    best: tuple[tuple[int, float], MarkerDetection, CameraPose] | None = None
    errors: list[tuple[int, ImagingError]] = []
    for det in detections:
        try:
            pose = fit(det)
        except ImagingError as e:
            errors.append((len(det.ids), e))
            continue
        key = (-len(pose.ids), pose.rms_error_px)
        if best is None or key < best[0]:
            best = (key, det, pose)
    if best is None:
        raise max(errors, key=lambda x: x[0])[1]
    return best[1], best[2]


def _stats_source(
    frame: RawFrame, radiometry: Radiometry | None
) -> tuple[RawFrame, tuple[float, float, float]]:
    """The frame the statistics are computed on and the black level reported per channel."""
    if radiometry is None:
        return frame, frame.black_level_per_channel()
    return radiometry.frame, radiometry.black_per_channel


def _common_stderr(
    radiometry: Radiometry | None, roi: RoiMask, stats: Sequence[ChannelStats]
) -> tuple[float, float, float]:
    """The calibration frames' part of an ROI's standard errors (DN), zero without them."""
    if radiometry is None:
        return (0.0, 0.0, 0.0)
    return radiometry.common_stderr_dn(roi, stats)


def decode_view(spec: PhotoSpec) -> tuple[RawFrame, ...]:
    """Decode a photo's file and its bracket members (the reference first)."""
    first = decode_raw(spec.path, spec.name)
    return (first, *(decode_raw(m.path, m.path.name) for m in spec.bracket))


def view_radiometry(
    frames: Sequence[RawFrame],
    spec: PhotoSpec,
    settings: ExtractionSettings,
    calibration: Calibration | None,
) -> Radiometry | None:
    """`prepare_radiometry` of a decoded view, or None when it is one uncalibrated file."""
    if len(frames) == 1 and calibration is None:
        return None
    exposures = [resolve_exposure(frames[0], spec.exposure_time_s, spec.f_number, spec.iso)]
    for frame, m in zip(frames[1:], spec.bracket, strict=True):
        try:
            exposures.append(resolve_exposure(frame, m.exposure_time_s, m.f_number, m.iso))
        except ImagingError as e:
            text = (
                str(e)
                .replace(f"photo {frame.name!r}: ", "", 1)
                .replace(
                    "this photo's [[photos]] entry",
                    "this photo's [[photos]] entry (one value per file)",
                )
            )
            raise ImagingError(
                f"photo {spec.name!r}, bracket file {frame.name!r}: {text}"
            ) from None
    return prepare_radiometry(frames, exposures, calibration, settings, spec.name)


def photo_digest(spec: PhotoSpec) -> str:
    """SHA-256 of a photo's file, or the combined digest of a bracket's files (as in the rows)."""
    paths = (spec.path, *(m.path for m in spec.bracket))
    return combined_sha256([file_sha256(p, MAX_RAW_BYTES) for p in paths])


def measure_photo(
    spec: PhotoSpec,
    settings: ExtractionSettings,
    preview: str | Path | None = None,
    *,
    preview_cache: str | Path | None = None,
    calibration: Calibration | None = None,
) -> tuple[MeasurementRow, ...]:
    """Decode one photo (all files of a bracket), measure it, and optionally write its preview.

    When the measurement fails after decoding, the preview is still written (with the markers
    found, if a layout was given) so that the failure can be looked at; then the error is raised.

    Args:
        spec, settings: what to measure and how.
        preview: the preview PNG to write, or None for none.
        preview_cache: a folder (`preview_cache_dir` of a measurement cache) where a copy of
            the preview of a successful measurement is kept under `cached_preview_name`, so
            that `measure_photos` can reuse it with the cached rows. Only used with `preview`.
        calibration: the built calibration frames of `spec.calibration` (`build_calibration`);
            built here when `spec.calibration` is set and this is None.
    """
    if spec.calibration is not None and calibration is None:
        calibration = build_calibration(spec.calibration, settings.saturation_level)
    frames = decode_view(spec)
    outcome, write = _measure_decoded(frames, spec, settings, preview, preview_cache, calibration)
    if write is not None:
        write()
    if isinstance(outcome, ImagingError):
        raise outcome
    return outcome


_PreviewJob = Callable[[], None]


def _measure_decoded(
    frames: Sequence[RawFrame],
    spec: PhotoSpec,
    settings: ExtractionSettings,
    preview: str | Path | None,
    preview_cache: str | Path | None,
    calibration: Calibration | None = None,
) -> tuple[tuple[MeasurementRow, ...] | ImagingError, _PreviewJob | None]:
    """`measure_photo` of a decoded photo, the preview left to the caller: (rows or error, job).

    The job (None without `preview`) renders the preview (of the reference exposure) and writes
    it (and its cached copy after a success); it holds the frame until it has run.
    """
    frame = frames[0]
    try:
        radiometry = view_radiometry(frames, spec, settings, calibration)
        result = measure_frame(frame, spec, settings, radiometry)
    except ImagingError as e:
        if preview is None:
            raise
        det = _detect_layout(frame, spec.markers) if spec.markers else None
        # for drawing roi_px by hand: the markers found, the given polygons, a pixel grid
        job = partial(_write_previews, frame, {}, det, settings, [Path(preview)], dict(spec.rois))
        return e, job
    if preview is None:
        return result.rows, None
    paths = [Path(preview)]
    if preview_cache is not None:
        name = cached_preview_name(result.rows[0].photo_sha256, cache_key(spec, settings))
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
            atomic_bytes(path, png)
        except OSError:
            if k == 0:
                raise


def _measure_in_process(
    todo: Sequence[PhotoSpec],
    settings: ExtractionSettings,
    pdir: Path | None,
    pcache: Path | None,
    bar: tqdm,
    calibrations: Mapping[CalibrationSpec, Calibration],
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
        upcoming = [reader.submit(decode_view, todo[0])] if todo else []
        for k, spec in enumerate(todo):
            if k + 1 < len(todo):
                upcoming.append(reader.submit(decode_view, todo[k + 1]))
            pv = preview_path(pdir, spec) if pdir else None
            calib = calibrations.get(spec.calibration) if spec.calibration else None
            try:
                frames = upcoming.pop(0).result()
                outcome, job = _measure_decoded(frames, spec, settings, pv, pcache, calib)
            except ImagingError as e:
                outcome, job = e, None
            frames = None  # the preview job holds the reference frame if it needs it
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
    to `raw__IMG_1.dng-HASH.png`, with `.`/`..` parts dropped, so a photo's name can never
    place its preview elsewhere; HASH (8 hex digits of the name's SHA-256) keeps two names that
    flatten alike (`a/IMG.dng`, `a__IMG.dng`) apart. A plain file name keeps `<name>.png`.
    """
    name = spec.name
    parts = [p for p in name.replace("\\", "/").split("/") if p not in ("", ".", "..")]
    flat = "__".join(parts) or "photo"
    if flat == name:
        return Path(preview_dir) / f"{name}.png"
    digest = hashlib.sha256(name.encode("utf-8", "surrogateescape")).hexdigest()[:8]
    return Path(preview_dir) / f"{flat}-{digest}.png"


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


def _load_cache(cache: Path | None, secret: bytes | None) -> VerifiedCache | None:
    return read_cache(cache, TABLE_VERSION, secret)


def _cached_rows(
    spec: PhotoSpec,
    settings: ExtractionSettings,
    cached: VerifiedCache | None,
) -> tuple[MeasurementRow, ...] | None:
    """A photo's cached rows if the photo's SHA-256 and its `cache_key` both match, else None."""
    rows = cached.table.for_photo(spec.name) if cached is not None else None
    if not rows or not spec.path.is_file():
        return None
    key = cache_key(spec, settings)
    if any(r.settings_key != key for r in rows):
        return None
    try:
        sha = photo_digest(spec)
    except OSError:  # not a regular file, or too large: decoding says why
        return None
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
    cache_secret: bytes | None = None,
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
            the file are deleted. The table's `from_cache` names the photos whose rows were
            reused.
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
        cache_secret: the key of the cache's checksum (HMAC-SHA256; imaging/_cache.py): a
            cache written without it, or edited since, is not used. None: a plain SHA-256,
            which catches damage but not deliberate edits.

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
    check_preview_names(specs)
    cached = _load_cache(cache_path, cache_secret)
    done: dict[str, tuple[MeasurementRow, ...]] = {}
    errors: dict[str, str] = {}
    bar = tqdm(total=len(specs), unit="photo", desc="photos", disable=not progress)
    todo = []
    for spec in specs:
        rows = _cached_rows(spec, settings, cached)
        if rows is not None and pdir is not None:
            name = cached_preview_name(rows[0].photo_sha256, rows[0].settings_key)
            png = cached.preview(pcache, name) if cached and pcache else None
            if png is None:
                rows = None  # decode again to make the preview
            else:
                atomic_bytes(preview_path(pdir, spec), png)
        if rows is None:
            todo.append(spec)
        else:
            done[spec.name] = rows
            bar.update(1)
    reused = tuple(s.name for s in specs if s.name in done)
    workers = max_workers or min(2, os.cpu_count() or 1)
    workers = max(1, min(workers, len(todo)))
    try:
        cals = _build_calibrations(todo, settings)
        run = (todo, settings, pdir, pcache, bar, cals)
        new_done, new_errors = (
            _measure_in_process(*run) if workers == 1 else _measure_in_pool(*run, workers)
        )
        done |= new_done
        errors |= new_errors
    finally:
        bar.close()
    rows = tuple(r for s in specs if s.name in done for r in done[s.name])
    table = MeasurementTable(rows, from_cache=reused)
    if cache_path is not None:
        _write_cache(cache_path, table, cached, cache_secret, wrote_previews=pcache is not None)
    same_bytes_warnings(table)
    low_signal_warnings(table)
    return _with_failures(table, [(n, errors[n]) for n in names if n in errors], raise_on_failure)


def _write_cache(
    cache: Path,
    table: MeasurementTable,
    cached: VerifiedCache | None,
    secret: bytes | None,
    wrote_previews: bool,
) -> None:
    """Write the cache with the digests of the previews it may vouch for: those written now
    (`wrote_previews`, of rows measured now) and those the verified cache listed with the same
    bytes; a preview file nobody vouches for is removed."""
    folder = preview_cache_dir(cache)
    names = {cached_preview_name(r.photo_sha256, r.settings_key) for r in table.rows}
    fresh = {
        cached_preview_name(r.photo_sha256, r.settings_key)
        for r in table.rows
        if wrote_previews and r.photo not in table.from_cache
    }
    digests = preview_digests(folder, names)
    old = cached.previews if cached is not None else {}
    listed = {n: d for n, d in digests.items() if n in fresh or old.get(n) == d}
    if write_cache(cache, table, TABLE_VERSION, secret, listed):
        prune_previews(folder, set(listed))


def check_preview_names(specs: Sequence[PhotoSpec]) -> None:
    """No two photos may write the same preview file (names are unique, so this only fails
    for a SHA-256 prefix collision; then rename a photo)."""
    seen: dict[str, str] = {}
    for spec in specs:
        name = preview_path(".", spec).name
        if name in seen:
            raise ImagingError(
                f"photos {seen[name]!r} and {spec.name!r} would share the preview {name}; "
                "rename one of them"
            )
        seen[name] = spec.name


def _measure_in_pool(
    todo: Sequence[PhotoSpec],
    settings: ExtractionSettings,
    pdir: Path | None,
    pcache: Path | None,
    bar: tqdm,
    calibrations: Mapping[CalibrationSpec, Calibration],
    workers: int,
) -> tuple[dict[str, tuple[MeasurementRow, ...]], dict[str, str]]:
    """Measure photos in `workers` spawned processes: (rows by photo, errors by photo)."""
    done: dict[str, tuple[MeasurementRow, ...]] = {}
    errors: dict[str, str] = {}
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
                calibration=calibrations.get(spec.calibration) if spec.calibration else None,
            ): spec
            for spec in todo
        }
        try:
            _collect(futures, done, errors, bar)
        except BaseException:  # an interruption: do not start the photos still queued
            pool.shutdown(wait=False, cancel_futures=True)
            raise
    return done, errors


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


def _build_calibrations(
    todo: Sequence[PhotoSpec], settings: ExtractionSettings
) -> dict[CalibrationSpec, Calibration]:
    """The calibration frames the photos to decode need, each set built once.

    Raises:
        ImagingError: a calibration frame is unusable (one line naming it; no photo measured).
    """
    specs = dict.fromkeys(s.calibration for s in todo if s.calibration is not None)
    return {c: build_calibration(c, settings.saturation_level) for c in specs}


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
