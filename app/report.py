"""Everything `fit` writes: results.json, tables, figures, report.html, and the summary.

Degrees on every axis and in every file [conventions §1]; the fitted broadening is reported as
`sigma_deg`.
"""

from __future__ import annotations

import csv
import datetime
import html
import json
import os
import platform
import sys
from importlib import metadata
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from matplotlib.figure import Figure

from stairfit.fitting import ESS_MIN, RHAT_MAX

from . import __version__
from ._gloss_report import gloss_html, gloss_record
from ._misfit_report import (
    assessment_record,
    misfit_html,
    residual_pattern_figure,
    rounding_record,
    rounding_sentence,
    summary_lines,
)
from .figures import (
    SaveFigure,
    brdf_map,
    fixed_layout,
    log_y,
    reflected_colours,
    refractive_index,
    save,
)
from .fileio import write_file, writing
from .outcome import FitOutcome, sha256_of

if TYPE_CHECKING:
    from collections.abc import Iterable

    from stairfit import fitting
    from stairfit.fitting.posterior import PosteriorResult
    from stairfit.model.materials import Dispersion

    from ._jsontypes import JSONValue, Record

DEG = np.pi / 180
PACKAGES = (
    "jax",
    "jaxlib",
    "optimistix",
    "equinox",
    "numpy",
    "emcee",
    "rawpy",
    "opencv-contrib-python-headless",
    "colour-science",
    "tifffile",
    "matplotlib",
    "arviz",
    "h5netcdf",
)


# --- parameters at the edge ---------------------------------------------------------------


def display_param(param: str) -> str:
    """A parameter's name in files and on screens, without its wedge (`sigma_rad` is shown in
    degrees, as `sigma_deg`; as in truth.json and `fixed_parameters`)."""
    return "sigma_deg" if param == "sigma_rad" else param


def display_name(p: fitting.Estimate | fitting.Parameter) -> tuple[str, float]:
    """Name and factor for files and screens of a parameter (a `fitting.Estimate` or
    `fitting.Parameter`): widths become degrees (`sigma_deg`, `sigma_deg[2: 30 deg]`)."""
    return p.label(display_param(p.param)), 1.0 / DEG if p.param == "sigma_rad" else 1.0


def display_unit(p: fitting.Estimate | fitting.Parameter) -> str:
    """Unit for files and screens of a parameter (see `display_name`)."""
    return "deg" if p.param == "sigma_rad" else p.unit


def parameter_records(outcome: FitOutcome) -> list[Record]:
    """One record per free parameter: least-squares and posterior estimates, display units."""
    fit, post = outcome.selection.fit, outcome.posterior
    records = []
    sampled = [] if post is None else [(p.param, p.wedge) for p in post.parameters]
    for i, e in enumerate(fit.estimates):
        name, f = display_name(e)
        rec: Record = {
            "name": name,
            "parameter": e.param,
            "wedge": e.wedge,
            "unit": display_unit(e),
            "least_squares": {
                "value": e.value * f,
                "stderr": None if e.stderr is None else e.stderr * f,
                "at_bound": e.at_bound,
            },
        }
        if (e.param, e.wedge) in sampled:
            j = sampled.index((e.param, e.wedge))
            rec["posterior"] = {
                "median": float(post.median[j]) * f,
                "p16": float(post.p16[j]) * f,
                "p84": float(post.p84[j]) * f,
                "p2_5": float(post.p2_5[j]) * f,
                "p97_5": float(post.p97_5[j]) * f,
                "width_over_ls_stderr": float(post.width_ratio[j]),
                **chain_checks(post, j),
            }
        rec["index"] = i
        records.append(rec)
    return records


def chain_checks(post: PosteriorResult, j: int) -> Record:
    """Parameter `j`'s convergence diagnostics for results.json: split R-hat, bulk and tail
    ESS, and whether they pass the thresholds (R-hat < 1.01, ESS >= 400; docs/fitting.md §5)."""
    rhat, bulk, tail = float(post.rhat[j]), float(post.ess_bulk[j]), float(post.ess_tail[j])
    return {
        "rhat": rhat,
        "ess_bulk": bulk,
        "ess_tail": tail,
        "converged": bool(rhat < RHAT_MAX and min(bulk, tail) >= ESS_MIN),
    }


def fixed_parameters(outcome: FitOutcome) -> Record:
    """Parameters the chosen variant kept fixed, with their values (display units)."""
    fit = outcome.selection.fit
    free = set(fit.variant.free)
    out: Record = {}
    for name in ("delta_n", "edge_radius_um", "fillet_radius_um", "floor", "model_error_frac"):
        if name not in free:
            out[name] = float(getattr(fit.params, name))
    if "sigma_rad" not in free and not fit.variant.per_wedge_sigma:
        out["sigma_deg"] = float(np.mean(fit.params.sigma_rad)) / DEG
    return out


def compare_table(outcome: FitOutcome, truth: dict[str, float]) -> str:
    """Recovered against true values, the 95% interval, and the deviation in standard deviations.

    A truth outside its 95% interval happens for about 1 parameter in 20 by chance; the last
    column says how far off it is (|pull| > 3 would point to a bias, not to chance).
    """
    lines = [
        f"  {'parameter':<16} {'true':>12} {'recovered':>12} {'95% interval':>26}  "
        f"{'inside?':>7}  {'(rec - true) / sd':>17}"
    ]
    records = parameter_records(outcome)
    for rec in records:  # matched by identity: each wedge's own width against the one truth
        name, key = rec["name"], display_param(rec["parameter"])
        if key not in truth:
            continue
        true = truth[key]
        po, ls = rec.get("posterior"), rec["least_squares"]
        if po is not None:
            val, lo, hi = po["median"], po["p2_5"], po["p97_5"]
        elif ls["stderr"] is not None:
            val, lo, hi = (
                ls["value"],
                ls["value"] - 2 * ls["stderr"],
                ls["value"] + 2 * ls["stderr"],
            )
        else:
            val, lo, hi = ls["value"], np.nan, np.nan
        inside = "yes" if lo <= true <= hi else "NO"
        sd = 0.25 * (hi - lo)  # the interval spans about +-2 standard deviations
        pull = f"{(val - true) / sd:+.2f}" if sd > 0 else "-"
        interval = f"[{lo:.6g}, {hi:.6g}]"
        lines.append(
            f"  {name:<16} {true:>12.6g} {val:>12.6g} {interval:>26}  {inside:>7}  {pull:>17}"
        )
    fitted = {display_param(r["parameter"]) for r in records}
    fixed = [k for k in truth if k not in fitted]
    for k in fixed:
        lines.append(f"  {k:<16} {truth[k]:>12.5g} {'(not fitted: the chosen model fixes it)':>40}")
    return "\n".join(lines)


def truth_records(outcome: FitOutcome, records: list[Record]) -> list[Record]:
    """The scene's `[truth]` beside the fit (results.json's `truth`; [] without a truth table).

    One record per fitted parameter that has a true value (each wedge's own width against the
    one true `sigma_deg`), then one per remaining true value: fixed by the chosen model
    (`fitted` is the value it was fixed at), or not a parameter of this fit (`fitted` None).
    `records` are `parameter_records(outcome)`; display units throughout.
    """
    truth = getattr(outcome.scene, "truth", None)
    if truth is None:
        return []
    given = dict(truth.items())
    out: list[Record] = []
    for rec in records:
        key = display_param(rec["parameter"])
        if key in given:
            ls, po = rec["least_squares"], rec.get("posterior")
            out.append(
                {
                    "name": rec["name"],
                    "parameter": key,
                    "true": given[key],
                    "status": "fitted",
                    "fitted": ls["value"],
                    "stderr": ls["stderr"],
                    "posterior_median": None if po is None else po["median"],
                    "p2_5": None if po is None else po["p2_5"],
                    "p97_5": None if po is None else po["p97_5"],
                }
            )
    fitted = {r["parameter"] for r in out}
    fixed = fixed_parameters(outcome)
    for key, true in given.items():
        if key not in fitted:
            out.append(
                {
                    "name": key,
                    "parameter": key,
                    "true": true,
                    "status": "fixed" if key in fixed else "not a parameter of this fit",
                    "fitted": fixed.get(key),
                    "stderr": None,
                    "posterior_median": None,
                    "p2_5": None,
                    "p97_5": None,
                }
            )
    return out


# --- files ----------------------------------------------------------------------------------


def write_outputs(
    outcome: FitOutcome,
    out: Path,
    drawn: dict[str, str] | None = None,
    draw: SaveFigure = save,
) -> None:
    """Write every output into `out` (a temporary folder moved into place by the caller);
    `drawn`: the figures `fit_figures` already drew into `out / "figures"` (drawn here if
    None); `draw`: how a figure is drawn and written (`figures.save`)."""
    from .photo_reports import MARKER_COLUMNS, fit_marker_reports, write_table

    out.mkdir(parents=True, exist_ok=True)
    outcome.table.write_csv(out / "measurements.csv")
    markers = fit_marker_reports(outcome.scene, outcome.photo_specs, outcome.table)
    write_table(out / "markers.csv", markers, MARKER_COLUMNS)
    write_observations(outcome, out / "observations.csv")
    figures = write_figures(outcome, out / "figures", drawn, draw)
    results = results_dict(outcome, figures)
    results["gloss"] = _jsonable(gloss_record(results, out))  # reads out/chain.npz
    write_file(out / "results.json", json.dumps(results, indent=2, allow_nan=False))
    write_file(out / "report.html", report_html(outcome, results, figures, out))
    if outcome.posterior is not None:  # the chain for ArviZ (docs/fitting.md §5)
        outcome.posterior.to_netcdf(out / "chain.nc", degrees=True)


def write_observations(outcome: FitOutcome, path: Path) -> None:
    """The fitted rows: geometry, measurement, model, uncertainty and whitened residual, and
    what the fit's error model and aperture used per row: the ROI group and its channel
    correlations (docs/fitting.md §Correlated channels) and the row's viewing spread."""
    fit = outcome.selection.fit
    with writing(path) as fh:
        w = csv.writer(fh)
        w.writerow(
            [
                "photo",
                "wedge",
                "channel",
                "light_deg",
                "view_deg",
                "theta_i_deg",
                "theta_o_deg",
                "value",
                "stderr",
                "used",
                "model",
                "uncertainty",
                "whitened_residual",
                "roi_index",
                "corr_01",
                "corr_02",
                "corr_12",
                "view_spread",
            ]
        )
        obs = outcome.observations.data
        for i, info in enumerate(outcome.observations.labels):
            w.writerow(
                [
                    info.photo,
                    info.wedge,
                    info.channel,
                    info.light_deg,
                    info.view_deg,
                    f"{info.theta_i_deg:.6g}",
                    f"{info.theta_o_deg:.6g}",
                    f"{obs.value[i]:.8g}",
                    f"{obs.stderr[i]:.6g}",
                    int(bool(obs.use[i])),
                    f"{fit.model[i]:.8g}",
                    f"{fit.uncertainty[i]:.6g}",
                    f"{fit.residuals[i]:.5g}",
                    int(obs.roi_index[i]),
                    f"{obs.corr_01[i]:.6g}",
                    f"{obs.corr_02[i]:.6g}",
                    f"{obs.corr_12[i]:.6g}",
                    f"{obs.view_spread[i]:.6g}",
                ]
            )


def _jsonable(x: object) -> JSONValue:
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, np.generic):
        return _jsonable(x.item())
    if isinstance(x, float) and not np.isfinite(x):
        return None
    if isinstance(x, Path):
        return str(x)
    return x


def table_records_of(rows: Iterable[fitting.ComparisonRow]) -> list[Record]:
    """`table_records` of any comparison rows (e.g. the facet kernels' probe fits)."""
    return [
        {"variant": r.name, "n_free": r.n_free, "chi2": r.chi2, "bic": r.bic, "delta": r.delta,
         "status": r.status_text, "notes": r.notes}
        for r in rows
    ]  # fmt: skip


def table_records(sel: fitting.Selection) -> list[Record]:
    """results.json's `model_selection.table`: one record per ladder variant."""
    return [
        {
            "variant": r.name,
            "features": list(r.features),
            "n_free": r.n_free,
            "chi2": r.chi2,
            "log_likelihood": r.log_likelihood,
            "bic": r.bic,
            "aic": r.aic,
            "laplace_log_evidence": r.laplace_log_evidence,
            "delta": r.delta,
            "status": r.status,
            "detail": r.detail,
            "chi2_measurement_errors_only": r.chi2_measurement,
            "elapsed_s": r.elapsed_s,
            "solver_steps": r.solver_steps,
            "work_gflop": r.work_gflop,
            "notes": r.notes,
        }
        for r in sel.table
    ]


def posterior_diagnostics(post: PosteriorResult | None) -> Record | None:
    """results.json's `diagnostics.posterior` (None without a posterior)."""
    if post is None:
        return None
    return {
        "seed": post.seed,
        "moves": post.moves,
        "n_walkers": post.n_walkers,
        "n_steps": post.n_steps,
        "tau": list(post.tau),
        "tau_max": post.tau_max,
        "converged": post.converged,
        "burn_in": post.burn_in,
        "thin": post.thin,
        "n_samples": post.n_samples,
        "n_independent": post.n_independent,
        "acceptance_fraction": post.acceptance_fraction,
        "rhat_max": RHAT_MAX,
        "ess_min": ESS_MIN,
        "tau_reliable": post.tau_reliable,
        "chain_file": "chain.npz",
        "inference_data_file": "chain.nc",
        "warnings": [
            {"code": w.code, "parameter": w.parameter, "message": w.message} for w in post.warnings
        ],
    }


def results_dict(outcome: FitOutcome, figures: dict[str, str]) -> Record:
    """The content of results.json (see the README's "Outputs")."""
    sel, fit, post = outcome.selection, outcome.selection.fit, outcome.posterior
    names = [display_name(e)[0] for e in fit.estimates]
    corr = None if fit.correlation is None else np.round(fit.correlation, 6)
    records = parameter_records(outcome)
    result = {
        "stairfit_version": __version__,
        "created": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "python": sys.version.split()[0],
        "platform": platform.platform(),
        "package_versions": package_versions(),
        # XLA's options change the last bits of the numbers (docs/fitting.md §7)
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        "settings": {
            "preset": outcome.options.preset.as_dict(),
            "posterior": outcome.options.posterior,
            "forced_model": outcome.options.model,
            "forced_kernel": outcome.options.kernel,
            "model_error": outcome.options.model_error,
            "seed": outcome.options.seed,
            "workers": outcome.options.workers,
        },
        "inputs": inputs_record(outcome),
        "model_selection": {
            "chosen": sel.chosen,
            "forced": sel.forced,
            "criterion": sel.criterion,
            "threshold": sel.threshold,
            "reason": sel.reason,
            "table": table_records(sel),
            "rounding": rounding_record(outcome),
        },
        "assessment": assessment_record(outcome),
        "directions": directions_record(outcome),
        "accuracy": None if outcome.accuracy is None else outcome.accuracy.record(),
        "specimen": specimen_record(outcome),
        "parameters": records,
        "fixed_parameters": fixed_parameters(outcome),
        "truth": truth_records(outcome, records),
        "spectral": spectral_record(outcome),
        "correlation": {"names": names, "matrix": corr},
        "diagnostics": {
            "least_squares": least_squares_diagnostics(fit),
            "posterior": posterior_diagnostics(post),
            "notes": outcome.notes,
            "timings_s": outcome.timings,
        },
        "files": {
            "measurements": "measurements.csv",
            "observations": "observations.csv",
            "report": "report.html",
            "figures": figures,
            "previews": "previews/",
        },
    }
    return _jsonable(result)


SPECIMEN_INDEX_NM = np.arange(380.0, 781.0, 10.0)
"""Where results.json's `specimen.index` samples the material's index (every 10 nm)."""


def specimen_record(outcome: FitOutcome) -> Record:
    """results.json's `specimen`: the layer thickness, each wedge's name and angle (deg) in the
    order of the fit's wedge indices, and the material's index without `delta_n` every 10 nm
    (what `stairfit predict --gloss --fit` reads; a per-channel index through its channels'
    effective wavelengths)."""
    spec = outcome.scene.specimen
    n = np.asarray(refractive_index(_along_wavelength(outcome), SPECIMEN_INDEX_NM, 0.0))
    return {
        "layer_um": spec.layer_um,
        "wedges": [{"name": w.name, "angle_deg": w.angle_deg} for w in spec.wedges],
        "index": {
            "wavelength_nm": SPECIMEN_INDEX_NM,
            "n": np.round(np.real(n), 8),
            "k": np.round(np.imag(n), 8),
        },
    }


def _given_kernel(kernel: str | None, lab: bool) -> str | None:
    """Why the lab model's facets are what they are when no probes ran."""
    return f"given (--kernel {kernel}): the kernels were not compared" if kernel and lab else None


def directions_record(outcome: FitOutcome) -> Record:
    """How the fit modelled the directions (docs/fitting.md §10): `model` ("lab" or
    "in_plane"), why, the facets' kernel and how it was chosen, the roughness `alpha` of
    microfacet facets (`tan` of the fitted width, with its delta-method error), and each
    measured face's largest out-of-plane angles of light and view (deg; faces placed in 3-D
    only)."""
    from .lab import out_of_plane

    fit, sel = outcome.selection.fit, outcome.selection
    lab = fit.problem is not None and fit.problem.lab is not None
    kernel = fit.requested.kernel
    given = _given_kernel(outcome.options.kernel, lab)
    record: Record = {
        "model": "lab" if lab else "in_plane",
        "reason": outcome.lab_reason,
        "facets": kernel if lab else "gaussian",
        "facets_reason": sel.facets.reason if sel.facets is not None else given,
        "facets_table": [] if sel.facets is None else table_records_of(sel.facets.rows),
        "alpha": [],
        "out_of_plane": [],
    }
    if lab and kernel != "gaussian":
        for est in fit.estimates:
            if est.param == "sigma_rad":
                se = None if est.stderr is None else est.stderr / np.cos(est.value) ** 2
                record["alpha"].append({"name": est.label("alpha"), "value": np.tan(est.value),
                                        "stderr": se})  # fmt: skip
    scene = outcome.scene
    reference = scene.reference.name if scene.reference is not None else None
    rows = [r for r in outcome.table if r.wedge != reference]
    if any(r.face_points_mm for r in rows):
        record["out_of_plane"] = [
            {"photo": f.photo, "wedge": f.wedge, "light_deg": f.light_deg, "view_deg": f.view_deg}
            for f in out_of_plane(scene, rows)
        ]
    return record


def package_versions() -> dict[str, str | None]:
    """Installed versions of the packages a result depends on (None where not installed)."""
    versions: dict[str, str | None] = {}
    for pkg in PACKAGES:
        try:
            versions[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            versions[pkg] = None
    return versions


def inputs_record(outcome: FitOutcome) -> Record:
    """results.json's `inputs`: SHA-256 of the scene file, every photo and calibration frame;
    for each photo whether its values were measured now or read from the measurement cache."""
    scene = outcome.scene
    cached = set(getattr(outcome.table, "from_cache", ()))
    return {
        "scene": {"file": scene.path.name, "sha256": sha256_of(scene.path)},
        "photos": [
            {
                "file": name,
                "sha256": outcome.table.for_photo(name)[0].photo_sha256,
                "measured_from": "cache" if name in cached else "photo",
            }
            for name in outcome.table.photos()
        ],  # a bracket's: SHA-256 of its files' digests joined by "," (docs/imaging.md)
        "calibration": [
            {"field": where, "file": name, "sha256": sha256_of(path)}
            for where, name, path in scene.input_fields()
            if where.startswith("calibration.")
        ],
    }


def least_squares_diagnostics(fit: fitting.FitResult) -> Record:
    """results.json's `diagnostics.least_squares` of the chosen fit (a `fitting.FitResult`)."""
    return {
        "solver": fit.solver,
        "success": fit.success,
        "message": fit.message,
        "num_steps": fit.num_steps,
        "chi2": fit.chi2,
        "dof": fit.dof,
        "reduced_chi2": fit.reduced_chi2,
        "n_used": fit.n_used,
        "n_rows": fit.n_rows,
        "n_excluded": len(fit.excluded_rows),
        "n_saturated": fit.n_saturated,
        "starts_sigma_deg": [s / DEG for s in fit.starts_sigma_rad],
        "starts_chi2": list(fit.starts_chi2),
        "unidentified": list(fit.unidentified),
        "warnings": [
            {"code": w.code, "parameter": w.parameter, "message": w.message} for w in fit.warnings
        ],
    }


def spectral_record(outcome: FitOutcome) -> Record:
    """The camera model's channels for results.json [conventions §7, §8]: each channel's
    effective wavelength (its sensitivity x illuminant weighted mean, `ChannelWeights.
    effective_nm`; what the "effective" sampling evaluates) and the material's index there,
    without `delta_n` (`index_n`, `index_k`)."""
    from stairfit.model import materials

    from .scene import CHANNELS

    scene = outcome.scene
    eff = outcome.setup.effective_nm
    index = np.asarray(materials.index_per_channel(outcome.setup.index, eff[:, None]))[:, 0]
    return {
        "camera": scene.camera.sensitivity,
        "illuminant": scene.light.illuminant,
        "sampling": outcome.options.preset.spectral,
        "channels": list(CHANNELS[: eff.size]),
        "effective_wavelength_nm": np.round(eff, 3),
        "index_n": np.round(np.real(index), 8),
        "index_k": np.round(np.imag(index), 8),
    }


# --- figures --------------------------------------------------------------------------------


def write_figures(
    outcome: FitOutcome,
    folder: Path,
    drawn: dict[str, str] | None = None,
    draw: SaveFigure = save,
) -> dict[str, str]:
    """Every figure of the report; returns {key: relative path}. `drawn`: what `fit_figures`
    already drew into `folder` (while the posterior was sampled); drawn here if None. `draw`:
    as in `write_outputs`."""
    figs = dict(fit_figures(outcome, folder, draw) if drawn is None else drawn)
    if outcome.posterior is not None and outcome.posterior.samples.shape[1] >= 1:
        figs["corner"] = _rel(draw(corner_figure(outcome), folder / "corner.png"), folder)
    return {k: figs[k] for k in FIGURE_ORDER if k in figs}


FIGURE_ORDER = ("fit", "residuals", "misfit", "corner", "brdf_map", "colours")
"""The report's figures in the order it shows them."""


def fit_figures(outcome: FitOutcome, folder: Path, draw: SaveFigure = save) -> dict[str, str]:
    """The figures that need the least-squares fit only (every one but the corner plot);
    returns {key: relative path}. `stairfit fit` builds them in a second thread while the
    posterior is sampled (its model evaluations release the interpreter most of the time).

    The model-only figures (fitted BRDF, reflected colours) follow the preset's
    `diffuse_nodes` and `float32_figures`.
    """
    from stairfit.model.spectral import VISIBLE_NM

    fit = outcome.selection.fit
    p = fit.params
    preset = outcome.options.preset
    figs: dict[str, str] = {}
    figs["fit"] = _rel(draw(fit_per_wedge(outcome), folder / "fit_per_wedge.png"), folder)
    figs["residuals"] = _rel(draw(residual_figure(outcome), folder / "residuals.png"), folder)
    figs["misfit"] = _rel(
        draw(residual_pattern_figure(outcome), folder / "residual_pattern.png"), folder
    )
    wedges = [w.angle_deg for w in outcome.scene.specimen.wedges]
    pick = sorted({min(wedges), max(wedges)})
    sigma_deg = float(np.mean(p.sigma_rad)) / DEG
    disp = _along_wavelength(outcome)
    lam = VISIBLE_NM  # the grid of reflected_colours: one compilation serves both figures
    n_lam = refractive_index(disp, lam, float(p.delta_n))
    n550 = complex(np.interp(550.0, lam, n_lam.real), np.interp(550.0, lam, np.imag(n_lam)))
    n550 = n550.real if n550.imag == 0 else n550
    figs["brdf_map"] = _rel(
        draw(
            brdf_map(
                pick,
                n=n550,
                sigma_deg=sigma_deg,
                title=f"fitted BRDF at 550 nm (sigma = {sigma_deg:.3g} deg)",
                float32=preset.float32_figures,
            ),
            folder / "brdf_map.png",
        ),
        folder,
    )
    figs["colours"] = _rel(
        draw(
            reflected_colours(
                wedges,
                disp,
                delta_n=float(p.delta_n),
                sigma_deg=sigma_deg,
                diffuse_nodes=preset.diffuse_nodes,
                float32=preset.float32_figures,
            ),
            folder / "colours.png",
        ),
        folder,
    )
    return figs


def _along_wavelength(outcome: FitOutcome) -> Dispersion:
    """The fit's index as a function of wavelength for the figures: a dispersion model as it
    is, a per-channel index through its channels' effective wavelengths."""
    from stairfit.model import materials

    index = outcome.setup.index
    if not isinstance(index, materials.PerChannel):
        return index
    return index.along_wavelength(outcome.setup.effective_nm)


def _rel(path: Path, folder: Path) -> str:
    return f"figures/{path.relative_to(folder)}"


LINE_STYLES = ("-", "--", ":", "-.")
"""The model curves' styles, one per light angle of a wedge (in the order of the angles)."""


def model_curves_of(outcome: FitOutcome) -> list[fitting.ModelCurve] | None:
    """The chosen fit's dense model curves (`fitting.model_curves`), or None when the fit
    carries no prepared problem (a result assembled by hand)."""
    from stairfit import fitting

    fit = outcome.selection.fit
    if getattr(fit, "problem", None) is None or getattr(fit, "spec", None) is None:
        return None
    return fitting.model_curves(fit)


def fit_per_wedge(outcome: FitOutcome, curves: list[fitting.ModelCurve] | None = None) -> Figure:
    """Measured (error bars) and fitted radiance against the face-frame viewing angle, one
    panel per wedge and one colour per channel (like the paper's Fig. 9). The model is drawn as
    a dense curve over the viewing angle (`curves`: `fitting.model_curves`, computed here when
    None), one line style per light angle, so that the lobes between the measured views show;
    without a prepared fit, as lines through the model at the measured views."""
    fit, obs = outcome.selection.fit, outcome.observations.data
    if curves is None:
        curves = model_curves_of(outcome)
    wedges = outcome.scene.specimen.wedges
    ncol = min(3, len(wedges))
    nrow = int(np.ceil(len(wedges) / ncol))
    fig = Figure(figsize=(4.3 * ncol, 3.2 * nrow))  # no pyplot: no global state (app/figures.py)
    axes = fig.subplots(nrow, ncol, squeeze=False)
    colours = ("tab:red", "tab:green", "tab:blue")
    theta_o = np.array([r.theta_o_deg for r in outcome.observations.labels])
    for k, wedge in enumerate(wedges):
        ax = axes.flat[k]
        lights = sorted({round(c.theta_i_rad / DEG, 6) for c in curves or () if c.wedge == k})
        for c, col in enumerate(colours):
            sel = (obs.wedge_index == k) & (obs.channel_index == c)
            if not np.any(sel):
                continue
            order = np.argsort(theta_o[sel])
            x, y = theta_o[sel][order], obs.value[sel][order]
            used = obs.use[sel][order]
            err = fit.uncertainty[sel][order]
            ax.errorbar(
                x[used],
                y[used],
                yerr=err[used],
                fmt="o",
                ms=3,
                color=col,
                alpha=0.8,
                label="RGB"[c],
            )
            if np.any(~used):
                ax.plot(x[~used], y[~used], "x", color=col, alpha=0.6)
            if curves is None:
                ax.plot(x, fit.model[sel][order], "-", color=col, lw=1)
        for cv in curves or ():
            if cv.wedge == k and cv.channel < len(colours):
                style = LINE_STYLES[lights.index(round(cv.theta_i_rad / DEG, 6)) % 4]
                ax.plot(cv.theta_o_rad / DEG, cv.value, style, color=colours[cv.channel], lw=1)
        if len(lights) > 1:  # which line is which light angle
            for j, t in enumerate(lights):
                ax.plot([], [], LINE_STYLES[j % 4], color="0.3", label=f"theta_i {t:.3g} deg")
            ax.legend(fontsize="x-small")
        ax.set(
            title=f"{wedge.name} ({wedge.angle_deg:g} deg)",
            xlabel="theta_o (deg, face)",
            ylabel="relative radiance",
        )
        log_y(ax)
    for ax in axes.flat[len(wedges) :]:
        ax.axis("off")
    axes.flat[0].legend(fontsize="small", title="channel")
    how = ("lines through the model at the measured views" if curves is None else
           "curves: the model at every 0.5 deg of the viewing angle")  # fmt: skip
    if curves and curves[0].mean_geometry:
        how += " at each wedge's mean geometry, through the fitted values"
    fig.suptitle(
        f"measured (points, x = not fitted) and model '{outcome.selection.chosen}' ({how})"
    )
    fixed_layout(fig, nrow, ncol, top=0.75, wspace=0.85, hspace=0.85)
    return fig


def residual_figure(outcome: FitOutcome) -> Figure:
    """Whitened residuals against viewing angle per wedge, and their histogram vs N(0, 1)."""
    fit, obs = outcome.selection.fit, outcome.observations.data
    theta_o = np.array([r.theta_o_deg for r in outcome.observations.labels])
    used = np.asarray(obs.use, bool)
    fig = Figure(figsize=(11, 3.6))
    a1, a2 = fig.subplots(1, 2, gridspec_kw={"width_ratios": [2, 1]})
    for k, wedge in enumerate(outcome.scene.specimen.wedges):
        sel = used & (obs.wedge_index == k)
        a1.plot(theta_o[sel], fit.residuals[sel], "o", ms=3, label=wedge.name)
    a1.axhline(0, color="k", lw=0.8)
    a1.set(xlabel="theta_o (deg, face)", ylabel="(measured - model) / uncertainty")
    a1.legend(fontsize="x-small", ncol=3)
    r = fit.residuals[used]
    a2.hist(r, bins=30, density=True, alpha=0.6)
    x = np.linspace(-4, 4, 200)
    a2.plot(x, np.exp(-0.5 * x * x) / np.sqrt(2 * np.pi), "k-", label="N(0, 1)")
    a2.set(xlabel="whitened residual", title=f"reduced chi2 = {fit.reduced_chi2:.3g}")
    a2.legend(fontsize="small")
    fixed_layout(fig, 1, 2, top=0.35, wspace=0.6)
    return fig


def corner_figure(outcome: FitOutcome) -> Figure:
    """Corner plot of the posterior samples (display units), titled with the median and the
    16-84% interval in plain text (corner's own titles are mathtext, slow to set up).

    Drawn on a plain `Figure` of corner's own size (`corner_size_in`), so that corner does not
    create it through pyplot (which would pick an interactive backend where there is a display).
    """
    import corner

    post = outcome.posterior
    labels, factors = zip(*(display_name(p) for p in post.parameters), strict=True)
    samples = post.samples * np.asarray(factors)[None, :]
    q16, q50, q84 = np.quantile(samples, (0.16, 0.5, 0.84), axis=0)
    titles = [
        f"{lab} = {value_with_errors(m, m - lo, hi - m)}"
        for lab, lo, m, hi in zip(labels, q16, q50, q84, strict=True)
    ]
    size = corner_size_in(samples.shape[1])
    return corner.corner(
        samples,
        fig=Figure(figsize=(size, size)),
        labels=list(labels),
        titles=titles,
        quantiles=(0.16, 0.5, 0.84),
        show_titles=True,
        title_fmt=None,
        title_kwargs={"fontsize": "medium"},
    )


def corner_size_in(n_params: int) -> float:
    """The figure size (inches) `corner.corner` chooses for `n_params` parameters when it makes
    the figure itself (corner 2.3 core.py: 2 inches per panel, gaps of 5%, margins 0.5 x 2 and
    0.2 x 2 inches); its margins are fractions of that size, so the layout stays corner's."""
    factor, whspace = 2.0, 0.05
    return 0.5 * factor + factor * n_params + factor * (n_params - 1.0) * whspace + 0.2 * factor


def value_with_errors(value: float, minus: float, plus: float) -> str:
    """`value +plus -minus`, rounded to the second significant digit of the smaller error but
    never above the units (`6.00034 +0.00011 -0.00012`, `1999778 +107 -113`)."""
    err = min(abs(minus), abs(plus))
    if not np.isfinite(err) or err <= 0 or not np.isfinite(value):
        return f"{value:.6g} +{plus:.2g} -{minus:.2g}"
    decimals = max(0, 1 - int(np.floor(np.log10(err))))
    return f"{value:.{decimals}f} +{plus:.{decimals}f} -{minus:.{decimals}f}"


# --- report and summary ---------------------------------------------------------------------


def _parameter_rows_html(results: Record) -> list[str]:
    """The rows of the report's parameter table."""
    e = html.escape
    rows = []
    for rec in results["parameters"]:
        ls = rec["least_squares"]
        se = "n/a" if ls["stderr"] is None else f"{ls['stderr']:.4g}"
        po = rec.get("posterior")
        post = (
            f"{po['median']:.5g} [{po['p16']:.5g}, {po['p84']:.5g}] "
            f"(95%: {po['p2_5']:.5g} .. {po['p97_5']:.5g})"
            if po
            else "not sampled"
        )
        rows.append(
            f"<tr><td>{e(rec['name'])}</td><td>{e(rec['unit'])}</td>"
            f"<td>{ls['value']:.5g} &plusmn; {se}</td><td>{e(post)}</td>{_checks_html(po)}</tr>"
        )
    return rows


def _truth_html(results: Record) -> str:
    """The report's truth table (the scene's `[truth]` beside the fit); "" without one."""
    e = html.escape
    rows = []
    for t in results.get("truth", []):
        if t["status"] == "fitted":
            se = "n/a" if t["stderr"] is None else f"{t['stderr']:.4g}"
            fit = f"{t['fitted']:.5g} &plusmn; {se}"
            if t["posterior_median"] is not None:
                fit += (
                    f"; posterior {t['posterior_median']:.5g} (95%: {t['p2_5']:.5g} .. "
                    f"{t['p97_5']:.5g})"
                )
        elif t["status"] == "fixed":
            fit = f"fixed at {t['fitted']:.5g}"
        else:
            fit = e(t["status"])
        rows.append(f"<tr><td>{e(t['name'])}</td><td>{t['true']:.5g}</td><td>{fit}</td></tr>")
    if not rows:
        return ""
    return (
        "<h2>Truth</h2><p>From the scene file's [truth] (a synthetic scene's parameters, or "
        "values measured independently); the fit does not use them.</p><table><tr><th>parameter"
        f"</th><th>true</th><th>fitted (least squares)</th></tr>{''.join(rows)}</table>"
    )


def report_html(
    outcome: FitOutcome, results: Record, figures: dict[str, str], out: Path
) -> str:
    """A single self-explaining HTML page (figures referenced by relative path)."""
    e = html.escape
    sel = outcome.selection
    rows = _parameter_rows_html(results)
    fixed = "".join(f"<li>{e(k)} = {v:.4g}</li>" for k, v in results["fixed_parameters"].items())
    table = "".join(
        f"<tr><td>{'&#10003;' if r['variant'] == sel.chosen else ''}</td><td>{e(r['variant'])}"
        f"</td><td>{_fmt(r['n_free'], 'd')}</td><td>{_fmt(r['chi2'], '.5g')}</td>"
        f"<td>{_fmt(r['bic'], '.6g')}</td><td>{_fmt(r['delta'], '.3g')}</td>"
        f"<td>{e(r['status'])}{' (' + e(r['detail']) + ')' if r.get('detail') else ''}"
        f"{'; ' + e(r['notes']) if r['notes'] else ''}</td></tr>"
        for r in results["model_selection"]["table"]
    )
    imgs = "".join(
        f"<h3>{e(title)}</h3><img src='{e(figures[key])}' style='max-width:100%'>"
        for key, title in (
            ("fit", "Measured against model"),
            ("residuals", "Residuals"),
            ("misfit", "Residual pattern per wedge and view"),
            ("corner", "Posterior"),
            ("brdf_map", "Fitted BRDF (Fig. 3 style)"),
            ("colours", "Colour of the reflected light (Fig. 7 style)"),
        )
        if key in figures and not (key == "misfit" and _misfits(outcome))  # shown on top
    )
    previews = sorted((out / "previews").glob("*.png")) if (out / "previews").exists() else []
    prev = "".join(
        f"<figure style='display:inline-block;width:30%'><img src='previews/{e(p.name)}' "
        f"style='width:100%'><figcaption>{e(p.stem)}</figcaption></figure>"
        for p in previews
    )
    diag = results["diagnostics"]
    ls = diag["least_squares"]
    po = diag["posterior"]
    post_line = (
        "posterior not sampled"
        if po is None
        else f"posterior: {po['n_walkers']} walkers x {po['n_steps']} steps, tau_max = "
        f"{po['tau_max']:.3g}, {po['n_independent']:.0f} independent samples, acceptance "
        f"{po['acceptance_fraction']:.2f}, {'converged' if po['converged'] else 'NOT converged'}"
    )
    warn = "".join(
        f"<li>{e(w['message'])}</li>" for w in ls["warnings"] + (po["warnings"] if po else [])
    )
    notes = "".join(f"<li>{e(n)}</li>" for n in diag["notes"])
    return f"""<!doctype html><html><head><meta charset="utf-8"><title>stairfit report</title>
<style>body{{font-family:sans-serif;max-width:1100px;margin:auto}}td,th{{padding:2px 8px}}
table{{border-collapse:collapse}}tr:nth-child(even){{background:#f3f3f3}}</style></head><body>
<h1>stairfit report: {e(outcome.scene.folder.name)}</h1>{misfit_html(outcome, figures)}
<p>Chosen model: <b>{e(sel.chosen)}</b>. {e(sel.reason)}</p>
<h2>Parameters</h2><table><tr><th>parameter</th><th>unit</th><th>least squares</th>
<th>posterior median [16%, 84%]</th><th>R-hat</th><th>ESS bulk / tail</th></tr>{"".join(rows)}
</table><p>R-hat: rank-normalised split R-hat over the emcee walkers; ESS: effective sample
sizes (ArviZ). In red: outside R-hat &lt; {RHAT_MAX:g}, ESS &ge; {ESS_MIN:g}.</p>
<p>Fixed:</p><ul>{fixed}</ul>
{_truth_html(results)}
<h2>Model selection ({e(sel.criterion.upper())}, threshold {sel.threshold:g})</h2>
<table><tr><th></th><th>variant</th><th>k</th><th>chi2</th><th>BIC</th><th>delta</th>
<th>status / notes</th></tr>{table}</table>
<p>Rounded edges: {e(rounding_sentence(outcome))}.</p>
{_directions_html(results["directions"])}
{gloss_html(results["gloss"]) if "gloss" in results else ""}
<h2>Diagnostics</h2><p>least squares: {e(ls["message"])}, {ls["num_steps"]} steps; chi2 =
{ls["chi2"]:.5g} for {ls["dof"]} degrees of freedom (reduced {ls["reduced_chi2"]:.3g});
{ls["n_used"]} of {ls["n_rows"]} measurements fitted.<br>{e(_accuracy_line(outcome))}
<br>{e(post_line)}</p>
<ul>{warn}{notes}</ul>
<h2>Figures</h2>{imgs}
<h2>Regions of interest</h2>{prev}<h3>Markers per photo</h3>{_markers_html(outcome)}
{renders_html(out)}
<p style="color:#777">stairfit {e(__version__)}; conventions: docs/conventions.md; all numbers
also in results.json.</p></body></html>
"""


def _directions_html(d: Record) -> str:
    """The report's section on how the directions were modelled, the facets, and each wedge's
    largest out-of-plane angles."""
    e = html.escape
    if d["model"] == "lab":
        why = f" ({e(d['facets_reason'])})" if d["facets_reason"] else ""
        head = (f"<p>Fitted with the <b>lab model</b> (each face's own 3-D light and view "
                f"directions) because {e(d['reason'] or '')}. Facets: <b>{e(d['facets'])}</b>"
                f"{why}.</p>")  # fmt: skip
    else:
        head = "<p>Fitted in one plane of incidence with a distant light (the in-plane model).</p>"
    alpha = "".join(
        f"<li>{e(a['name'])} = {a['value']:.4g}"
        + ("" if a["stderr"] is None else f" &plusmn; {a['stderr']:.2g}")
        + "</li>"
        for a in d["alpha"]
    )
    if alpha:
        alpha = (
            f"<p>Facet roughness (Mitsuba's alpha, tan of the fitted width):</p><ul>{alpha}</ul>"
        )
    probes = "".join(
        f"<tr><td>{e(r['variant'])}</td><td>{_fmt(r['chi2'], '.5g')}</td>"
        f"<td>{_fmt(r['bic'], '.6g')}</td><td>{_fmt(r['delta'], '.3g')}</td>"
        f"<td>{e(r['status'])}</td></tr>"
        for r in d["facets_table"]
    )
    if probes:
        probes = ("<table><tr><th>facets</th><th>chi2</th><th>BIC</th><th>delta</th>"
                  f"<th>status</th></tr>{probes}</table>")  # fmt: skip
    worst: dict[str, tuple[float, float]] = {}
    for f in d["out_of_plane"]:
        li, vi = worst.get(f["wedge"], (0.0, 0.0))
        worst[f["wedge"]] = (max(li, f["light_deg"]), max(vi, f["view_deg"]))
    angles = "".join(
        f"<tr><td>{e(w)}</td><td>{li:.2f}</td><td>{vi:.2f}</td></tr>"
        for w, (li, vi) in worst.items()
    )
    if angles:
        angles = ("<p>Largest angles out of the plane of incidence over the photos (deg):</p>"
                  "<table><tr><th>wedge</th><th>light</th><th>view</th></tr>"
                  f"{angles}</table>")  # fmt: skip
    return f"<h2>Directions and facets</h2>{head}{alpha}{probes}{angles}"


def _accuracy_line(outcome: FitOutcome) -> str:
    acc = getattr(outcome, "accuracy", None)
    return "numerical accuracy not checked" if acc is None else f"accuracy: {acc.message}"


def _misfits(outcome: FitOutcome) -> bool:
    a = outcome.selection.assessment
    return a is not None and a.misfits


def _checks_html(po: Record | None) -> str:
    """The R-hat and ESS cells of a parameter row (red outside the thresholds)."""
    if not po:
        return "<td></td><td></td>"
    style = "" if po["converged"] else " style='color:#b00;font-weight:bold'"
    return (
        f"<td{style}>{_fmt(po['rhat'], '.4f')}</td>"
        f"<td{style}>{_fmt(po['ess_bulk'], '.0f')} / {_fmt(po['ess_tail'], '.0f')}</td>"
    )


def _markers_html(outcome: FitOutcome) -> str:
    """The per-photo marker table (app/commands/measure.py), as in markers.csv."""
    from .photo_reports import MARKER_COLUMNS, fit_marker_reports, html_table

    reports = fit_marker_reports(outcome.scene, outcome.photo_specs, outcome.table)
    return html_table(reports, MARKER_COLUMNS)


def _fmt(x: object, spec: str) -> str:
    """Format a number, or an empty cell for None (skipped variants)."""
    return "" if x is None else format(x, spec)


def _checks_text(po: Record | None) -> str:
    """`1.0032  1893/2410` (R-hat, bulk / tail ESS) for the summary, `!` past a threshold."""
    if not po:
        return ""
    rhat, bulk, tail = (float("nan") if v is None else v
                        for v in (po["rhat"], po["ess_bulk"], po["ess_tail"]))  # fmt: skip
    flag = "" if po["converged"] else " !"
    return f"{rhat:>6.4f} {bulk:>5.0f}/{tail:<5.0f}{flag}"


def posterior_warning_lines(post: PosteriorResult | None) -> list[str]:
    """The posterior's warnings for the summary: the step limit and the acceptance as they
    are, R-hat and ESS one line each naming every parameter concerned."""
    if post is None:
        return []
    lines = [w.message for w in post.warnings if w.code not in ("rhat_high", "ess_low")]
    named = {"rhat_high": [], "ess_low": []}
    for w in post.warnings:
        if w.code in named:
            named[w.code].append(w.parameter)
    if named["rhat_high"]:
        lines.append(
            f"split R-hat is not below {RHAT_MAX:g} for {', '.join(named['rhat_high'])}: the "
            "walkers have not mixed; run a longer chain (e.g. --preset accurate)"
        )
    if named["ess_low"]:
        lines.append(
            f"bulk or tail ESS is below {ESS_MIN:g} for {', '.join(named['ess_low'])}: the "
            "intervals (the 95% most) are noisy; run a longer chain"
        )
    return lines


def print_summary(outcome: FitOutcome, out: Path, source: Path | None = None) -> None:
    """The one-screen summary printed at the end of `fit` (`source`: the photo folder)."""
    sel = outcome.selection
    recs = parameter_records(outcome)
    print()
    print(f"stairfit fit: {source or outcome.scene.folder}")
    for line in summary_lines(outcome):  # a misfit is said first (issue 13)
        print(f"  {line}")
    print(f"  model: {sel.chosen}  ({sel.reason})")
    print(
        f"  {'parameter':<26} {'least squares':>24}   {'posterior median [16%, 84%]':>34}"
        f"  {'R-hat':>6} {'ESS b/t':>11}"
    )
    for rec in recs:
        ls = rec["least_squares"]
        se = "n/a" if ls["stderr"] is None else f"{ls['stderr']:.3g}"
        po = rec.get("posterior")
        pos = f"{po['median']:.5g} [{po['p16']:.5g}, {po['p84']:.5g}]" if po else "-"
        print(
            f"  {rec['name'] + ' (' + rec['unit'] + ')':<26} {ls['value']:>13.5g} +- {se:<8}"
            f"   {pos:>34}  {_checks_text(po)}"
        )
    for k, v in fixed_parameters(outcome).items():
        print(f"  {k} fixed at {v:.4g}")
    fit = sel.fit
    print(
        f"  chi2 / dof = {fit.chi2:.4g} / {fit.dof}; {fit.n_used} of {fit.n_rows} "
        f"measurements fitted"
    )
    for w in fit.warnings:
        print(f"  warning: {w.message}")
    acc = getattr(outcome, "accuracy", None)
    if acc is not None and acc.error is not None:
        print(f"  {'warning' if acc.action != 'none' else 'note'}: {acc.message}")
    for line in posterior_warning_lines(outcome.posterior):
        print(f"  warning: {line}")
    for note in outcome.notes:
        print(f"  note: {note}")
    print(f"  results: {out / 'results.json'}; report: {out / 'report.html'}")


# --- renders (`stairfit render`, docs/render.md) ---------------------------------------------

RENDERS_START = "<!-- stairfit render: start -->"
RENDERS_END = "<!-- stairfit render: end -->"
"""The marks around the renders' section, so that `stairfit render` replaces it in place."""


def renders_html(folder: Path) -> str:
    """The report's section of `stairfit render`'s output (`folder/renders/renders.json`):
    for every photographed view the photo and the render of the fitted material side by side
    (the same display scale: the photo's white), with each face's mean relative radiance in
    both; for a mesh, its render. The marks alone when there are no renders."""
    path = folder / "renders" / "renders.json"
    if not path.is_file():
        return f"{RENDERS_START}{RENDERS_END}"
    try:
        record = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return f"{RENDERS_START}{RENDERS_END}"
    e = html.escape
    parts = [RENDERS_START, "<h2>Renders of the fitted material</h2>"]
    if record.get("kind") == "specimen":
        parts.append(
            "<p>Each photo beside a path-traced render (Mitsuba 3) of the fitted material on the "
            "specimen, from the camera pose the markers gave and under the scene's lamp; both in "
            "the photos' relative radiance, shown with the photo's white. The plate and the "
            "wedges' walls are diffuse stand-ins; the faces carry the fitted staircase (RGL "
            "tables in renders/materials/). docs/render.md.</p>"
        )
    for v in record.get("views", []):
        title = v.get("photo") or v.get("mesh", "")
        if "view_deg" in v:
            title = f"{title}: light {v.get('light_deg')} deg, view {v.get('view_deg')} deg"
        imgs = "".join(
            f"<figure style='display:inline-block;width:49%;margin:0'><img "
            f"src='renders/{e(v[key])}' style='width:100%'><figcaption>{label}</figcaption>"
            "</figure>"
            for key, label in (("photo_png", "photo"), ("render_png", "render"))
            if key in v
        )
        rows = "".join(
            f"<tr><td>{e(f['wedge'])}</td><td>{_fmt(_green(f['photo']), '.4g')}</td>"
            f"<td>{_fmt(_green(f['render']), '.4g')}</td><td>{_ratio(f)}</td></tr>"
            for f in v.get("faces", [])
        )
        table = ("<table><tr><th>face</th><th>photo (G)</th><th>render (G)</th>"
                 f"<th>render / photo</th></tr>{rows}</table>") if rows else ""  # fmt: skip
        parts.append(f"<h3>{e(str(title))}</h3><div>{imgs}</div>{table}")
    parts.append(RENDERS_END)
    return "".join(parts)


def _green(values: object) -> float | None:
    return None if not values else float(values[1])


def _ratio(face: Record) -> str:
    p, r = _green(face.get("photo")), _green(face.get("render"))
    return "" if not p or r is None else f"{r / p:.3f}"


def with_renders(report: str, section: str) -> str:
    """`report` (report.html's text) with its renders section replaced by `section`, or
    `section` inserted before the footer of a report written before the section existed."""
    start, end = report.find(RENDERS_START), report.find(RENDERS_END)
    if start >= 0 and end > start:
        return report[:start] + section + report[end + len(RENDERS_END):]
    footer = report.rfind('<p style="color:#777">stairfit')
    at = footer if footer >= 0 else report.rfind("</body>")
    at = at if at >= 0 else len(report)
    return report[:at] + section + "\n" + report[at:]
