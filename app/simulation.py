"""A synthetic photo folder (real DNGs, scene file, truth) from known physical parameters: the
library behind `stairfit simulate` and `stairfit demo` (app/commands/simulate.py parses their
options).

The model predicts each wedge face's relative radiance in every photo
(`stairfit.fitting.model_radiance` at the face angles of the scene geometry, conventions §1 and
§9); `stairfit.imaging.synthetic` renders and writes the RAW photos. The truth goes to
`truth.json` (with the noise-free face radiances and the settings) and its parameters to the
scene file's `[truth]` table, which the fit does not use and the report shows beside the fitted
values (docs/scene.md).
"""

from __future__ import annotations

import json
import math
import multiprocessing
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from . import __version__
from ._specimen_layout import SpecimenLayout, camera_for
from .errors import UserError
from .fileio import write_file
from .scene import SCENE_FILE, SCENE_VERSION

if TYPE_CHECKING:
    import jax

    from stairfit import fitting, model
    from stairfit.imaging import Exposure, synthetic

    from ._jsontypes import Record

DEG = np.pi / 180
TRUTH_FILE = "truth.json"
MIN_MEGAPIXELS = 0.3
"""Smaller photos make the 60-degree face at -80 degrees too small for the default erosion."""

MARKER_STYLES: tuple[str, ...] = ("quiet-zone", "no-quiet-zone")
"""ArUco markers printed on white paper with a one-cell white margin, or straight on the dark
base plate (their black border touches the plate)."""

MARKER_WHITE_PER_SCALE = 0.003
"""Relative radiance of the markers' white paper per unit of the truth's `scale`: a Lambertian
white that, like every diffuse surface under the fixed light, has the same radiance in every
photo (6000 at the default scale, 1.5 times the default floor). Exposures are chosen for the
wedges, so in the bright specular views the markers come out dark, as in a real session."""

MARKER_INK = 0.04
"""Radiance of the markers' black ink, as a fraction of the white paper."""

BASE_PLATE = 0.10
"""Radiance of the dark base plate the wedges and markers sit on, as a fraction of the paper."""

MAX_EXPOSURE_S = 30.0
"""The longest exposure the synthetic camera takes (s): the longest timed exposure of most
cameras. Views darker than that allows stay dark (`view_exposures`)."""


@dataclass(frozen=True)
class Truth:
    """The physical parameters a synthetic scene is rendered from (units in the names)."""

    sigma_deg: float = 6.0
    delta_n: float = 0.0
    edge_radius_um: float = 0.0
    fillet_radius_um: float = 0.0  # concave fillets between the layers (docs/rounded.md §1)
    scale: float = 2.0e6  # relative radiance per unit density: exposures of about a second
    floor: float = 4000.0  # a Lambertian body reflection of about 1/1000 of scale


@dataclass(frozen=True)
class SessionEffects:
    """The real-world effects a synthetic session can have (`stairfit simulate` options).

    Attributes:
        vignetting: the lens's fall-off in the image corners (0.15: 15% darker), cos^4 law.
        flat_frames: flat-field photos to write (a uniform target, same lens) and declare in
            `[calibration] flat_field`; 0 for none (then vignetting stays uncorrected).
        dark_frames: dark frames to write and declare in `[calibration] dark_frames`.
        black_error_dn: the sensor's true dark level above the black level its files declare
            (DN); only dark frames measure it.
        bracket: exposures per view (an HDR bracket, each 4 times the previous; the shortest is
            the reference, listed first).
        fixed_exposure: one exposure (or bracket) for every view, set by the brightest face of
            the whole session, as a real session would use; otherwise each view is exposed for
            its own brightest face.
    """

    vignetting: float = 0.0
    flat_frames: int = 0
    dark_frames: int = 0
    black_error_dn: float = 0.0
    bracket: int = 1
    fixed_exposure: bool = False


@dataclass(frozen=True)
class SimulationSettings:
    """Everything about a synthetic scene other than the physics."""

    wedges_deg: tuple[float, ...] = (10.0, 20.0, 30.0, 40.0, 45.0, 60.0)
    layer_um: float = 150.0
    material: str = "pla"
    camera: str = "Nikon 5100 (NPL)"
    illuminant: str = "D65"
    light_deg: float = -10.0  # base frame: slightly uphill, so tread and retro peaks are seen
    views_deg: tuple[float, ...] = tuple(float(v) for v in np.linspace(-80.0, 20.0, 19))
    megapixels: float = 12.0
    light_angular_diameter_deg: float = 1.0
    camera_angular_extent_deg: float = 1.0
    seed: int = 1
    workers: int = 1
    truth: Truth = field(default_factory=Truth)
    exposure_tags: str = "exif"  # where the DNGs carry the exposure (imaging.synthetic)
    markers: str = "quiet-zone"  # MARKER_STYLES
    effects: SessionEffects = field(default_factory=SessionEffects)


def check_radii(s: SimulationSettings) -> None:
    """The tip arcs and the fillets of `s.truth` fit every wedge's cell (a `UserError` naming the
    option, `--edge-radius-um` or `--fillet-radius-um`, and the largest that fits)."""
    _check_edge_radius(s)
    _check_fillet_radius(s)


def _check_edge_radius(s: SimulationSettings) -> None:
    r = s.truth.edge_radius_um
    if r < 0:
        raise UserError("--edge-radius-um: must be >= 0")
    if r > 0:
        from stairfit import model

        r_max = min(float(model.max_edge_radius(b * DEG, s.layer_um)) for b in s.wedges_deg)
        if r > r_max:
            raise UserError(
                f"--edge-radius-um: {r} um does not fit the finest cell; the maximum for these "
                f"wedges and {s.layer_um} um layers is {r_max:.1f} um"
            )


def _check_fillet_radius(s: SimulationSettings) -> None:
    """The fillets fit beside the tip arcs in every wedge's cell: `0 <= r_f <= min(l1, l2) - r`
    (`model.max_fillet_radius`, docs/rounded.md §1); checked after the tip radius."""
    rf, r = s.truth.fillet_radius_um, s.truth.edge_radius_um
    if rf < 0:
        raise UserError(
            f"--fillet-radius-um: {rf:g} is negative; give a radius >= 0 (0 = sharp concave "
            "corners)"
        )
    if rf > 0:
        from stairfit import model

        room = model.max_fillet_radius(np.asarray(s.wedges_deg) * DEG, s.layer_um, r)
        k = int(np.argmin(np.asarray(room)))
        rf_max = float(np.asarray(room)[k])
        if rf > rf_max + (rf_max + r) * 1e-12:
            raise UserError(
                f"--fillet-radius-um: {rf:g} um does not fit beside --edge-radius-um {r:g} in "
                f"the {s.wedges_deg[k]:g} deg wedge's cell ({s.layer_um:g} um layers; r + r_f "
                f"<= min(l1, l2) = {rf_max + r:.6g} um); give at most {rf_max:.6g} um"
            )


def image_size(megapixels: float) -> tuple[int, int]:
    """(width, height) with a 4:3 aspect ratio and even sides (whole CFA tiles)."""
    h = round(float(np.sqrt(megapixels * 1e6 * 3 / 4)) / 2) * 2
    w = round(h * 4 / 3 / 2) * 2
    return w, h


PROFILE_NODES = 33
"""Nodes of a face's radiance profile along its uphill direction (`face_radiance`): linear
interpolation between them errs by < 1e-5 of the peak for lobes of 1 deg or wider."""


def face_radiance(settings: SimulationSettings) -> np.ndarray:
    """(n_views, n_wedges, Q, 3) true relative radiance along every face in every photo.

    A face is seen at the viewing angle `theta_o - s h cos(theta_o)` at its coordinate `s` in
    [-1, 1] from its foot to its top (`h` = half the camera's `angular_extent_deg`: a camera
    at finite distance sees the uphill end of a face from a smaller angle; conventions §9),
    sampled at Q = `PROFILE_NODES` evenly spaced `s` (Q = 1 for a point-like face). Each node
    is evaluated with the accurate settings (5 nm spectra, 5 nodes across the light), so that
    a fit with faster settings also meets the model error a real scene would show.
    """
    from stairfit import fitting, model

    layout = SpecimenLayout(settings.wedges_deg)
    half_o = 0.5 * settings.camera_angular_extent_deg * DEG
    nodes = np.linspace(-1.0, 1.0, PROFILE_NODES) if half_o > 0 else np.zeros(1)
    rows = []
    for p, view in enumerate(settings.views_deg):
        for k, beta2 in enumerate(layout.wedges_deg):
            ti, to = settings.light_deg - beta2, view + beta2  # scene.Scene.face_angles_deg
            for s in nodes:
                to_s = to * DEG - s * half_o * math.cos(to * DEG)
                for c in range(3):
                    rows.append((p, k, c, ti * DEG, to_s, beta2 * DEG))
    a = np.array(rows, float)
    obs = fitting.Observations.from_arrays(
        theta_i_rad=a[:, 3],
        theta_o_rad=np.clip(a[:, 4], -np.pi / 2, np.pi / 2),
        beta2_rad=a[:, 5],
        layer_um=np.full(len(a), settings.layer_um),
        wedge_index=a[:, 1].astype(int),
        channel_index=a[:, 2].astype(int),
        value=np.zeros(len(a)),
        stderr=np.ones(len(a)),
        photo_index=a[:, 0].astype(int),
    )
    t = settings.truth
    spectral = fitting.spectral_setup(
        settings.material, settings.camera, settings.illuminant, _sampling(settings)
    )
    params = fitting.Params(
        sigma_rad=t.sigma_deg * DEG,
        delta_n=t.delta_n,
        edge_radius_um=t.edge_radius_um,
        scale=t.scale,
        floor=t.floor,
        fillet_radius_um=t.fillet_radius_um,
    )
    aperture = model.Aperture(0.5 * settings.light_angular_diameter_deg * DEG, 0.0, 5)
    if t.edge_radius_um > 0 or t.fillet_radius_um > 0:  # rounded, filleted (docs/rounded.md)
        values = fitting.model_radiance(params, obs, spectral, aperture=aperture)
    else:  # the same model, compiled once: about 10x faster than evaluating op by op
        values = np.asarray(_sharp_values(obs, spectral, params, aperture))
    shape = (len(settings.views_deg), len(settings.wedges_deg), nodes.size, 3)
    return np.asarray(values).reshape(shape)


def _sampling(settings: SimulationSettings) -> str:
    """The spectral sampling of the render: every 5 nm ("full"), except for rounded edges or
    fillets on a material of constant index, where one sample per channel ("effective") is
    exact.

    With a constant index the density is the same at every wavelength, and a channel's band
    average of a constant is that constant [conventions §8]. The rounded and filleted models'
    memory grows with the samples (81 at 5 nm): at 81 a single filleted face's profile nodes
    need gigabytes (docs/history.md).
    """
    from stairfit.model import materials

    t = settings.truth
    constant = isinstance(materials.get_material(settings.material), materials.ConstantIndex)
    return "effective" if (t.edge_radius_um > 0 or t.fillet_radius_um > 0) and constant else "full"


def face_mean(profile: np.ndarray) -> np.ndarray:
    """(..., 3) the mean over a face of its (..., Q, 3) profile, linear between the nodes
    (the trapezoid rule; the node itself for Q = 1)."""
    if profile.shape[-2] == 1:
        return profile[..., 0, :]
    w = np.ones(profile.shape[-2])
    w[[0, -1]] = 0.5
    return np.einsum("...qc,q->...c", profile, w / w.sum())


def _sharp_values(
    obs: fitting.Observations,
    spectral: fitting.Spectral,
    params: fitting.Params,
    aperture: model.Aperture,
) -> jax.Array:
    import jax

    from stairfit import model

    def values(
        ti: jax.Array, to: jax.Array, b2: jax.Array, n: jax.Array, w: jax.Array
    ) -> jax.Array:
        dens = model.band_density(ti, to, b2, n, w, params.sigma_rad, aperture)
        return model.radiance(dens, ti, to, params.scale, params.floor)

    n = np.asarray(spectral.n_base)[obs.channel_index] + params.delta_n
    w = np.asarray(spectral.weights)[obs.channel_index]
    return jax.jit(values)(obs.theta_i_rad, obs.theta_o_rad, obs.beta2_rad, n, w)


def simulate(folder: Path, settings: SimulationSettings, progress: bool = False) -> Record:
    """Render every photo (and any calibration frames) into `folder`; write scene and truth."""
    import tomli_w

    layout = SpecimenLayout(settings.wedges_deg)
    profile = face_radiance(settings)
    radiance = face_mean(profile)
    size = image_size(settings.megapixels)
    exposures = view_exposures(settings, radiance)
    jobs = [
        _PhotoJob(
            folder, p, view, size, layout, profile[p], settings.seed * 1000 + p, exposures[p],
            settings.effects, settings.exposure_tags, settings.markers,
            MARKER_WHITE_PER_SCALE * settings.truth.scale,
        )
        for p, view in enumerate(settings.views_deg)
    ]  # fmt: skip
    photos = _render_all(jobs, settings.workers, progress)
    calibration = write_calibration_frames(folder, settings, size, exposures[0][0])
    scene = _scene_dict(settings, layout, photos, calibration)
    text = _compact_arrays(tomli_w.dumps(scene))
    write_file(folder / SCENE_FILE, _SCENE_HEADER + text)
    truth = {
        "stairfit_version": __version__,
        "parameters": {
            "sigma_deg": settings.truth.sigma_deg,
            "delta_n": settings.truth.delta_n,
            "edge_radius_um": settings.truth.edge_radius_um,
            "fillet_radius_um": settings.truth.fillet_radius_um,
            "scale": settings.truth.scale,
            "floor": settings.truth.floor,
        },
        "settings": {k: v for k, v in asdict(settings).items() if k != "truth"},
        "face_radiance": {
            "note": "noise-free relative radiance per photo, wedge and channel (R, G, B), "
            "the mean over the whole face (its radiance varies along the face with the viewing "
            "angle; an eroded ROI's mean differs at second order)",
            "values": np.round(radiance, 6).tolist(),
        },
    }
    write_file(folder / TRUTH_FILE, json.dumps(truth, indent=2))
    return truth


SENSOR_BLACK_DN = 1024
"""The black level the synthetic camera's files declare."""


def _sensor(effects: SessionEffects) -> synthetic.SensorModel:
    from stairfit.imaging import synthetic

    return synthetic.SensorModel(
        bits=14, black_level=SENSOR_BLACK_DN, gain_e_per_dn=1.0, read_noise_dn=2.0,
        bias_dn=effects.black_error_dn,
    )  # fmt: skip


def view_exposures(
    settings: SimulationSettings, radiance: np.ndarray
) -> list[tuple[Exposure, ...]]:
    """Per view, its exposures (one, or a bracket): a photographer's choice.

    The (first, shortest) exposure puts the brightest face of the view (with `fixed_exposure`:
    of the whole session) at about half of the raw range, at f/5.6 and ISO 100, rounded down to
    a third of a stop; a bracket adds exposures 4, 16, ... times longer. No exposure is longer
    than `MAX_EXPOSURE_S` (a view whose faces are all but black, e.g. off-specular with no
    diffuse floor, gets the longest exposure and stays dark, as with a real camera).
    """
    from stairfit.imaging import Exposure

    e = settings.effects
    sensor = _sensor(e)
    f_number, iso = 5.6, 100.0
    full = sensor.white - sensor.black_level
    longest = MAX_EXPOSURE_S / 4.0 ** (e.bracket - 1)  # the reference of a bracket at the limit
    out = []
    for p in range(radiance.shape[0]):
        peak = float(radiance.max() if e.fixed_exposure else radiance[p].max())
        wanted = 0.5 * full * f_number**2 / (iso / 100.0) / peak if peak > 0 else math.inf
        t = _third_stop(min(wanted, longest))
        out.append(tuple(Exposure(t * 4.0**k, f_number, iso) for k in range(e.bracket)))
    return out


def write_calibration_frames(
    folder: Path, settings: SimulationSettings, size: tuple[int, int], exposure: Exposure
) -> dict[str, list[str]]:
    """Write the session's flat-field photos and dark frames; the scene's [calibration] table.

    Flat fields: a uniform target at about half of the raw range seen through the same lens
    (its vignetting), 0.2% texture. Dark frames: the lens capped, at the first view's exposure.
    """
    from stairfit.imaging import synthetic

    e = settings.effects
    sensor = _sensor(e)
    table: dict[str, list[str]] = {}
    half = 0.5 * (sensor.white - sensor.black_level) * exposure.scale
    for kind, n, level in (
        ("flat_field", e.flat_frames, half),
        ("dark_frames", e.dark_frames, 0.0),
    ):
        names = []
        for k in range(n):
            photo = synthetic.render_photo(
                size, {}, {}, exposure, background=np.full(3, level), sensor=sensor,
                texture_amplitude=0.002 if level > 0 else 0.0,
                vignetting=e.vignetting if level > 0 else 0.0,
                seed=settings.seed * 1000 + (900 if level > 0 else 950) + k,
            )  # fmt: skip
            name = f"{'FLAT' if level > 0 else 'DARK'}_{k + 1:02d}.dng"
            photo.write_dng(folder / name, exposure_tags=settings.exposure_tags)
            names.append(name)
        if names:
            table[kind] = names
    return table


def _render_all(jobs: Sequence[_PhotoJob], workers: int, progress: bool) -> list[Record]:
    """Render every photo (in `workers` spawned processes when > 1), with a progress bar.

    The bar is closed (its line ended) and queued jobs are cancelled however this ends, so an
    interruption's one-line message starts on a line of its own.
    """
    from tqdm import tqdm

    photos: list[Record] = []
    with tqdm(total=len(jobs), desc="rendering photos", unit="photo", disable=not progress) as bar:
        if workers <= 1:
            for job in jobs:
                photos.append(_render(job))
                bar.update()
            return photos
        # "spawn": never fork a process that has run JAX
        ctx = multiprocessing.get_context("spawn")
        pool = ProcessPoolExecutor(max_workers=workers, mp_context=ctx)
        try:
            for entry in pool.map(_render, jobs):
                photos.append(entry)
                bar.update()
        finally:
            pool.shutdown(wait=True, cancel_futures=True)
    return photos


@dataclass(frozen=True)
class _PhotoJob:
    folder: Path
    index: int
    view_deg: float
    size: tuple[int, int]
    layout: SpecimenLayout
    radiance: np.ndarray  # (n_wedges, Q, 3): the profile along each face (face_radiance)
    seed: int
    exposures: tuple[Exposure, ...]  # the reference (shortest) first
    effects: SessionEffects
    exposure_tags: str = "exif"
    markers: str = "quiet-zone"
    paper: float = 6000.0  # relative radiance of the markers' white paper


def _render(job: _PhotoJob) -> Record:
    """Render and write one view (every exposure of a bracket); its [[photos]] entry."""
    from stairfit.imaging import MarkerLayout, synthetic

    names = [_wedge_name(b) for b in job.layout.wedges_deg]
    cam = camera_for(job.layout, job.view_deg, *job.size)
    faces = {n: cam.project(job.layout.face_corners_mm(k)).tolist() for k, n in enumerate(names)}
    ends = {n: _profile_ends(cam.project(job.layout.face_corners_mm(k)))
            for k, n in enumerate(names)}  # fmt: skip
    sensor = _sensor(job.effects)
    markers_mm = dict(job.layout.markers_mm())
    src = np.array([c for m in markers_mm.values() for c in m], float)
    dst = cam.project_base(src)
    import cv2

    h, _ = cv2.findHomography(src, dst)
    files = []
    for k, exposure in enumerate(job.exposures):
        photo = synthetic.render_photo(
            job.size,
            faces,
            {n: _profile(job.radiance[k_w]) for k_w, n in enumerate(names)},
            exposure,
            profile_ends=ends,
            background=np.full(3, BASE_PLATE * job.paper),
            sensor=sensor,
            markers=MarkerLayout({i: c.tolist() for i, c in markers_mm.items()}),
            plane_to_image=h,
            marker_white=np.full(3, job.paper),
            marker_black=np.full(3, MARKER_INK * job.paper),
            marker_quiet_zone_cells=1.0 if job.markers == "quiet-zone" else 0.0,
            # the pipeline corrects vignetting only with a flat field (SessionEffects)
            vignetting=job.effects.vignetting,
            seed=job.seed if k == 0 else job.seed + 100_000 * k,
            texture_seed=None if len(job.exposures) == 1 else job.seed,
        )
        name = f"IMG_{job.index + 1:04d}.dng" if k == 0 else f"IMG_{job.index + 1:04d}_{k}.dng"
        photo.write_dng(job.folder / name, exposure_tags=job.exposure_tags)
        files.append(name)
    entry: Record = {
        "file": files[0] if len(files) == 1 else files,
        "light_deg": None,  # filled in by _scene_dict (same light for every photo)
        "view_deg": round(job.view_deg, 6),
    }
    if job.exposure_tags == "none":  # the scene file gives what the files lack (one per file)
        e = job.exposures
        one = len(e) == 1
        entry |= {
            key: getattr(e[0], key) if one else [getattr(x, key) for x in e]
            for key in ("exposure_time_s", "f_number", "iso")
        }
    entry["roi_px"] = {n: [[round(x, 2), round(y, 2)] for x, y in faces[n]] for n in names}
    return entry


def _profile_ends(corners_px: np.ndarray) -> tuple[list[float], list[float]]:
    """Pixel positions of a face's foot and top (the midpoints of its low and high edges,
    `SpecimenLayout.face_corners_mm` order): where its profile coordinate is -1 and +1."""
    c = np.asarray(corners_px, float)
    return (0.5 * (c[0] + c[3])).tolist(), (0.5 * (c[1] + c[2])).tolist()


def _profile(values: np.ndarray) -> np.ndarray:
    """A face's radiance for `render_photo`: (3,) when uniform (Q = 1), else its (Q, 3)."""
    return values[0] if values.shape[0] == 1 else values


def _compact_arrays(toml_text: str) -> str:
    """Put numeric and string arrays (and arrays of them, e.g. polygons) on one line each.

    tomli_w writes every element of a nested array on its own line; the document's meaning is
    unchanged (checked by `load_scene` reading it back in the tests).
    """
    import re

    number = r"-?[0-9][0-9_.eE+-]*"
    flat = re.compile(rf"\[\s*((?:(?:{number}|\"[^\"\n]*\"),\s*)+)\]")
    nested = re.compile(r"\[\s*((?:\[[^\[\]\n]*\],\s*)+)\]")

    def join(m: re.Match[str]) -> str:
        items = [x.strip() for x in m.group(1).split(",") if x.strip()]
        return "[" + ", ".join(items) + "]"

    def join_nested(m: re.Match[str]) -> str:
        items = re.findall(r"\[[^\[\]\n]*\]", m.group(1))
        return "[" + ", ".join(items) + "]"

    return nested.sub(join_nested, flat.sub(join, toml_text))


def _third_stop(t: float) -> float:
    """Round an exposure time down to the nearest third of a stop (a camera's steps)."""
    return float(2.0 ** (np.floor(np.log2(t) * 3) / 3))


def _wedge_name(beta2_deg: float) -> str:
    return f"w{beta2_deg:g}".replace(".", "p")


def _scene_dict(
    s: SimulationSettings,
    layout: SpecimenLayout,
    photos: Sequence[Record],
    calibration: dict[str, list[str]] | None = None,
) -> Record:
    wedges = [
        {
            "name": _wedge_name(b),
            "angle_deg": b,
            "face_mm": np.round(layout.face_base_mm(k), 4).tolist(),
        }
        for k, b in enumerate(layout.wedges_deg)
    ]
    return {
        "version": SCENE_VERSION,
        "angles_relative_to": "base",
        "specimen": {"layer_um": s.layer_um, "material": s.material, "wedges": wedges},
        "light": {"illuminant": s.illuminant, "angular_diameter_deg": s.light_angular_diameter_deg},
        "camera": {"sensitivity": s.camera, "angular_extent_deg": s.camera_angular_extent_deg},
        "markers": {
            "dictionary": "DICT_4X4_50",
            "marker": [{"id": i, "corners_mm": c.tolist()} for i, c in layout.markers_mm()],
        },
        "photos": [{**p, "light_deg": s.light_deg} for p in photos],
        **({"calibration": calibration} if calibration else {}),
        "truth": asdict(s.truth),  # scene.TRUTH_FIELDS: not used by the fit, shown in its report
    }


_SCENE_HEADER = """\
# stairfit scene file, written by `stairfit simulate` (see docs/scene.md for every field).
# Angles are in degrees, relative to the specimen base: a positive light_deg puts the light on
# the downhill side of the wedges, a positive view_deg the camera on the uphill side.
# Each photo lists its wedge ROIs in pixels (x right, y down); face_mm + [markers] would place
# them automatically instead. [truth] holds the parameters the photos were rendered from: the
# fit does not use it, its report shows it beside the fitted values.

"""
