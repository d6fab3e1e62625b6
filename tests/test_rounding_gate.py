"""The `when_needed` policy fits the rounded rungs only when the sharp variants misfit
(`fitting.rounding_needed`, `select_model(rounded_rungs=...)`; README "Speed and accuracy")."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import zoo

from stairfit import fitting

DEG = np.pi / 180


def _selection(chi2: float, dof: int, model_error: float | None = None) -> SimpleNamespace:
    free = {"sigma_rad", "scale"} | ({"model_error_frac"} if model_error is not None else set())
    est = {"model_error_frac": SimpleNamespace(value=model_error)}
    fit = SimpleNamespace(chi2=chi2, dof=dof, variant=SimpleNamespace(free=free),
                          estimate=lambda n: est[n])  # fmt: skip
    return SimpleNamespace(fit=fit, chosen="sharp")


def test_a_good_sharp_fit_skips_the_rounded_rungs() -> None:
    needed, why = fitting.rounding_needed(_selection(chi2=100.0, dof=100))
    assert not needed and "describes the data" in why


def test_a_needed_model_error_term_triggers_them() -> None:
    needed, why = fitting.rounding_needed(_selection(chi2=100.0, dof=100, model_error=0.03))
    assert needed and "model-error" in why and "3" in why


@pytest.mark.parametrize(("chi2", "expect"), [(130.0, False), (160.0, True)])
def test_the_chi2_tail_probability_decides_without_model_error(chi2, expect) -> None:
    # chi^2 with 100 dof: P(> 130) = 0.023, P(> 160) = 1.1e-4 (tables); the gate is 1e-3
    needed, _ = fitting.rounding_needed(_selection(chi2=chi2, dof=100))
    assert needed == expect


def test_not_fitted_rungs_are_listed_with_the_reason() -> None:
    obs, spec, _ = zoo.standard(fitting.Params(sigma_rad=6 * DEG, scale=1.0), seed=1)
    ladder = tuple(zoo.LADDER[n] for n in ("sharp", "sharp+floor", "rounded", "rounded+floor"))
    sel = fitting.select_model(obs, spec, ladder, rounded_rungs="when_needed")
    rows = {r.name: r for r in sel.table}
    assert [r.name for r in sel.table] == [v.name for v in ladder]
    for name in ("rounded", "rounded+floor"):
        assert rows[name].status == fitting.Status.NOT_FITTED and np.isnan(rows[name].bic)
        assert "rounding not needed" in rows[name].status_text
    assert sel.rounding is not None and not sel.rounding.fitted and sel.rounding.n_variants == 2
    assert "describes the data" in sel.rounding.reason
    assert sel.reason.endswith(sel.rounding.reason) and "were not fitted" in sel.reason


def test_an_unknown_policy_is_refused() -> None:
    obs, spec, _ = zoo.standard(fitting.Params(sigma_rad=6 * DEG, scale=1.0), seed=1)
    with pytest.raises(fitting.FitInputError, match="rounded_rungs"):
        fitting.select_model(obs, spec, zoo.SHARP_LADDER, rounded_rungs="sometimes")
