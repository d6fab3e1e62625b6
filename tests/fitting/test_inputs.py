"""Bad input gives a clear message naming the row/field and the fix; failures are never success.

[conventions §1, §9]
"""

from __future__ import annotations

import numpy as np
import pytest
import zoo

from stairfit import fitting
from stairfit.fitting import FitError, FitInputError, posterior

DEG = np.pi / 180


def _arrays(n: int = 6) -> dict:
    return {
        "theta_i_rad": np.full(n, 20 * DEG),
        "theta_o_rad": np.linspace(-60, 60, n) * DEG,
        "beta2_rad": np.full(n, 30 * DEG),
        "layer_um": np.full(n, 150.0),
        "wedge_index": np.zeros(n, int),
        "channel_index": np.zeros(n, int),
        "value": np.linspace(0.1, 0.6, n),
        "stderr": np.full(n, 0.01),
    }


@pytest.mark.parametrize(
    ("field", "bad", "words"),
    [
        ("stderr", np.nan, ["row 3", "stderr", "> 0", "use=False"]),
        ("stderr", -0.01, ["row 3", "stderr", "> 0"]),
        ("stderr", 0.0, ["row 3", "stderr"]),
        ("value", np.nan, ["row 3", "value", "finite"]),
        ("theta_o_rad", 95 * DEG, ["row 3", "theta_o_rad", "[-90, 90] deg", "radians"]),
        ("theta_i_rad", np.inf, ["row 3", "theta_i_rad"]),
        ("beta2_rad", 0.0, ["row 3", "beta2_rad", "(0, 90)"]),
        ("layer_um", -1.0, ["row 3", "layer_um"]),
    ],
)
def test_invalid_row_names_row_field_and_fix(field, bad, words):
    a = _arrays()
    a[field] = a[field].astype(float)
    a[field][3] = bad
    with pytest.raises(FitInputError) as info:
        fitting.Observations.from_arrays(**a)
    for w in words:
        assert w in str(info.value), (w, str(info.value))


def test_invalid_values_in_excluded_rows_are_allowed_and_sanitised():
    a = _arrays()
    a["value"][2] = np.nan
    a["stderr"][2] = -1.0
    a["theta_o_rad"][2] = 4.0
    use = np.ones(6, bool)
    use[2] = False
    obs = fitting.Observations.from_arrays(**a, use=use)
    assert obs.n_used == 5
    assert list(obs.excluded_rows) == [2]
    assert np.all(np.isfinite(obs.value)) and np.all(obs.stderr > 0)


def test_empty_table():
    a = {k: np.asarray(v)[:0] for k, v in _arrays().items()}
    with pytest.raises(FitInputError, match="empty"):
        fitting.Observations.from_arrays(**a)
    with pytest.raises(FitInputError, match="empty"):
        fitting.Observations.from_rows([])


def test_all_rows_flagged_or_saturated():
    a = _arrays()
    with pytest.raises(
        FitInputError, match=r"all 6 observation rows are excluded \(4 saturated, 2 flagged"
    ):
        fitting.Observations.from_arrays(
            **a, use=[True, True, True, True, False, False], saturated=[1, 1, 1, 1, 0, 0]
        )


def test_saturated_rows_are_excluded_and_reported(tmp_path):
    obs, spec, _ = zoo.small(fitting.Params(sigma_rad=8 * DEG), seed=2)
    sat = obs.value > 0.8 * obs.value.max()
    obs = fitting.Observations.from_arrays(**{**obs._asdict(), "saturated": sat})
    assert not np.any(obs.use[sat])
    fit = fitting.fit_least_squares(obs, spec)
    assert fit.n_used == obs.n_rows - int(sat.sum())
    assert fit.n_saturated == int(sat.sum()) > 0
    assert set(fit.excluded_rows) == set(np.flatnonzero(sat).tolist())
    assert f"{int(sat.sum())} excluded ({int(sat.sum())} saturated)" in fit.report()
    assert np.all(fit.residuals[sat] == 0.0)


def test_mismatched_columns_and_missing_keys():
    a = _arrays()
    a["value"] = a["value"][:4]
    with pytest.raises(FitInputError, match="different lengths"):
        fitting.Observations.from_arrays(**a)
    rows = [{"theta_i_deg": 20, "theta_o_deg": 0, "wedge_deg": 30, "layer_um": 150,
             "wedge_index": 0, "channel_index": 0, "value": 0.1}]  # fmt: skip
    with pytest.raises(FitInputError, match="row 0 has no 'stderr'"):
        fitting.Observations.from_rows(rows)
    rows[0]["stderr"] = "abc"
    with pytest.raises(FitInputError, match="stderr"):
        fitting.Observations.from_rows(rows)


def test_boolean_columns_reject_strings():
    rows = [
        {"theta_i_deg": 20, "theta_o_deg": 0, "wedge_deg": 30, "layer_um": 150,
         "wedge_index": 0, "channel_index": 0, "value": 0.1, "stderr": 0.01, "use": "no"}
    ]  # fmt: skip
    with pytest.raises(FitInputError, match="use = 'no' is invalid; the column must hold booleans"):
        fitting.Observations.from_rows(rows)


def test_from_rows_converts_degrees():
    rows = [
        {"theta_i_deg": 20, "theta_o_deg": t, "wedge_deg": 30, "layer_um": 150,
         "wedge_index": 0, "channel_index": 0, "value": 0.1, "stderr": 0.01, "extra": "x"}
        for t in (-30, 0, 30)
    ]  # fmt: skip
    obs = fitting.Observations.from_rows(rows)
    np.testing.assert_allclose(obs.theta_o_rad, np.deg2rad([-30, 0, 30]))
    np.testing.assert_allclose(obs.beta2_rad, np.deg2rad(30))


def test_inconsistent_wedge_geometry():
    a = _arrays()
    a["beta2_rad"][4] = 40 * DEG
    with pytest.raises(FitInputError, match="differs from the other rows of wedge 0"):
        fitting.Observations.from_arrays(**a)


def test_channel_missing_from_spectral_setup():
    obs = fitting.Observations.from_arrays(**{**_arrays(), "channel_index": np.full(6, 2)})
    spec = zoo.grey()
    with pytest.raises(FitInputError, match="channel_index = 2 but the spectral setup has 1"):
        fitting.fit_least_squares(obs, spec)


def test_unknown_solver_variant_and_options():
    obs = fitting.Observations.from_arrays(**_arrays())
    spec = zoo.grey()
    with pytest.raises(FitInputError, match="solver"):
        fitting.fit_least_squares(obs, spec, solver="bfgs")
    with pytest.raises(FitInputError, match="unknown parameter"):
        fitting.fit_least_squares(obs, spec, fitting.Variant("x", frozenset({"sigma"})))
    with pytest.raises(FitInputError, match="fixed parameter scale"):
        fitting.fit_least_squares(obs, spec, fixed=fitting.Params(scale=-1.0))
    with pytest.raises(FitInputError, match="sampling"):
        fitting.spectral_setup("pla", sampling="coarse")
    with pytest.raises(FitInputError, match="unknown material"):
        fitting.spectral_setup("unobtainium")


@pytest.fixture(scope="module")
def small_scene():
    obs, spec, _ = zoo.small(fitting.Params(sigma_rad=8 * DEG, scale=1.0), seed=5)
    return obs, spec


def test_non_converging_fit_raises(small_scene):
    obs, spec = small_scene
    with pytest.raises(FitError, match=r"did not converge.*max_steps = 1"):
        fitting.fit_least_squares(obs, spec, max_steps=1)


def test_non_converging_fit_flagged_is_not_success(small_scene):
    obs, spec = small_scene
    with pytest.warns(fitting.ConvergenceWarning, match="did not converge"):
        fit = fitting.fit_least_squares(obs, spec, max_steps=1, on_failure="flag")
    assert not fit.success
    assert fit.covariance is None and fit.correlation is None and fit.stderrs is None
    assert all(e.stderr is None for e in fit.estimates)
    assert "NOT CONVERGED" in fit.report()
    assert np.all(np.isfinite(fit.values))  # the values are finite, but flagged as failed
    with pytest.raises(FitError, match="converged least-squares fit"):
        posterior.sample_posterior(fit)
