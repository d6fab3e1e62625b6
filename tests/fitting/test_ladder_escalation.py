"""The ladder on data a rung cannot improve (issue 40): a rung that adds nothing over its parent
is reported as such, not scored (no tie on rounding noise) and not escalated from; a time
budget ends the selection with the rungs it did not try listed."""

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


def test_a_spent_time_budget_leaves_the_other_rungs_untried():
    obs, spec = zoo.standard(fitting.Params(sigma_rad=6 * DEG, delta_n=0.05, scale=1.0), 3,
                             0.02)[:2]  # fmt: skip
    sel = fitting.select_model(obs, spec, ladder=LADDER, time_budget_s=1e-6)
    rows = {r.name: r for r in sel.table}
    assert rows["sharp"].status in (fitting.Status.OK, fitting.Status.MISFITS)  # always fitted
    untried = [r for r in sel.table if r.name != "sharp"]
    assert all(r.status == fitting.Status.NOT_FITTED for r in untried), sel.report()
    assert all("time budget (1e-06 CPU s)" in r.detail for r in untried)
    with pytest.raises(fitting.FitInputError, match="time_budget_s"):
        fitting.select_model(obs, spec, ladder=LADDER, time_budget_s=0.0)


def test_the_time_budget_counts_cpu_time_not_wall_time(monkeypatch):
    """A busy machine must not change the choice: wall time that passes while the fit waits
    for a core (here: a wall clock that jumps an hour per reading) does not spend the budget,
    so every rung is tried."""
    import types

    from stairfit.fitting import _selection

    real = _selection.time
    hour = iter(range(0, 10**9, 3600))
    fake = types.SimpleNamespace(perf_counter=lambda: float(next(hour)),
                                 process_time=real.process_time)  # fmt: skip
    monkeypatch.setattr(_selection, "time", fake)
    obs, spec = zoo.standard(fitting.Params(sigma_rad=6 * DEG, delta_n=0.05, scale=1.0), 3,
                             0.02)[:2]  # fmt: skip
    sel = fitting.select_model(obs, spec, ladder=LADDER, time_budget_s=3600.0)
    assert not any("time budget" in r.detail for r in sel.table), sel.report()
