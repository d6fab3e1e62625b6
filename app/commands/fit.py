"""`stairfit fit DIR`: decode -> extract -> fit -> select model -> posterior -> results.

Degrees at this edge, radians inside [conventions §1]. Every stage shows a progress bar; the
results are written into a temporary folder that is moved into place only when complete.
"""

from __future__ import annotations

import argparse
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .. import _ranges
from .._compile_watch import watching_compilation
from .._prefetch import FIT_MODULES, REPORT_MODULES, prefetch
from ..errors import StairfitWarning, UserError
from ..imaging_specs import CACHE_DIR, extraction_settings, measurement_cache, photo_specs
from ..outcome import FitOptions, FitOutcome
from ..presets import PRESETS, Preset, get_preset
from ..scene import Scene, load_scene
from . import _exclusions
from ._failed_previews import FAILED_PREVIEWS, forget_previews, keep_previews

if TYPE_CHECKING:
    from ..figures import SaveFigure

DEG = np.pi / 180


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register the `fit` command."""
    p = sub.add_parser(
        "fit",
        help="fit the staircase model to a folder of RAW photos",
        description=(
            "Decode the RAW photos listed in DIR/scene.toml, measure every wedge face, fit the "
            "model ladder by least squares, choose the simplest model the data support, sample "
            "its posterior, and write results.json, the measurement table, figures and "
            "report.html to the output folder."
        ),
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("folder", type=Path, metavar="DIR", help="photo folder with scene.toml")
    add_fit_options(p)
    p.set_defaults(func=run)


def add_fit_options(p: argparse.ArgumentParser) -> None:
    """Options shared by `fit` and `demo`."""
    p.add_argument(
        "-o",
        "--output",
        type=Path,
        default=None,
        help="results folder (default: DIR-fit next to DIR)",
    )
    p.add_argument(
        "--preset",
        default="balanced",
        choices=sorted(PRESETS),
        help="speed/accuracy preset (README: Speed and accuracy)",
    )
    p.add_argument("--no-posterior", action="store_true", help="skip the emcee posterior")
    p.add_argument(
        "--model",
        default=None,
        help="force one model variant (e.g. 'sharp+delta_n') instead of selecting",
    )
    p.add_argument(
        "--no-model-error", action="store_true", help="do not fit a fractional model-error term"
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the posterior sampler")
    p.add_argument(
        "--workers", type=int, default=1, help="processes decoding photos (1 is fastest on 2 cores)"
    )
    p.add_argument(
        "--no-cache", action="store_true", help=f"decode every photo again (ignore DIR/{CACHE_DIR})"
    )
    p.add_argument("--force", action="store_true", help="replace an existing results folder")
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def options_from_args(args: argparse.Namespace) -> FitOptions:
    """Validated options (user mistakes raise UserError)."""
    _ranges.check_workers(args.workers)
    if args.seed < 0:
        raise UserError(f"--seed: {args.seed} is negative; give an integer >= 0")
    if args.model is not None:
        check_model_name(args.model)
    return FitOptions(
        preset=get_preset(args.preset),
        posterior=not args.no_posterior,
        model=args.model,
        model_error=not args.no_model_error,
        freeze_imports=bool(getattr(args, "freeze_imports", False)),
        seed=args.seed,
        workers=args.workers,
        cache=not args.no_cache,
        progress=not args.quiet,
    )


def check_model_name(name: str) -> None:
    """A `--model` that is not a ladder variant is a user error, caught before any work."""
    from stairfit import fitting

    names = [v.name for v in fitting.DEFAULT_LADDER]
    if name not in names:
        import difflib

        near = difflib.get_close_matches(name, names, n=1)
        hint = f"did you mean {near[0]!r}?" if near else f"variants: {', '.join(names)}"
        raise UserError(f"--model: unknown variant {name!r}; {hint}")


def default_output(folder: Path) -> Path:
    """`DIR-fit` next to the photo folder."""
    from ..fileio import resolved

    folder = resolved(folder)
    return folder.with_name(f"{folder.name}-fit")


def run(args: argparse.Namespace) -> int:
    """`stairfit fit DIR`."""
    from ..outputs import staged_folder

    options = options_from_args(args)
    scene = load_scene(args.folder)
    out = args.output or default_output(args.folder)
    inputs = (scene.folder, *scene.input_files())
    reserved = (scene.folder / CACHE_DIR,)
    with staged_folder(out, args.force, command="fit", inputs=inputs, reserved=reserved) as tmp:
        check_photos(scene)
        outcome = fit_scene(scene, tmp, options)
    from ..report import print_summary

    print_summary(outcome, out)
    return 0


def check_photos(scene: Scene) -> None:
    """Every listed file (photos, bracket members, calibration frames) is a regular file (a
    one-line error names the one that is not)."""
    for where, name, _ in scene.input_fields():
        remove = "the [[photos]] entry" if where.endswith(".file") else "it from the list"
        problem = photo_file_problem(scene.folder / name, scene.folder, remove)
        if problem is not None:
            raise UserError(f"{scene.path}: {where}: {name!r} {problem}")


def photo_file_problem(
    path: Path, folder: Path, remove: str = "the [[photos]] entry"
) -> str | None:
    """Why `path` cannot be read as a photo (missing, a folder, a pipe, a device, a broken link,
    a loop of links), or None.

    Checked before decoding: reading a link to /dev/zero would never end. `remove` names what
    to remove in the advice for a missing file.
    """
    from ..fileio import describe

    problem = describe(path)
    if problem is None:
        return None
    if problem == "does not exist":
        spaces = " (mind the spaces around the name)" if path.name != path.name.strip() else ""
        return f"is not in {folder}{spaces}; fix the name or remove {remove}"
    if problem.endswith("which does not exist") or "loop" in problem:
        return f"{problem}; fix the link"
    if problem.endswith("a folder"):
        return f"{problem}, not a RAW file; name the photo file itself"
    return f"{problem}, not a RAW file; give the photo's RAW file"


def fit_scene(scene: Scene, out: Path, options: FitOptions) -> FitOutcome:
    """The whole pipeline into the (temporary) folder `out`."""
    timings: dict[str, float] = {}
    notes: list[str] = []
    t0 = time.perf_counter()
    table = measure(scene, out, options)
    timings["measure_s"] = time.perf_counter() - t0
    # the posterior's and the report's imports, in a thread while the model is compiled and
    # fitted (not while the photos are decoded, which keeps both cores busy)
    prefetch(FIT_MODULES if options.posterior else REPORT_MODULES, options.freeze_imports)
    return _fit_measured(scene, out, options, table, timings, notes)


def _fit_measured(
    scene: Scene,
    out: Path,
    options: FitOptions,
    table: Any,
    timings: dict[str, float],
    notes: list[str],
) -> FitOutcome:
    """`fit_scene` once the photos are measured: fit, posterior, outputs (the figures drawn
    in a thread beside the posterior, in this process: nothing is left running if it is
    killed)."""
    t0 = time.perf_counter()
    try:
        observations, row_info, excluded_notes = to_observations(scene, table)
    except UserError as err:  # nothing usable: keep the previews (ROIs, saturation) to look at
        kept = scene.folder / CACHE_DIR / FAILED_PREVIEWS
        shown = "ROIs, saturated pixels in magenta"
        where = keep_previews(kept, out / "previews", photo_specs(scene), table.photos(), shown)
        raise UserError(f"{err}{where}") from None
    notes.extend(excluded_notes)
    notes.extend(cache_notes(scene, table))
    spectral, aperture = fit_setup(scene, options.preset)
    notes.extend(index_notes(scene, spectral))
    lab, reason, warning = lab_setup(scene, table)
    if reason is not None:
        notes.append(f"fitted with the lab model (3-D directions per face) because {reason}")
    if warning is not None:
        notes.append(warning)
        warnings.warn(warning, StairfitWarning, stacklevel=2)
    with watching_compilation(options.progress) as compiled:
        selection = select(observations, spectral, aperture, options, lab)
        selection, accuracy = refine(scene, observations, selection, options)
        timings["fit_s"] = time.perf_counter() - t0

        outcome = FitOutcome(scene, options, table, observations, row_info, spectral,
                             selection, None, timings, notes, accuracy, reason)  # fmt: skip
        drawn = None
        if options.posterior:
            t0 = time.perf_counter()
            outcome.posterior, drawn = sample_while_drawing(outcome, out)
            timings["posterior_s"] = time.perf_counter() - t0
    timings.update(compiled.as_timings())
    from ..report import write_outputs

    t0 = time.perf_counter()
    write_outputs(outcome, out, drawn)
    timings["outputs_s"] = time.perf_counter() - t0
    return outcome


def sample_while_drawing(
    outcome: FitOutcome, out: Path, draw: SaveFigure | None = None
) -> tuple[Any, dict[str, str]]:
    """The posterior of the chosen fit, and meanwhile, in a second thread, the report's figures
    that need the least-squares fit only (`report.fit_figures`), drawn by `draw` (default
    `figures.save`): the sampler's model evaluations release the interpreter most of the time.
    Whatever ends the sampling (an error, Ctrl-C), the figures are handed over first."""
    from concurrent.futures import ThreadPoolExecutor

    from ..figures import save
    from ..report import fit_figures

    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="stairfit-figures") as pool:
        drawing = pool.submit(fit_figures, outcome, out / "figures", draw or save)
        posterior = sample(outcome.selection.fit, out, outcome.options)
        return posterior, drawing.result()


# --- stages ---------------------------------------------------------------------------------


def measure(scene: Scene, out: Path, options: FitOptions) -> Any:
    """Decode and measure every photo (cached in DIR/.stairfit-cache), previews into out."""
    from stairfit import imaging

    settings = extraction_settings(scene)
    cache, secret = measurement_cache(scene, options.cache)
    specs = photo_specs(scene)
    kept = scene.folder / CACHE_DIR / FAILED_PREVIEWS
    try:
        table = imaging.measure_photos(
            specs,
            settings,
            cache=cache,
            preview_dir=out / "previews",
            progress=options.progress,
            max_workers=options.workers,
            cache_secret=secret,
        )
    except imaging.ImagingError as err:
        failed = getattr(err, "failed_photos", ())
        where = keep_previews(kept, out / "previews", specs, failed)
        raise UserError(f"{scene.path}: {err}{where}") from None
    forget_previews(kept)
    return table


def cache_notes(scene: Scene, table: Any) -> list[str]:
    """A note (printed, and in results.json) saying which photos' values came from the
    measurement cache rather than from decoding the photos now."""
    reused = tuple(getattr(table, "from_cache", ()))
    if not reused:
        return []
    shown = ", ".join(reused[:5]) + (f" and {len(reused) - 5} more" if len(reused) > 5 else "")
    return [
        f"the measurements of {len(reused)} of {len(table.photos())} photos ({shown}) came from "
        f"the measurement cache in {scene.folder / CACHE_DIR} (checked against each photo's "
        "SHA-256 and this user's cache key); --no-cache measures them again"
    ]


def _spread(row: Any, extent_deg: float, to_deg: float) -> float:
    """A measurement row's `view_spread` for the fit [conventions §9]: for an ROI placed through
    a pinhole with its own spread of viewing angles (`view_half_width_deg`), that spread over
    the one the aperture gives the row, `extent / 2 x cos(theta_o)` (it may exceed 1: a face
    longer along its slope than `angular_extent_deg` assumes; docs/imaging.md §Viewing
    spread); else the eroded ROI's share `view_spread`; 1 (the whole face) where neither is
    defined."""
    value, half_width_deg = row.view_spread, row.view_half_width_deg
    if half_width_deg is not None and np.isfinite(half_width_deg) and extent_deg > 0:
        seen = 0.5 * extent_deg * float(np.cos(np.deg2rad(to_deg)))
        if seen > 0:
            return float(half_width_deg) / seen
    return float(value) if np.isfinite(value) and 0 <= value <= 1 else 1.0


def to_observations(scene: Scene, table: Any) -> tuple[Any, list[dict[str, Any]], list[str]]:
    """The fit's observation table from the measurement table and the scene geometry.

    Rows that imaging flagged, or in which any pixel saturated (their mean is biased low), are
    kept but excluded from the fit (`use = False`) and counted in the notes. The channels of
    one photo x wedge share an `roi_index` and carry the ROI's error correlations, which the
    fit whitens (`roi_correlations`; docs/fitting.md §Correlated channels).
    """
    from stairfit import fitting

    wedges = {w.name: (k, w) for k, w in enumerate(scene.specimen.wedges)}
    photos = {p.file: (k, p) for k, p in enumerate(scene.photos)}
    channels = {"R": 0, "G": 1, "B": 2}
    rows, info = [], []
    n_flagged = n_saturated = 0
    reference = scene.reference.name if scene.reference is not None else None
    rois: dict[tuple[str, str], int] = {}
    for r in table:
        if r.wedge == reference:
            continue
        k, wedge = wedges[r.wedge]
        p, photo = photos[r.photo]
        ti, to = scene.face_angles_deg(photo, wedge)
        if r.face_view_deg is not None and np.isfinite(r.face_view_deg):
            to = r.face_view_deg + wedge.angle_deg  # the face's own view angle (pinhole)
        flagged = bool(r.flag)
        saturated = r.saturated_fraction > 0
        n_flagged += flagged
        n_saturated += saturated and not flagged
        finite = np.isfinite(r.value) and np.isfinite(r.stderr) and r.stderr > 0
        use = not flagged and not saturated and finite
        rows.append(
            {
                "theta_i_deg": ti,
                "theta_o_deg": to,
                "beta2_deg": wedge.angle_deg,
                "layer_um": scene.specimen.layer_um,
                "wedge_index": k,
                "channel_index": channels[r.channel],
                "value": r.value if finite else 0.0,
                "stderr": r.stderr if finite else 1.0,
                "use": use,
                "photo_index": p,
                "saturated": saturated,
                "roi_index": rois.setdefault((r.photo, r.wedge), len(rois)),
                **roi_correlations(r),
                "view_spread": _spread(r, scene.camera.angular_extent_deg, to),
            }
        )
        info.append(
            {
                "photo": r.photo,
                "wedge": r.wedge,
                "channel": r.channel,
                "light_deg": photo.light_deg,
                "view_deg": photo.view_deg,
                "theta_i_deg": ti,
                "theta_o_deg": to,
                "use": use,
            }
        )
    fitted_rows = [r for r in table if r.wedge != reference]
    if not rows or not any(r["use"] for r in rows):
        counts = _exclusions.count_reasons(fitted_rows)
        why = _exclusions.nothing_usable(len(rows), counts, fitted_rows, scene.extraction.block_px)
        raise UserError(f"{scene.path}: {why}")
    try:
        obs = fitting.Observations.from_rows(rows)
    except fitting.FitInputError as err:
        raise UserError(f"{scene.path}: {err}") from None
    notes = []
    if n_flagged:
        flags = _exclusions.count_reasons(r for r in fitted_rows if r.flag)
        notes.append(
            f"{n_flagged} measurements flagged by imaging ({_exclusions.describe(flags)}) were "
            "not fitted"
        )
    if n_saturated:
        notes.append(f"{n_saturated} measurements with some saturated pixels were not fitted")
    return obs, info, notes


def roi_correlations(row: Any) -> dict[str, float]:
    """The fit's `corr_01`, `corr_02`, `corr_12` (channels R = 0, G = 1, B = 2) from a
    measurement row's `corr_rg`, `corr_rb`, `corr_gb`; an unknown (NaN) correlation is 0."""
    pairs = (("corr_01", "corr_rg"), ("corr_02", "corr_rb"), ("corr_12", "corr_gb"))
    out = {}
    for key, name in pairs:
        c = float(getattr(row, name, np.nan))
        out[key] = min(max(c, -1.0), 1.0) if np.isfinite(c) else 0.0
    return out


def fit_setup(scene: Scene, preset: Preset) -> tuple[Any, Any]:
    """Spectral setup and aperture from the scene and the preset [conventions §8, §9]."""
    from stairfit import fitting, model

    spectral = fitting.spectral_setup(
        scene.specimen.index.build(),
        scene.camera.sensitivity,
        scene.light.illuminant,
        sampling=preset.spectral,
    )
    aperture = model.Aperture(
        0.5 * scene.light.angular_diameter_deg * DEG,
        0.5 * scene.camera.angular_extent_deg * DEG,
        preset.aperture_nodes
        if (scene.light.angular_diameter_deg > 0 or scene.camera.angular_extent_deg > 0)
        else 1,
        foreshortened=True,  # angular_extent_deg is the spread seen face-on (docs/scene.md)
        light_shape=scene.light.shape,
    )
    return spectral, aperture


def index_notes(scene: Scene, spectral: Any) -> list[str]:
    """A warning (and a note for results.json) when the fit uses the index outside `valid_nm`."""
    from .._index_checks import extrapolation_warning

    index = scene.specimen.index
    name = index.name if index.model == "named" else f"the scene's {index.model} index"
    message = extrapolation_warning(
        index.build(), name, spectral.wavelength_nm, spectral.weights, user="the fit"
    )
    return [message] if message else []


def lab_setup(scene: Scene, table: Any) -> tuple[Any, str | None, str | None]:
    """(the lab geometry of the observation table's rows, why the fit uses the lab model, a
    warning), the first two None when it does not (`stairfit.lab.lab_choice`)."""
    from ..lab import lab_choice, lab_geometry

    reference = scene.reference.name if scene.reference is not None else None
    rows = [r for r in table if r.wedge != reference]  # to_observations' rows, in its order
    choice = lab_choice(scene, rows)
    if not choice.use:
        return None, None, choice.warning
    return lab_geometry(scene, rows), choice.reason, choice.warning


def ladder_for(preset: Preset, lab: bool = False) -> tuple[Any, ...]:
    """The model ladder of a preset (shared sigma only, or also per-wedge sigma); the lab
    model has no fillet rungs (docs/model.md §7.6)."""
    from stairfit import fitting

    ladder = fitting.DEFAULT_LADDER
    if lab:
        ladder = tuple(v for v in ladder if fitting.FILLET not in v.free)
    if preset.ladder == "full":
        return ladder
    return tuple(v for v in ladder if not v.per_wedge_sigma)


def select(
    observations: Any, spectral: Any, aperture: Any, options: FitOptions, lab: Any = None
) -> Any:
    """Fit the ladder and choose (or fit the forced variant): `fitting.select_model` with the
    preset's settings; the science (nested starts, the rounding gate, status words) is there.
    With `lab` geometry, the lab model with every facet kernel offered."""
    from stairfit import fitting, model

    ladder = ladder_for(options.preset, lab is not None)
    resolution = fitting.Resolution(options.preset.rounded_resolution, options.preset.fillet_rays)
    try:
        problem = fitting.prepare(
            observations, spectral, aperture=aperture, resolution=resolution, lab=lab
        )
    except fitting.FitInputError as err:
        raise UserError(f"the fit failed: {err}") from None
    kernels = model.LAB_KERNELS if lab is not None else ("gaussian",)
    if options.model is not None:
        check_model_name(options.model)
        ladder = fitting.DEFAULT_LADDER
    forced = options.model is not None  # select_model reports each ladder fit, not a forced one
    # the kernel probes (a second, rounded one when the first misfits), and the kernels
    # compared again at the chosen variant
    total = (1 if forced else len(ladder)) + (3 * len(kernels) - 1 if len(kernels) > 1 else 0)
    bar = _Progress(options.progress, "fitting models", total=total)
    with bar as tick, warnings.catch_warnings():
        warnings.simplefilter("ignore", fitting.FitWarningCategory)
        try:
            selection = fitting.select_model(
                problem,
                None,
                ladder,
                force=options.model,
                model_error=options.model_error,
                rounded_rungs=options.preset.rounded_rungs,
                sigma_starts_rad=tuple(s * DEG for s in options.preset.sigma_starts_deg),
                on_variant=lambda name: tick(),
                kernels=kernels,
                time_budget_s=options.preset.ladder_budget_s,
            )
        except (fitting.FitError, fitting.FitInputError) as err:
            raise UserError(f"the fit failed: {err}") from None
        if forced:
            tick()
    return selection


def refine(scene: Scene, observations: Any, selection: Any, options: FitOptions) -> Any:
    """The preset's numerical error at the optimum, and the chosen fit refined when the data
    need it (app/commands/_accuracy_check.py; issue 13)."""
    from ._accuracy_check import check_accuracy

    with _Progress(options.progress, "checking numerical accuracy") as tick:
        out = check_accuracy(scene, observations, selection, options.preset)
        tick()
    return out


def sample(fit: Any, out: Path, options: FitOptions) -> Any:
    """The posterior of the chosen variant; the chain is saved as out/chain.npz."""
    from stairfit import fitting

    try:
        return fitting.sample_posterior(
            fit,
            seed=options.seed,
            tau_factor=options.preset.posterior_tau_factor,
            max_steps=options.preset.posterior_max_steps,
            chunk_steps=options.preset.posterior_chunk_steps,
            chain_path=out / "chain.npz",
            progress=options.progress,
            emit_warnings=False,
        )
    except (fitting.FitError, fitting.FitInputError) as err:
        raise UserError(f"the posterior could not be sampled: {err}") from None


class _Progress:
    """A tqdm bar over the few steps of a stage that has no finer progress to report."""

    def __init__(self, enabled: bool, desc: str, total: int = 1) -> None:
        self.enabled, self.desc, self.total = enabled, desc, total

    def __enter__(self) -> Callable[[], None]:
        from tqdm import tqdm

        self.bar = tqdm(total=self.total, desc=self.desc, disable=not self.enabled, unit="stage")
        return lambda: self.bar.update()

    def __exit__(self, *exc: object) -> None:
        self.bar.close()
