"""The fitting layer's typed API: one record per parameter, estimates found by identity, options
objects, and the physical Jacobian for design studies against an independent finite difference."""

from __future__ import annotations

import numpy as np
import pytest
import zoo

from stairfit import fitting
from stairfit.fitting import _params, posterior

DEG = np.pi / 180
TRUTH = fitting.Params(sigma_rad=np.deg2rad([6.0, 9.0]), delta_n=0.02, scale=1.3, floor=0.003)


def test_every_slot_has_one_record_with_its_identity():
    lay = _params.Layout(3)
    records = lay.parameters()
    assert [p.slot for p in records] == list(range(lay.size))
    keys = [(p.param, p.wedge) for p in records]
    assert len(set(keys)) == lay.size  # no two slots share an identity
    assert keys[:4] == [("sigma_rad", None), ("sigma_rad", 0), ("sigma_rad", 1), ("sigma_rad", 2)]
    assert {p.param for p in records} == set(fitting.PARAM_NAMES)
    for p in records:
        info = fitting.PARAMETERS[fitting.PARAM_NAMES.index(p.param)]
        assert (p.unit, p.transform, p.bounds) == (info.unit, info.transform, info.bounds)
        assert lay.slot(p.param, p.wedge) == p.slot
    assert lay.kinds == tuple(p.transform for p in records)


def test_fit_records_and_estimates_are_found_by_param_and_wedge():
    obs, spec, _ = zoo.small(TRUTH, seed=4)
    v = fitting.variant("w", "delta_n", "floor", per_wedge_sigma=True)
    fit = fitting.fit_least_squares(obs, spec, v, emit_warnings=False)
    keys = [(e.param, e.wedge) for e in fit.estimates]
    assert keys == [("sigma_rad", 0), ("sigma_rad", 1), ("delta_n", None), ("scale", None),
                    ("floor", None)]  # fmt: skip
    assert [(p.param, p.wedge) for p in fit.parameters] == keys
    assert all(p.free and p.prior is not None for p in fit.parameters)
    e = fit.estimate("sigma_rad", 1)
    assert e.name == "sigma_rad[1: 45 deg]" and e.label("sigma_deg") == "sigma_deg[1: 45 deg]"
    assert e.value == fit.params.sigma_rad[1]
    assert fit.estimates[fit.index("floor")] is fit.estimate("floor")
    with pytest.raises(KeyError, match="edge_radius_um"):
        fit.estimate("edge_radius_um")
    # the posterior keeps the same records in the same order
    post = posterior.sample_posterior(fit, chunk_steps=20, max_steps=20, emit_warnings=False)
    assert [(p.param, p.wedge) for p in post.parameters] == keys
    assert post.index("sigma_rad", 1) == 1
    assert post.chain.shape == (20, post.n_walkers, len(keys))
    assert post.log_prob.shape == (20, post.n_walkers)


def test_options_objects_and_keywords_are_the_same_fit():
    obs, spec, _ = zoo.small(fitting.Params(sigma_rad=8 * DEG), seed=2)
    starts = (3 * DEG, 10 * DEG)
    opts = fitting.LeastSquaresOptions(solver="gauss_newton", sigma_starts_rad=starts)
    a = fitting.fit_least_squares(obs, spec, options=opts)
    b = fitting.fit_least_squares(obs, spec, solver="gauss_newton", sigma_starts_rad=starts)
    assert a.solver == b.solver == "gauss_newton" and a.starts_sigma_rad == pytest.approx(starts)
    np.testing.assert_array_equal(a.values, b.values)
    with pytest.raises(TypeError, match="unknown least-squares option"):
        fitting.fit_least_squares(obs, spec, solvr="lm")
    with pytest.raises(TypeError, match="unknown posterior option"):
        posterior.sample_posterior(a, max_stpes=10)


def test_model_jacobian_matches_central_differences_of_the_model():
    # The Jacobian goes through the fit's forward (grid, custom JVPs); the reference is central
    # differences of `model_radiance`, which evaluates `stairfit.model` row by row.
    obs, spec, _ = zoo.small(TRUTH, seed=1)
    keys = [("sigma_rad", 0), ("sigma_rad", 1), ("delta_n", None), ("scale", None),
            ("floor", None), ("model_error_frac", None)]  # fmt: skip
    jac = fitting.model_jacobian(TRUTH, obs, spec, keys)
    assert jac.shape == (obs.n_rows, len(keys))

    def shifted(param: str, wedge: int | None, h: float) -> fitting.Params:
        if param == "sigma_rad":
            sigma = np.array(TRUTH.sigma_rad, float)
            sigma[wedge] += h
            return TRUTH._replace(sigma_rad=sigma)
        return TRUTH._replace(**{param: getattr(TRUTH, param) + h})

    for k, (param, wedge) in enumerate(keys):
        h = 1e-6
        up = fitting.model_radiance(shifted(param, wedge, h), obs, spec)
        down = fitting.model_radiance(shifted(param, wedge, -h), obs, spec)
        fd = (up - down) / (2 * h)
        np.testing.assert_allclose(jac[:, k], fd, rtol=1e-6, atol=1e-8 * np.abs(jac).max())
    assert np.all(jac[:, -1] == 0.0)  # the model error changes the variance, not the model
    # and the Fisher information of the rows is J^T diag(1 / sd^2) J
    sd = obs.stderr
    fisher = np.asarray(fitting.fisher_information(jac[:, :-1], sd))
    np.testing.assert_allclose(fisher, (jac[:, :-1] / sd[:, None] ** 2).T @ jac[:, :-1],
                               rtol=1e-12)  # fmt: skip
