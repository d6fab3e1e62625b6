"""The ladder's robustness on data like the demo's (a bug found end to end).

Photos of a wedge row are mostly off-specular: the values are dominated by the diffuse floor
and the lobes are caught by a few views. The floor variant must recover the truth from the
default starts; a variant that cannot fit such data at all (no floor: its width runs off to
infinity and is unidentified) must be reported as failed in the comparison table, not abort
the whole model selection (it used to raise FitError out of `select_model`).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
import zoo

from stairfit import fitting

LADDER = zoo.LADDER
TRUTH = fitting.Params(sigma_rad=np.deg2rad(6.0), scale=2.0e6, floor=4000.0)


@pytest.fixture(scope="module")
def floor_dominated():
    spec = zoo.grey()
    # base-frame light at -10 deg, views -80 .. 20 deg: face angles as `stairfit simulate` makes
    wedges = fitting.STANDARD_WEDGES_DEG
    views = np.linspace(-80.0, 20.0, 7)
    rows = [
        {"theta_i_deg": -10.0 - b, "theta_o_deg": v + b, "beta2_deg": b, "layer_um": 150.0,
         "wedge_index": k, "channel_index": 0, "value": 1.0, "stderr": 1.0}
        for k, b in enumerate(wedges)
        for v in views
    ]  # fmt: skip
    skeleton = fitting.Observations.from_rows(rows)
    clean = fitting.model_radiance(TRUTH, skeleton, spec)
    stderr = 1e-3 * clean
    rng = np.random.default_rng(3)
    value = clean + stderr * rng.standard_normal(clean.shape)
    obs = fitting.Observations.from_rows(
        [{**r, "value": float(x), "stderr": float(e)}
         for r, x, e in zip(rows, value, stderr, strict=True)]
    )  # fmt: skip
    return obs, spec


def test_floor_dominated_data_are_fitted_from_the_default_starts(floor_dominated):
    obs, spec = floor_dominated
    fit = fitting.fit_least_squares(obs, spec, LADDER["sharp+floor"], emit_warnings=False)
    est = {e.param: e for e in fit.estimates}
    for name, true in (("sigma_rad", TRUTH.sigma_rad), ("scale", 2.0e6), ("floor", 4000.0)):
        assert abs(est[name].value - true) < 4 * est[name].stderr, name
    assert fit.chi2 < 2 * obs.n_used


def test_a_variant_that_fails_is_reported_not_fatal(floor_dominated):
    obs, spec = floor_dominated
    sel = fitting.select_model(obs, spec, (LADDER["sharp"], LADDER["sharp+floor"]))
    assert sel.chosen == "sharp+floor"
    rows = {r.name: r for r in sel.table}
    assert rows["sharp+floor"].status == "ok"
    # 'sharp' cannot describe a floor: it either fails (reported) or loses by a wide margin
    assert rows["sharp"].status != "ok" or rows["sharp"].delta > 100


def test_denser_widths_fill_the_gaps_geometrically():
    from stairfit.fitting._core import denser_widths

    every, new = denser_widths((1.0, 4.0, 16.0))
    np.testing.assert_allclose(new, (0.5, 2.0, 8.0, 32.0))
    np.testing.assert_allclose(every, (0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 32.0))


def _five_view_demo_rows(seed: int) -> tuple[fitting.Observations, fitting.Spectral]:
    """The 5-view demo's geometry (light -10 deg, views -80 .. 20 deg in the base frame, three
    channels) with about a fifth of the rows usable, as at 0.3 MP where most ROIs are flagged,
    0.2% noise: the chi^2 surface of sigma has a narrow basin at the truth."""
    spec = fitting.spectral_setup("pla", camera="Nikon 5100 (NPL)", illuminant="D65")
    rows = [(k, c, -10.0 - b, v + b, b) for v in (-80.0, -55.0, -30.0, -5.0, 20.0)
            for k, b in enumerate(fitting.STANDARD_WEDGES_DEG) for c in range(3)]  # fmt: skip
    a = np.array(rows)
    geometry = {
        "theta_i_rad": np.deg2rad(a[:, 2]),
        "theta_o_rad": np.deg2rad(a[:, 3]),
        "beta2_rad": np.deg2rad(a[:, 4]),
        "layer_um": np.full(len(a), 150.0),
        "wedge_index": a[:, 0].astype(int),
        "channel_index": a[:, 1].astype(int),
    }
    ones = np.ones(len(a))
    design = fitting.Observations.from_arrays(**geometry, value=ones, stderr=ones)
    m = np.asarray(fitting.model_radiance(TRUTH, design, spec))
    rng = np.random.default_rng(seed)
    use = rng.random(len(a)) < 0.2
    se = 0.002 * m
    obs = fitting.Observations.from_arrays(
        **geometry, value=m + se * rng.standard_normal(len(a)), stderr=se, use=use
    )
    return obs, spec


def test_when_every_start_misfits_the_widths_between_them_are_tried(monkeypatch):
    """Seed 12 of the 5-view geometry: from the balanced preset's starts 1, 4 and 12 deg alone
    no start reaches the basin of the true 6 deg and the fit fails; the denser round finds it."""
    from stairfit.fitting import _core

    obs, spec = _five_view_demo_rows(seed=12)
    starts = tuple(np.deg2rad((1.0, 4.0, 12.0)))
    v = LADDER["sharp+floor"]
    monkeypatch.setattr(_core, "DENSER_START_ROUNDS", 0)
    try:
        without = fitting.fit_least_squares(obs, spec, variant=v, sigma_starts_rad=starts)
        missed = abs(without.estimate("sigma_rad").value - TRUTH.sigma_rad) > np.deg2rad(0.5)
    except fitting.FitError:
        missed = True
    assert missed  # the case this test guards: the three starts alone fail here
    monkeypatch.undo()
    fit = fitting.fit_least_squares(obs, spec, variant=v, sigma_starts_rad=starts)
    est = fit.estimate("sigma_rad")
    assert abs(est.value - TRUTH.sigma_rad) < 3 * est.stderr
    assert len(fit.starts_sigma_rad) > len(starts)


def test_a_start_that_ran_out_of_steps_continues(monkeypatch):
    """No start meets the tolerance in `max_steps`: the best continues from where it stopped
    (`fitting._core.CONTINUE_ROUNDS` more budgets, same compiled program)."""
    from stairfit.fitting import _core

    obs, spec, _ = zoo.standard(fitting.Params(sigma_rad=np.deg2rad(6.0), scale=1.0), seed=3)
    v = LADDER["sharp"]
    monkeypatch.setattr(_core, "CONTINUE_ROUNDS", 0)
    with pytest.raises(fitting.FitError, match="max_steps = 4"):
        fitting.fit_least_squares(obs, spec, variant=v, max_steps=4)
    monkeypatch.undo()
    fit = fitting.fit_least_squares(obs, spec, variant=v, max_steps=4)
    assert fit.success and fit.num_steps > 4
    full = fitting.fit_least_squares(obs, spec, variant=v)
    np.testing.assert_allclose(fit.chi2, full.chi2, rtol=1e-8)


def test_a_clearly_better_start_that_ran_out_of_steps_beats_a_worse_converged_one(monkeypatch):
    """A start that converged to a worse optimum must not win over one that only ran out of
    steps at a far better `-2 log L` (`fitting._core.BETTER_BY`): that one continues and is
    chosen. Seen on the demo's model-refilled data (seed 1, 3 of 25 draws): the 1-deg start
    "converged" to sigma = 7 rad with a 180% model-error term (-2 log L 3823) while the 4- and
    12-deg starts stood at the truth (-2 log L 780), their model-error term creeping to 0; the
    fit was reported as unidentifiable. Here the first start's result is replaced by its state
    after one step, marked converged, and the others are marked as out of steps."""
    from stairfit.fitting import _core

    obs, spec, _ = zoo.standard(fitting.Params(sigma_rad=np.deg2rad(6.0), scale=1.0), seed=3)
    v = LADDER["sharp"]
    starts = tuple(np.deg2rad((1.0, 4.0, 12.0)))
    full = fitting.fit_least_squares(obs, spec, variant=v, sigma_starts_rad=starts)
    real_run = _core._run
    calls = []

    def rigged(z0: np.ndarray, static: Any, data: Any, solver: Any, max_steps: int) -> Any:
        run = real_run(z0, static, data, solver, max_steps)
        calls.append(run)
        if len(calls) == 1:  # "converged" after one step: a point far worse than the optimum
            return real_run(z0, static, data, solver, 1)._replace(name="successful")
        if len(calls) <= len(starts):  # the others stop short of the tolerance
            return run._replace(name="nonlinear_max_steps_reached", msg="max steps")
        return run  # the continuation

    monkeypatch.setattr(_core, "_run", rigged)
    fit = fitting.fit_least_squares(obs, spec, variant=v, sigma_starts_rad=starts)
    assert len(calls) > len(starts)  # the better short start was continued
    assert fit.success
    np.testing.assert_allclose(fit.chi2, full.chi2, rtol=1e-8)
    np.testing.assert_allclose(
        fit.estimate("sigma_rad").value, full.estimate("sigma_rad").value, rtol=1e-6
    )


def test_a_short_start_within_better_by_of_a_converged_one_is_not_continued() -> None:
    """`_short_to_continue`: a short start is continued when nothing converged or when it
    beats every converged start by more than `BETTER_BY` in -2 log L, else not."""
    from stairfit.fitting import _core

    def run(name: str, m2logl: float) -> _core.StartRun:
        ev = _core.Evaluation(*(np.zeros(1),) * 4, np.float64(1.0), np.float64(-m2logl / 2),
                              np.zeros((1, 1)))  # fmt: skip
        return _core.StartRun(np.zeros(1), name, "", 1, ev, True)

    ok, short = "successful", "nonlinear_max_steps_reached"
    gap = _core.BETTER_BY
    assert _core._short_to_continue([run(ok, 100.0), run(short, 100.0 - 0.5 * gap)]) is None
    assert _core._short_to_continue([run(ok, 100.0), run(short, 100.0 - 2 * gap)]) == 1
    assert _core._short_to_continue([run(short, 5.0), run(short, 3.0)]) == 1
    assert _core._short_to_continue([run(ok, 100.0), run(ok, 3.0)]) is None


def test_model_error_rise_is_the_gaussian_log_likelihood_difference() -> None:
    """`_core.model_error_rise` against scipy's multivariate normal: groups of 3 correlated
    rows and single rows, `C = S R S + diag((f m)^2)` with f and without."""
    from types import SimpleNamespace

    from scipy.stats import multivariate_normal

    from stairfit.fitting import _core

    rng = np.random.default_rng(5)
    n = 10  # three groups of three rows and one single row (padded slots point at row 0)
    m = rng.uniform(1.0, 3.0, n)
    s = rng.uniform(0.01, 0.05, n)
    v = m + s * rng.standard_normal(n)
    rows = np.array([[0, 1, 2], [3, 4, 5], [6, 7, 8], [9, 0, 0]])
    mask = np.array([[1.0, 1, 1], [1, 1, 1], [1, 1, 1], [1, 0, 0]])
    corr = np.broadcast_to(np.eye(3), (4, 3, 3)).copy()
    for g in range(3):
        a = rng.uniform(0.2, 0.8, 3)
        r = np.array([[1, a[0], a[1]], [a[0], 1, a[2]], [a[1], a[2], 1]])
        corr[g] = r if np.linalg.eigvalsh(r).min() > 0.05 else np.eye(3)
    data = SimpleNamespace(value=v, stderr=s, grp_rows=rows, grp_mask=mask, grp_corr=corr)
    ev = SimpleNamespace(model=m)
    f = 0.02

    def m2logl(frac: float) -> float:
        total = 0.0
        for g in range(4):
            k = mask[g] > 0
            idx = rows[g][k]
            cov = corr[g][np.ix_(k, k)] * np.outer(s[idx], s[idx]) + np.diag((frac * m[idx]) ** 2)
            total += -2.0 * multivariate_normal(m[idx], cov).logpdf(v[idx])
        return total

    want = m2logl(0.0) - m2logl(f)
    assert abs(want) > 1.0  # the term matters at this f: not a comparison of two zeros
    assert _core.model_error_rise(ev, data, f) == pytest.approx(want, rel=1e-9)
    assert _core.model_error_rise(ev, data, 0.0) == pytest.approx(0.0, abs=1e-9)


@pytest.mark.slow
def test_a_model_error_term_creeping_to_zero_is_fixed_and_the_forced_fit_converges(
    tmp_path: Any,
) -> None:
    """The demo's photos of seed 12 (2 MP, 9 views): every start of the forced `sharp+floor`
    stood at one optimum (-2 log L equal to 1e-3) with the model-error term creeping to 0,
    none met the solver's tolerance and the fit raised "did not converge". The term's removal
    raises -2 log L by less than `MODEL_ERROR_RISE`: it is fixed at 0 and the refit converges
    with the truth inside every 95% interval."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
    from bench_demo_model_data import demo_observations, fit_pulls, truth_params

    obs, spectral, aperture, options, truth = demo_observations(12, Path(tmp_path))
    rec = fit_pulls(obs, spectral, aperture, options, truth_params(truth))
    assert 0.7 < rec["reduced_chi2"] < 1.3
    assert all(p["95"] for p in rec["params"].values()), rec


def test_starts_solved_in_threads_equal_the_starts_solved_one_after_another() -> None:
    """`_run_starts` solves a sharp fit's starts after the first in `START_THREADS` threads
    (issue 14); every start's optimum, result and step count equal the one-after-another
    solves' to the bit, in the same order."""
    from stairfit.fitting import _core
    from stairfit.fitting._problem import as_problem, spec_for

    obs, spec, _ = zoo.standard(fitting.Params(sigma_rad=np.deg2rad(6.0), scale=1.0), seed=3)
    problem = as_problem(obs, spec)
    free = spec_for(LADDER["sharp+floor"], problem)
    static, data = problem.static_for(free), problem.arrays_for(free)
    z0s = _core.start_vectors(problem, free, tuple(np.deg2rad((1.0, 4.0, 12.0, 25.0))))
    solver = _core.make_solver("lm", 1e-8, 1e-8)
    assert not static.rounded and len(z0s) >= 3  # the threaded path is the one taken
    threaded = _core._run_starts(z0s, static, data, solver, 256)
    serial = [_core._run(z0, static, data, solver, 256) for z0 in z0s]
    assert len(threaded) == len(serial)
    for a, b in zip(threaded, serial, strict=True):
        np.testing.assert_array_equal(a.z, b.z)
        assert (a.name, a.steps, a.finite) == (b.name, b.steps, b.finite)
        np.testing.assert_array_equal(a.ev.chi2, b.ev.chi2)
    assert len({tuple(np.asarray(z0)) for z0 in z0s}) == len(z0s)  # distinct starts
    assert len({r.steps for r in serial}) > 1  # which take different paths
