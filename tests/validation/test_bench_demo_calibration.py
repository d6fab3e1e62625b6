"""benchmarks/bench_demo_calibration.py's bookkeeping (issue 13): what it reads from one
results.json and how it judges many seeds. Expected values are worked out by hand here."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import bench_demo_calibration as bdc


def results_json(scale: float, scale_se: float, post: tuple[float, ...]) -> dict:
    """A minimal results.json: sigma (deg), scale, a per-wedge sigma and the model error."""
    med, p16, p84, p2_5, p97_5 = post
    posterior = {"median": med, "p16": p16, "p84": p84, "p2_5": p2_5, "p97_5": p97_5}
    return {
        "model_selection": {"chosen": "sharp+floor"},
        "diagnostics": {"least_squares": {"reduced_chi2": 0.9, "chi2": 139.5, "dof": 155}},
        "parameters": [
            {"parameter": "sigma_rad", "wedge": None,
             "least_squares": {"value": 6.3, "stderr": 0.1}},
            {"parameter": "scale", "wedge": None,
             "least_squares": {"value": scale, "stderr": scale_se}, "posterior": posterior},
            {"parameter": "sigma_rad", "wedge": 2,
             "least_squares": {"value": 9.0, "stderr": 0.1}},
            {"parameter": "model_error_frac", "wedge": None,
             "least_squares": {"value": 2.6e-4, "stderr": 3.3e-5}},
        ],
    }  # fmt: skip


def test_seed_record_pulls_intervals_and_model_error() -> None:
    """scale 1.99e6 +- 4e3 against 2e6: pull -2.5, outside +-1 and +-1.96 se; the posterior's
    95% interval [1.9905e6, 2.0001e6] holds the truth, its 68% [1.9925e6, 1.9975e6] does not,
    its median pull (1.995e6 - 2e6) / 2.5e3 = -2; sigma in degrees (6.3 vs 6: +3); the
    per-wedge width is left out (no truth of its own); the model-error term is read."""
    res = results_json(1.99e6, 4e3, (1.995e6, 1.9925e6, 1.9975e6, 1.9905e6, 2.0001e6))
    rec = bdc.seed_record(res, {"sigma_deg": 6.0, "scale": 2e6, "floor": 4000.0})
    assert set(rec["params"]) == {"sigma_deg", "scale"}
    s = rec["params"]["scale"]
    assert s["pull"] == pytest.approx(-2.5)
    assert s["ls"] == {"68": False, "95": False}
    assert s["post"] == {"68": False, "95": True}
    assert s["post_pull"] == pytest.approx(-2.0)
    assert rec["params"]["sigma_deg"]["pull"] == pytest.approx(3.0)
    assert rec["model_error_frac"]["value"] == 2.6e-4
    assert (rec["chosen"], rec["dof"]) == ("sharp+floor", 155)


def records(pulls: list[float]) -> list[dict]:
    """Seed records with the given scale pulls (stderr 1, truth 0)."""
    return [
        {"params": {"scale": {"pull": z, "ls": {"68": abs(z) <= 1, "95": abs(z) <= 1.959964}}}}
        for z in pulls
    ]


def test_summarize_flags_a_bias_but_not_honest_pulls() -> None:
    """Ten pulls 1.5 / 2.0 / 2.5 (mean 2): 2 > 3/sqrt(10) = 0.95, flagged; none within +-1
    (0/10: the 99% Clopper-Pearson upper end 1 - 0.005^(1/10) = 0.41 < 0.68, off) and the
    three 1.5s within +-1.96 (3/10, upper end about 0.75 < 0.95, off). Alternating +-1: mean
    0, not flagged; 10/10 within +-1 (lower end 0.005^(1/10) = 0.59 <= 0.68, ok)."""
    biased = bdc.summarize(records([1.5, 2.0, 2.5, 1.5, 2.0, 2.5, 1.5, 2.0, 2.5, 2.0]))["scale"]
    assert biased["pull"]["mean"] == pytest.approx(2.0)
    assert biased["pull"]["bias_flag"]
    assert biased["ls"]["68"]["k"] == 0 and not biased["ls"]["68"]["ok"]
    assert biased["ls"]["68"]["cp_high"] == pytest.approx(1 - 0.005**0.1)
    assert biased["ls"]["95"]["k"] == 3 and not biased["ls"]["95"]["ok"]
    honest = bdc.summarize(records([1.0, -1.0] * 5))["scale"]
    assert honest["pull"]["mean"] == pytest.approx(0.0, abs=1e-12)
    assert not honest["pull"]["bias_flag"]
    assert honest["ls"]["68"]["k"] == 10 and honest["ls"]["68"]["ok"]
    assert honest["ls"]["68"]["cp_low"] == pytest.approx(0.005**0.1)
    assert 3 / math.sqrt(10) == pytest.approx(0.9487, abs=1e-4)
