"""The `when_needed` presets fit the rounded rungs only when the sharp variants misfit
(stairfit.fit.rounding_needed; README "Speed and accuracy")."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from stairfit import fitting
from stairfit.fit import _rounded_not_fitted, rounding_needed


def _selection(chi2: float, dof: int, model_error: float | None = None) -> SimpleNamespace:
    names = ("sigma_rad", "scale") + (("model_error_frac",) if model_error is not None else ())
    est = {"model_error_frac": SimpleNamespace(value=model_error)}
    fit = SimpleNamespace(chi2=chi2, dof=dof, names=names, estimate=lambda n: est[n])
    return SimpleNamespace(fit=fit, chosen="sharp")


def test_a_good_sharp_fit_skips_the_rounded_rungs() -> None:
    needed, why = rounding_needed(_selection(chi2=100.0, dof=100))
    assert not needed and "describes the data" in why


def test_a_needed_model_error_term_triggers_them() -> None:
    needed, why = rounding_needed(_selection(chi2=100.0, dof=100, model_error=0.03))
    assert needed and "model-error" in why and "3" in why


@pytest.mark.parametrize(("chi2", "expect"), [(130.0, False), (160.0, True)])
def test_the_chi2_tail_probability_decides_without_model_error(chi2, expect) -> None:
    # chi^2 with 100 dof: P(> 130) = 0.023, P(> 160) = 1.1e-4 (tables); the gate is 1e-3
    needed, _ = rounding_needed(_selection(chi2=chi2, dof=100))
    assert needed == expect


def test_not_fitted_rungs_are_listed_with_the_reason() -> None:
    rounded = [v for v in fitting.DEFAULT_LADDER if "edge_radius_um" in v.free][:2]
    sel = fitting.Selection("sharp", None, (), "'sharp' has the lowest BIC", "bic", 2.0, False, {})  # type: ignore[arg-type]
    out = _rounded_not_fitted(sel, rounded, "the best sharp variant describes the data")
    assert [r.name for r in out.table] == [v.name for v in rounded]
    assert all(r.status.startswith("not fitted") and np.isnan(r.bic) for r in out.table)
    assert out.reason.endswith("because the best sharp variant describes the data")
