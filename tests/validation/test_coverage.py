"""Interval coverage on data the fit was not tuned to (issue 13): benchmarks/bench_coverage.py's
statistics, its quick run, and (slow) smaller versions of its two levels judged against the same
binomial limits: Observations datasets on a design unlike the standard one, and photo folders
of the second renderer (tests/independent_photos.py) fitted through the stages of `stairfit fit`.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import bench_coverage as bc


@pytest.mark.parametrize(("k", "n"), [(0, 10), (3, 10), (10, 10), (136, 200), (190, 200), (1, 50)])
@pytest.mark.parametrize("confidence", [0.95, 0.99])
def test_clopper_pearson_is_the_exact_binomial_interval(k: int, n: int, confidence: float) -> None:
    """Its ends are the Beta quantiles of the definition, and the binomial tail at each end is
    alpha / 2 (the property that defines the interval, checked with scipy.stats.binom)."""
    lo, hi = bc.clopper_pearson(k, n, confidence)
    a = 1.0 - confidence
    want_lo = 0.0 if k == 0 else stats.beta.ppf(a / 2, k, n - k + 1)
    want_hi = 1.0 if k == n else stats.beta.ppf(1 - a / 2, k + 1, n - k)
    assert lo == pytest.approx(want_lo, abs=1e-12)
    assert hi == pytest.approx(want_hi, abs=1e-12)
    if k > 0:
        assert stats.binom.sf(k - 1, n, lo) == pytest.approx(a / 2, rel=1e-8)
    if k < n:
        assert stats.binom.cdf(k, n, hi) == pytest.approx(a / 2, rel=1e-8)


def test_clopper_pearson_closed_form_at_zero_successes() -> None:
    """k = 0: the upper end is 1 - (alpha/2)^(1/n); 0 of 10 at 95% gives 0.3085 (the textbook
    value)."""
    assert bc.clopper_pearson(0, 10, 0.95) == pytest.approx((0.0, 1 - 0.025**0.1), abs=1e-12)
    assert bc.clopper_pearson(0, 10, 0.95)[1] == pytest.approx(0.3085, abs=5e-5)
    with pytest.raises(ValueError):
        bc.clopper_pearson(11, 10)


def test_coverage_cell_flags_coverage_outside_its_limits() -> None:
    """200 datasets: 136 hits (68%) are consistent with 68.27%, 110 (55%) and 160 (80%) are
    not; 190 (95%) are consistent with 95%, 175 (87.5%) are not."""

    def cell(k: int, nominal: float) -> dict:
        return bc.coverage_cell([True] * k + [False] * (200 - k), nominal)

    assert cell(136, 0.6827)["ok"]
    assert not cell(110, 0.6827)["ok"]
    assert not cell(160, 0.6827)["ok"]
    assert cell(190, 0.95)["ok"]
    assert not cell(175, 0.95)["ok"]
    c = cell(136, 0.6827)
    assert (c["n"], c["k"], c["coverage"]) == (200, 136, 0.68)


def test_least_squares_intervals_hold_the_truth_within_z_standard_errors() -> None:
    assert bc.ls_hits(1.0, 0.5, 1.6) == {"68": False, "95": True}
    assert bc.ls_hits(1.0, 0.5, 1.4) == {"68": True, "95": True}
    assert bc.ls_hits(1.0, 0.5, 2.0) == {"68": False, "95": False}


def test_pull_and_chi2_summaries_on_known_distributions() -> None:
    """Standard normal pulls give mean 0 and sd 1; chi^2 draws of 50 dof give reduced chi^2 of
    mean 1 and sd 0.2 and a uniform tail probability (KS p not small); chi^2 inflated by 30%
    is detected."""
    rng = np.random.default_rng(3)
    p = bc.pull_summary(rng.standard_normal(4000))
    assert abs(p["mean"]) < 4 * p["mean_se"]
    assert abs(p["sd"] - 1) < 4 * p["sd_se"]
    chi2 = stats.chi2.rvs(50, size=1000, random_state=rng)
    ok = bc.chi2_summary(chi2, [50] * 1000)
    assert ok["mean"] == pytest.approx(1.0, abs=0.03)
    assert ok["sd"] == pytest.approx(0.2, rel=0.1)
    assert ok["expected_sd"] == pytest.approx(0.2)
    assert ok["ks_p"] > 1e-3
    assert bc.chi2_summary(1.3 * chi2, [50] * 1000)["ks_p"] < 1e-6


def test_the_quick_run_writes_consistent_results(tmp_path: Path) -> None:
    """bench_coverage's own run, cut to one design and noise level (2 datasets; no posterior and
    no photos, to stay within the default suite's 20 s): coverage.json and coverage.md are
    written and every cell counts what the datasets gave."""
    args = "--quick --datasets 2 --posterior 0 --photos 0 --designs standard --noise 0.02"
    bc.main([*args.split(), "--out-dir", str(tmp_path)])
    summary = json.loads((tmp_path / "coverage.json").read_text())
    cell = summary["observations"]["standard"]["0.02"]
    assert cell["n_datasets"] == 2
    assert set(cell["ls"]) == {"sigma_rad", "delta_n", "scale", "floor"}
    for p, c in cell["ls"].items():
        fitted = 2 - cell["n_failed"]  # a collapsed fit lacks the parameter it fixed
        assert fitted - cell["n_collapsed"] <= c["68"]["n"] <= fitted, p
        assert c["68"]["k"] <= c["95"]["k"]  # a 95% interval holds whatever the 68% one holds
    assert cell["posterior"] == {}
    assert cell["reduced_chi2"]["n"] == 2 - cell["n_failed"]
    assert 0 <= cell["chosen_true"] <= 1
    text = (tmp_path / "coverage.md").read_text()
    assert "## Observations level: least squares" in text
    assert "## Cells outside their binomial limits" in text


# --- slow: smaller versions of the benchmark's two levels ---------------------------------------


def _ls_records(design: object, rel: float, n: int) -> list[dict]:
    import warnings

    from stairfit import fitting

    spec = fitting.spectral_setup(bc.MATERIAL, sampling="effective")
    out = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", fitting.FitWarningCategory)
        for s in range(n):
            obs = bc.simulate(design, spec, rel, 50_000 + s)
            fit = fitting.fit_least_squares(obs, spec, bc.true_variant(), emit_warnings=False)
            out.append({"ls": bc.fit_record(fit)})
    return out


@pytest.mark.slow
def test_least_squares_coverage_on_a_design_we_did_not_tune_to() -> None:
    """200 datasets of bench_coverage's custom design (5 other wedges, two lights, 16 other
    views) at 0.5% noise, the true variant: every parameter's 68% and 95% intervals cover the
    truth within the 99% Clopper-Pearson limits of 200 datasets (seeds other than the
    benchmark's)."""
    recs = _ls_records(bc.custom_design(), 0.005, 200)
    cells = bc.summarise_cells(recs, "ls", {k: v[1] for k, v in bc.LEVELS.items()})
    assert set(cells) == {"sigma_rad", "delta_n", "scale", "floor"}
    bad = [
        (p, lev, c[lev]["coverage"])
        for p, c in cells.items()
        for lev in bc.LEVELS
        if not c[lev]["ok"]
    ]
    assert not bad, bad


@pytest.fixture(scope="module")
def photo_cells() -> dict:
    """10 folders of the independent renderer (its default round 0.6-deg light; seeds 200-209,
    not the benchmark's), each measured and fitted through the stages of `stairfit fit`; the
    coverage cells of sigma, scale and floor."""
    import jax

    jax.config.update("jax_enable_x64", True)
    recs = [{"ls": bc.photo_dataset(200 + k, bc.PHOTO_LIGHTS["disk 0.6 deg"])} for k in range(10)]
    failed = [r["ls"] for r in recs if "failed" in r["ls"]]
    recs = [r for r in recs if "failed" not in r["ls"]]  # test_every_photo_set_is_fitted
    # ROIs large enough that few_blocks is rare (and flagged rows are left out, as in the CLI):
    # the benchmark's 40 sets had 15 of 7200 rows flagged, seeds 200-209 have 19 of 1800
    flagged, rows = sum(r["ls"]["flagged"] for r in recs), sum(r["ls"]["rows"] for r in recs)
    assert flagged <= 0.02 * rows, [r["ls"]["flags"] for r in recs]
    cells = bc.summarise_cells(recs, "ls", {k: v[1] for k, v in bc.LEVELS.items()})
    return {"cells": cells, "failed": failed}


@pytest.mark.slow
def test_photo_level_coverage_of_scale_and_floor(photo_cells: dict) -> None:
    """Scale and floor from 10 independent photo sets: 68% and 95% intervals within the 99%
    Clopper-Pearson limits of 10 datasets (benchmark, 20 sets with the round light: scale 75% /
    90%, floor 60% / 90%)."""
    for p in ("scale", "floor"):
        for lev in bc.LEVELS:
            cell = photo_cells["cells"][p][lev]
            assert cell["ok"], (p, lev, cell)


@pytest.mark.slow
def test_photo_level_coverage_of_sigma(photo_cells: dict) -> None:
    """sigma from 10 independent photo sets: 68% and 95% intervals within the 99%
    Clopper-Pearson limits of 10 datasets. It failed (pull mean -3.4) while the fit averaged
    every ROI over its whole face's viewing spread; with each ROI's `view_spread` it passes.
    The benchmark's 20 sets with this round light still fail (pull mean -1.53, 95% coverage
    65%; the point light passes, -0.64): n = 10 has wider limits than that residual bias."""
    for lev in bc.LEVELS:
        cell = photo_cells["cells"]["sigma_rad"][lev]
        assert cell["ok"], (lev, cell)


@pytest.mark.slow
def test_every_photo_set_is_fitted(photo_cells: dict) -> None:
    """Every one of the 10 photo sets is fitted (`stairfit fit` would stop on any that is not);
    the coverage tests above use the ones that are. Seed 202 used to stop with
    nonlinear_max_steps_reached after whitening (a 2.7e-5 model-error term slows LM); the best
    start now continues (`fitting._core.CONTINUE_ROUNDS`)."""
    assert not photo_cells["failed"], photo_cells["failed"]
