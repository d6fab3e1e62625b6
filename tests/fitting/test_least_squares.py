"""Least squares recovers known parameters with honest (calibrated) standard errors.

Synthetic data come from `stairfit.model` plus Gaussian noise with the stated standard errors
(`fitting.simulate_observations`); the fits go through the fitting layer's own forward, so a
recovered truth also checks transforms and bookkeeping [conventions §9].
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import zoo

from stairfit import fitting

DEG = np.pi / 180
FEATURES = {
    "sharp": fitting.variant("sharp"),
    "dn_floor": fitting.variant("dn_floor", "delta_n", "floor"),
    "dn": fitting.variant("dn", "delta_n"),
    "dn_sigma_w": fitting.variant("dn_sigma_w", "delta_n", per_wedge_sigma=True),
}

TRUTHS = [
    # (id, truth, variant, material, sampling)
    ("narrow", fitting.Params(sigma_rad=3 * DEG, scale=1.0), "sharp", "pla", "effective"),
    (
        "medium",
        fitting.Params(sigma_rad=8 * DEG, delta_n=0.08, scale=0.5, floor=0.003),
        "dn_floor",
        "pla",
        "effective",
    ),
    (
        "wide_overlapping",
        fitting.Params(sigma_rad=15 * DEG, delta_n=-0.06, scale=3.0, floor=0.001),
        "dn_floor",
        "pla",
        "effective",
    ),
    (
        "per_wedge",
        fitting.Params(sigma_rad=np.deg2rad([4, 5, 6, 7, 8, 10]), delta_n=0.03, scale=1.2),
        "dn_sigma_w",
        "pla",
        "effective",
    ),
    (
        "dispersive_full_spectrum",
        fitting.Params(sigma_rad=6 * DEG, delta_n=0.05, scale=2.0),
        "dn",
        "pla-bodurov2016",
        "full",
    ),
]


def _truth_vector(fit: fitting.FitResult, truth: fitting.Params) -> np.ndarray:
    out = []
    sig = truth.sigma_per_wedge(len(fit.params.sigma_rad))
    for e in fit.estimates:
        if e.param == "sigma_rad":
            out.append(sig[0 if e.wedge is None else e.wedge])
        else:
            out.append(getattr(truth, e.param))
    return np.asarray(out, float)


@pytest.mark.parametrize(("label", "truth", "vname", "material", "sampling"), TRUTHS,
                         ids=[t[0] for t in TRUTHS])  # fmt: skip
def test_least_squares_recovers_truth_within_3_sigma(label, truth, vname, material, sampling):
    spec = zoo.effective(material) if sampling == "effective" else zoo.full(material)
    obs = zoo.standard(truth, seed=11, spec=spec).obs
    with warnings.catch_warnings():
        warnings.simplefilter("error", fitting.FitWarningCategory)  # no warning expected here
        fit = fitting.fit_least_squares(obs, spec, FEATURES[vname])
    assert fit.success, fit.message
    assert set(fit.variant.free) == set(FEATURES[vname].free)  # nothing was dropped
    pulls = (fit.values - _truth_vector(fit, truth)) / fit.stderrs
    assert np.all(np.abs(pulls) < 3.0), dict(zip(fit.names, pulls, strict=True))
    assert 0.7 < fit.reduced_chi2 < 1.4  # the true model fits to within the noise


def test_least_squares_recovers_fitted_model_error():
    # Data with 5% multiplicative scatter on top of 1% measurement noise: the fitted fractional
    # model error must find it (the log-determinant residuals make least squares = max. lik.).
    obs, spec, truth = zoo.standard(fitting.Params(sigma_rad=6 * DEG, scale=1.0), 4, noise=0.01)
    clean = fitting.model_radiance(truth, obs, spec)
    rng = np.random.default_rng(4)
    value = clean * (
        1 + 0.05 * rng.standard_normal(clean.shape)
    ) + obs.stderr * rng.standard_normal(clean.shape)
    obs = obs._replace(value=value)
    fit = fitting.fit_least_squares(obs, spec, fitting.variant("me", "model_error_frac"))
    e = fit.estimate("model_error_frac")
    assert abs(e.value - 0.05) < 3 * e.stderr
    assert e.stderr < 0.01
    # without the term, chi^2 is far too large; with it, the whitened residuals are ~N(0, 1)
    plain = fitting.fit_least_squares(obs, spec)
    assert plain.reduced_chi2 > 3.0
    assert 0.8 < fit.reduced_chi2 < 1.25


def test_multistart_escapes_local_minimum(monkeypatch):
    # Broad overlapping lobes (sigma = 20 deg): a start at 1 deg ends in a local minimum with a
    # far worse chi^2; the multi-start keeps the best start.
    from stairfit.fitting import _core

    truth = fitting.Params(sigma_rad=20 * DEG, delta_n=0.03, scale=1.0, floor=0.002)
    obs, spec, _ = zoo.standard(truth, seed=1)
    v = fitting.variant("dn_floor", "delta_n", "floor")
    multi = fitting.fit_least_squares(obs, spec, v)
    chi2 = np.asarray(multi.starts_chi2)
    assert multi.chi2 == pytest.approx(chi2.min(), rel=1e-9)
    assert multi.starts_sigma_rad[0] == pytest.approx(1 * DEG)
    assert chi2[0] > 10 * chi2.min()  # the 1-degree start ends in a far worse local minimum
    with monkeypatch.context() as m:
        m.setattr(_core, "DENSER_START_ROUNDS", 0)
        single = fitting.fit_least_squares(
            obs, spec, v, sigma_starts_rad=(1 * DEG,), identifiability=False
        )
    assert single.chi2 > 10 * multi.chi2  # ... which is what a single start would report
    # unless its misfit makes the fit try the widths around it (docs/fitting.md, starts)
    retried = fitting.fit_least_squares(
        obs, spec, v, sigma_starts_rad=(1 * DEG,), identifiability=False
    )
    assert retried.chi2 == pytest.approx(multi.chi2, rel=1e-6)
    assert len(retried.starts_sigma_rad) > 1
    assert abs(multi.params.sigma_rad[0] - truth.sigma_rad) < 3 * multi.estimate("sigma_rad").stderr


@pytest.fixture(scope="module")
def standard_fit_data():
    truth = fitting.Params(sigma_rad=7 * DEG, delta_n=0.04, scale=1.5, floor=0.002)
    obs, spec, _ = zoo.standard(truth, seed=8, noise=0.015)
    return obs, spec


@pytest.mark.parametrize("solver", [s for s in zoo.SOLVERS if s != "lm"])
def test_solvers_agree_with_levenberg_marquardt(standard_fit_data, solver):
    obs, spec = standard_fit_data
    v = fitting.variant("dn_floor", "delta_n", "floor")
    lm = fitting.fit_least_squares(obs, spec, v)
    other = fitting.fit_least_squares(obs, spec, v, solver=solver)
    assert other.success and other.solver == solver
    np.testing.assert_allclose(other.values, lm.values, rtol=1e-6)
    assert other.chi2 == pytest.approx(lm.chi2, rel=1e-9)


def test_covariance_and_correlation_are_consistent(standard_fit_data):
    obs, spec = standard_fit_data
    fit = fitting.fit_least_squares(obs, spec, fitting.variant("dn_floor", "delta_n", "floor"))
    cov, corr = fit.covariance, fit.correlation
    np.testing.assert_allclose(cov, cov.T, rtol=1e-12)
    assert np.all(np.linalg.eigvalsh(cov) > 0)
    np.testing.assert_allclose(np.diag(corr), 1.0, rtol=1e-12)
    assert np.all(np.abs(corr) <= 1.0 + 1e-12)
    # delta method: the physical covariance is the unconstrained one scaled by dx/dz
    # (log for sigma and scale, identity for delta_n and floor)
    d = np.array([fit.values[0], 1.0, fit.values[2], 1.0])
    np.testing.assert_allclose(cov, fit.covariance_z * np.outer(d, d), rtol=1e-12)
    # and it agrees with the inverse of a finite-difference Hessian of chi^2 / 2 (Gauss-Newton
    # neglects the residual-curvature term, small at a good fit: 5% is the stated tolerance)
    h = _fd_hessian(fit, obs, spec)
    np.testing.assert_allclose(np.sqrt(np.diag(np.linalg.inv(h))),
                               np.sqrt(np.diag(fit.covariance_z)), rtol=0.05)  # fmt: skip


def _fd_hessian(fit: fitting.FitResult, obs, spec) -> np.ndarray:
    """Central-difference Hessian of chi^2 / 2 in the free unconstrained coordinates."""
    import jax
    import jax.numpy as jnp

    from stairfit.fitting import _forward

    prob = fit.problem
    static, data = prob.static_for(fit.spec), prob.arrays_for(fit.spec)
    slots = list(fit.free_slots)

    # one compiled program for the 4 p^2 evaluations (eager calls dispatch op by op)
    residuals = jax.jit(lambda z: _forward.residuals(z, (static, data)))

    def f(t: np.ndarray) -> float:
        z = fit.z.copy()
        z[slots] = t
        r = np.asarray(residuals(jnp.asarray(z)))
        return 0.5 * float(r @ r)

    t0 = fit.z[slots]
    p = len(slots)
    step = 1e-4 * np.sqrt(np.diag(fit.covariance_z)) * 10
    hess = np.zeros((p, p))
    for i in range(p):
        for j in range(p):
            ei, ej = np.eye(p)[i] * step[i], np.eye(p)[j] * step[j]
            hess[i, j] = (f(t0 + ei + ej) - f(t0 + ei - ej) - f(t0 - ei + ej) + f(t0 - ei - ej)) / (
                4 * step[i] * step[j]
            )
    return hess


def _calibration(n_sets: int, seed0: int) -> dict[str, np.ndarray]:
    """Coverage of the LS 68% and 95% intervals over `n_sets` small synthetic datasets."""
    truth = fitting.Params(sigma_rad=8 * DEG, delta_n=0.02, scale=1.0, floor=0.003)
    v = fitting.variant("dn_floor", "delta_n", "floor")
    pulls = []
    for k in range(n_sets):
        obs, spec, _ = zoo.small(truth, seed0 + k)
        fit = fitting.fit_least_squares(obs, spec, v, emit_warnings=False)
        assert fit.success and set(fit.variant.free) == set(v.free)
        pulls.append((fit.values - _truth_vector(fit, truth)) / fit.stderrs)
    pulls = np.abs(np.asarray(pulls))
    return {"c68": np.mean(pulls < 1.0, axis=0), "c95": np.mean(pulls < 1.959964, axis=0),
            "all68": np.mean(pulls < 1.0), "all95": np.mean(pulls < 1.959964)}  # fmt: skip


@pytest.mark.slow  # 120 fits, 15 s; covered in the default suite's stead below
def test_least_squares_intervals_are_calibrated():
    """120 datasets x 4 parameters. Pooled over parameters: the issue's bounds (68% intervals
    cover 60-76%, 95% intervals 90-99%). Per parameter, 120 datasets give a binomial sd of
    4.3% (68%) and 2% (95%), so the per-parameter bounds are wider: 55-81% and 88-100%.

    Slow (issue 14): the same calibration is checked more strictly by
    `test_least_squares_intervals_are_calibrated_long` (500 datasets, slow) and by
    `benchmarks/bench_coverage.py` (1200 datasets against binomial limits); in the default
    suite `test_least_squares_recovers_truth_within_3_sigma` checks the pulls of every fit."""
    cov = _calibration(120, seed0=1000)
    assert 0.60 <= cov["all68"] <= 0.76, cov
    assert 0.90 <= cov["all95"] <= 0.99, cov
    assert np.all((cov["c68"] >= 0.55) & (cov["c68"] <= 0.81)), cov
    assert np.all(cov["c95"] >= 0.88), cov


@pytest.mark.slow
def test_least_squares_intervals_are_calibrated_long():
    # 500 datasets: per-parameter binomial sd 2.1% (68%) and 1% (95%); the bounds hold
    # for every parameter.
    cov = _calibration(500, seed0=5000)
    assert np.all((cov["c68"] >= 0.60) & (cov["c68"] <= 0.76)), cov
    assert np.all((cov["c95"] >= 0.90) & (cov["c95"] <= 0.99)), cov
