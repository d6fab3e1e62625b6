"""simulate -> fit, end to end through the CLI: the truth lies inside the posterior intervals.

Issue 6's check, with and without edge rounding. Real DNG files are written, decoded, measured
(ROIs from the scene), fitted with model selection, and sampled; the truth comes from
`truth.json`, which the fit never reads. "Inside" means within the central 99.7% posterior
interval (+-3 sd), measured from the median in units of the half-width of the 68% interval:
a pass for a correct pipeline except by a 0.3%-per-parameter chance, a failure for any bias of
a few standard errors.
"""

from __future__ import annotations

import html
import json
import os
from pathlib import Path

import pytest

from stairfit.cli import main

PULL_MAX = 3.0


def _run(tmp_path: Path, *sim_args: str, fit_args: tuple[str, ...] = ()) -> tuple[dict, dict]:
    photos = tmp_path / "photos"
    sim = ["simulate", str(photos), "--megapixels", "0.5", "--views", "9", "--quiet", *sim_args]
    assert main(sim) == 0
    out = tmp_path / "fit"
    assert main(["fit", str(photos), "-o", str(out), "--quiet", *fit_args]) == 0
    for name in ("fit_per_wedge", "residuals", "residual_pattern", "corner", "brdf_map", "colours"):
        assert (out / "figures" / f"{name}.png").is_file(), name
    assert (out / "report.html").is_file()
    truth = json.loads((photos / "truth.json").read_text())["parameters"]
    return truth, json.loads((out / "results.json").read_text())


def _pulls(truth: dict, results: dict) -> dict[str, float]:
    pulls = {}
    for rec in results["parameters"]:
        name = rec["name"]
        if name not in truth:
            continue
        po = rec["posterior"]
        half = 0.5 * (po["p84"] - po["p16"])
        pulls[name] = (po["median"] - truth[name]) / half
    return pulls


def test_sharp_scene_is_recovered(tmp_path: Path) -> None:
    truth, results = _run(tmp_path)
    chosen = results["model_selection"]["chosen"]
    assert "rounded" not in chosen and "delta_n" not in chosen, chosen
    pulls = _pulls(truth, results)
    assert {"sigma_deg", "scale"} <= set(pulls), pulls
    assert all(abs(p) < PULL_MAX for p in pulls.values()), pulls
    _check_chain_diagnostics(tmp_path / "fit", results)
    _check_observation_columns(tmp_path / "fit")
    # the sharp scene is described by its model, and the report says what became of rounding
    assert results["assessment"]["misfits"] is False, results["assessment"]["headline"]
    rounding = results["model_selection"]["rounding"]
    assert rounding["policy"] == "when_needed" and rounding["n_variants"] == 4
    page = (tmp_path / "fit" / "report.html").read_text()
    assert "does not describe the data" not in page
    assert f"Rounded edges: {html.escape(rounding['sentence'])}" in page
    # what XLA compiled with is recorded (the suite compiles as the command line does)
    assert results["xla_flags"] == os.environ.get("XLA_FLAGS", "")


def _check_observation_columns(out: Path) -> None:
    """observations.csv records what the fit's error model used: each ROI's three channel rows
    share a `roi_index` and its correlations, and every row has a viewing spread in (0, 1]
    (what benchmarks/scipy_sharp_fit.py reads to solve the same problem)."""
    import csv

    with open(out / "observations.csv", newline="") as fh:
        rows = [r for r in csv.DictReader(fh) if r["used"] == "1"]
    groups: dict[str, set] = {}
    for r in rows:
        assert 0 < float(r["view_spread"]) <= 1, r
        key = tuple(r[k] for k in ("corr_01", "corr_02", "corr_12"))
        groups.setdefault(r["roi_index"], set()).add((r["photo"], r["wedge"], key))
    assert "-1" not in groups and len(groups) >= len(rows) / 3
    assert all(len(g) == 1 for g in groups.values()), "one ROI per roi_index, one set of corr"
    assert any(float(r["view_spread"]) < 1 for r in rows)  # eroded ROIs see less than the face


def _check_chain_diagnostics(out: Path, results: dict) -> None:
    """R-hat and ESS per parameter in results.json, and chain.nc opens in ArviZ with the
    same draws (degrees for widths) and the same diagnostics."""
    import arviz as az
    import numpy as np

    post = results["diagnostics"]["posterior"]
    assert (post["rhat_max"], post["ess_min"]) == (1.01, 400)
    records = [r for r in results["parameters"] if "posterior" in r]
    idata = az.from_netcdf(out / post["inference_data_file"])
    # az.rhat / az.ess, not az.summary: on a chain with many repeated draws (a model-error term
    # at its bound, 21877 distinct values in 112736) summary's r_hat differed from az.rhat's by
    # 1.5e-6 (ArviZ 0.23.4), while ours equals az.rhat's to the last digit
    rhat, ess = az.rhat(idata), az.ess(idata, method="bulk")
    assert len(idata.posterior.data_vars) == len(records)
    for rec, var in zip(records, idata.posterior.data_vars, strict=True):
        po = rec["posterior"]
        np.testing.assert_allclose(float(rhat[var]), po["rhat"], rtol=1e-9)
        np.testing.assert_allclose(float(ess[var]), po["ess_bulk"], rtol=1e-9)
        # same draws in the same units (results.json's percentiles come from the thinned chain)
        half = 0.5 * (po["p84"] - po["p16"])
        assert abs(float(idata.posterior[var].median()) - po["median"]) < 0.1 * half, var
        # the default preset runs the chain until the field's thresholds pass
        assert po["converged"] and po["rhat"] < 1.01, po
        assert min(po["ess_bulk"], po["ess_tail"]) >= 400, po


@pytest.mark.slow  # the rounded model compiles for minutes on 2 cores
def test_rounded_scene_is_recovered(tmp_path: Path) -> None:
    truth, results = _run(tmp_path, "--edge-radius-um", "30")
    chosen = results["model_selection"]["chosen"]
    assert "rounded" in chosen, chosen
    pulls = _pulls(truth, results)
    assert "edge_radius_um" in pulls, pulls
    assert all(abs(p) < PULL_MAX for p in pulls.values()), pulls
