"""Benchmark: the speed/accuracy trade of every knob, and the presets chosen from it (issue 7).

For each setting of each knob that trades accuracy for time it measures, in one run:

* (a) **model error** against a converged high-accuracy reference,
* (b) **fit error**: the fitted parameters on synthetic data with known truth, in units of their
  standard errors (truth simulated with the accurate settings, fitted with the setting under
  test; several seeds, plus one noiseless copy that isolates the bias),
* (c) **wall time**: medians of repeats after compilation; compilation reported apart.

The knobs [conventions §8, §9, §10; docs/fitting.md]: spectral sampling (`"effective"`, one
wavelength per channel, or `"full"`, 5 nm), aperture quadrature (`model.Aperture.n_nodes` per
axis), float32 versus float64 for evaluating the model (fits are always float64), the diffuse
integral's nodes (`model.diffuse_broadened(n_nodes=)`), the rounded-edge resolution
(`model.brdf_rounded(resolution=)`, model error only), the number of least-squares starts, and
the posterior chain length (`sample_posterior(tau_factor=)`). Side by side: the NumPy +
`scipy.optimize.least_squares` baseline of the sharp fit (`bench_fit.scipy_fit`) and the ratio.
Finally every preset of `stairfit.presets.PRESETS` is measured as a whole, and at three noise
levels (`NOISE_LEVELS`: 2%, 0.5%, 0.05% relative; the absolute part scaled with it, 0.05 x the
level x the peak, which is `fitting.Noise`'s default 1e-3 x the peak at 2%): the preset's
numerical error at its optimum against the converged reference (5 nm, 12 aperture nodes) as
`fitting.numerical_error` computes it (rms over the rows of `(model - reference) / stderr`, the
figure the accuracy refine of app/accuracy.py compares with `fitting.ACCURACY_LIMIT`),
its largest difference over the median standard error, the fit's bias in standard errors on
noiseless data with that noise level's errors, and whether `stairfit fit`'s check (against
the accurate preset's knobs) would refit (`balanced`), warn (`fast`) or do nothing.
`--noise-only` measures only these rows and merges them into an existing tradeoff.csv.

Cases. Material `pla-bodurov2016` (dispersive, so the spectral knob matters), ideal RGB camera,
D65. Aperture: a light of 5 deg angular diameter and a face spanning 3 deg (half-widths 2.5 and
1.5 deg). Truth: sigma 6 deg, delta_n 0.05, scale 2 (as benchmarks/bench_fit.py). Model error on
a "figure grid" (6 wedges 10-60 deg x 171 views -85..85 deg x 3 channels, theta_i 20 deg) as
max |m - ref| / max |ref| (`model_err_rel`) and as max |m - ref| / stderr with the 2% noise model
of `fitting.Noise` (`model_err_noise`: below ~0.3 the error is invisible under the noise). Fits:
variant `sharp+delta_n` on `fitting.standard_design()` (342 rows), 2% noise. References:
5 nm spectra, 12 aperture nodes (checked against 16), float64; diffuse 24 nodes (checked against
32); rounded resolution 12 (checked against 16).

Outputs (`--out-dir`, default benchmarks/results, or benchmarks/results/quick with `--quick`):
`tradeoff.csv` (one row per measured configuration; columns in `COLUMNS`), `tradeoff.md`
(tables) and `tradeoff_pareto.png` (error against time, Pareto front, presets marked).

    python benchmarks/bench_tradeoff.py [--quick] [--seeds 5] [--repeats 5] [--out-dir DIR]
    python benchmarks/bench_tradeoff.py --noise-only     # the noise-level axis only

`--quick` (fewer settings, seeds and repeats, no rounded model) finishes in under 3 minutes on
an idle 2-core machine.
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _timing import first_call_seconds, median_seconds

DEG = np.pi / 180
MATERIAL = "pla-bodurov2016"
HALF_WIDTHS_DEG = (2.5, 1.5)  # light (5 deg diameter), viewed face (3 deg)
TRUTH = {"sigma_rad": 6 * DEG, "delta_n": 0.05, "scale": 2.0}
VARIANT = "sharp+delta_n"
NOISE = 0.02
NOISE_LEVELS: tuple[float, ...] = (0.02, 0.005, 0.0005)
"""Relative noise levels of the noise axis (issue 13)."""
ABSOLUTE_PER_RELATIVE = 0.05
"""The noise axis's absolute part: this x the relative level x the peak (1e-3 x peak at 2%)."""
REF_APERTURE_NODES, CHECK_APERTURE_NODES = 12, 16
REF_DIFFUSE_NODES, CHECK_DIFFUSE_NODES = 24, 32
REF_RESOLUTION, CHECK_RESOLUTION = 12, 16
FIG_WEDGES_DEG = (10.0, 20.0, 30.0, 40.0, 45.0, 60.0)
FIG_VIEWS_DEG = np.arange(-85.0, 85.5, 1.0)
THETA_I_DEG = 20.0

COLUMNS: dict[str, str] = {
    "group": "what was varied: model, fit, starts, diffuse, rounded, posterior, baseline, preset",
    "config": "short label of the configuration",
    "spectral": "spectral sampling: effective (K = 1) or full (5 nm, K = 81)",
    "aperture_nodes": "Gauss-Legendre nodes per axis over the light and the viewed face",
    "dtype": "float32 or float64 for evaluating the model (fits are always float64)",
    "diffuse_nodes": "nodes per piece of model.diffuse_broadened",
    "rounded_resolution": "panels per sub-interval of model.brdf_rounded",
    "tau_factor": "posterior chain length in autocorrelation times",
    "n_starts": "least-squares starts (widths from the preset or the default)",
    "model_err_rel": "max |model - reference| / max |reference| on the case's grid",
    "model_err_noise": "max |model - reference| / stderr of 2% noise (invisible below ~0.3)",
    "fit_bias_z": "max over parameters |fit - truth| / stderr on noiseless data (pure bias)",
    "fit_z_rms": "rms over seeds and parameters of (fit - truth) / stderr (1 = honest)",
    "fit_z_max": "max over seeds and parameters of |fit - truth| / stderr",
    "n_seeds": "noisy datasets behind fit_z_rms / fit_z_max",
    "post_mc_err": "1 / sqrt(independent samples): Monte Carlo error of a posterior mean in sd",
    "post_steps": "posterior chain length in steps (walkers x steps samples)",
    "time_s": "median wall time of the timed operation after compilation (s)",
    "post_s": "preset rows: wall time of the posterior after compilation (s)",
    "compile_s": "first call minus median: tracing + compilation (s)",
    "noise": "noise axis: relative noise level of the data (absolute part scaled with it)",
    "num_err_rms": "noise axis: fitting.numerical_error rms of (model - reference) / stderr",
    "num_err_max_median_se": "noise axis: max |model - reference| / median stderr",
    "refine": "noise axis: what stairfit fit's accuracy check does (none, refit, warn)",
    "timed": "what time_s measures",
    "note": "remarks",
}


@dataclass
class Row:
    """One measured configuration (fields = COLUMNS; None = not applicable)."""

    group: str
    config: str
    spectral: str | None = None
    aperture_nodes: int | None = None
    dtype: str | None = None
    diffuse_nodes: int | None = None
    rounded_resolution: int | None = None
    tau_factor: float | None = None
    n_starts: int | None = None
    model_err_rel: float | None = None
    model_err_noise: float | None = None
    fit_bias_z: float | None = None
    fit_z_rms: float | None = None
    fit_z_max: float | None = None
    n_seeds: int | None = None
    post_mc_err: float | None = None
    post_steps: int | None = None
    time_s: float | None = None
    post_s: float | None = None
    compile_s: float | None = None
    noise: float | None = None
    num_err_rms: float | None = None
    num_err_max_median_se: float | None = None
    refine: str | None = None
    timed: str = ""
    note: str = field(default="")


@dataclass(frozen=True)
class Settings:
    """What a run measures (`--quick` or full)."""

    quick: bool
    seeds: int
    repeats: int
    aperture_nodes: tuple[int, ...]
    diffuse_nodes: tuple[int, ...]
    resolutions: tuple[int, ...]
    chains: tuple[tuple[float, int, int], ...]  # (tau_factor, max_steps, chunk_steps)
    post_seeds: int
    fit_spectral: tuple[str, ...]
    fit_aperture_nodes: tuple[int, ...]
    presets: bool


def settings_for(quick: bool, seeds: int | None, repeats: int | None) -> Settings:
    """Full run, or the short one for notebooks and tests."""
    if quick:
        return Settings(
            quick=True,
            seeds=seeds or 2,
            repeats=repeats or 3,
            aperture_nodes=(1, 2),
            diffuse_nodes=(3, 6),
            resolutions=(),
            chains=((20.0, 1000, 100),),
            post_seeds=1,
            fit_spectral=("effective", "full"),
            fit_aperture_nodes=(1,),
            presets=False,
        )
    return Settings(
        quick=False,
        seeds=seeds or 4,
        repeats=repeats or 3,
        aperture_nodes=(1, 2, 3, 5),
        diffuse_nodes=(2, 3, 4, 6, 8),
        resolutions=(2, 4, 8),
        chains=(
            (10.0, 1500, 100),
            (10.0, 20_000, 100),
            (20.0, 20_000, 100),
            (20.0, 20_000, 500),
            (50.0, 20_000, 100),
            (50.0, 20_000, 500),
            (100.0, 50_000, 500),
        ),
        post_seeds=1,
        fit_spectral=("effective", "full"),
        fit_aperture_nodes=(1, 2, 3),
        presets=True,
    )


# --------------------------------------------------------------------------------------------
# Cases
# --------------------------------------------------------------------------------------------


def spectral(sampling: str):
    """The spectral setup of every case."""
    from stairfit import fitting

    return fitting.spectral_setup(MATERIAL, sampling=sampling)


def aperture(n_nodes: int):
    """The case's finite light and face, with `n_nodes` per axis [conventions §9]."""
    from stairfit import model

    return model.Aperture(HALF_WIDTHS_DEG[0] * DEG, HALF_WIDTHS_DEG[1] * DEG, n_nodes)


def figure_grid(sampling: str) -> dict[str, np.ndarray]:
    """Rows (wedge x view x channel) of the model-error case, with their spectral arrays."""
    spec = spectral(sampling)
    b, to, ch = np.meshgrid(
        np.asarray(FIG_WEDGES_DEG) * DEG, FIG_VIEWS_DEG * DEG, np.arange(3), indexing="ij"
    )
    ch = ch.ravel()
    return {
        "theta_i": np.full(ch.size, THETA_I_DEG * DEG),
        "theta_o": to.ravel(),
        "beta2": b.ravel(),
        "n": np.asarray(spec.n_base)[ch] + TRUTH["delta_n"],
        "w": np.asarray(spec.weights)[ch],
    }


def model_function(n_nodes: int) -> Callable[..., jax.Array]:
    """Jitted radiance on the figure grid with the given aperture quadrature [conventions §9]."""
    from stairfit import model

    ap = aperture(n_nodes)

    def f(ti, to, b2, n, w, sigma, scale):
        dens = model.band_density(ti, to, b2, n, w, sigma, ap)
        return model.radiance(dens, ti, to, scale)

    return jax.jit(f)


def noise_stderr(ref: np.ndarray) -> np.ndarray:
    """The stderr `fitting.Noise(0.02)` would give these values."""
    return np.sqrt((NOISE * ref) ** 2 + (1e-3 * np.max(np.abs(ref))) ** 2)


def errors(m: np.ndarray, ref: np.ndarray) -> tuple[float, float]:
    """(max relative to the peak, max in noise stderrs)."""
    d = np.abs(np.asarray(m, np.float64) - ref)
    return float(d.max() / np.abs(ref).max()), float(np.max(d / noise_stderr(ref)))


# --------------------------------------------------------------------------------------------
# (a) Model error and time: spectral x aperture x dtype; diffuse nodes; rounded resolution
# --------------------------------------------------------------------------------------------


def model_rows(st: Settings) -> tuple[list[Row], str]:
    """The sharp measurement model on the figure grid, every combination of three knobs."""
    args64 = {s: figure_grid(s) for s in ("effective", "full")}
    sigma, scale = TRUTH["sigma_rad"], TRUTH["scale"]

    def run(
        sampling: str, n_nodes: int, dtype: Any, timed: bool = True
    ) -> tuple[np.ndarray, float, float]:
        fn = model_function(n_nodes)
        a = args64[sampling]
        xs = [jnp.asarray(a[k], dtype) for k in ("theta_i", "theta_o", "beta2", "n", "w")]
        xs += [jnp.asarray(sigma, dtype), jnp.asarray(scale, dtype)]
        first = first_call_seconds(lambda: fn(*xs))
        if not timed:
            return np.asarray(fn(*xs), np.float64), first, 0.0
        t = median_seconds(lambda: fn(*xs), max(3, 2 * st.repeats), min_time=0.2)
        return np.asarray(fn(*xs), np.float64), t, first - t

    ref = run("full", REF_APERTURE_NODES, jnp.float64, timed=False)[0]
    check = run("full", CHECK_APERTURE_NODES, jnp.float64, timed=False)[0]
    conv = errors(check, ref)[0]
    note = f"reference: full, {REF_APERTURE_NODES} nodes, float64 ({CHECK_APERTURE_NODES} nodes differ by {conv:.1e})"  # noqa: E501
    rows = []
    for sampling in ("effective", "full"):
        for n_nodes in st.aperture_nodes:
            for dt in (jnp.float64, jnp.float32):
                m, t, c = run(sampling, n_nodes, dt)
                e_rel, e_noise = errors(m, ref)
                name = jnp.dtype(dt).name
                rows.append(
                    Row(
                        "model",
                        f"{sampling}/{n_nodes}n/{name}",
                        sampling,
                        n_nodes,
                        name,
                        model_err_rel=e_rel,
                        model_err_noise=e_noise,
                        time_s=t,
                        compile_s=c,
                        timed=f"radiance, {m.size} rows",
                    )
                )
    return rows, note


def diffuse_rows(st: Settings) -> list[Row]:
    """`diffuse_broadened` against many nodes: 6 wedges x 361 views, sigma 6 deg."""
    from stairfit import model

    to = np.linspace(-90, 90, 361) * DEG
    b2 = np.asarray(FIG_WEDGES_DEG)[:, None] * DEG
    xs = (jnp.asarray(to), jnp.asarray(b2), 1.46 + TRUTH["delta_n"], TRUTH["sigma_rad"])

    def run(n_nodes: int, timed: bool = True) -> tuple[np.ndarray, float, float]:
        fn = jax.jit(lambda a, b, n, s: model.diffuse_broadened(a, b, n, s, n_nodes=n_nodes))
        first = first_call_seconds(lambda: fn(*xs))
        if not timed:
            return np.asarray(fn(*xs)), first, 0.0
        t = median_seconds(lambda: fn(*xs), max(3, 2 * st.repeats), min_time=0.2)
        return np.asarray(fn(*xs)), t, first - t

    ref = run(REF_DIFFUSE_NODES, timed=False)[0]
    check = run(CHECK_DIFFUSE_NODES, timed=False)[0]
    conv = float(np.abs(check - ref).max() / np.abs(ref).max())
    rows = []
    for k in st.diffuse_nodes:
        m, t, c = run(k)
        rows.append(
            Row(
                "diffuse",
                f"diffuse {k} nodes",
                diffuse_nodes=k,
                model_err_rel=float(np.abs(m - ref).max() / np.abs(ref).max()),
                time_s=t,
                compile_s=c,
                timed=f"diffuse integral, {m.size} values",
                note=f"reference {REF_DIFFUSE_NODES} nodes ({CHECK_DIFFUSE_NODES} differ "
                f"by {conv:.1e})",
            )
        )
    return rows


def rounded_rows(st: Settings) -> list[Row]:
    """`brdf_rounded` at each resolution: wedges 10/30/60 deg, r = 0.3 r_max, sigma 2 deg."""
    from stairfit import model

    b2 = np.array([10.0, 30.0, 60.0])[:, None] * DEG
    r = 0.3 * np.asarray(model.max_edge_radius(b2, 150.0))
    to = FIG_VIEWS_DEG[None, :] * DEG
    xs = (jnp.full_like(b2, THETA_I_DEG * DEG), jnp.asarray(to), jnp.asarray(b2), jnp.asarray(r))

    def run(res: int, timed: bool = True) -> tuple[np.ndarray, float, float]:
        fn = jax.jit(
            lambda ti, to, b, rr: model.brdf_rounded(
                ti, to, b, 1.46 + TRUTH["delta_n"], 2 * DEG, 150.0, rr, resolution=res
            )
        )
        first = first_call_seconds(lambda: fn(*xs))
        if not timed:
            return np.asarray(fn(*xs)), first, 0.0
        t = median_seconds(lambda: fn(*xs), max(3, st.repeats), min_time=0.2)
        return np.asarray(fn(*xs)), t, first - t

    ref = run(REF_RESOLUTION, timed=False)[0]
    conv = float(np.abs(run(CHECK_RESOLUTION, timed=False)[0] - ref).max() / np.abs(ref).max())
    rows = []
    for res in st.resolutions:
        m, t, c = run(res)
        rows.append(
            Row(
                "rounded",
                f"rounded resolution {res}",
                rounded_resolution=res,
                model_err_rel=float(np.abs(m - ref).max() / np.abs(ref).max()),
                time_s=t,
                compile_s=c,
                timed=f"brdf_rounded, {m.size} values",
                note=f"reference resolution {REF_RESOLUTION} ({CHECK_RESOLUTION} differs "
                f"by {conv:.1e}); model/_rounded.py as of this run",
            )
        )
    return rows


# --------------------------------------------------------------------------------------------
# (b) Fits on synthetic data with known truth
# --------------------------------------------------------------------------------------------


@dataclass
class FitCase:
    """Synthetic datasets (noisy seeds and one noiseless copy) simulated with the reference."""

    noisy: list[Any]
    clean: Any


def fit_case(n_seeds: int) -> FitCase:
    """Truth simulated with 5 nm spectra and the reference aperture quadrature."""
    from stairfit import fitting

    spec, ap = spectral("full"), aperture(REF_APERTURE_NODES)
    truth, design = fitting.Params(**TRUTH), fitting.standard_design()
    noisy = [
        fitting.simulate_observations(
            truth, design, spec, fitting.Noise(NOISE), seed=1000 + s, aperture=ap
        )
        for s in range(n_seeds)
    ]
    clean = noisy[0]._replace(value=fitting.model_radiance(truth, noisy[0], spec, aperture=ap))
    return FitCase(noisy, clean)


def sharp_variant():
    """The ladder's `sharp+delta_n` (sigma, delta_n, scale)."""
    from stairfit import fitting

    return {v.name: v for v in fitting.DEFAULT_LADDER}[VARIANT]


def z_scores(fit: Any) -> np.ndarray:
    """(estimate - truth) / stderr for each free parameter."""
    truth = np.array([TRUTH[e.param] for e in fit.estimates])
    return (np.asarray(fit.values) - truth) / np.asarray(fit.stderrs)


def measure_fit(
    case: FitCase, sampling: str, n_nodes: int, starts_rad: Sequence[float], repeats: int
) -> tuple[dict[str, float], Any]:
    """Fit error and time of one configuration; also returns the seed-0 fit."""
    from stairfit import fitting

    spec, ap, v = spectral(sampling), aperture(n_nodes), sharp_variant()

    def fit(obs: Any) -> Any:
        return fitting.fit_least_squares(
            obs, spec, v, aperture=ap, sigma_starts_rad=tuple(starts_rad), emit_warnings=False
        )

    first = first_call_seconds(lambda: fit(case.noisy[0]))
    t = median_seconds(lambda: fit(case.noisy[0]), repeats)
    bias = np.abs(z_scores(fit(case.clean)))
    zs = np.concatenate([z_scores(fit(o)) for o in case.noisy])
    out = {
        "fit_bias_z": float(bias.max()),
        "fit_z_rms": float(np.sqrt(np.mean(zs**2))),
        "fit_z_max": float(np.abs(zs).max()),
        "n_seeds": len(case.noisy),
        "time_s": t,
        "compile_s": max(first - t, 0.0),
    }
    return out, fit(case.noisy[0])


def fit_rows(st: Settings, case: FitCase) -> tuple[list[Row], dict[tuple[str, int], Any]]:
    """Spectral sampling x aperture nodes, default starts."""
    from stairfit import fitting

    starts = fitting.DEFAULT_SIGMA_STARTS_RAD
    rows, fits = [], {}
    for sampling in st.fit_spectral:
        for n_nodes in st.fit_aperture_nodes:
            m, fits[(sampling, n_nodes)] = measure_fit(case, sampling, n_nodes, starts, st.repeats)
            rows.append(
                Row(
                    "fit",
                    f"{sampling}/{n_nodes}n",
                    sampling,
                    n_nodes,
                    "float64",
                    n_starts=len(starts),
                    timed="least-squares fit (4 starts), 342 rows",
                    **m,
                )
            )
    return rows, fits


def start_rows(st: Settings, case: FitCase) -> list[Row]:
    """Number of least-squares starts (effective spectra, 2 aperture nodes)."""
    widths = {1: (4.0,), 2: (2.0, 8.0), 3: (1.0, 4.0, 12.0), 4: (1.0, 3.0, 10.0, 30.0)}
    rows = []
    for k, w in widths.items():
        m, _ = measure_fit(case, "effective", 2, tuple(x * DEG for x in w), st.repeats)
        rows.append(
            Row(
                "starts",
                f"{k} starts {w} deg",
                "effective",
                2,
                "float64",
                n_starts=k,
                timed="least-squares fit, 342 rows",
                **m,
            )
        )
    return rows


# --------------------------------------------------------------------------------------------
# Posterior chain length
# --------------------------------------------------------------------------------------------


def posterior_compile(fit: Any) -> float:
    """Compilation of the posterior's log probability (a 10-step run)."""
    from stairfit import fitting
    from stairfit.fitting.posterior import sample_posterior

    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", fitting.FitWarningCategory)
        sample_posterior(fit, seed=0, chunk_steps=10, max_steps=10, emit_warnings=False)
    return time.perf_counter() - t0


def run_posterior(
    fit: Any, tau_factor: float, seed: int, max_steps: int = 20_000, chunk_steps: int = 500
) -> Any:
    """One posterior, the stopping rule checked every `chunk_steps` steps (as the app does with
    the preset's `posterior_chunk_steps`); the app ignores the warning of a chain cut at
    `max_steps` (it reports `converged`)."""
    from stairfit import fitting
    from stairfit.fitting.posterior import sample_posterior

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", fitting.FitWarningCategory)
        return sample_posterior(
            fit,
            seed=seed,
            tau_factor=tau_factor,
            max_steps=max_steps,
            chunk_steps=chunk_steps,
            emit_warnings=False,
        )


def posterior_rows(st: Settings, case: FitCase) -> list[Row]:
    """Chain length (tau_factor, max_steps, chunk_steps) on fits of `post_seeds` datasets
    (effective spectra, 2 aperture nodes: the balanced fit)."""
    from stairfit import fitting

    spec, ap, v = spectral("effective"), aperture(2), sharp_variant()
    fits = [
        fitting.fit_least_squares(o, spec, v, aperture=ap, emit_warnings=False)
        for o in case.noisy[: st.post_seeds]
    ]
    compile_s = posterior_compile(fits[0])
    rows = []
    for tf, max_steps, chunk in st.chains:
        posts = [run_posterior(f, tf, 7 + i, max_steps, chunk) for i, f in enumerate(fits)]
        truth = np.array([TRUTH[e.param] for e in fits[0].estimates])
        zs = np.concatenate([(p.median - truth) / (0.5 * (p.p84 - p.p16)) for p in posts])
        widths = np.concatenate([p.width_ratio for p in posts])
        rows.append(
            Row(
                "posterior",
                f"tau_factor {tf:g}, max {max_steps} steps, checked every {chunk}",
                "effective",
                2,
                "float64",
                tau_factor=tf,
                fit_z_rms=float(np.sqrt(np.mean(zs**2))),
                fit_z_max=float(np.abs(zs).max()),
                n_seeds=len(posts),
                post_mc_err=float(np.median([1 / math.sqrt(p.n_independent) for p in posts])),
                post_steps=int(np.median([p.n_steps for p in posts])),
                time_s=float(np.median([p.elapsed_s for p in posts])),
                compile_s=compile_s,
                timed="sample_posterior (32 walkers)",
                note=f"posterior width / LS stderr {widths.min():.2f}-{widths.max():.2f}; "
                f"converged {sum(p.converged for p in posts)}/{len(posts)}",
            )
        )
    return rows


# --------------------------------------------------------------------------------------------
# Baseline and presets
# --------------------------------------------------------------------------------------------


def baseline_rows(st: Settings, case: FitCase, fit_table: list[Row]) -> list[Row]:
    """SciPy trf + FD Jacobian on the NumPy model, against stairfit on the same data."""
    from bench_fit import scipy_fit

    from stairfit import fitting

    rows = []
    for sampling in st.fit_spectral:
        spec = spectral(sampling)
        starts = fitting.DEFAULT_SIGMA_STARTS_RAD
        ours = next(r for r in fit_table if r.spectral == sampling and r.aperture_nodes == 1)
        t = median_seconds(
            lambda s=spec, w=starts: scipy_fit(case.noisy[0], s, w), max(3, st.repeats)
        )
        _, chi2 = scipy_fit(case.noisy[0], spec, starts)
        lm = fitting.fit_least_squares(case.noisy[0], spec, sharp_variant(), emit_warnings=False)
        # both reach the same optimum before any time is compared
        assert abs(chi2 - lm.chi2) < 1e-6 * lm.chi2 + 1e-6, (chi2, lm.chi2)
        rows.append(
            Row(
                "baseline",
                f"SciPy {sampling}/1n",
                sampling,
                1,
                "float64",
                n_starts=len(starts),
                time_s=t,
                timed="scipy least_squares trf + FD",
                note=f"chi2 {chi2:.2f} = stairfit {lm.chi2:.2f}; SciPy / stairfit = "
                f"{t / ours.time_s:.1f}x",
            )
        )
    return rows


def preset_rows(st: Settings, case: FitCase, table: list[Row]) -> list[Row]:
    """Each preset as a whole: its model error, fit error, fit time and posterior time."""
    from stairfit.presets import PRESETS

    rows = []
    for p in PRESETS.values():
        dt = "float32" if p.float32_figures else "float64"
        mrow = next(
            (
                r
                for r in table
                if r.group == "model"
                and r.spectral == p.spectral
                and r.aperture_nodes == p.aperture_nodes
                and r.dtype == dt
            ),
            None,
        )
        drow = next((r for r in table if r.diffuse_nodes == p.diffuse_nodes), None)
        rrow = next((r for r in table if r.rounded_resolution == p.rounded_resolution), None)
        starts = tuple(s * DEG for s in p.sigma_starts_deg)
        m, fit = measure_fit(case, p.spectral, p.aperture_nodes, starts, st.repeats)
        frow = next(
            (
                r
                for r in table
                if r.group == "fit"
                and r.spectral == p.spectral
                and r.aperture_nodes == p.aperture_nodes
            ),
            None,
        )
        if frow is not None:  # compiled there already (the starts do not recompile)
            m["compile_s"] = frow.compile_s
        post_compile = posterior_compile(fit)
        post = run_posterior(
            fit, p.posterior_tau_factor, 3, p.posterior_max_steps, p.posterior_chunk_steps
        )
        extra = [f"posterior compile {post_compile:.1f} s, converged {post.converged}"]
        if drow is not None:
            extra.append(f"diffuse err {drow.model_err_rel:.1e}")
        if rrow is not None:
            extra.append(f"rounded err {rrow.model_err_rel:.1e}")
        rows.append(
            Row(
                "preset",
                p.name,
                p.spectral,
                p.aperture_nodes,
                dt,
                p.diffuse_nodes,
                p.rounded_resolution,
                p.posterior_tau_factor,
                len(starts),
                model_err_rel=mrow.model_err_rel if mrow else None,
                model_err_noise=mrow.model_err_noise if mrow else None,
                post_mc_err=1 / math.sqrt(post.n_independent),
                post_steps=post.n_steps,
                post_s=post.elapsed_s,
                timed="least-squares fit (preset starts)",
                note="; ".join(extra),
                **m,
            )
        )
    return rows


# --------------------------------------------------------------------------------------------
# Noise axis: the presets' numerical error at 2%, 0.5% and 0.05% noise (issue 13)
# --------------------------------------------------------------------------------------------


def noise_observations(rel: float, seed: int = 2000) -> tuple[Any, Any]:
    """(noisy, noiseless) standard-scene data at relative noise `rel`, simulated with the
    reference knobs; the noiseless copy keeps the noisy one's standard errors."""
    from stairfit import fitting

    spec, ap = spectral("full"), aperture(REF_APERTURE_NODES)
    truth, design = fitting.Params(**TRUTH), fitting.standard_design()
    skeleton = fitting.simulate_observations(
        truth, design, spec, fitting.Noise(rel, 0.0), seed, aperture=ap
    )
    clean = fitting.model_radiance(truth, skeleton, spec, aperture=ap)
    noise = fitting.Noise(rel, absolute=ABSOLUTE_PER_RELATIVE * rel * float(np.max(clean)))
    noisy = fitting.simulate_observations(truth, design, spec, noise, seed, aperture=ap)
    return noisy, noisy._replace(value=clean)


def refine_action(preset: str, exceeds: bool) -> str:
    """What app/accuracy.py does with a numerical error beyond the limit."""
    if preset == "accurate":
        return "none (reference)"
    if not exceeds:
        return "none"
    return "warn" if preset == "fast" else "refit"


def noise_row(p: Any, rel: float, data: tuple[Any, Any]) -> Row:
    """One preset at one noise level: numerical error at the optimum of the noisy fit, bias on
    the noiseless copy, and the accuracy check's decision."""
    from stairfit import fitting

    noisy, clean = data
    spec, ap = spectral(p.spectral), aperture(p.aperture_nodes)
    kw = {
        "aperture": ap,
        "sigma_starts_rad": tuple(s * DEG for s in p.sigma_starts_deg),
        "emit_warnings": False,
    }
    fit = fitting.fit_least_squares(noisy, spec, sharp_variant(), **kw)
    ref_spec = spectral("full")
    converged = fitting.numerical_error(fit, ref_spec, aperture=aperture(REF_APERTURE_NODES))
    check = fitting.numerical_error(fit, ref_spec, aperture=aperture(3))  # the app's reference
    ref = fitting.model_radiance(fit.params, noisy, ref_spec, aperture=aperture(REF_APERTURE_NODES))
    diff = np.abs(np.asarray(fit.model) - ref)
    bias = np.abs(z_scores(fitting.fit_least_squares(clean, spec, sharp_variant(), **kw)))
    return Row(
        "noise",
        f"{p.name} at {100 * rel:g}%",
        p.spectral,
        p.aperture_nodes,
        "float64",
        n_starts=len(p.sigma_starts_deg),
        noise=rel,
        model_err_rel=converged.of_peak,
        num_err_rms=converged.rms,
        num_err_max_median_se=float(diff.max() / np.median(noisy.stderr)),
        fit_bias_z=float(bias.max()),
        refine=refine_action(p.name, check.exceeds),
        note=f"check against the accurate knobs: rms {check.rms:.3g} (limit {check.limit:g})",
    )


def noise_rows() -> list[Row]:
    """Every preset at every level of NOISE_LEVELS (no timing: errors only)."""
    from stairfit.presets import PRESETS

    rows = []
    for rel in NOISE_LEVELS:
        data = noise_observations(rel)
        rows += [noise_row(p, rel, data) for p in PRESETS.values()]
    return rows


# --------------------------------------------------------------------------------------------
# Output
# --------------------------------------------------------------------------------------------


def write_csv(rows: list[Row], path: Path) -> None:
    """One row per configuration, columns as documented in COLUMNS."""
    names = [f.name for f in fields(Row)]
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(names)
        for r in rows:
            w.writerow(["" if getattr(r, n) is None else _csv_value(getattr(r, n)) for n in names])


def _csv_value(x: Any) -> str:
    return f"{x:.6g}" if isinstance(x, float) else str(x)


def _g(x: float | None, fmt: str = ".2g") -> str:
    return "" if x is None else format(x, fmt)


def _ms(x: float | None) -> str:
    if x is None:
        return ""
    return f"{x * 1e3:.3g} ms" if x < 1 else f"{x:.3g} s"


def markdown(rows: list[Row], st: Settings, ref_note: str, elapsed: float) -> str:
    """The tables of tradeoff.md."""
    by = {g: [r for r in rows if r.group == g] for g in dict.fromkeys(r.group for r in rows)}
    out = [
        "# Speed and accuracy: measured trade of every knob" + (" (quick run)" if st.quick else ""),
        "",
        "Generated by `python benchmarks/bench_tradeoff.py"
        + (" --quick" if st.quick else "")
        + f"` in {elapsed / 60:.1f} min; medians of {st.repeats}+ repeats after compilation, "
        "compilation apart. Cases, references and columns: the script's docstring and "
        "`tradeoff.csv`. Material `pla-bodurov2016`, light 5 deg and face 3 deg wide, truth "
        "sigma 6 deg, delta_n 0.05, scale 2, 2% noise. Times depend on the machine's load (2 "
        "cores here); ratios within one table are comparable. "
        f"Model {ref_note}.",
        "",
    ]
    if "preset" in by:
        out += [
            "## Presets (app/presets.py)",
            "",
            "| preset | spectral | aperture nodes | dtype (figures) | starts | tau_factor "
            "| model error (max rel / noise) | fit bias / z rms (seeds) | LS fit | LS compile "
            "| posterior | posterior MC err | other |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
        ]
        for r in by["preset"]:
            out.append(
                f"| **{r.config}** | {r.spectral} | {r.aperture_nodes} | {r.dtype} | "
                f"{r.n_starts} | {r.tau_factor:g} | {_g(r.model_err_rel)} / "
                f"{_g(r.model_err_noise)} | {_g(r.fit_bias_z)} / {_g(r.fit_z_rms)} "
                f"({r.n_seeds}) | {_ms(r.time_s)} | {_ms(r.compile_s)} | {_ms(r.post_s)} "
                f"({r.post_steps} steps) | {_g(r.post_mc_err)} | {r.note} |"
            )
        out.append("")
    if "noise" in by:
        out += noise_table(by["noise"])
    titles = {
        "model": "## Model evaluation: spectral sampling x aperture nodes x dtype",
        "fit": "## Least-squares fit (sharp+delta_n): spectral sampling x aperture nodes",
        "starts": "## Number of least-squares starts",
        "baseline": "## Baseline: NumPy + scipy.optimize.least_squares (point aperture)",
        "diffuse": "## Diffuse integral nodes",
        "rounded": "## Rounded-edge resolution (model error only)",
        "posterior": "## Posterior chain length",
    }
    cols = {
        "model": ["config", "model_err_rel", "model_err_noise", "time_s", "compile_s"],
        "fit": ["config", "fit_bias_z", "fit_z_rms", "fit_z_max", "n_seeds", "time_s", "compile_s"],
        "starts": ["config", "fit_bias_z", "fit_z_rms", "fit_z_max", "time_s"],
        "baseline": ["config", "time_s", "note"],
        "diffuse": ["config", "model_err_rel", "time_s", "compile_s", "note"],
        "rounded": ["config", "model_err_rel", "time_s", "compile_s", "note"],
        "posterior": [
            "config",
            "post_steps",
            "post_mc_err",
            "fit_z_rms",
            "fit_z_max",
            "time_s",
            "compile_s",
            "note",
        ],
    }
    for g, title in titles.items():
        if g not in by:
            continue
        c = cols[g]
        out += [title, "", "| " + " | ".join(c) + " |", "|" + "---|" * len(c)]
        for r in by[g]:
            cells = []
            for n in c:
                x = getattr(r, n)
                cells.append(
                    _ms(x)
                    if n.endswith("_s")
                    else _g(x)
                    if isinstance(x, float)
                    else ""
                    if x is None
                    else str(x)
                )
            out.append("| " + " | ".join(cells) + " |")
        out.append("")
    out += ["## Columns", ""] + [f"* `{k}`: {v}" for k, v in COLUMNS.items()] + [""]
    return "\n".join(out)


def noise_table(rows: list[Row]) -> list[str]:
    """The presets at three noise levels (errors only, no times)."""
    out = [
        "## Presets x noise level (numerical error at the optimum; no timing)",
        "",
        "Standard scene, `sharp+delta_n`, data simulated with the reference knobs. `rms / se`: "
        "`fitting.numerical_error` against the converged reference (5 nm, "
        f"{REF_APERTURE_NODES} nodes), what the accuracy check compares with "
        "`fitting.ACCURACY_LIMIT` = 0.2; `max / median se`: the largest difference over the "
        "median standard error; `bias`: max |fit - truth| / stderr on noiseless data with that "
        "noise level's errors; `check`: what `stairfit fit` does (its reference is the accurate "
        "preset's knobs).",
        "",
        "| preset | noise | of peak | rms / se | max / median se | bias (se) | check | note |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        out.append(
            f"| {r.config.split(' at ')[0]} | {100 * (r.noise or 0):g}% | {_g(r.model_err_rel)} "
            f"| {_g(r.num_err_rms)} | {_g(r.num_err_max_median_se)} | {_g(r.fit_bias_z)} "
            f"| {r.refine} | {r.note} |"
        )
    return [*out, ""]


PRESET_COLOURS = {"fast": "tab:green", "balanced": "tab:orange", "accurate": "tab:red"}


def read_csv(path: Path) -> list[Row]:
    """Rows back from tradeoff.csv (for `--replot`)."""
    types = {f.name: f.type for f in fields(Row)}
    rows = []
    with path.open() as fh:
        for rec in csv.DictReader(fh):
            kw: dict[str, Any] = {}
            for k, v in rec.items():
                t = str(types[k])
                if v == "":
                    kw[k] = None if "None" in t else ""
                elif t.startswith("int"):
                    kw[k] = int(v)
                elif t.startswith("float"):
                    kw[k] = float(v)
                else:
                    kw[k] = v
            rows.append(Row(**kw))
    return rows


def pareto_front(points: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """Non-dominated points (less time and less error), sorted by time."""
    front, best = [], math.inf
    for t, e in sorted(points):
        if e < best:
            front.append((t, e))
            best = e
    return front


def plot(rows: list[Row], path: Path) -> None:
    """Error against time, one panel per kind of error, Pareto fronts, presets marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [
        ("model", "model_err_rel", "model evaluation (figure grid)", "max |error| / max value"),
        ("fit", "fit_bias_z", "least-squares fit (standard scene)", "max |bias| / stderr"),
        ("diffuse", "model_err_rel", "diffuse integral / rounded model", "max |error| / max value"),
        ("posterior", "post_mc_err", "posterior", "MC error of a mean / sd"),
    ]
    fig, axes = plt.subplots(2, 2, figsize=(11, 8.5))
    presets = [r for r in rows if r.group == "preset"]
    for ax, (group, ecol, title, ylabel) in zip(axes.ravel(), panels, strict=True):
        groups = (
            [group, "starts"]
            if group == "fit"
            else [group, "rounded"]
            if group == "diffuse"
            else [group]
        )
        for g, marker in zip(groups, ("o", "s"), strict=False):
            pts = [
                (r.time_s, max(getattr(r, ecol), 1e-17), r.config)
                for r in rows
                if r.group == g and getattr(r, ecol) is not None
            ]
            if not pts:
                continue
            ax.scatter([p[0] for p in pts], [p[1] for p in pts], marker=marker, label=g, s=22)
            for t, e, lab in pts:
                ax.annotate(lab, (t, e), fontsize=6, xytext=(3, 2), textcoords="offset points")
            front = pareto_front([(p[0], p[1]) for p in pts])
            ax.step(
                [p[0] for p in front], [p[1] for p in front], where="post", lw=0.8, color="grey"
            )
        for r in presets:
            x = r.post_s if group == "posterior" else r.time_s
            y = None if group == "diffuse" else getattr(r, ecol)
            if x is not None and y is not None:
                ax.scatter(
                    [x],
                    [max(y, 1e-17)],
                    marker="*",
                    s=160,
                    edgecolor="k",
                    zorder=5,
                    color=PRESET_COLOURS.get(r.config, "k"),
                    label=f"preset {r.config}",
                )
        ax.set(
            xscale="log",
            yscale="log",
            xlabel="wall time after compilation (s)",
            ylabel=ylabel,
            title=title,
        )
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def merge_noise_rows(out_dir: Path, st: Settings, elapsed: float) -> None:
    """`--noise-only`: the noise axis measured now, every other row kept from tradeoff.csv
    (whose tables keep the full run's header; a line says which rows are new)."""
    import datetime

    t0 = time.perf_counter()
    old = [r for r in read_csv(out_dir / "tradeoff.csv") if r.group != "noise"]
    rows = old + noise_rows()
    write_csv(rows, out_dir / "tradeoff.csv")
    md = out_dir / "tradeoff.md"
    head = md.read_text().split("\n## ", 1)[0].rstrip() if md.exists() else ""
    day = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d")
    stamp = (
        f"The noise-axis rows were measured on {day} by `python benchmarks/bench_tradeoff.py "
        f"--noise-only` ({(time.perf_counter() - t0 + elapsed) / 60:.1f} min, errors only); "
        "every other row and time is from the full run above."
    )
    body = markdown(rows, st, "", 0.0).split("\n## ", 1)[1]
    md.write_text(f"{head}\n\n{stamp}\n\n## {body}")
    plot(rows, out_dir / "tradeoff_pareto.png")


def main() -> None:
    """Command line entry."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="short run (< 3 min) for notebooks/tests")
    ap.add_argument("--seeds", type=int, default=None, help="noisy datasets per fit setting")
    ap.add_argument("--repeats", type=int, default=None, help="timed repeats (median)")
    ap.add_argument("--out-dir", type=Path, default=None, help="where to write the results")
    ap.add_argument("--replot", action="store_true", help="only redraw the plot from the csv")
    ap.add_argument(
        "--noise-only",
        action="store_true",
        help="measure only the noise-level axis and merge it into the existing tradeoff.csv",
    )
    args = ap.parse_args()
    jax.config.update("jax_enable_x64", True)
    st = settings_for(args.quick, args.seeds, args.repeats)
    here = Path(__file__).resolve().parent / "results"
    out_dir = args.out_dir or (here / "quick" if st.quick else here)
    out_dir.mkdir(parents=True, exist_ok=True)
    if args.replot:
        plot(read_csv(out_dir / "tradeoff.csv"), out_dir / "tradeoff_pareto.png")
        return
    t0 = time.perf_counter()

    def log(msg: str) -> None:
        print(f"[{time.perf_counter() - t0:6.0f} s] {msg}", flush=True)

    if args.noise_only:
        merge_noise_rows(out_dir, st, time.perf_counter() - t0)
        log(f"noise axis merged into {out_dir}")
        return

    rows, ref_note = model_rows(st)
    log("model grid done")
    rows += diffuse_rows(st)
    log("diffuse done")
    if st.resolutions:
        rows += rounded_rows(st)
        log("rounded done")
    case = fit_case(st.seeds)
    log("synthetic data done")
    f_rows, _ = fit_rows(st, case)
    rows += f_rows
    log("fits done")
    if not st.quick:
        rows += start_rows(st, case)
        log("starts done")
    rows += baseline_rows(st, case, f_rows)
    log("baseline done")
    rows += posterior_rows(st, case)
    log("posterior done")
    if st.presets:
        rows = preset_rows(st, case, rows) + rows
        log("presets done")
    rows += noise_rows()
    log("noise axis done")
    write_csv(rows, out_dir / "tradeoff.csv")
    text = markdown(rows, st, ref_note, time.perf_counter() - t0)
    (out_dir / "tradeoff.md").write_text(text)
    plot(rows, out_dir / "tradeoff_pareto.png")
    print(text)
    log(f"wrote {out_dir}")


if __name__ == "__main__":
    main()
