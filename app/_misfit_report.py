"""A misfit that cannot hide (issue 13): what `fit` says first when the chosen model does not
describe the data, the residual pattern per wedge and per view, and whether (why, how long) the
rounded-edge rungs were fitted.

The judgement is `fitting.describe_fit` (`Selection.assessment`; docs/fitting.md §4, "Status
words"); this module only shows it: results.json records, summary lines, the report's section
and its figure. Degrees at this edge [conventions §1].
"""

from __future__ import annotations

import html
import textwrap
from typing import TYPE_CHECKING

import numpy as np
from matplotlib.figure import Figure

from .figures import fixed_layout
from .outcome import FitOutcome

if TYPE_CHECKING:
    from stairfit import fitting

    from ._jsontypes import Record


def _photo_label(outcome: FitOutcome, label: str) -> str:
    """`IMG_0003.dng (view 40 deg)` for a photo index label of the assessment."""
    photos = outcome.scene.photos
    k = int(label) if label.isdigit() else -1
    if not 0 <= k < len(photos):
        return label
    name = photos[k].file if isinstance(photos[k].file, str) else photos[k].file[0]
    return f"{name} (view {photos[k].view_deg:g} deg)"


def _group_line(g: fitting.ResidualGroup, what: str) -> str:
    """One line describing a residual group (measurement errors alone)."""
    where = "above" if g.mean < 0 else "below"
    return (
        f"{what}: rms {g.rms:.3g}, mean {g.mean:+.3g} (the model mostly {where} the data), "
        f"model / measured {g.ratio_min:.3g}-{g.ratio_max:.3g}, {g.n} rows"
    )


def pattern_lines(outcome: FitOutcome) -> list[str]:
    """Per wedge, then per view, one line of the residual pattern (`describe_fit`)."""
    a = outcome.selection.assessment
    if a is None:
        return []
    lines = [_group_line(g, f"wedge {g.label}") for g in a.by_wedge]
    lines += [_group_line(g, f"photo {_photo_label(outcome, g.label)}") for g in a.by_photo]
    return lines


def assessment_record(outcome: FitOutcome) -> Record | None:
    """results.json's `assessment`: whether the chosen fit describes the data, with chi^2 with
    and without the model-error term and the residual pattern (docs/fitting.md §4)."""
    a = outcome.selection.assessment
    if a is None:
        return None
    groups = [
        {"group": kind, "label": g.label, "n": g.n, "mean": g.mean, "rms": g.rms,
         "ratio_min": g.ratio_min, "ratio_max": g.ratio_max}
        for kind, gs in (("wedge", a.by_wedge), ("photo", a.by_photo)) for g in gs
    ]  # fmt: skip
    return {
        "status": str(a.status),
        "misfits": a.misfits,
        "reasons": list(a.reasons),
        "headline": a.headline(),
        "chi2": a.chi2,
        "chi2_measurement_errors_only": a.chi2_measurement,
        "dof": a.dof,
        "p_value": a.p_value,
        "model_error_frac": a.model_error_frac,
        "model_error_limit": a.model_error_limit,
        "median_rel_stderr": a.median_rel_stderr,
        "pattern": a.pattern,
        "residual_groups": groups,
    }


def rounding_sentence(outcome: FitOutcome) -> str:
    """Whether the rounded-edge rungs were fitted, why and how long it took (or why not)."""
    r = outcome.selection.rounding
    if r is None:
        if outcome.selection.forced:
            return f"only the forced variant {outcome.selection.chosen!r} was fitted"
        return "the ladder has no rounded-edge variants (this preset)"
    if r.fitted:
        text = (
            f"the {r.n_variants} rounded-edge variants were fitted ({r.policy}) in "
            f"{r.elapsed_s:.0f} s, because {r.reason}"
        )
    else:
        text = f"the {r.n_variants} rounded-edge variants were not fitted ({r.policy}): {r.reason}"
    return text + _fillet_clause(r)


def _fillet_clause(r: fitting.Rounding) -> str:
    """The fillet rungs' part of `rounding_sentence` ("" when the ladder has none)."""
    if not r.fillet_n_variants:
        return ""
    if r.fillet_fitted:
        return (
            f"; the {r.fillet_n_variants} fillet variants were fitted in "
            f"{r.fillet_elapsed_s:.0f} s, because {r.fillet_reason}"
        )
    return f"; the {r.fillet_n_variants} fillet variants were not fitted: {r.fillet_reason}"


def rounding_record(outcome: FitOutcome) -> Record | None:
    """results.json's `rounding` (`fitting.Rounding`), or None when the ladder had none."""
    r = outcome.selection.rounding
    if r is None:
        return None
    return {
        "policy": r.policy,
        "fitted": r.fitted,
        "reason": r.reason,
        "n_variants": r.n_variants,
        "elapsed_s": r.elapsed_s,
        "fillet": {
            "fitted": r.fillet_fitted,
            "reason": r.fillet_reason,
            "n_variants": r.fillet_n_variants,
            "elapsed_s": r.fillet_elapsed_s,
        },
        "sentence": rounding_sentence(outcome),
    }


SUMMARY_PHOTOS = 3
"""The summary lists the photos with the largest residuals, this many (report.html: all)."""


def summary_lines(outcome: FitOutcome, width: int = 100) -> list[str]:
    """The lines the summary prints first when the chosen fit misfits (else none): the
    headline, wrapped, the residual pattern per wedge and the `SUMMARY_PHOTOS` worst views."""
    a = outcome.selection.assessment
    if a is None or not a.misfits:
        return []
    lines = textwrap.wrap(a.headline(), width - 2, subsequent_indent="    ")
    lines += ["    residuals with the measurement errors alone:"]
    lines += [f"      {_group_line(g, f'wedge {g.label}')}" for g in a.by_wedge]
    worst = sorted(a.by_photo, key=lambda g: -g.rms)[:SUMMARY_PHOTOS]
    lines += [f"      {_group_line(g, f'photo {_photo_label(outcome, g.label)}')}" for g in worst]
    if len(a.by_photo) > len(worst):
        lines.append(
            f"      (the {len(worst)} photos with the largest residuals of {len(a.by_photo)}; "
            "all in report.html, figures/residual_pattern.png)"
        )
    return lines


def residual_pattern_figure(outcome: FitOutcome) -> Figure:
    """The residual pattern: the mean residual with the measurement errors alone per wedge x
    photo (left), and model / measured against the face-frame viewing angle per wedge (right)."""
    from stairfit import fitting

    fit, obs = outcome.selection.fit, outcome.observations.data
    used = np.asarray(obs.use, bool)
    z = fitting.measurement_residuals(fit)
    wedges, photos = outcome.scene.specimen.wedges, outcome.scene.photos
    cells = np.full((len(wedges), len(photos)), np.nan)
    for k in range(len(wedges)):
        for j in range(len(photos)):
            sel = used & (obs.wedge_index == k) & (obs.photo_index == j)
            if np.any(sel):
                cells[k, j] = np.mean(z[sel])
    fig = Figure(figsize=(12, 0.45 * len(wedges) + 3.2))
    a1, a2 = fig.subplots(1, 2, gridspec_kw={"width_ratios": [3, 2]})
    lim = max(3.0, float(np.nanmax(np.abs(cells))) if np.any(np.isfinite(cells)) else 3.0)
    im = a1.imshow(cells, cmap="RdBu_r", vmin=-lim, vmax=lim, aspect="auto")
    a1.set_yticks(range(len(wedges)), [f"{w.name} ({w.angle_deg:g} deg)" for w in wedges])
    a1.set_xticks(range(len(photos)), [f"{p.view_deg:g}" for p in photos], fontsize="small")
    a1.set(xlabel="photo: view (deg)", title="mean whitened residual (measurement errors)")
    fig.colorbar(im, ax=a1, shrink=0.8)
    theta_o = np.array([r.theta_o_deg for r in outcome.observations.labels])
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.asarray(fit.model) / np.asarray(obs.value)
    for k, wedge in enumerate(wedges):
        sel = used & (obs.wedge_index == k) & np.isfinite(ratio)
        order = np.argsort(theta_o[sel])
        a2.plot(theta_o[sel][order], ratio[sel][order], "o-", ms=3, lw=0.8, label=wedge.name)
    a2.axhline(1.0, color="k", lw=0.8)
    a2.set(xlabel="theta_o (deg, face)", ylabel="model / measured", title="model / measured")
    a2.legend(fontsize="x-small", ncol=2)
    fixed_layout(fig, 1, 2, left=1.6, top=0.4, wspace=1.2)
    return fig


def misfit_html(outcome: FitOutcome, figures: dict[str, str]) -> str:
    """The report's first section when the chosen fit misfits (else ''): the headline in red,
    the residual pattern per wedge and per view, and its figure."""
    a = outcome.selection.assessment
    if a is None or not a.misfits:
        return ""
    e = html.escape
    items = "".join(f"<li>{e(line)}</li>" for line in pattern_lines(outcome))
    img = (
        f"<img src='{e(figures['misfit'])}' style='max-width:100%'>" if "misfit" in figures else ""
    )
    return (
        "<div style='border:3px solid #b00;padding:6px 12px;margin:12px 0'>"
        f"<h2 style='color:#b00'>The model does not describe the data</h2><p>{e(a.headline())}"
        "</p><p>Residuals with the measurement errors alone (the model-error term left out):"
        f"</p><ul>{items}</ul>{img}</div>"
    )
