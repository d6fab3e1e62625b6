"""simulate -> fit, end to end through the CLI: the truth lies inside the posterior intervals.

Issue 6's check, with and without edge rounding. Real DNG files are written, decoded, measured
(ROIs from the scene), fitted with model selection, and sampled; the truth comes from
`truth.json`, which the fit never reads. "Inside" means within the central 99.7% posterior
interval (+-3 sd), measured from the median in units of the half-width of the 68% interval:
a pass for a correct pipeline except by a 0.3%-per-parameter chance, a failure for any bias of
a few standard errors.
"""

from __future__ import annotations

import json
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
    for name in ("fit_per_wedge", "residuals", "corner", "brdf_map", "colours"):
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


@pytest.mark.slow  # the rounded model compiles for minutes on 2 cores
def test_rounded_scene_is_recovered(tmp_path: Path) -> None:
    truth, results = _run(tmp_path, "--edge-radius-um", "30")
    chosen = results["model_selection"]["chosen"]
    assert "rounded" in chosen, chosen
    pulls = _pulls(truth, results)
    assert "edge_radius_um" in pulls, pulls
    assert all(abs(p) < PULL_MAX for p in pulls.values()), pulls
