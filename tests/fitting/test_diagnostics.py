"""Posterior convergence diagnostics (issue 13): split R-hat, bulk / tail ESS and their warnings,
checked on chains whose answer is known without ArviZ (AR(1) processes, walkers stuck apart),
and arviz kept out of `import stairfit.fitting`. docs/fitting.md §5 ("Diagnostics")."""

from __future__ import annotations

import subprocess
import sys

import numpy as np

from stairfit.fitting import _diagnostics as diag


def _ar1(rng: np.random.Generator, n_steps: int, n_walkers: int, phi: float) -> np.ndarray:
    """Unit-variance AR(1) chains `(n_steps, n_walkers)`: integrated autocorrelation time
    `(1 + phi) / (1 - phi)`."""
    x = np.empty((n_steps, n_walkers))
    x[0] = rng.standard_normal(n_walkers)
    eps = rng.standard_normal((n_steps, n_walkers)) * np.sqrt(1 - phi**2)
    for t in range(1, n_steps):
        x[t] = phi * x[t - 1] + eps[t]
    return x


def _split_rhat(x: np.ndarray) -> float:
    """Classic split R-hat (Gelman et al., BDA3 §11.4) of `(n_steps, n_walkers)`, by hand."""
    half = x.shape[0] // 2
    chains = np.concatenate([x[:half], x[half : 2 * half]], axis=1)  # (n, 2 m)
    n = chains.shape[0]
    w = np.mean(np.var(chains, axis=0, ddof=1))
    b = n * np.var(np.mean(chains, axis=0), ddof=1)
    return float(np.sqrt(((n - 1) / n * w + b / n) / w))


def test_ess_follows_the_autocorrelation_time_per_parameter():
    rng = np.random.default_rng(5)
    n_steps, n_walkers, phi = 2000, 32, 0.8
    chain = np.stack(
        [_ar1(rng, n_steps, n_walkers, phi), rng.standard_normal((n_steps, n_walkers))], axis=2
    )
    d = diag.chain_diagnostics(chain, burn_in=0)
    n = n_steps * n_walkers
    tau = (1 + phi) / (1 - phi)
    # ESS = N / tau; +-15% is several times the estimator's scatter at 64000 draws. Walkers and
    # steps swapped (the axes of ArviZ's (chain, draw)) would give N for the AR(1) parameter.
    np.testing.assert_allclose(d.ess_bulk, [n / tau, n], rtol=0.15)
    # the tail ESS (of the 5% / 95% quantile indicators) of a Gaussian AR(1) lies between its
    # bulk ESS (indicators decorrelate faster than the values) and the independent case
    assert 0.85 * n / tau < d.ess_tail[0] < 0.5 * n, d.ess_tail
    assert d.ess_tail[1] > 0.8 * n, d.ess_tail
    assert np.all(d.rhat < 1.005), d.rhat
    assert diag.diagnostic_warnings(d, ("a", "b")) == ()


def test_walkers_stuck_apart_give_a_high_rhat_and_a_warning_for_that_parameter_only():
    rng = np.random.default_rng(6)
    n_steps, n_walkers = 1000, 32
    mixed = rng.standard_normal((n_steps, n_walkers))
    stuck = rng.standard_normal((n_steps, n_walkers)) + 0.04 * np.arange(n_walkers)[None, :]
    d = diag.chain_diagnostics(np.stack([mixed, stuck], axis=2), burn_in=100)
    expected = _split_rhat(stuck[100:])
    assert expected > 1.03  # the walkers' means differ by several of their standard errors
    # ArviZ's rank-normalised R-hat is the classic one on nearly Gaussian draws (the rank
    # transform distorts far-apart walkers, whose mixture is not Gaussian: kept small here)
    np.testing.assert_allclose(d.rhat[1] - 1, expected - 1, rtol=0.2)
    assert d.rhat[0] < diag.RHAT_MAX
    warned = diag.diagnostic_warnings(d, ("mixed", "stuck"))
    assert {(w.code, w.parameter) for w in warned} >= {("rhat_high", "stuck")}
    assert all(w.parameter == "stuck" for w in warned), warned
    assert "R-hat" in warned[0].message and "1.01" in warned[0].message


def test_a_short_chain_warns_about_its_effective_sample_size():
    rng = np.random.default_rng(7)
    chain = rng.standard_normal((60, 4, 1))  # 200 independent draws after burn-in: ESS about 200
    d = diag.chain_diagnostics(chain, burn_in=10)
    assert 100 < d.ess_bulk[0] < diag.ESS_MIN
    codes = [w.code for w in diag.diagnostic_warnings(d, ("x",))]
    assert "ess_low" in codes  # (R-hat of 8 half-chains of 25 draws scatters about 1.01 too)
    # too short to split: not a number, and a warning rather than silence
    tiny = diag.chain_diagnostics(chain[:3], burn_in=0)
    assert np.isnan(tiny.rhat[0])
    assert {w.code for w in diag.diagnostic_warnings(tiny, ("x",))} == {"rhat_high", "ess_low"}


def test_import_of_fitting_does_not_import_arviz():
    code = (
        "import sys, stairfit.fitting\n"
        "print(sorted(m for m in ('arviz', 'xarray', 'pandas', 'h5netcdf') if m in sys.modules))"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert run.stdout.strip() == "[]", run.stdout
