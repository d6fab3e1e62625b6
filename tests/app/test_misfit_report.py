"""A misfit cannot hide (issue 13): when the chosen fit needs a large model-error term, the
summary says so first, results.json records chi^2 with and without the term and the residual
pattern per wedge and view, and the report opens with it; the rounded rungs are accounted for.

The data (a diffuse floor, made by `stairfit.model` through tests/zoo.py) are fitted with the
sharp variant only and a model-error term, which absorbs the floor; the numbers the report shows
are recomputed here from the observations and the fitted model, not taken from `describe_fit`.
"""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import zoo

from stairfit import fitting
from stairfit._misfit_report import (
    assessment_record,
    misfit_html,
    residual_pattern_figure,
    rounding_sentence,
    summary_lines,
)
from stairfit.report import print_summary

DEG = np.pi / 180


def _outcome(sel: fitting.Selection, s: zoo.Scene) -> SimpleNamespace:
    """The parts of `stairfit.pipeline.FitOutcome` the summary and the report read."""
    obs = s.obs
    n_photos = int(np.max(obs.photo_index)) + 1
    views = [float(np.rad2deg(obs.theta_o_rad[obs.photo_index == j][0])) for j in range(n_photos)]
    wedge_deg = [float(np.rad2deg(obs.beta2_rad[obs.wedge_index == k][0]))
                 for k in range(int(np.max(obs.wedge_index)) + 1)]  # fmt: skip
    scene = SimpleNamespace(
        folder=Path("photos"),
        photos=[SimpleNamespace(file=f"IMG_{j:02d}.dng", view_deg=v) for j, v in enumerate(views)],
        specimen=SimpleNamespace(
            wedges=[SimpleNamespace(name=f"w{d:g}", angle_deg=d) for d in wedge_deg]
        ),
    )
    labels = [SimpleNamespace(theta_o_deg=float(t)) for t in np.rad2deg(obs.theta_o_rad)]
    observations = SimpleNamespace(data=obs, labels=labels)
    return SimpleNamespace(scene=scene, observations=observations, selection=sel,
                           posterior=None, notes=())  # fmt: skip


def _photo_residuals(sel: fitting.Selection, s: zoo.Scene) -> list[tuple[int, np.ndarray]]:
    """Per photo, the used rows' (measured - model) / stderr, computed here."""
    use = np.asarray(s.obs.use, bool)
    z = (np.asarray(s.obs.value) - np.asarray(sel.fit.model)) / np.asarray(s.obs.stderr)
    return [(j, z[use & (s.obs.photo_index == j)]) for j in np.unique(s.obs.photo_index)]


@pytest.fixture(scope="module")
def misfit() -> tuple[fitting.Selection, zoo.Scene]:
    s = zoo.standard(fitting.Params(sigma_rad=3 * DEG, scale=1.0, floor=0.03), seed=4)
    sel = fitting.select_model(s.obs, s.spec, (zoo.LADDER["sharp"],), model_error=True)
    return sel, s


def test_chi2_with_and_without_the_model_error_term_are_the_data_s(misfit):
    sel, s = misfit
    rec = assessment_record(_outcome(sel, s))
    use = np.asarray(s.obs.use, bool)
    value, se = np.asarray(s.obs.value)[use], np.asarray(s.obs.stderr)[use]
    model = np.asarray(sel.fit.model)[use]
    f = sel.fit.estimate("model_error_frac").value
    chi2_meas = np.sum(((value - model) / se) ** 2)
    chi2_with = np.sum((value - model) ** 2 / (se**2 + (f * model) ** 2))  # fitting.md §3
    assert rec["misfits"] and rec["model_error_frac"] > 0.01
    np.testing.assert_allclose(rec["chi2_measurement_errors_only"], chi2_meas, rtol=1e-9)
    np.testing.assert_allclose(rec["chi2"], chi2_with, rtol=1e-6)
    assert rec["chi2_measurement_errors_only"] > 10 * rec["chi2"]
    wedges = [g for g in rec["residual_groups"] if g["group"] == "wedge"]
    photos = [g for g in rec["residual_groups"] if g["group"] == "photo"]
    assert len(wedges) == 6 and len(photos) == 19
    assert sum(g["n"] for g in wedges) == int(use.sum())


def test_the_summary_says_misfit_first(misfit, capsys):
    sel, s = misfit
    outcome = _outcome(sel, s)
    print_summary(outcome, Path("out"))
    lines = [line for line in capsys.readouterr().out.splitlines() if line.strip()]
    assert lines[0].startswith("stairfit fit:")
    assert lines[1].strip().startswith("MISFIT"), lines[:3]
    text = "\n".join(lines)
    a = sel.assessment
    assert f"{a.chi2_measurement:.4g}" in text and f"{a.chi2:.4g}" in text
    assert text.index("MISFIT") < text.index("model: sharp")
    # one line per wedge and per view, and the pattern names the worst wedge
    assert sum(line.strip().startswith("wedge ") for line in lines) == 6
    shown = [line for line in lines if line.strip().startswith("photo IMG_")]
    assert len(shown) == 3  # the worst views; every view is in the report
    rms = {f"IMG_{j:02d}.dng": np.sqrt(np.mean(z**2)) for j, z in _photo_residuals(sel, s)}
    worst = sorted(rms, key=lambda name: -rms[name])[:3]
    assert [line.split()[1] for line in shown] == worst
    assert len(lines) < 40  # one screen


def test_the_report_opens_with_the_misfit_and_its_pattern_figure(misfit, tmp_path):
    sel, s = misfit
    outcome = _outcome(sel, s)
    fig = residual_pattern_figure(outcome)
    cells = np.asarray(fig.axes[0].images[0].get_array())
    z = (np.asarray(s.obs.value) - np.asarray(sel.fit.model)) / np.asarray(s.obs.stderr)
    k, j = 2, 5
    sel_kj = (s.obs.wedge_index == k) & (s.obs.photo_index == j) & np.asarray(s.obs.use)
    np.testing.assert_allclose(cells[k, j], np.mean(z[sel_kj]), rtol=1e-9)
    page = misfit_html(outcome, {"misfit": "figures/residual_pattern.png"})
    assert "does not describe the data" in page and "residual_pattern.png" in page
    assert page.count("<li>") == 6 + 19


def test_a_good_fit_shows_no_misfit_and_the_rounding_is_accounted_for():
    s = zoo.standard(fitting.Params(sigma_rad=3 * DEG, scale=1.0), seed=5)
    sel = fitting.select_model(s.obs, s.spec, (zoo.LADDER["sharp"],), model_error=True)
    outcome = _outcome(sel, s)
    assert not sel.assessment.misfits
    assert summary_lines(outcome) == [] and misfit_html(outcome, {}) == ""
    assert "no rounded-edge variants" in rounding_sentence(outcome)
    skipped = fitting.Rounding("when_needed", False, "the best sharp variant describes it", 4, 0)
    fitted = fitting.Rounding("always", True, "the preset fits them always", 4, 83.4)
    assert "were not fitted (when_needed): the best sharp" in rounding_sentence(
        SimpleNamespace(selection=SimpleNamespace(rounding=skipped, forced=False))
    )
    assert "were fitted (always) in 83 s, because the preset" in rounding_sentence(
        SimpleNamespace(selection=SimpleNamespace(rounding=fitted, forced=False))
    )
    # the fillet rungs (issue 15) add their own clause only when the ladder has them
    assert "fillet" not in rounding_sentence(
        SimpleNamespace(selection=SimpleNamespace(rounding=fitted, forced=False))
    )
    with_fillets = fitted._replace(fillet_n_variants=2, fillet_reason="the rounded misfits")
    assert rounding_sentence(
        SimpleNamespace(selection=SimpleNamespace(rounding=with_fillets, forced=False))
    ).endswith("; the 2 fillet variants were not fitted: the rounded misfits")
    fitted_fillets = with_fillets._replace(fillet_fitted=True, fillet_elapsed_s=240.2)
    assert "; the 2 fillet variants were fitted in 240 s, because the rounded" in (
        rounding_sentence(
            SimpleNamespace(selection=SimpleNamespace(rounding=fitted_fillets, forced=False))
        )
    )
