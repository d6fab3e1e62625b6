"""Issue 13's "Done when" on the demo: `stairfit demo --megapixels 2 --views 9`.

The chosen fit's reduced chi^2 must lie in [0.8, 1.25] (with each ROI's channels whitened by
their 3 x 3 covariance, docs/fitting.md §Correlated channels; 0.26 when the stderrs were
inflated instead), results.json must report split R-hat and bulk/tail ESS per parameter, and
the truth must be a plausible draw from the reported errors (a joint test at a 1e-3 false-alarm
rate; whether the errors are calibrated is a many-seed question, answered by
benchmarks/bench_demo_calibration.py). One demo run (ladder, rounded rungs and posterior: about
a minute) serves the tests of this module.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy import stats

from stairfit.cli import main


@pytest.fixture(scope="module")
def demo(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict, dict]:
    """(results.json, truth.json parameters) of one demo run."""
    out = tmp_path_factory.mktemp("demo") / "demo"
    assert main(["demo", str(out), "--megapixels", "2", "--views", "9", "--quiet"]) == 0
    results = json.loads((out / "fit" / "results.json").read_text())
    truth = json.loads((out / "photos" / "truth.json").read_text())["parameters"]
    return results, truth


@pytest.mark.slow
def test_demo_reduced_chi2_is_calibrated_and_diagnostics_reported(demo: tuple[dict, dict]) -> None:
    results, _ = demo
    ls = results["diagnostics"]["least_squares"]
    assert ls["success"]
    assert 0.8 <= ls["reduced_chi2"] <= 1.25, (ls["chi2"], ls["dof"])
    for p in results["parameters"]:
        post = p["posterior"]
        assert post["rhat"] < 1.01 and min(post["ess_bulk"], post["ess_tail"]) >= 400, p


JOINT_P_MIN = 1e-3
"""The joint test's false-alarm rate on honest errors: one seed in a thousand."""
PULL_MAX = 3.29
"""|pull| above this (two-sided 1e-3 for a standard normal) is a bias, not a draw."""


def joint_distance(results: dict, truth: dict) -> tuple[float, int, dict[str, float]]:
    """The truth's squared Mahalanobis distance from the least-squares optimum over the
    parameters with a truth (results.json's stderr and correlation matrix), their number and
    their pulls. Honest errors make it chi^2 with that many degrees of freedom."""
    names = results["correlation"]["names"]
    corr = np.asarray(results["correlation"]["matrix"], float)
    keep, pulls = [], {}
    for p in results["parameters"]:
        key = "sigma_deg" if p["parameter"] == "sigma_rad" else p["parameter"]
        if key not in truth or p["wedge"] is not None:
            continue
        ls = p["least_squares"]
        pulls[key] = (ls["value"] - truth[key]) / ls["stderr"]
        keep.append(names.index(p["name"]))
    z = np.array(list(pulls.values()))
    r = corr[np.ix_(keep, keep)]
    return float(z @ np.linalg.solve(r, z)), len(z), pulls


@pytest.mark.slow
def test_demo_truth_is_a_plausible_draw(demo: tuple[dict, dict]) -> None:
    """Seed 0's scale pull is one draw, not a bias. Over 80 seeds of the same demo
    (benchmarks/bench_demo_calibration.py, benchmarks/results/demo_calibration.md) scale's pull
    has mean -0.06 +- 0.11 and sd 0.95, and its 68% / 95% intervals cover 56 and 75 of 80,
    within their 99% Clopper-Pearson limits. Seed 0's -2.16 (least squares; -2.29 in
    posterior sd) is a 1-in-30 draw. (sigma's mean, -0.43 +- 0.10, is a small bias that the
    photos bring and model data do not; docs/fitting.md.) One seed can only reject a gross
    bias, so this test asks what one seed can answer, at a false-alarm rate of 1e-3. The
    truth's joint distance from the optimum (chi^2 with one degree of freedom per parameter,
    using the reported correlations; seed 0: 6.03 for 3, tail 0.11) must have a tail
    probability above 1e-3, and no single pull may exceed 3.29. It replaces the strict xfail
    "every truth inside its 95% interval", which calibrated errors fail on about 1 seed in 7
    (13 of those 80)."""
    results, truth = demo
    d2, k, pulls = joint_distance(results, truth)
    assert k >= 3, pulls  # sigma, scale, floor at least
    assert stats.chi2.sf(d2, k) > JOINT_P_MIN, (d2, k, pulls)
    assert all(abs(z) < PULL_MAX for z in pulls.values()), pulls
