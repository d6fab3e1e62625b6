"""Model selection chooses the variant that generated the data, at realistic noise.

The standard scene (6 wedges 10-60 deg x 19 viewing angles x 3 channels, theta_i fixed) with
1-2% relative errors [conventions §9]; the rule is in docs/fitting.md.
"""

from __future__ import annotations

import numpy as np
import pytest
import zoo

from stairfit import fitting

DEG = np.pi / 180
SHARP_LADDER = zoo.SHARP_LADDER
"""The default suite's tests use the ladder without the rounded-edge variants, because every
rounded fit costs tens of seconds (compilation) and the data here are sharp; the rounded rungs
are checked by the slow tests at the end."""


def _select(truth: fitting.Params, seed: int, noise: float, **kw) -> fitting.Selection:
    obs, spec, _ = zoo.standard(truth, seed, noise)
    kw.setdefault("ladder", SHARP_LADDER)
    return fitting.select_model(obs, spec, **kw)


@pytest.mark.parametrize(("seed", "noise"), [(0, 0.01), (1, 0.02), (2, 0.02)])
def test_selection_without_delta_n_picks_sharp(seed, noise):
    sel = _select(fitting.Params(sigma_rad=6 * DEG, scale=1.0), seed, noise)
    assert sel.chosen == "sharp", sel.report()
    assert sel.fit.names == ("sigma_rad", "scale")


@pytest.mark.parametrize(("seed", "noise"), [(3, 0.01), (4, 0.02), (5, 0.02)])
def test_selection_with_delta_n_picks_delta_n(seed, noise):
    sel = _select(fitting.Params(sigma_rad=6 * DEG, delta_n=0.05, scale=1.0), seed, noise)
    assert sel.chosen == "sharp+delta_n", sel.report()
    e = sel.fit.estimate("delta_n")
    assert abs(e.value - 0.05) < 3 * e.stderr


def test_selection_with_floor_and_per_wedge_sigma():
    truth = fitting.Params(sigma_rad=np.deg2rad([4, 5, 6, 7, 8, 10]), scale=1.0, floor=0.003)
    sel = _select(truth, seed=6, noise=0.02)
    assert sel.chosen == "sharp+floor+sigma_per_wedge", sel.report()


@pytest.mark.parametrize(
    "ladder",
    [SHARP_LADDER, pytest.param(fitting.DEFAULT_LADDER, marks=pytest.mark.slow)],
    ids=["sharp-ladder", "full-ladder"],
)
def test_selection_table_reason_and_report(ladder):
    sel = _select(
        fitting.Params(sigma_rad=6 * DEG, delta_n=0.05, scale=1.0), 7, 0.02, ladder=ladder
    )
    names = [row.name for row in sel.table]
    assert names == [v.name for v in ladder]
    chosen_row = next(r for r in sel.table if r.name == sel.chosen)
    fitted = [r for r in sel.table if r.status == "ok"]
    best = min(r.bic for r in fitted)
    assert chosen_row.bic <= best + sel.threshold
    # no variant with fewer free parameters is within the threshold
    assert all(r.bic > best + sel.threshold for r in fitted if r.n_free < chosen_row.n_free)
    assert sel.chosen in sel.reason and "BIC" in sel.reason
    text = sel.report()
    assert sel.reason in text and "sharp+delta_n+floor" in text


def test_selection_can_be_forced():
    truth = fitting.Params(sigma_rad=6 * DEG, delta_n=0.05, scale=1.0)
    sel = _select(truth, 8, 0.02, force="sharp+delta_n+sigma_per_wedge")
    assert sel.forced and sel.chosen == "sharp+delta_n+sigma_per_wedge" and len(sel.table) == 1
    assert len(sel.fit.names) == 8  # 6 widths, delta_n, scale: forced, not selected away
    assert "forced" in sel.reason
    with pytest.raises(fitting.FitInputError, match="not a variant of the ladder"):
        _select(fitting.Params(sigma_rad=6 * DEG, scale=1.0), 8, 0.02, force="nonsense")


@pytest.mark.slow  # the rounded model's Jacobian takes about a minute to compile (XLA)
@pytest.mark.parametrize(("radius_frac", "expect_rounded"), [(0.0, False), (0.3, True)])
def test_selection_with_and_without_edge_rounding(radius_frac, expect_rounded):
    # A two-rung ladder (sharp, rounded) keeps this to two rounded fits per dataset; the full
    # ladder adds the same comparison with delta_n / floor / per-wedge widths on top.
    skeleton = zoo.standard(fitting.Params(), seed=0).obs
    r_max = fitting.max_edge_radius_um(skeleton)
    truth = fitting.Params(sigma_rad=6 * DEG, scale=1.0, edge_radius_um=radius_frac * r_max)
    obs, spec, _ = zoo.standard(truth, seed=9)
    ladder = tuple(v for v in fitting.DEFAULT_LADDER if v.name in ("sharp", "rounded"))
    sel = fitting.select_model(obs, spec, ladder)
    assert (sel.chosen == "rounded") == expect_rounded, sel.report()
    assert (sel.chosen == "sharp") == (not expect_rounded), sel.report()
    if expect_rounded:
        e = sel.fit.estimate("edge_radius_um")
        assert abs(e.value - truth.edge_radius_um) < 3 * e.stderr
