"""Benchmark: least-squares fits and posteriors on the standard scene (issue 4).

The standard scene: 6 wedges (10-60 deg) x 19 viewing angles x 3 channels, theta_i = 20 deg in
every photo, ideal RGB camera under D65, PLA (Bodurov dispersion), 2% noise; the variant
`sharp+delta_n` (sigma, delta_n, scale). For each spectral sampling (K = 81 samples per channel,
or K = 1 effective wavelength) it times, in one run and after compilation (reported apart):

* `stairfit.fitting.fit_least_squares` with LevenbergMarquardt, Dogleg and GaussNewton, with the
  default 4-start multi-start and with a single start;
* `scipy.optimize.least_squares` (trf, 2-point finite-difference Jacobian) on the plain NumPy
  model `benchmarks/numpy_staircase.py` with the same parameterisation, data and starts;
* the posterior (`sample_posterior`, 32 walkers, run until 50 tau): independent samples per
  second (n_walkers x (n_steps - burn-in) / tau / sampling time).

Optionally (`--calibration N`) it checks the coverage of the least-squares intervals on N small
synthetic datasets and of the posterior intervals on N / 5 of them (the long versions of the
calibration tests in tests/fitting/test_least_squares.py and tests/fitting/test_posterior.py).

    python benchmarks/bench_fit.py [--repeats 7] [--sampling both] [--calibration 0] [--out f.md]
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import jax
import numpy as np
from scipy.optimize import least_squares as scipy_least_squares

sys.path.insert(0, str(Path(__file__).resolve().parent))
import numpy_staircase as nps
from _timing import fmt_ms, median_seconds

DEG = np.pi / 180
TRUTH = {"sigma_rad": 6 * DEG, "delta_n": 0.05, "scale": 2.0}
SOLVER_NAMES = {"lm": "LevenbergMarquardt", "dogleg": "Dogleg", "gauss_newton": "GaussNewton"}


def scene(sampling: str):
    """(observations, spectral setup) of the standard scene."""
    from stairfit import fitting

    spec = fitting.spectral_setup("pla-bodurov2016", sampling=sampling)
    truth = fitting.Params(**TRUTH)
    obs = fitting.simulate_observations(
        truth, fitting.standard_design(), spec, fitting.Noise(0.02), seed=1
    )
    return obs, spec


def scipy_fit(obs, spec, starts_rad: tuple[float, ...]) -> tuple[np.ndarray, float]:
    """SciPy trf + 2-point FD Jacobian on the NumPy model; best of the starts (chi^2)."""
    n = np.asarray(spec.n_base)[obs.channel_index]
    w = np.asarray(spec.weights)[obs.channel_index]

    def resid(p: np.ndarray) -> np.ndarray:
        model = nps.band_radiance(
            obs.theta_i_rad, obs.theta_o_rad, obs.beta2_rad, n + p[1], w, np.exp(p[0]),
            np.exp(p[2]),
        )  # fmt: skip
        return (obs.value - model) / obs.stderr

    best = None
    for s in starts_rad:
        # same start as stairfit: the linear least-squares scale for the starting width
        m1 = nps.band_radiance(obs.theta_i_rad, obs.theta_o_rad, obs.beta2_rad, n, w, s, 1.0)
        wt = 1 / obs.stderr**2
        scale0 = float(np.sum(wt * m1 * obs.value) / np.sum(wt * m1 * m1))
        sol = scipy_least_squares(resid, np.array([np.log(s), 0.0, np.log(scale0)]),
                                  method="trf", jac="2-point")  # fmt: skip
        chi2 = float(2 * sol.cost)
        if best is None or chi2 < best[1]:
            best = (sol.x, chi2)
    return best


def run_fits(sampling: str, repeats: int) -> tuple[list[tuple[str, ...]], object]:
    """Rows for one spectral sampling, and the LM fit (for the posterior)."""
    from stairfit import fitting

    obs, spec = scene(sampling)
    v = fitting.variant("sharp+delta_n", "delta_n")
    starts = fitting.DEFAULT_SIGMA_STARTS_RAD
    one = (starts[2],)  # 10 deg
    rows = []
    k = spec.n_samples
    results = {}
    for solver in SOLVER_NAMES:
        t0 = time.perf_counter()
        fit = fitting.fit_least_squares(obs, spec, v, solver=solver)
        first = time.perf_counter() - t0
        t_multi = median_seconds(lambda s=solver: fitting.fit_least_squares(obs, spec, v, solver=s),
                                 repeats)  # fmt: skip
        t_one = median_seconds(
            lambda s=solver: fitting.fit_least_squares(obs, spec, v, solver=s,
                                                       sigma_starts_rad=one), repeats
        )  # fmt: skip
        results[solver] = (fit, first, t_multi, t_one)
    t_sp_one = median_seconds(lambda: scipy_fit(obs, spec, one), max(3, repeats // 2))
    t_sp_multi = median_seconds(lambda: scipy_fit(obs, spec, starts), max(3, repeats // 2))
    _, chi2_sp_multi = scipy_fit(obs, spec, starts)
    lm = results["lm"][0]
    # both reach the same optimum before any time is compared
    assert abs(chi2_sp_multi - lm.chi2) < 1e-6 * lm.chi2 + 1e-6, (chi2_sp_multi, lm.chi2)
    tag = f"K={k}"
    for solver, (fit, first, t_multi, t_one) in results.items():
        assert abs(fit.chi2 - lm.chi2) < 1e-6 * lm.chi2, (solver, fit.chi2, lm.chi2)
        rows.append((tag, f"stairfit {SOLVER_NAMES[solver]}", fmt_ms(t_multi), fmt_ms(t_one),
                     f"{t_sp_multi / t_multi:.1f}x / {t_sp_one / t_one:.1f}x",
                     f"first call {first:.2f} s (compile); {fit.num_steps} steps"))  # fmt: skip
    rows.append(
        (
            tag,
            "SciPy trf + FD Jacobian (NumPy model)",
            fmt_ms(t_sp_multi),
            fmt_ms(t_sp_one),
            "1x",
            f"chi2 {chi2_sp_multi:.2f} = stairfit {lm.chi2:.2f}",
        )
    )
    return rows, lm


def run_posterior(fit) -> tuple[str, ...]:
    """Posterior throughput on one LS fit: compile apart, then a full run to 50 tau."""
    from stairfit import fitting
    from stairfit.fitting.posterior import sample_posterior

    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", fitting.ConvergenceWarning)
        sample_posterior(fit, seed=0, chunk_steps=10, max_steps=10)
    compile_s = time.perf_counter() - t0
    post = sample_posterior(fit, seed=1)
    k = fit.problem.spectral.n_samples
    rate = post.n_independent / post.sampling_s
    return (
        f"K={k}",
        f"emcee, {post.n_walkers} walkers, to 50 tau",
        f"{post.elapsed_s:.2f} s",
        f"{post.n_independent:.0f} independent samples",
        f"{rate:.0f} /s",
        f"tau_max {post.tau_max:.0f} steps, {post.n_steps} steps, acceptance "
        f"{post.acceptance_fraction:.2f}, compile {compile_s:.2f} s, converged {post.converged}",
    )


def run_calibration(n_sets: int) -> list[tuple[str, str, str]]:
    """Coverage of LS intervals (n_sets datasets) and posterior intervals (n_sets // 5)."""
    from stairfit import fitting
    from stairfit.fitting.posterior import sample_posterior

    spec = fitting.spectral_setup("pla", sampling="effective", channels=(1,))
    design = fitting.Design((20.0, 45.0), (20.0,) * 9, tuple(np.linspace(-80, 80, 9)),
                            channels=(0,))  # fmt: skip
    truth = fitting.Params(sigma_rad=8 * DEG, delta_n=0.02, scale=1.0, floor=0.003)
    t = np.array([truth.sigma_rad, truth.delta_n, truth.scale, truth.floor])
    v = fitting.variant("dn_floor", "delta_n", "floor")
    ls68, ls95, po68, po95 = [], [], [], []
    for k in range(n_sets):
        obs = fitting.simulate_observations(truth, design, spec, fitting.Noise(0.02), 10_000 + k)
        fit = fitting.fit_least_squares(obs, spec, v, emit_warnings=False)
        z = np.abs(fit.values - t) / fit.stderrs
        ls68.append(z < 1.0)
        ls95.append(z < 1.959964)
        if k < n_sets // 5:
            post = sample_posterior(fit, seed=k, emit_warnings=False)
            po68.append((post.p16 <= t) & (t <= post.p84))
            po95.append((post.p2_5 <= t) & (t <= post.p97_5))
    rows = [(f"least squares, {n_sets} datasets x 4 parameters",
             f"{np.mean(ls68):.1%}", f"{np.mean(ls95):.1%}")]  # fmt: skip
    if po68:
        rows.append((f"posterior, {len(po68)} datasets x 4 parameters",
                     f"{np.mean(po68):.1%}", f"{np.mean(po95):.1%}"))  # fmt: skip
    return rows


def main() -> None:
    """Command line entry."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--repeats", type=int, default=7, help="timed repeats (median)")
    ap.add_argument("--sampling", choices=["full", "effective", "both"], default="both")
    ap.add_argument("--no-posterior", action="store_true", help="skip the posterior timing")
    ap.add_argument(
        "--calibration",
        type=int,
        default=0,
        metavar="N",
        help="also check interval coverage on N small datasets (N/5 posteriors)",
    )
    ap.add_argument("--out", type=Path, default=None, help="also write the tables here (markdown)")
    args = ap.parse_args()
    jax.config.update("jax_enable_x64", True)
    samplings = ["full", "effective"] if args.sampling == "both" else [args.sampling]
    fit_rows, post_rows = [], []
    for s in samplings:
        rows, lm = run_fits(s, args.repeats)
        fit_rows += rows
        if not args.no_posterior:
            post_rows.append(run_posterior(lm))
    text = (
        "Least squares, standard scene (342 rows; sigma, delta_n, scale); medians of "
        f"{args.repeats} runs after compilation\n\n"
        "| spectral sampling | solver | 4 starts (default) | 1 start | SciPy / stairfit "
        "(4 / 1 starts) | note |\n|---|---|---|---|---|---|\n"
        + "\n".join("| " + " | ".join(r) + " |" for r in fit_rows)
    )
    if post_rows:
        text += (
            "\n\nPosterior, same scene and fit\n\n| spectral sampling | sampler | wall time "
            "| independent samples | per second of sampling | note |\n|---|---|---|---|---|---|\n"
            + "\n".join("| " + " | ".join(r) + " |" for r in post_rows)
        )
    if args.calibration > 0:
        rows = run_calibration(args.calibration)
        text += (
            "\n\nInterval coverage (small scene: 2 wedges x 9 views x 1 channel, 2% noise)\n\n"
            "| intervals | 68% coverage | 95% coverage |\n|---|---|---|\n"
            + "\n".join("| " + " | ".join(r) + " |" for r in rows)
        )
    print(text)
    if args.out:
        args.out.write_text(text + "\n")


if __name__ == "__main__":
    main()
