"""Model only what a scene requires: fit a ladder of variants and choose the simplest supported.

The rule (docs/fitting.md): fit every variant of the ladder (multi-start least squares, with
parameters on bounds or unidentified removed), compute BIC; among the variants whose BIC is
within `threshold` (default 2, the edge of "positive" evidence on the Kass-Raftery scale) of
the lowest, choose the one with the fewest free parameters (ties: lower BIC, then ladder order).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from stairfit import model

from ._errors import FitError, FitInputError, emit
from ._least_squares import LeastSquaresOptions, fit_least_squares
from ._observations import Observations, Spectral
from ._params import DEFAULT_LADDER, DEFAULTS, Params, Priors, Variant
from ._problem import Problem, as_problem
from ._result import FitResult

CRITERIA: tuple[str, ...] = ("bic", "laplace")
"""`bic`: `-2 log L + k ln N`. `laplace`: `-2 x` the Laplace-approximated log evidence."""

DEFAULT_THRESHOLD = 2.0
"""Kass & Raftery (1995): a difference below 2 in `2 ln B` (or in BIC) is "not worth more than
a bare mention"; a richer variant must beat the simpler one by more than this."""


@dataclass(frozen=True)
class ComparisonRow:
    """One line of the comparison table.

    `name`, `features` (optional features switched on as requested), `n_free` (free
    parameters after removing unidentified / bound ones), `chi2`, `log_likelihood`, `bic`,
    `aic`, `laplace_log_evidence` (None without covariance), `delta` (criterion minus the
    best), `status` (`ok`, `not converged`, `skipped: ...`), `notes` (parameters fixed by the
    fit and why, in short).
    """

    name: str
    features: tuple[str, ...]
    n_free: int
    chi2: float
    log_likelihood: float
    bic: float
    aic: float
    laplace_log_evidence: float | None
    delta: float
    status: str
    notes: str


def not_fitted_row(v: Variant, status: str) -> ComparisonRow:
    """The table row of a variant that was not fitted (numbers NaN), with its `status`."""
    nan = math.nan
    return ComparisonRow(v.name, v.features, 0, nan, nan, nan, nan, None, nan, status, "")


@dataclass(frozen=True)
class Selection:
    """The outcome of model selection.

    `chosen`: name of the chosen variant; `fit`: its least-squares result; `table`: one
    `ComparisonRow` per ladder variant, in ladder order; `reason`: one sentence saying why;
    `criterion`, `threshold`: the rule used; `forced`: True when the caller forced the variant;
    `fits`: every successful `FitResult` by variant name.
    """

    chosen: str
    fit: FitResult
    table: tuple[ComparisonRow, ...]
    reason: str
    criterion: str
    threshold: float
    forced: bool
    fits: dict[str, FitResult] = field(repr=False)

    def report(self) -> str:
        """The comparison table and the reason, as plain text."""
        crit = "BIC" if self.criterion == "bic" else "-2 ln Z"
        lines = [
            f"model selection by {crit} (threshold {self.threshold:g}): chose {self.chosen!r}",
            f"  {'variant':<40} {'k':>3} {'chi2':>10} {crit:>12} {'delta':>9}  status / notes",
        ]
        lines += [self._line(row) for row in self.table]
        lines.append(f"  reason: {self.reason}")
        return "\n".join(lines)

    def _line(self, row: ComparisonRow) -> str:
        mark = "*" if row.name == self.chosen else " "
        if row.status.startswith("skipped"):
            return f" {mark}{row.name:<40} {'':>3} {'':>10} {'':>12} {'':>9}  {row.status}"
        if self.criterion == "bic":
            value = row.bic
        elif row.laplace_log_evidence is None:
            value = float("nan")
        else:
            value = -2 * row.laplace_log_evidence
        notes = f"{row.status}{'; ' + row.notes if row.notes else ''}"
        return (
            f" {mark}{row.name:<40} {row.n_free:>3} {row.chi2:>10.4g} {value:>12.6g} "
            f"{row.delta:>9.3g}  {notes}"
        )


def _criterion(fit: FitResult, criterion: str) -> float | None:
    if criterion == "bic":
        return fit.bic
    if fit.laplace_log_evidence is None:
        return None
    return -2.0 * fit.laplace_log_evidence


def select_model(
    observations: Observations | Problem,
    spectral: Spectral | None = None,
    ladder: tuple[Variant, ...] = DEFAULT_LADDER,
    *,
    criterion: str = "bic",
    threshold: float = DEFAULT_THRESHOLD,
    force: str | Variant | None = None,
    model_error: bool = False,
    fixed: Params = DEFAULTS,
    priors: Priors | None = None,
    aperture: model.Aperture | None = None,
    resolution: int | None = None,
    options: LeastSquaresOptions | None = None,
    **option_overrides: Any,
) -> Selection:
    """Fit every variant of `ladder` and choose the simplest the data support (module doc).

    `force` (a variant or a ladder name) skips the comparison and fits only that variant.
    `model_error=True` frees `model_error_frac` in every variant. `options` (and keywords
    naming its fields, e.g. `solver`, `max_steps`, `sigma_starts_rad`) set each least-squares
    fit; failures are recorded in the table (`on_failure="flag"`), and warnings of the chosen
    fit are emitted while those of the others are only recorded in their results.
    """
    if criterion not in CRITERIA:
        raise FitInputError(f"criterion = {criterion!r}; choose one of {', '.join(CRITERIA)}")
    if not threshold >= 0:
        raise FitInputError(f"threshold = {threshold!r}; give a non-negative number")
    problem = as_problem(observations, spectral, fixed=fixed, priors=priors, aperture=aperture,
                         resolution=resolution)  # fmt: skip
    opts = (options or LeastSquaresOptions()).updated(**option_overrides)
    opts = opts._replace(on_failure="flag", emit_warnings=False)
    if force is not None:
        return _forced(problem, _find(force, ladder), model_error, criterion, threshold, opts)
    if len(ladder) == 0:
        raise FitInputError("the ladder is empty; give at least one variant")
    fits, skipped = _fit_ladder(problem, ladder, model_error, opts)
    return _choose(ladder, fits, skipped, criterion, threshold)


def _forced(
    problem: Problem,
    v: Variant,
    model_error: bool,
    criterion: str,
    threshold: float,
    opts: LeastSquaresOptions,
) -> Selection:
    v = v.with_free(model_error=True) if model_error else v
    fit = fit_least_squares(problem, variant=v, options=opts)
    if not fit.success:
        raise FitError(f"the forced variant {v.name!r} did not converge: {fit.message}")
    emit(fit.warnings)
    row = _row(fit, v, 0.0)
    return Selection(v.name, fit, (row,), f"{v.name!r} was forced by the caller", criterion,
                     threshold, True, {v.name: fit})  # fmt: skip


def _fit_ladder(
    problem: Problem, ladder: tuple[Variant, ...], model_error: bool, opts: LeastSquaresOptions
) -> tuple[dict[str, FitResult], dict[str, str]]:
    """(converged fits by variant name, status of every variant that failed)."""
    fits: dict[str, FitResult] = {}
    skipped: dict[str, str] = {}
    for v in ladder:
        v_run = v.with_free(model_error=True) if model_error else v
        try:
            fit = fit_least_squares(problem, variant=v_run, options=opts)
        except FitError as err:  # e.g. a variant whose width the data cannot constrain
            skipped[v.name] = f"failed: {err}"
            continue
        if fit.success:
            fits[v.name] = fit
        else:
            skipped[v.name] = f"not converged ({fit.message.split(':')[0]})"
    return fits, skipped


def _choose(
    ladder: tuple[Variant, ...],
    fits: dict[str, FitResult],
    skipped: dict[str, str],
    criterion: str,
    threshold: float,
) -> Selection:
    """Apply the rule (module doc) to the fitted variants and build the table."""
    scored = {n: _criterion(f, criterion) for n, f in fits.items()}
    scored = {n: c for n, c in scored.items() if c is not None and math.isfinite(c)}
    if not scored:
        raise FitError(
            "no variant of the ladder converged: "
            + "; ".join(f"{k}: {v}" for k, v in skipped.items())
        )
    best_name = min(scored, key=lambda n: scored[n])
    best = scored[best_name]
    order = {v.name: i for i, v in enumerate(ladder)}
    candidates = [n for n, c in scored.items() if c <= best + threshold]
    chosen = min(candidates, key=lambda n: (fits[n].n_free, round(scored[n], 6), order[n]))
    table = []
    for v in ladder:
        if v.name not in fits:
            table.append(not_fitted_row(v, skipped[v.name]))
            continue
        c = scored.get(v.name)
        table.append(_row(fits[v.name], v, float("nan") if c is None else c - best))
    reason = _reason(chosen, best_name, fits, scored, criterion, threshold)
    emit(fits[chosen].warnings)
    return Selection(chosen, fits[chosen], tuple(table), reason, criterion, threshold, False, fits)


def _find(force: str | Variant, ladder: tuple[Variant, ...]) -> Variant:
    if isinstance(force, Variant):
        return force
    for v in ladder:
        if v.name == force:
            return v
    names = ", ".join(v.name for v in ladder)
    raise FitInputError(f"force = {force!r} is not a variant of the ladder; choose one of {names}")


def _row(fit: FitResult, v: Variant, delta: float) -> ComparisonRow:
    notes = ", ".join(f"{w.parameter} {w.code.replace('_', ' ')}" for w in fit.warnings
                      if w.code in ("unidentified", "at_bound"))  # fmt: skip
    return ComparisonRow(
        name=v.name,
        features=v.features,
        n_free=fit.n_free,
        chi2=fit.chi2,
        log_likelihood=fit.log_likelihood,
        bic=fit.bic,
        aic=fit.aic,
        laplace_log_evidence=fit.laplace_log_evidence,
        delta=delta,
        status="ok",
        notes=notes,
    )


def _reason(
    chosen: str,
    best: str,
    fits: dict[str, FitResult],
    scored: dict[str, float],
    criterion: str,
    threshold: float,
) -> str:
    """One sentence: why this variant."""
    crit = "BIC" if criterion == "bic" else "-2 ln Z"
    k = fits[chosen].n_free
    simpler = [scored[n] - scored[best] for n in scored if fits[n].n_free < k]
    tail = (
        f"; every simpler variant is worse by at least {min(simpler):.3g}"
        if simpler
        else "; no simpler variant was fitted"
    )
    if chosen == best:
        return f"{chosen!r} ({k} free parameters) has the lowest {crit}" + tail
    d = scored[chosen] - scored[best]
    return (
        f"{chosen!r} ({k} free parameters) is within {crit} {d:.3g} <= {threshold:g} of the best "
        f"variant {best!r} ({fits[best].n_free} free), so the extra parameters are not "
        "supported" + tail
    )
