"""Benchmark: interval coverage on data the fit was not tuned to (issue 13).

Two levels, each judged against binomial limits: a cell (noise level x design x parameter x
interval) of `n` datasets of which `k` cover the truth passes when the nominal coverage lies
inside the 99% Clopper-Pearson interval of `k / n` (`clopper_pearson`). With 200 datasets that
interval is about +-8 points at 68% and +-4 points at 95%; at 99% per cell about one cell in a
hundred fails by chance.

**Observations level** (`fitting.simulate_observations`): at each relative noise level (2%,
0.5%, 0.05% of the value; a small absolute part, 1e-3 of the noise level times the peak, keeps
rows in the lobes' deep tails from getting vanishing errors) and on two designs:
`fitting.standard_design()` (6 wedges 10-60 deg, theta_i 20 deg, 19 views) and `CUSTOM_DESIGN`
(5 other wedges, 100 um layers, two lights at 0 and 35 deg, 16 other views), the truth
`TRUTH` (sigma 6 deg, delta_n 0.03, scale 2, floor 1e-3: true variant `sharp+delta_n+floor`)
is simulated and fitted with the same model knobs (effective wavelengths, point aperture:
what is measured is the statistics, not the numerical error, which bench_tradeoff.py measures).
Per dataset: the least-squares fit of the true variant, 68% (+-1 se) and 95% (+-1.96 se)
intervals and the pull `(fit - truth) / se` of every parameter, the reduced chi^2;
`fitting.select_model` over the 8 sharp variants (shared and per-wedge sigma; the rounded rungs
cost minutes of compilation each and are left out) and how often it chooses the true variant;
on the first `--posterior` datasets of the standard design, `fitting.posterior.sample_posterior`
(tau_factor 20 checked every 100 steps and R-hat < 1.01, ESS >= 400: the balanced preset's
rule; docs/fitting.md §5; moves `--moves`, default the library's default "laplace"; runs before
5 December 2026 used "de" or the stretch move with the R-hat / ESS extension off) with its
16-84% and 2.5-97.5% intervals.
All datasets of one design share their shapes, so every fit reuses one compiled program.

**Photo level** (tests/independent_photos.py, the second renderer, which imports nothing of
`stairfit.imaging.synthetic`): `--photos` folders (seeds 100, 101, ...) of 10 views (+-25..65
deg) at 2 MP with its 15% vignetting and flat-field photo, for each of two lights (its round
0.6-deg light, and a point light as a control), measured and fitted by the functions
`stairfit fit` runs (`stairfit.pipeline`: `measure`, `observations`, `fit_setup`, `select`,
`refine`; balanced preset, model-error term on, variant `sharp+floor` forced, no posterior), and
the intervals of sigma, scale and floor (and the model-error term's value) against the
renderer's truth. The standard errors are those of the CLI as of this run (per-ROI
`channel_inflation`, or the whitening of branch `whiten` once merged; the results file says).

Outputs: benchmarks/results/coverage.md and coverage.json (benchmarks/results/quick/ with
`--quick`).

    python benchmarks/bench_coverage.py [--quick] [--datasets 200] [--posterior 50]
        [--photos 20] [--designs standard custom] [--noise 0.02 0.005 0.0005] [--out-dir DIR]
    python benchmarks/bench_coverage.py --photos-only   # the photo level again, merged in
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy import special, stats

HERE = Path(__file__).resolve().parent
TESTS = HERE.parent / "tests"
DEG = math.pi / 180.0

NOISE_LEVELS: tuple[float, ...] = (0.02, 0.005, 0.0005)
"""Relative noise levels of the issue: 2%, 0.5%, 0.05% of the value."""
ABSOLUTE_OF_PEAK = 1e-3
"""The absolute noise part, as a fraction of (noise level x the scene's peak)."""
MATERIAL = "pla-bodurov2016"
TRUTH: dict[str, float] = {"sigma_rad": 6 * DEG, "delta_n": 0.03, "scale": 2.0, "floor": 1e-3}
TRUE_VARIANT = "sharp+delta_n+floor"
LEVELS: dict[str, tuple[float, float]] = {"68": (1.0, 0.6827), "95": (1.959964, 0.95)}
"""Interval name -> (half-width in standard errors, nominal coverage) for least squares."""
POSTERIOR_NOMINAL: dict[str, tuple[str, str, float]] = {
    "68": ("p16", "p84", 0.68),
    "95": ("p2_5", "p97_5", 0.95),
}
CONFIDENCE = 0.99
"""Confidence of the Clopper-Pearson interval a coverage must fall in."""
PHOTO_VIEWS_DEG: tuple[float, ...] = tuple(float(s * v) for s in (-1, 1) for v in range(25, 70, 10))
"""10 views, +-25..65 deg every 10 deg: at 2 MP few ROIs are flagged few_blocks (15 of 7200
rows in the 40 sets of the first run; at +-75 deg and near +-5 deg more are; at 1.2 MP and 8
views of -70..70 several); flagged rows are left out, as `stairfit fit` does."""
PHOTO_MEGAPIXELS = 2.0
PHOTO_LIGHTS: dict[str, dict[str, float]] = {
    "disk 0.6 deg": {},
    "point light": {"light_diameter_deg": 0.0},
}
"""The renderer's round 0.6-deg light (its default), and a point light as a control: the fit
averages a finite light over its shape (`[light] shape`; the renderer writes "disk" for its
round light), docs/conventions.md §9."""
PHOTO_VARIANT = "sharp+floor"


# --------------------------------------------------------------------------------------------
# Statistics (pure functions; tests/validation/test_coverage.py checks them)
# --------------------------------------------------------------------------------------------


def clopper_pearson(k: int, n: int, confidence: float = CONFIDENCE) -> tuple[float, float]:
    """The exact (Clopper-Pearson) two-sided interval for a binomial proportion, `k` of `n`:
    the lower end solves P(X >= k | p) = alpha / 2, the upper P(X <= k | p) = alpha / 2, i.e.
    quantiles of Beta(k, n - k + 1) and Beta(k + 1, n - k) (0 and 1 at k = 0 and k = n)."""
    if n <= 0 or not 0 <= k <= n:
        raise ValueError(f"need 0 <= k <= n and n > 0, got k={k}, n={n}")
    alpha = 1.0 - confidence
    lo = 0.0 if k == 0 else float(special.betaincinv(k, n - k + 1, alpha / 2))
    hi = 1.0 if k == n else float(special.betaincinv(k + 1, n - k, 1 - alpha / 2))
    return lo, hi


def coverage_cell(hits: Sequence[bool], nominal: float, confidence: float = CONFIDENCE) -> dict:
    """Coverage of one cell: n, k, the fraction, its Clopper-Pearson interval and `ok` (the
    nominal coverage lies inside it)."""
    h = np.asarray(hits, bool)
    n, k = int(h.size), int(h.sum())
    lo, hi = clopper_pearson(k, n, confidence)
    return {
        "n": n,
        "k": k,
        "coverage": k / n,
        "cp_low": lo,
        "cp_high": hi,
        "nominal": nominal,
        "ok": bool(lo <= nominal <= hi),
    }


def pull_summary(pulls: Sequence[float]) -> dict[str, float]:
    """Mean and sd of pulls (0 and 1 when the errors are honest), with the mean's standard
    error `sd / sqrt(n)` and the sd's `sd / sqrt(2 (n - 1))`."""
    p = np.asarray(pulls, float)
    n = p.size
    sd = float(np.std(p, ddof=1)) if n > 1 else float("nan")
    return {
        "n": int(n),
        "mean": float(np.mean(p)),
        "sd": sd,
        "mean_se": sd / math.sqrt(n),
        "sd_se": sd / math.sqrt(2 * (n - 1)) if n > 1 else float("nan"),
    }


def chi2_summary(chi2: Sequence[float], dof: Sequence[int]) -> dict[str, float]:
    """The reduced chi^2 distribution: mean, sd, 5/50/95% quantiles, what chi^2 with that dof
    gives (mean 1, sd sqrt(2 / dof)), and the Kolmogorov-Smirnov p-value of the chi^2 tail
    probabilities against uniform (small: the chi^2 do not follow the chi^2 distribution)."""
    c, d = np.asarray(chi2, float), np.asarray(dof, float)
    red = c / d
    q = np.quantile(red, [0.05, 0.5, 0.95])
    tail = stats.chi2.sf(c, d)
    return {
        "n": int(c.size),
        "mean": float(red.mean()),
        "sd": float(red.std(ddof=1)),
        "q05": float(q[0]),
        "median": float(q[1]),
        "q95": float(q[2]),
        "expected_sd": float(np.sqrt(2.0 / np.median(d))),
        "dof": float(np.median(d)),
        "ks_p": float(stats.kstest(tail, "uniform").pvalue) if c.size > 1 else float("nan"),
    }


def ls_hits(value: float, stderr: float, truth: float) -> dict[str, bool]:
    """Whether each least-squares interval `value +- z stderr` (LEVELS) holds the truth."""
    return {name: abs(value - truth) <= z * stderr for name, (z, _) in LEVELS.items()}


# --------------------------------------------------------------------------------------------
# Observations level
# --------------------------------------------------------------------------------------------


def custom_design() -> Any:
    """A design unlike the standard one: 5 other wedges, 100 um layers, two lights (0 and
    35 deg, face frame), 16 views -77.5..72.5 deg every 10 deg (none shared with the standard
    design's grid)."""
    from stairfit import fitting

    views = tuple(float(v) for v in np.arange(-77.5, 75.0, 10.0))
    lights = (0.0, 35.0)
    return fitting.Design(
        wedge_deg=(12.0, 25.0, 35.0, 50.0, 55.0),
        theta_i_deg=tuple(t for t in lights for _ in views),
        theta_o_deg=views * len(lights),
        layer_um=100.0,
    )


def designs() -> dict[str, Any]:
    """The designs of the Observations level, by name."""
    from stairfit import fitting

    return {"standard": fitting.standard_design(), "custom": custom_design()}


def sharp_ladder() -> tuple[Any, ...]:
    """The 8 sharp variants of the default ladder (shared and per-wedge sigma)."""
    from stairfit import fitting

    return tuple(v for v in fitting.DEFAULT_LADDER if not v.name.startswith("rounded"))


def true_variant() -> Any:
    from stairfit import fitting

    return {v.name: v for v in fitting.DEFAULT_LADDER}[TRUE_VARIANT]


def simulate(design: Any, spec: Any, rel: float, seed: int) -> Any:
    """One dataset at relative noise `rel` (module doc)."""
    from stairfit import fitting

    truth = fitting.Params(**TRUTH)
    skeleton = fitting.simulate_observations(truth, design, spec, fitting.Noise(rel, 0.0), seed)
    peak = float(np.max(fitting.model_radiance(truth, skeleton, spec)))
    noise = fitting.Noise(rel, absolute=ABSOLUTE_OF_PEAK * rel * peak)
    return fitting.simulate_observations(truth, design, spec, noise, seed)


def fit_record(fit: Any) -> dict[str, Any]:
    """Pulls and interval hits of a least-squares fit against TRUTH."""
    out: dict[str, Any] = {"chi2": float(fit.chi2), "dof": int(fit.dof), "params": {}}
    for e in fit.estimates:
        t = TRUTH[e.param]
        if e.stderr is None or not np.isfinite(e.stderr):
            continue
        out["params"][e.param] = {"pull": (e.value - t) / e.stderr, **ls_hits(e.value, e.stderr, t)}
    return out


def posterior_record(post: Any) -> dict[str, Any]:
    """Interval hits of a posterior against TRUTH, and its median's pull (in posterior sd)."""
    out: dict[str, Any] = {"n_steps": int(post.n_steps), "params": {}}
    for i, p in enumerate(post.parameters):
        t = TRUTH[p.param]
        rec = {
            name: bool(getattr(post, lo)[i] <= t <= getattr(post, hi)[i])
            for name, (lo, hi, _) in POSTERIOR_NOMINAL.items()
        }
        sd = 0.5 * (post.p84[i] - post.p16[i])
        out["params"][p.param] = {"pull": float((post.median[i] - t) / sd), **rec}
    return out


def one_dataset(
    obs: Any, spec: Any, posterior_seed: int | None, moves: str = "laplace"
) -> dict[str, Any]:
    """The true variant's fit, the selection, and (with a seed) the posterior of one dataset."""
    from stairfit import fitting
    from stairfit.fitting.posterior import sample_posterior

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", fitting.FitWarningCategory)
        fit = fitting.fit_least_squares(
            obs, spec, true_variant(), on_failure="flag", emit_warnings=False
        )
        rec: dict[str, Any] = {"success": bool(fit.success), "variant_fitted": fit.variant.name}
        if fit.success:
            rec["ls"] = fit_record(fit)
        try:
            sel = fitting.select_model(obs, spec, sharp_ladder(), emit_warnings=False)
            rec["chosen"] = sel.chosen.name if hasattr(sel.chosen, "name") else str(sel.chosen)
        except fitting.FitError as err:
            rec["chosen"] = f"failed: {err}"
        if posterior_seed is not None and fit.success:
            post = sample_posterior(
                fit,
                seed=posterior_seed,
                tau_factor=20,
                chunk_steps=100,
                max_steps=20_000,
                moves=moves,
                emit_warnings=False,
            )
            rec["posterior"] = posterior_record(post)
    return rec


def dataset_seed(design: str, rel: float) -> int:
    """The first seed of a cell: every design and noise level draws its own noise (the same
    draws scaled to another level would repeat one cell's pulls three times)."""
    offset = 10_000_000 * ("standard", "custom").index(design)
    return 10_000 + offset + round(rel * 1e7)  # 200000, 50000, 5000: far apart for n < 4000


def observations_level(
    n_datasets: int,
    n_posterior: int,
    log: Callable[[str], None],
    design_names: Sequence[str] = ("standard", "custom"),
    noise_levels: Sequence[float] = NOISE_LEVELS,
    moves: str = "laplace",
) -> dict[str, dict[str, list[dict[str, Any]]]]:
    """Every dataset's record, by design and noise level (keys `f"{rel:g}"`)."""
    from stairfit import fitting

    spec = fitting.spectral_setup(MATERIAL, sampling="effective")
    out: dict[str, dict[str, list[dict[str, Any]]]] = {}
    for name in design_names:
        design = designs()[name]
        out[name] = {}
        for rel in noise_levels:
            seed = dataset_seed(name, rel)
            recs = []
            t0 = time.perf_counter()
            for s in range(n_datasets):
                post_seed = s if (name == "standard" and s < n_posterior) else None
                data = simulate(design, spec, rel, seed + s)
                recs.append(one_dataset(data, spec, post_seed, moves))
            out[name][f"{rel:g}"] = recs
            log(
                f"observations {name} {100 * rel:g}%: {n_datasets} datasets "
                f"({time.perf_counter() - t0:.0f} s)"
            )
    return out


def summarise_cells(records: list[dict[str, Any]], key: str, nominal: dict[str, float]) -> dict:
    """Per parameter: coverage cells (per interval) and the pull summary of `key` ("ls" or
    "posterior") over the records that have it."""
    params: dict[str, list[dict[str, Any]]] = {}
    for r in records:
        for p, v in (r.get(key) or {}).get("params", {}).items():
            params.setdefault(p, []).append(v)
    return {
        p: {
            "pulls": pull_summary([v["pull"] for v in vs]),
            **{lev: coverage_cell([v[lev] for v in vs], nom) for lev, nom in nominal.items()},
        }
        for p, vs in params.items()
    }


def summarise_observations(raw: dict[str, dict[str, list[dict[str, Any]]]]) -> dict:
    """Coverage, pulls, chi^2 and selection per design and noise level."""
    ls_nominal = {k: v[1] for k, v in LEVELS.items()}
    post_nominal = {k: v[2] for k, v in POSTERIOR_NOMINAL.items()}
    out: dict[str, Any] = {}
    for name, by_noise in raw.items():
        out[name] = {}
        for rel, recs in by_noise.items():
            ok = [r for r in recs if "ls" in r]
            chosen = [r.get("chosen") for r in recs]
            out[name][rel] = {
                "n_datasets": len(recs),
                "n_failed": len(recs) - len(ok),
                "n_collapsed": sum(r["variant_fitted"] != TRUE_VARIANT for r in ok),
                "ls": summarise_cells(ok, "ls", ls_nominal),
                "posterior": summarise_cells(ok, "posterior", post_nominal),
                "reduced_chi2": chi2_summary(
                    [r["ls"]["chi2"] for r in ok], [r["ls"]["dof"] for r in ok]
                ),
                "chosen_true": sum(c == TRUE_VARIANT for c in chosen) / len(chosen),
                "chosen": {c: chosen.count(c) for c in sorted(set(map(str, chosen)))},
            }
    return out


# --------------------------------------------------------------------------------------------
# Photo level
# --------------------------------------------------------------------------------------------


PHOTO_TRUTH_KEYS = {"sigma_rad": "sigma_deg", "scale": "scale", "floor": "floor"}


def photo_options() -> Any:
    """`stairfit fit --model sharp+floor --no-posterior --no-cache --quiet` (balanced preset,
    model-error term on)."""
    from stairfit.outcome import FitOptions
    from stairfit.presets import get_preset

    return FitOptions(
        preset=get_preset("balanced"),
        posterior=False,
        model=PHOTO_VARIANT,
        model_error=True,
        seed=0,
        workers=1,
        cache=False,
        progress=False,
    )


def fit_photo_folder(folder: Path, out: Path) -> Any:
    """The stages of `stairfit fit` (`stairfit.pipeline.fit_scene` without writing outputs):
    measure, observations, selection (forced variant), accuracy check; the chosen fit and the
    table."""
    from stairfit import pipeline
    from stairfit.scene import load_scene

    options = photo_options()
    scene = load_scene(folder)
    out.mkdir(parents=True, exist_ok=True)
    table = pipeline.measure(scene, out, options)
    observed = pipeline.observations(scene, table)
    observations, notes = observed.data, list(observed.notes)
    setup = pipeline.fit_setup(scene, options.preset)
    selection = pipeline.select(observations, setup, options)
    selection, _ = pipeline.refine(scene, observations, selection, options, setup)
    flags = [str(r.flag) for r in table if r.flag]
    info = {"rows": len(list(table)), "flagged": len(flags), "notes": notes}
    return selection.fit, {**info, "flags": {f: flags.count(f) for f in sorted(set(flags))}}


def photo_record(fit: Any, truth: dict[str, float], info: dict[str, Any]) -> dict[str, Any]:
    """Pulls and interval hits of sigma, scale and floor against the renderer's truth."""
    rec: dict[str, Any] = {"chi2": float(fit.chi2), "dof": int(fit.dof), "params": {}, **info}
    for e in fit.estimates:
        if e.param == "model_error_frac":
            rec["model_error_frac"] = float(e.value)
            continue
        key = PHOTO_TRUTH_KEYS.get(e.param)
        if key is None or e.stderr is None:
            continue
        t = truth[key] * (DEG if e.param == "sigma_rad" else 1.0)
        rec["params"][e.param] = {"pull": (e.value - t) / e.stderr, **ls_hits(e.value, e.stderr, t)}
    rec.setdefault("model_error_frac", 0.0)
    return rec


def photo_dataset(seed: int, light: dict[str, float]) -> dict[str, Any]:
    """Render one folder (renderer defaults but for `light`), fit it, return its record."""
    from dataclasses import replace

    from stairfit.errors import UserError

    sys.path.insert(0, str(TESTS))
    import independent_photos as ip

    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="bench_coverage_") as name:
        folder = Path(name) / "photos"
        truth = ip.render_folder(
            folder,
            seed=seed,
            megapixels=PHOTO_MEGAPIXELS,
            views=PHOTO_VIEWS_DEG,
            setup=replace(ip.Setup(), **light),
        )
        try:
            fit, info = fit_photo_folder(folder, Path(name) / "fit")
        except UserError as err:  # what `stairfit fit` would print; the set counts as failed
            return {"seed": seed, "failed": str(err), "seconds": time.perf_counter() - t0}
    rec = photo_record(fit, truth["parameters"], info)
    rec["seed"] = seed
    rec["seconds"] = time.perf_counter() - t0
    return rec


def photo_level(
    n_photos: int, log: Callable[[str], None], lights: Sequence[str] = tuple(PHOTO_LIGHTS)
) -> dict[str, list[dict[str, Any]]]:
    """`n_photos` folders (seeds 100, 101, ...) of the independent renderer per light, each
    fitted like `stairfit fit`."""
    out: dict[str, list[dict[str, Any]]] = {}
    for light in lights:
        out[light] = []
        for k in range(n_photos):
            rec = photo_dataset(100 + k, PHOTO_LIGHTS[light])
            out[light].append(rec)
            what = (
                f"FAILED: {rec['failed']}"
                if "failed" in rec
                else f"chi2/dof {rec['chi2']:.1f}/{rec['dof']}, flagged {rec['flagged']}"
            )
            log(f"photos ({light}) {k + 1}/{n_photos}: {rec['seconds']:.0f} s, {what}")
    return out


def summarise_photos(all_recs: list[dict[str, Any]]) -> dict[str, Any]:
    """Coverage, chi^2, model-error term and flags of the photo sets that were fitted; the
    failed ones (seed and message) apart."""
    recs = [r for r in all_recs if "failed" not in r]
    if not recs:
        return {}
    failed = [{"seed": r["seed"], "message": r["failed"]} for r in all_recs if "failed" in r]
    mef = np.array([r["model_error_frac"] for r in recs])
    return {
        "n_datasets": len(all_recs),
        "failed": failed,
        "ls": summarise_cells(
            [{"ls": r} for r in recs], "ls", {k: v[1] for k, v in LEVELS.items()}
        ),
        "reduced_chi2": chi2_summary([r["chi2"] for r in recs], [r["dof"] for r in recs]),
        "model_error_frac": {
            "median": float(np.median(mef)),
            "max": float(mef.max()),
            "n_nonzero": int(np.sum(mef > 0)),
        },
        "flagged_rows": int(sum(r["flagged"] for r in recs)),
        "seconds_median": float(np.median([r["seconds"] for r in recs])),
    }


# --------------------------------------------------------------------------------------------
# Output
# --------------------------------------------------------------------------------------------


def failing_cells(summary: dict[str, Any]) -> list[str]:
    """Every cell whose nominal coverage lies outside its Clopper-Pearson interval."""
    bad = []

    def visit(prefix: str, cells: dict[str, Any]) -> None:
        for p, c in cells.items():
            for lev in LEVELS:
                if lev in c and not c[lev]["ok"]:
                    bad.append(
                        f"{prefix} {p} {lev}%: {100 * c[lev]['coverage']:.1f}% "
                        f"(99% CP {100 * c[lev]['cp_low']:.1f}-{100 * c[lev]['cp_high']:.1f}%)"
                    )

    for name, by_noise in summary.get("observations", {}).items():
        for rel, s in by_noise.items():
            visit(f"observations/{name}/{100 * float(rel):g}%/least squares", s["ls"])
            visit(f"observations/{name}/{100 * float(rel):g}%/posterior", s["posterior"])
    for light, s in summary.get("photos", {}).items():
        visit(f"photos/{light}/least squares", s["ls"])
    return bad


def _cov(c: dict[str, Any]) -> str:
    mark = "" if c["ok"] else " **FAIL**"
    return f"{100 * c['coverage']:.1f}% [{100 * c['cp_low']:.0f}, {100 * c['cp_high']:.0f}]{mark}"


def coverage_table(title: str, rows: list[tuple[str, dict[str, Any]]]) -> list[str]:
    """A markdown table: label, parameter, n, 68% and 95% coverage with their CP interval,
    pull mean and sd."""
    out = [
        title,
        "",
        "| cell | parameter | n | 68% coverage [99% CP] | 95% coverage [99% CP] "
        "| pull mean | pull sd |",
        "|---|---|---|---|---|---|---|",
    ]
    for label, cells in rows:
        for p, c in cells.items():
            pl = c["pulls"]
            out.append(
                f"| {label} | {p} | {c['68']['n']} | {_cov(c['68'])} | {_cov(c['95'])} | "
                f"{pl['mean']:+.2f} | {pl['sd']:.2f} |"
            )
    return [*out, ""]


def chi2_line(label: str, c: dict[str, Any]) -> str:
    return (
        f"| {label} | {c['n']} | {c['dof']:g} | {c['mean']:.3f} | {c['sd']:.3f} "
        f"({c['expected_sd']:.3f}) | {c['q05']:.2f} / {c['median']:.2f} / {c['q95']:.2f} "
        f"| {c['ks_p']:.2g} |"
    )


def photo_section(light: str, ph: dict[str, Any]) -> list[str]:
    """The photo level's tables for one light."""
    mef = ph["model_error_frac"]
    return [
        *coverage_table(
            f"## Photo level, {light} (tests/independent_photos.py, app/pipeline.py)",
            [(light, ph["ls"])],
        ),
        "| cell | n | dof | mean | sd (expected) | 5% / 50% / 95% | KS p |",
        "|---|---|---|---|---|---|---|",
        chi2_line(f"{light}: reduced chi^2", ph["reduced_chi2"]),
        "",
        f"Model-error term: median {mef['median']:.2g}, max {mef['max']:.2g}, non-zero in "
        f"{mef['n_nonzero']} of {ph['n_datasets'] - len(ph['failed'])} fitted; rows flagged by "
        f"imaging: {ph['flagged_rows']}; median {ph['seconds_median']:.0f} s per set (render, "
        "measure, fit; under load).",
        "",
        *[f"* Set of seed {f['seed']} failed: {f['message']}" for f in ph["failed"]],
        "",
    ]


def markdown(summary: dict[str, Any]) -> str:
    """coverage.md."""
    meta = summary["meta"]
    obs = summary.get("observations", {})
    out = [
        "# Interval coverage on data the fit was not tuned to"
        + (" (quick run)" if meta["quick"] else ""),
        "",
        f"Generated by `{meta['command']}` in {meta['elapsed_s'] / 60:.1f} min ({meta['date']}, "
        f"load average at the start {meta['load_start']}). Method: the script's docstring. "
        "A coverage is marked **FAIL** when the nominal value (68.27% / 95% for least squares, "
        "68% / 95% for the posterior's percentile intervals) lies outside the 99% "
        "Clopper-Pearson interval of the observed fraction.",
        "",
        f"Truth {TRUE_VARIANT}: sigma 6 deg, delta_n 0.03, scale 2, floor 1e-3 ({MATERIAL}, "
        "effective wavelengths, point aperture). Photo level: "
        f"{meta['photo_errors']}.",
        "",
    ]
    rows = [(f"{n} {100 * float(r):g}%", s["ls"]) for n, d in obs.items() for r, s in d.items()]
    out += coverage_table("## Observations level: least squares (true variant)", rows)
    rows = [
        (f"{n} {100 * float(r):g}%", s["posterior"])
        for n, d in obs.items()
        for r, s in d.items()
        if s["posterior"]
    ]
    if rows:
        out += coverage_table("## Observations level: posterior (emcee)", rows)
    out += [
        "## Reduced chi^2 and model selection",
        "",
        "| cell | n | dof | mean | sd (expected) | 5% / 50% / 95% | KS p |",
        "|---|---|---|---|---|---|---|",
    ]
    out += [
        chi2_line(f"{n} {100 * float(r):g}%", s["reduced_chi2"])
        for n, d in obs.items()
        for r, s in d.items()
    ]
    out += [
        "",
        "| cell | chose the true variant | choices | failed fits | collapsed |",
        "|---|---|---|---|---|",
    ]
    for n, d in obs.items():
        for r, s in d.items():
            ch = ", ".join(f"{k} {v}" for k, v in s["chosen"].items())
            out.append(
                f"| {n} {100 * float(r):g}% | {100 * s['chosen_true']:.1f}% | {ch} | "
                f"{s['n_failed']} | {s['n_collapsed']} |"
            )
    out.append("")
    for light, ph in summary.get("photos", {}).items():
        out += photo_section(light, ph)
    bad = summary["failing_cells"]
    out += ["## Cells outside their binomial limits", ""]
    out += [f"* {b}" for b in bad] if bad else ["None."]
    return "\n".join([*out, ""])


# --------------------------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Settings:
    """What a run measures (`--quick`, or the full run, or what the options say)."""

    quick: bool
    datasets: int
    posterior: int
    photos: int
    designs: tuple[str, ...] = ("standard", "custom")
    noise_levels: tuple[float, ...] = NOISE_LEVELS
    moves: str = "laplace"


def settings_from(args: argparse.Namespace) -> Settings:
    quick = bool(args.quick)

    def pick(x: int | None, full: int, short: int) -> int:
        return x if x is not None else (short if quick else full)

    return Settings(
        quick,
        pick(args.datasets, 200, 8),
        pick(args.posterior, 50, 2),
        pick(args.photos, 20, 1),
        tuple(args.designs or ("standard", "custom")),
        tuple(args.noise or NOISE_LEVELS),
        args.moves,
    )


def photo_error_model() -> str:
    """Which per-ROI error treatment the CLI of this checkout applies."""
    from stairfit import pipeline

    if hasattr(pipeline, "channel_inflation"):
        return "standard errors with the CLI's per-ROI channel_inflation"
    return "standard errors whitened per ROI (3x3 channel covariance)"


def run(st: Settings, out_dir: Path, command: str) -> dict[str, Any]:
    """Measure, summarise and write coverage.md / coverage.json; return the summary."""
    import datetime
    import os

    t0 = time.perf_counter()

    def log(msg: str) -> None:
        print(f"[{time.perf_counter() - t0:6.0f} s] {msg}", flush=True)

    load = os.getloadavg()[0]
    raw_obs = (
        observations_level(st.datasets, st.posterior, log, st.designs, st.noise_levels, st.moves)
        if st.datasets
        else {}
    )
    raw_photos = photo_level(st.photos, log) if st.photos else {}
    summary: dict[str, Any] = {
        "observations": summarise_observations(raw_obs),
        "photos": {k: summarise_photos(v) for k, v in raw_photos.items()},
    }
    summary["failing_cells"] = failing_cells(summary)
    summary["meta"] = {
        "quick": st.quick,
        "command": command,
        "elapsed_s": time.perf_counter() - t0,
        "date": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC"),
        "load_start": round(load, 1),
        "settings": st.__dict__,
        "truth": TRUTH,
        "noise_levels": NOISE_LEVELS,
        "photo_errors": photo_error_model(),
    }
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "coverage.json").write_text(
        json.dumps({**summary, "photo_records": raw_photos}, indent=1, default=float)
    )
    (out_dir / "coverage.md").write_text(markdown(summary))
    log(f"wrote {out_dir}")
    return summary


def rerun_photos(st: Settings, out_dir: Path, command: str) -> dict[str, Any]:
    """`--photos-only`: measure the photo level again and merge it into coverage.json /
    coverage.md, keeping the Observations level of the earlier run (its settings and date are
    kept under `meta.observations_run`)."""
    import datetime

    t0 = time.perf_counter()
    old = json.loads((out_dir / "coverage.json").read_text())
    raw = photo_level(st.photos, lambda m: print(f"[{time.perf_counter() - t0:6.0f} s] {m}"))
    summary = {
        "observations": old["observations"],
        "photos": {k: summarise_photos(v) for k, v in raw.items()},
    }
    summary["failing_cells"] = failing_cells(summary)
    meta = dict(old["meta"])
    meta["observations_run"] = {k: old["meta"][k] for k in ("command", "date", "elapsed_s")}
    meta |= {
        "command": f"{old['meta']['command']}; then {command}",
        "elapsed_s": old["meta"]["elapsed_s"] + time.perf_counter() - t0,
        "date": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC"),
        "photo_errors": photo_error_model(),
    }
    summary["meta"] = meta
    (out_dir / "coverage.json").write_text(
        json.dumps({**summary, "photo_records": raw}, indent=1, default=float)
    )
    (out_dir / "coverage.md").write_text(markdown(summary))
    return summary


def main(argv: list[str] | None = None) -> dict[str, Any]:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="smoke run (8, 2 and 1 of the below)")
    ap.add_argument("--datasets", type=int, help="Observations datasets per cell (200)")
    ap.add_argument("--posterior", type=int, help="posteriors per noise level (50)")
    ap.add_argument("--photos", type=int, help="photo-level folders per light (20)")
    ap.add_argument("--designs", nargs="+", choices=("standard", "custom"), help="(both)")
    ap.add_argument(
        "--noise", nargs="+", type=float, help="relative noise levels (0.02 0.005 0.0005)"
    )
    ap.add_argument("--out-dir", type=Path, default=None, help="where to write the results")
    ap.add_argument(
        "--moves",
        default="laplace",
        help="the posterior's proposal (fitting.posterior.MOVES; laplace)",
    )
    ap.add_argument(
        "--photos-only",
        action="store_true",
        help="measure the photo level again; keep the Observations level of coverage.json",
    )
    args = ap.parse_args(argv)
    import jax

    jax.config.update("jax_enable_x64", True)  # fits need float64 [conventions §10]
    st = settings_from(args)
    out_dir = args.out_dir or (HERE / "results" / "quick" if st.quick else HERE / "results")
    command = (
        "python benchmarks/bench_coverage.py"
        + (" " + " ".join(argv if argv is not None else sys.argv[1:])).rstrip()
    )
    if args.photos_only:
        summary = rerun_photos(st, out_dir, command.rstrip())
    else:
        summary = run(st, out_dir, command.rstrip())
    print(markdown(summary))
    return summary


if __name__ == "__main__":
    main()
