"""`stairfit demo`'s table of recovered against true values (`report.compare_table`) matches
parameters by identity (`parameter`, `wedge`), not by display name: with one width per wedge,
every wedge's `sigma_deg[k: ...]` is compared with the one true `sigma_deg`."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from stairfit import fitting
from stairfit.report import compare_table

DEG = np.pi / 180
TRUTH = {"sigma_deg": 6.0, "delta_n": 0.0, "scale": 1.0, "floor": 0.01}


def _outcome(estimates: list[fitting.Estimate]) -> SimpleNamespace:
    fit = SimpleNamespace(estimates=estimates)
    return SimpleNamespace(selection=SimpleNamespace(fit=fit), posterior=None)


def _rows(table: str) -> dict[str, list[str]]:
    return {line.split()[0]: line.split()[1:] for line in table.splitlines()[1:]}


def test_per_wedge_widths_are_compared_with_the_true_width():
    widths = [
        fitting.Estimate("sigma_rad", k, (6.0 + d) * DEG, 0.1 * DEG, "rad", wedge_deg=w)
        for k, (w, d) in enumerate([(10.0, 0.05), (30.0, -0.5)])
    ]
    scale = fitting.Estimate("scale", None, 1.02, 0.01, "1")
    rows = _rows(compare_table(_outcome([*widths, scale]), TRUTH))
    # 6.05 +- 0.2 holds 6; 5.5 +- 0.2 does not; scale 1.02 +- 0.02 holds 1
    # name, true, recovered, 95% interval, inside?, pull (the name is "sigma_deg[0: 10 deg]")
    assert rows["sigma_deg[0:"][2:7] == ["6", "6.05", "[5.85,", "6.25]", "yes"]
    assert rows["sigma_deg[1:"][2:7] == ["6", "5.5", "[5.3,", "5.7]", "NO"]
    assert rows["scale"][:2] == ["1", "1.02"] and rows["scale"][4] == "yes"
    # sigma was fitted (per wedge), so only delta_n and floor are "not fitted"
    assert "sigma_deg" not in rows
    assert sorted(k for k, v in rows.items() if "(not" in v) == ["delta_n", "floor"]
