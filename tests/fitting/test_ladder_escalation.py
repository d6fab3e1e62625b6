"""The ladder on data a rung cannot improve (issue 40): a rung that adds nothing over its parent
is reported as such, not scored (no tie on rounding noise) and not escalated from; a budget of
solver steps ends the selection with the rungs it did not try listed."""

from __future__ import annotations

import numpy as np
import pytest
import zoo

from stairfit import fitting

DEG = np.pi / 180
TRUTH = fitting.Params(sigma_rad=6 * DEG, scale=1.0)
LADDER = tuple(v for v in zoo.SHARP_LADDER if not v.per_wedge_sigma)


def _exact_observations() -> tuple[fitting.Observations, fitting.Spectral]:
    """The standard scene with the noisy values replaced by the truth's own (errors kept): no
    parameter beyond `sharp`'s can lower chi^2, which is then 0 up to rounding."""
    obs, spec, _ = zoo.standard(TRUTH, seed=0, noise=0.02)
    exact, _, _ = zoo.scene(TRUTH, fitting.standard_design(channels=(0, 1, 2)), spec,
                            fitting.Noise(1e-9), 0)  # fmt: skip
    return obs._replace(value=exact.value), spec


def test_a_rung_that_changes_nothing_is_reported_and_not_escalated_from():
    obs, spec = _exact_observations()
    sel = fitting.select_model(obs, spec, ladder=LADDER)
    rows = {r.name: r for r in sel.table}
    assert sel.chosen == "sharp", sel.report()
    for name in ("sharp+delta_n", "sharp+floor"):
        assert rows[name].status == fitting.Status.ADDS_NOTHING, sel.report()
        assert "'sharp'" in rows[name].detail
        assert name not in sel.fits  # not scored: no tie on rounding noise
    # "floor at bound: the fit is 'sharp' again": the row shows the parent's numbers (the fit
    # stopped when the floor was fixed), each note once
    floor = rows["sharp+floor"]
    assert "floor at bound" in floor.detail and floor.notes == "floor at bound", floor
    assert (floor.n_free, floor.bic) == (rows["sharp"].n_free, rows["sharp"].bic)
    both = rows["sharp+delta_n+floor"]
    assert both.status == fitting.Status.NOT_FITTED and "added nothing" in both.detail
    assert "adds nothing" in sel.report()


def _fixed(fit: fitting.FitResult) -> set[str | None]:
    return {w.parameter for w in fit.warnings if w.code in ("unidentified", "at_bound")}


def test_a_fit_told_to_stop_when_its_added_parameter_is_fixed_does_not_refit_without_it(
    monkeypatch,
):
    """The ladder needs only to know that a rung's added parameter is fixed (the rung is its
    parent again, which it has): `stop_when_fixed` ends the refinement there, one solve earlier
    than the full refinement, with the same warning."""
    from stairfit.fitting import _least_squares

    obs, spec = _exact_observations()
    v = next(u for u in LADDER if u.name == "sharp+floor")
    calls = []
    real = _least_squares.fit_core
    monkeypatch.setattr(_least_squares, "fit_core",
                        lambda *a, **k: calls.append(1) or real(*a, **k))  # fmt: skip
    opts = fitting.LeastSquaresOptions(on_failure="flag", emit_warnings=False)
    full = fitting.fit_least_squares(obs, spec, variant=v, options=opts)
    n_full, calls[:] = len(calls), []
    stopped = fitting.fit_least_squares(obs, spec, variant=v, options=opts,
                                        stop_when_fixed=frozenset({"floor"}))  # fmt: skip
    assert "floor" in _fixed(full) and "floor" in _fixed(stopped), (full.warnings,)
    assert len(calls) == n_full - 1, (len(calls), n_full)
    # a parameter the stop does not name is refined as before
    other = fitting.fit_least_squares(obs, spec, variant=v, options=opts,
                                      stop_when_fixed=frozenset({"delta_n"}))  # fmt: skip
    assert other.chi2 == full.chi2 and _fixed(other) == _fixed(full)


def _delta_n_observations() -> tuple[fitting.Observations, fitting.Spectral]:
    return zoo.standard(fitting.Params(sigma_rad=6 * DEG, delta_n=0.05, scale=1.0), 3, 0.02)[:2]


def test_a_spent_budget_leaves_the_other_rungs_untried():
    obs, spec = _delta_n_observations()
    sel = fitting.select_model(obs, spec, ladder=LADDER, work_budget_gflop=1e-9)
    rows = {r.name: r for r in sel.table}
    assert rows["sharp"].status in (fitting.Status.OK, fitting.Status.MISFITS)  # always fitted
    assert rows["sharp"].solver_steps > 0 and rows["sharp"].work_gflop > 0
    untried = [r for r in sel.table if r.name != "sharp"]
    assert all(r.status == fitting.Status.NOT_FITTED for r in untried), sel.report()
    assert all("budget (1e-09 Gflop of solver work) was spent" in r.detail for r in untried)
    assert all(r.solver_steps == 0 and r.work_gflop == 0 for r in untried)
    for bad in (0.0, -3.0, float("nan")):
        with pytest.raises(fitting.FitInputError, match="work_budget_gflop"):
            fitting.select_model(obs, spec, ladder=LADDER, work_budget_gflop=bad)


def test_the_budget_counts_work_so_the_choice_does_not_depend_on_the_clock(monkeypatch):
    """The budget is work, not time: a ladder given exactly the work its first rungs did
    stops at the same rung whatever the clocks say (here: clocks that jump an hour per reading,
    a machine far slower or busier than any); a row's work is its steps (every start and
    refit, at least its best start's) times the cost of one step."""
    import types

    from stairfit.fitting import _selection

    obs, spec = _delta_n_observations()
    whole = fitting.select_model(obs, spec, ladder=LADDER)
    order = sorted(LADDER, key=lambda u: len(u.features))
    rows = {r.name: r for r in whole.table}
    for name, fit in whole.fits.items():
        assert rows[name].solver_steps >= fit.num_steps > 0, whole.report()
        assert rows[name].work_gflop == pytest.approx(fit.work_gflop()) and fit.work_gflop() > 0
    from stairfit.report import table_records  # results.json keeps each row's work

    records = {r["variant"]: r for r in table_records(whole)}
    assert all((records[n]["solver_steps"], records[n]["work_gflop"])
               == (r.solver_steps, r.work_gflop) for n, r in rows.items())  # fmt: skip
    first_two = rows[order[0].name].work_gflop + rows[order[1].name].work_gflop
    assert all(rows[v.name].work_gflop > 0 for v in order[:2]), whole.report()
    hour = iter(range(0, 10**9, 3600))
    fake = types.SimpleNamespace(perf_counter=lambda: float(next(hour)),
                                 process_time=lambda: float(next(hour)))  # fmt: skip
    monkeypatch.setattr(_selection, "time", fake)
    cut = fitting.select_model(obs, spec, ladder=LADDER, work_budget_gflop=first_two)
    tried = [r.name for r in cut.table if "budget" not in r.detail]
    assert set(tried) == {v.name for v in order[:2]}, cut.report()
    assert cut.chosen in tried
    more = fitting.select_model(obs, spec, ladder=LADDER, work_budget_gflop=first_two * 1.001)
    assert {r.name for r in more.table if "budget" not in r.detail} >= set(tried) | {
        order[2].name}, more.report()


def test_a_step_of_a_richer_model_weighs_more():
    """The work of a step follows the forward model's cost: a rounded step weighs far more
    than a sharp one, and a free parameter more adds a Jacobian column."""
    from stairfit.fitting import _least_squares

    obs, spec = _delta_n_observations()
    problem = fitting.prepare(obs, spec)

    def per_step(name: str) -> float:
        v = next(u for u in fitting.DEFAULT_LADDER if u.name == name)
        s = _least_squares.spec_for(v, problem)
        return fitting.step_gflop(problem.static_for(s), problem.arrays_for(s))

    sharp, floor, rounded = per_step("sharp"), per_step("sharp+floor"), per_step("rounded")
    assert 0 < sharp < floor < rounded
    assert rounded > 10 * sharp


def test_each_solve_of_a_fit_is_weighed_at_its_own_cost():
    """A rounded rung whose radius the refinement fixes at 0 refits with the sharp model: its
    work weighs the rounded solve's steps at the rounded cost, not at the final sharp one."""
    import dataclasses

    from stairfit.fitting import _least_squares
    from stairfit.fitting._core import SolveWork

    obs, spec = _delta_n_observations()
    problem = fitting.prepare(obs, spec)
    fit = fitting.fit_least_squares(problem, variant=LADDER[0])

    def solve(name: str) -> SolveWork:
        v = next(u for u in fitting.DEFAULT_LADDER if u.name == name)
        s = _least_squares.spec_for(v, problem)
        return SolveWork.of(40, problem.static_for(s), problem.arrays_for(s))

    both = dataclasses.replace(fit, solves=(solve("rounded"), solve("sharp")))
    assert both.solver_steps == 80
    sharp_only = dataclasses.replace(fit, solves=(solve("sharp"), solve("sharp")))
    assert both.work_gflop() > 5 * sharp_only.work_gflop() > 0


def test_the_fit_notes_the_rungs_the_budget_left_untried():
    """`stairfit fit` says which rungs the preset's budget left out and how to fit them all;
    a ladder that tried every rung gets no such note."""
    from stairfit.pipeline import budget_notes
    from stairfit.presets import PRESETS

    obs, spec = _delta_n_observations()
    cut = fitting.select_model(obs, spec, ladder=LADDER, work_budget_gflop=1e-9)
    untried = fitting.budget_untried(cut)
    assert untried == tuple(v.name for v in LADDER if v.name != "sharp"), cut.report()
    (note,) = budget_notes(cut, PRESETS["balanced"])
    assert f"{len(untried)} rung(s) of the ladder were not tried" in note
    assert all(name in note for name in untried)
    assert "400 Gflop" in note and "--preset accurate" in note
    whole = fitting.select_model(obs, spec, ladder=LADDER)
    assert fitting.budget_untried(whole) == () and budget_notes(whole, PRESETS["balanced"]) == []
