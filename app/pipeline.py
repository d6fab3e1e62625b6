"""The fit pipeline as library functions: photos -> measurement table -> observations -> model
selection -> accuracy check -> posterior -> outputs (what `stairfit fit` runs; also `demo`,
`study`, `explore` and the benchmarks).

`fit_scene(scene, out, options)` runs it whole into a (temporary) folder; its stages are
`check_photos`, `measure`, `observations`, `fit_setup`, `lab_setup`, `select`, `refine` and
`sample`, each typed in and out. What a stage computes once (the photo specs, which hash the
calibration frames; the index and the effective wavelengths in `FitSetup`; the rows' labels in
`Observations`) travels on inside the `FitOutcome`, which the report only reads. Degrees at this
edge, radians inside [conventions §1].
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable, Iterable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from . import _exclusions
from ._compile_watch import watching_compilation
from ._failed_previews import FAILED_PREVIEWS, forget_previews, keep_previews
from .accuracy import check_accuracy
from .errors import StairfitWarning, UserError
from .fit_setup import FitSetup, fit_setup
from .imaging_specs import CACHE_DIR, extraction_settings, measurement_cache, photo_specs
from .outcome import FitOptions, FitOutcome, Observations, RowLabel
from .presets import Preset
from .scene import Scene, Specimen

if TYPE_CHECKING:
    from stairfit import fitting, imaging
    from stairfit.fitting.posterior import PosteriorResult

    from .accuracy import AccuracyCheck
    from .figures import SaveFigure

__all__ = [
    "FitOptions",
    "FitOutcome",
    "FitSetup",
    "Observations",
    "RowLabel",
    "budget_notes",
    "cache_notes",
    "check_model_name",
    "check_photos",
    "fit",
    "fit_scene",
    "fit_setup",
    "fitted_rows",
    "index_notes",
    "lab_setup",
    "ladder_for",
    "measure",
    "observations",
    "photo_file_problem",
    "refine",
    "roi_correlations",
    "sample",
    "sample_while_drawing",
    "select",
    "view_spread",
]

DEG = np.pi / 180


# --- the whole fit --------------------------------------------------------------------------


def fit_scene(scene: Scene, out: Path, options: FitOptions) -> FitOutcome:
    """The whole pipeline into the (temporary) folder `out`: measure the photos, their
    observations, then `fit`."""
    check_kernel(scene, options.kernel)
    specs = tuple(photo_specs(scene))
    t0 = time.perf_counter()
    table = measure(scene, out, options, specs)
    timings = {"measure_s": time.perf_counter() - t0}
    t0 = time.perf_counter()
    try:
        obs = observations(scene, table)
    except UserError as err:  # nothing usable: keep the previews (ROIs, saturation) to look at
        kept = scene.folder / CACHE_DIR / FAILED_PREVIEWS
        shown = "ROIs, saturated pixels in magenta"
        where = keep_previews(kept, out / "previews", specs, table.photos(), shown)
        raise UserError(f"{err}{where}") from None
    return fit(scene, table, obs, out, options, specs=specs, timings=timings, started=t0)


def fit(
    scene: Scene,
    table: imaging.MeasurementTable,
    obs: Observations,
    out: Path,
    options: FitOptions,
    *,
    specs: Sequence[imaging.PhotoSpec] | None = None,
    timings: dict[str, float] | None = None,
    started: float | None = None,
) -> FitOutcome:
    """Fit the observations `obs` of the measured photos (`table`) and write every output into
    `out`: model selection, accuracy check, posterior (the figures drawn in a thread beside
    it, in this process: nothing is left running if it is killed) and the report. `specs`: the
    photos' specs when already computed; `timings`: the stages' times so far (e.g.
    `measure_s`); `started`: the `time.perf_counter()` `fit_s` counts from (default: now)."""
    specs = tuple(photo_specs(scene) if specs is None else specs)
    timings = dict(timings or {})
    t0 = time.perf_counter() if started is None else started
    notes = [*scene.left_out, *obs.notes, *cache_notes(scene, table)]
    setup = fit_setup(scene, options.preset)
    notes.extend(index_notes(scene, setup))
    lab, reason, warning = lab_setup(scene, table)
    if reason is not None:
        notes.append(f"fitted with the lab model (3-D directions per face) because {reason}")
        notes.extend(plate_notes(scene.specimen))
    if warning is not None:
        notes.append(warning)
        warnings.warn(warning, StairfitWarning, stacklevel=2)
    with watching_compilation(options.progress) as compiled:
        selection = select(obs.data, setup, options, lab)
        notes.extend(budget_notes(selection, options.preset))
        selection, accuracy = refine(scene, obs.data, selection, options, setup)
        timings["fit_s"] = time.perf_counter() - t0
        fitted = FitOutcome(
            scene=scene,
            options=options,
            photo_specs=specs,
            table=table,
            observations=obs,
            setup=setup,
            selection=selection,
            posterior=None,
            timings=dict(timings),
            notes=tuple(notes),
            accuracy=accuracy,
            lab_reason=reason,
        )
        posterior, drawn = None, None
        if options.posterior:
            t0 = time.perf_counter()
            posterior, drawn = sample_while_drawing(fitted, out)
            timings["posterior_s"] = time.perf_counter() - t0
    timings.update(compiled.as_timings())
    from .report import write_outputs

    _freeze_imports(options)

    outcome = replace(fitted, posterior=posterior, timings=dict(timings))
    t0 = time.perf_counter()
    write_outputs(outcome, out, drawn)
    timings["outputs_s"] = time.perf_counter() - t0
    return replace(outcome, timings=timings)


def sample_while_drawing(
    outcome: FitOutcome, out: Path, draw: SaveFigure | None = None
) -> tuple[PosteriorResult, dict[str, str]]:
    """The posterior of the chosen fit, and meanwhile, in a second thread, the report's figures
    that need the least-squares fit only (`report.fit_figures`, drawn from `outcome`, which
    nothing changes meanwhile) by `draw` (default `figures.save`): the sampler's model
    evaluations release the interpreter most of the time. Whatever ends the sampling (an
    error, Ctrl-C), the figures are handed over first."""
    from concurrent.futures import ThreadPoolExecutor

    from .figures import save
    from .report import fit_figures

    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="stairfit-figures") as pool:
        drawing = pool.submit(fit_figures, outcome, out / "figures", draw or save)
        posterior = sample(outcome.selection.fit, out, outcome.options)
        return posterior, drawing.result()


# --- photos ---------------------------------------------------------------------------------


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
    from .fileio import describe

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


def measure(
    scene: Scene,
    out: Path,
    options: FitOptions,
    specs: Sequence[imaging.PhotoSpec] | None = None,
) -> imaging.MeasurementTable:
    """Decode and measure every photo (cached in DIR/.stairfit-cache), previews into out;
    `specs`: the photos' specs when already computed (`imaging_specs.photo_specs`)."""
    from stairfit import imaging

    settings = extraction_settings(scene)
    cache, secret = measurement_cache(scene, options.cache)
    specs = list(photo_specs(scene) if specs is None else specs)
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


def budget_notes(selection: fitting.Selection, preset: Preset) -> list[str]:
    """A note when the preset's ladder budget left rungs untried, naming them and the preset
    that fits every rung."""
    from stairfit import fitting

    untried = fitting.budget_untried(selection)
    if not untried:
        return []
    return [
        f"{len(untried)} rung(s) of the ladder were not tried ({', '.join(untried)}): the "
        f"'{preset.name}' preset's budget of {preset.ladder_budget_gflop:g} Gflop of solver "
        "work was spent; --preset accurate fits every rung"
    ]


def cache_notes(scene: Scene, table: imaging.MeasurementTable) -> list[str]:
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


# --- observations ---------------------------------------------------------------------------


def view_spread(row: imaging.MeasurementRow, extent_deg: float, to_deg: float) -> float:
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


def fitted_rows(
    scene: Scene, table: Iterable[imaging.MeasurementRow]
) -> list[imaging.MeasurementRow]:
    """The measurement rows the fit sees, in the table's order: all but the reference's."""
    reference = scene.reference.name if scene.reference is not None else None
    return [r for r in table if r.wedge != reference]


def observations(scene: Scene, table: imaging.MeasurementTable) -> Observations:
    """The fit's observations from the measurement table and the scene geometry.

    Rows that imaging flagged, or in which any pixel saturated (their mean is biased low), are
    kept but excluded from the fit (`use = False`) and counted in the notes. The channels of
    one photo x wedge share an `roi_index` and carry the ROI's error correlations, which the
    fit whitens (`roi_correlations`; docs/fitting.md §Correlated channels).

    Raises:
        UserError: no row can be fitted, or the rows are invalid (one line naming the scene).
    """
    from stairfit import fitting

    wedges = {w.name: (k, w) for k, w in enumerate(scene.specimen.wedges)}
    photos = {p.file: (k, p) for k, p in enumerate(scene.photos)}
    channels = {"R": 0, "G": 1, "B": 2}
    rows: list[dict[str, float | int | bool]] = []
    labels: list[RowLabel] = []
    n_flagged = n_saturated = 0
    rois: dict[tuple[str, str], int] = {}
    measured = fitted_rows(scene, table)
    for r in measured:
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
                "view_spread": view_spread(r, scene.camera.angular_extent_deg, to),
            }
        )
        labels.append(
            RowLabel(r.photo, r.wedge, r.channel, photo.light_deg, photo.view_deg, ti, to, use)
        )
    if not rows or not any(r["use"] for r in rows):
        counts = _exclusions.count_reasons(measured)
        why = _exclusions.nothing_usable(len(rows), counts, measured, scene.extraction.block_px)
        raise UserError(f"{scene.path}: {why}")
    try:
        data = fitting.Observations.from_rows(rows)
    except fitting.FitInputError as err:
        raise UserError(f"{scene.path}: {err}") from None
    notes = []
    if n_flagged:
        flags = _exclusions.count_reasons(r for r in measured if r.flag)
        notes.append(
            f"{n_flagged} measurements flagged by imaging ({_exclusions.describe(flags)}) were "
            "not fitted"
        )
    if n_saturated:
        notes.append(f"{n_saturated} measurements with some saturated pixels were not fitted")
    return Observations(data, tuple(labels), tuple(notes))


def roi_correlations(row: imaging.MeasurementRow) -> dict[str, float]:
    """The fit's `corr_01`, `corr_02`, `corr_12` (channels R = 0, G = 1, B = 2) from a
    measurement row's `corr_rg`, `corr_rb`, `corr_gb`; an unknown (NaN) correlation is 0."""
    pairs = (("corr_01", "corr_rg"), ("corr_02", "corr_rb"), ("corr_12", "corr_gb"))
    out = {}
    for key, name in pairs:
        c = float(getattr(row, name, np.nan))
        out[key] = min(max(c, -1.0), 1.0) if np.isfinite(c) else 0.0
    return out


# --- the fit --------------------------------------------------------------------------------


def index_notes(scene: Scene, setup: FitSetup) -> list[str]:
    """A warning (and a note for results.json) when the fit uses the index outside `valid_nm`."""
    from ._index_checks import extrapolation_warning

    index = scene.specimen.index
    name = index.name if index.model == "named" else f"the scene's {index.model} index"
    spectral = setup.spectral
    message = extrapolation_warning(
        setup.index, name, spectral.wavelength_nm, spectral.weights, user="the fit"
    )
    return [message] if message else []


def plate_notes(specimen: Specimen) -> list[str]:
    """The note of a lab fit whose scene gives no plate albedo: the plate's reflected light is
    then left out, which on a steep face seen from downhill is several per cent."""
    if specimen.plate_albedo > 0.0:
        return []
    return [
        "the light the plate reflects onto the faces is left out: give the plate's reflectance "
        'as [specimen] plate_albedo (docs/scene.md "A near lamp"); it can be several per cent '
        "of a steep face seen from downhill"
    ]


def lab_setup(
    scene: Scene, table: imaging.MeasurementTable
) -> tuple[fitting.LabGeometry | None, str | None, str | None]:
    """(the lab geometry of the observations' rows, why the fit uses the lab model, a warning),
    the first two None when it does not (`stairfit.lab.lab_choice`)."""
    from .lab import lab_choice, lab_geometry

    rows = fitted_rows(scene, table)  # the observations' rows, in their order
    choice = lab_choice(scene, rows)
    if not choice.use:
        return None, None, choice.warning
    return lab_geometry(scene, rows), choice.reason, choice.warning


def check_model_name(name: str) -> None:
    """A `--model` that is not a ladder variant is a user error, caught before any work."""
    from stairfit import fitting

    names = [v.name for v in fitting.DEFAULT_LADDER]
    if name not in names:
        import difflib

        near = difflib.get_close_matches(name, names, n=1)
        hint = f"did you mean {near[0]!r}?" if near else f"variants: {', '.join(names)}"
        raise UserError(f"--model: unknown variant {name!r}; {hint}")


def check_kernel_name(name: str) -> None:
    """A `--kernel` the lab model does not have is a user error, caught before any work."""
    from stairfit import model

    if name not in model.LAB_KERNELS:
        raise UserError(f"--kernel: unknown facet kernel {name!r}; use one of "
                        f"{', '.join(model.LAB_KERNELS)}")  # fmt: skip


def offered_kernels(lab: bool, given: str | None) -> tuple[str, ...]:
    """The facet kernels the fit compares: the given one alone (`--kernel`: no probes;
    `check_kernel` has checked that the scene allows it), else every kernel of the lab model,
    or the in-plane model's Gaussian."""
    from stairfit import model

    if given is not None:
        return (given,)
    return model.LAB_KERNELS if lab else ("gaussian",)


def check_kernel_geometry(kernel: str | None, lab: bool, scene: str, fix: str) -> None:
    """A microfacet `--kernel` on a scene the fit models in one plane (`lab` False: Gaussian
    facets only) is a user error; `scene` names the scene in the message, `fix` ends it."""
    if kernel is not None and kernel != "gaussian" and not lab:
        raise UserError(f"--kernel {kernel}: {scene} is fitted in one plane, where the facets "
                        f"are Gaussian; {fix}")  # fmt: skip


def check_kernel(scene: Scene, kernel: str | None) -> None:
    """`check_kernel_geometry` for a scene file, before the photos are measured."""
    from .lab import uses_lab_model

    check_kernel_geometry(kernel, uses_lab_model(scene), "this scene",
                          "microfacet facets need the lab model (give the lamp's position, or "
                          'set [fit] geometry = "lab"; docs/scene.md)')  # fmt: skip


def ladder_for(preset: Preset, lab: bool = False) -> tuple[fitting.Variant, ...]:
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
    observations: fitting.Observations,
    setup: FitSetup,
    options: FitOptions,
    lab: fitting.LabGeometry | None = None,
) -> fitting.Selection:
    """Fit the ladder and choose (or fit the forced variant): `fitting.select_model` with the
    preset's settings; the science (nested starts, the rounding gate, status words) is there.
    With `lab` geometry, the lab model with every facet kernel offered (`offered_kernels`)."""
    from stairfit import fitting

    ladder = ladder_for(options.preset, lab is not None)
    resolution = fitting.Resolution(options.preset.rounded_resolution, options.preset.fillet_rays)
    try:
        problem = fitting.prepare(
            observations, setup.spectral, aperture=setup.aperture, resolution=resolution, lab=lab
        )
    except fitting.FitInputError as err:
        raise UserError(f"the fit failed: {err}") from None
    kernels = offered_kernels(lab is not None, options.kernel)
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
                work_budget_gflop=options.preset.ladder_budget_gflop,
            )
        except (fitting.FitError, fitting.FitInputError) as err:
            raise UserError(f"the fit failed: {err}") from None
        if forced:
            tick()
    return selection


def refine(
    scene: Scene,
    observations: fitting.Observations,
    selection: fitting.Selection,
    options: FitOptions,
    setup: FitSetup | None = None,
) -> tuple[fitting.Selection, AccuracyCheck]:
    """The preset's numerical error at the optimum, and the chosen fit refined when the data
    need it (app/accuracy.py; issue 13); `setup`: the fit's, whose index the check reuses."""
    index = None if setup is None else setup.index
    with _Progress(options.progress, "checking numerical accuracy") as tick:
        out = check_accuracy(scene, observations, selection, options.preset, index)
        tick()
    return out


def sample(fit: fitting.FitResult, out: Path, options: FitOptions) -> PosteriorResult:
    """The posterior of the chosen variant; the chain is saved as out/chain.npz."""
    from stairfit import fitting
    from stairfit.fitting.posterior import sample_posterior

    _freeze_imports(options)
    try:
        return sample_posterior(
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


def _freeze_imports(options: FitOptions) -> None:
    """With `options.freeze_imports` (the console script, `cli.entry`), move what the fit's late
    imports made (emcee and SciPy, matplotlib and the report) into the collector's permanent
    generation (`gc.freeze()`): they live until the process ends, and every full collection
    would walk them again. Not in processes that go on (tests, notebooks, a study's workers):
    what is frozen is never collected."""
    if options.freeze_imports:
        import gc

        gc.freeze()


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
