"""Model only what a scene requires: fit a ladder of variants and choose the simplest supported.

The rule (docs/fitting.md): fit every variant of the ladder (multi-start least squares, with
parameters on bounds or unidentified removed), compute BIC; among the variants whose BIC is
within `threshold` (default 2, the edge of "positive" evidence on the Kass-Raftery scale) of
the lowest, choose the one with the fewest free parameters (ties: lower BIC, then ladder order).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, NamedTuple

from stairfit import model

from ._errors import FitError, FitInputError, UnconstrainedError, emit
from ._least_squares import FIXING_CODES, LeastSquaresOptions, fit_least_squares, fixed_names
from ._misfit import P_VALUE_LIMIT, Assessment, Status, chi2_p_value, chi2_text, describe_fit
from ._observations import Observations, Spectral
from ._params import DEFAULT_LADDER, DEFAULTS, FILLET, Params, Priors, Variant
from ._problem import Problem, as_problem
from ._result import FitResult

CRITERIA: tuple[str, ...] = ("bic", "laplace")
"""`bic`: `-2 log L + k ln N`. `laplace`: `-2 x` the Laplace-approximated log evidence."""

GAIN_MIN = 1.0
"""A rung whose added parameters lower `-2 log L` by less than this (one standard deviation of
one parameter's likelihood-ratio statistic) adds nothing over its parent (`Status.ADDS_NOTHING`)."""

DEFAULT_THRESHOLD = 2.0
"""Kass & Raftery (1995): a difference below 2 in `2 ln B` (or in BIC) is "not worth more than
a bare mention"; a richer variant must beat the simpler one by more than this."""


@dataclass(frozen=True)
class ComparisonRow:
    """One line of the comparison table.

    `name`, `features` (optional features switched on as requested), `n_free` (free
    parameters after removing unidentified / bound ones), `chi2`, `log_likelihood`, `bic`,
    `aic`, `laplace_log_evidence` (None without covariance), `delta` (criterion minus the
    best), `status` (a `Status`: ok, misfits, unidentifiable, did not converge, not fitted) and
    `detail` (its reason: the chi^2 and tail probability of a misfit, the parameter the data
    cannot constrain, the solver's message, why a rung was skipped), `notes` (parameters fixed
    by the fit and why, in short), `chi2_measurement` (chi^2 with the measurement errors alone,
    without the model-error term), `dof`, `elapsed_s` (wall time of the variant's fit),
    `solver_steps` (the solver steps the ladder spent on it, every start and refit) and
    `work_gflop` (their work, `FitResult.work_gflop`: what the ladder's budget counts); both 0
    where the row's fit came from the kernel probes or their recheck, or where a rung ended in
    an error without a fit. `status_text` is the status in words with its detail.
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
    status: Status
    notes: str
    detail: str = ""
    chi2_measurement: float = math.nan
    dof: int = 0
    elapsed_s: float = 0.0
    solver_steps: int = 0
    work_gflop: float = 0.0

    @property
    def status_text(self) -> str:
        """`misfits (chi^2 = 3.6e+04 for 340 dof, p < 1e-300)`, `ok`, ..."""
        return f"{self.status} ({self.detail})" if self.detail else str(self.status)


def not_fitted_row(
    v: Variant, status: Status | str, detail: str = "", chi2: float = math.nan, dof: int = 0
) -> ComparisonRow:
    """The table row of a variant without a usable fit (numbers NaN but a misfit's chi^2):
    a `Status` (a string is read as `not fitted` with that string as the detail)."""
    if not isinstance(status, Status):
        status, detail = Status.NOT_FITTED, detail or str(status)
    nan = math.nan
    return ComparisonRow(v.name, v.features, 0, chi2, nan, nan, nan, None, nan, status, "",
                         detail, nan, dof)  # fmt: skip


class Facets(NamedTuple):
    """How the facets' kernel of the lab model was chosen (`select_model(kernels=...)`):
    `kernel` the chosen one, `probe` the variant every kernel was fitted with, `rows` one
    `ComparisonRow` per kernel (its name the probe's with the kernel), `reason` in words."""

    kernel: str
    probe: str
    rows: tuple[ComparisonRow, ...]
    reason: str
    fits: tuple[FitResult, ...] = ()
    """The chosen kernel's converged probe fits: starts for the same variants of the ladder."""


class Rounding(NamedTuple):
    """Whether the rounded-edge rungs were fitted (`select_model(rounded_rungs=...)`):
    `policy` (`always`, `when_needed`), `fitted`, `reason` (in words), `n_variants` rounded
    variants in the ladder, `elapsed_s` spent fitting them. The same for the fillet rungs
    (variants with `fillet_radius_um` free, gated by the same policy on the best variant
    without fillets): `fillet_fitted`, `fillet_reason`, `fillet_n_variants` (0 when the ladder
    has none), `fillet_elapsed_s`."""

    policy: str
    fitted: bool
    reason: str
    n_variants: int
    elapsed_s: float
    fillet_fitted: bool = False
    fillet_reason: str = ""
    fillet_n_variants: int = 0
    fillet_elapsed_s: float = 0.0


@dataclass(frozen=True)
class Selection:
    """The outcome of model selection.

    `chosen`: name of the chosen variant; `fit`: its least-squares result; `table`: one
    `ComparisonRow` per ladder variant, in ladder order; `reason`: one sentence saying why;
    `criterion`, `threshold`: the rule used; `forced`: True when the caller forced the variant;
    `fits`: every successful `FitResult` by variant name; `rounding`: whether the rounded rungs
    were fitted, why and how long they took (None when the ladder has none); `assessment`:
    whether the chosen fit describes the data (`describe_fit`); `facets`: how the lab model's
    facet kernel was chosen (None when only one was offered).
    """

    chosen: str
    fit: FitResult
    table: tuple[ComparisonRow, ...]
    reason: str
    criterion: str
    threshold: float
    forced: bool
    fits: dict[str, FitResult] = field(repr=False)
    rounding: Rounding | None = None
    assessment: Assessment | None = field(default=None, repr=False)
    facets: Facets | None = None

    def with_fit(self, fit: FitResult) -> Selection:
        """This selection with the chosen variant's fit replaced by `fit` (the same variant fitted
        again, e.g. with finer quadrature knobs): its fit, its assessment and its entry in
        `fits`; the comparison table and the reason stay those of the selection."""
        return dataclasses.replace(
            self, fit=fit, assessment=describe_fit(fit), fits={**self.fits, self.chosen: fit}
        )

    def report(self) -> str:
        """The comparison table and the reason, as plain text."""
        crit = "BIC" if self.criterion == "bic" else "-2 ln Z"
        lines = [
            f"model selection by {crit} (threshold {self.threshold:g}): chose {self.chosen!r}",
            f"  {'variant':<40} {'k':>3} {'chi2':>10} {crit:>12} {'delta':>9}  status / notes",
        ]
        lines += [self._line(row) for row in self.table]
        lines.append(f"  reason: {self.reason}")
        if self.assessment is not None and self.assessment.misfits:
            lines.insert(0, self.assessment.headline())
        return "\n".join(lines)

    def _line(self, row: ComparisonRow) -> str:
        mark = "*" if row.name == self.chosen else " "
        if not math.isfinite(row.bic):
            return f" {mark}{row.name:<40} {'':>3} {'':>10} {'':>12} {'':>9}  {row.status_text}"
        if self.criterion == "bic":
            value = row.bic
        elif row.laplace_log_evidence is None:
            value = float("nan")
        else:
            value = -2 * row.laplace_log_evidence
        notes = f"{row.status_text}{'; ' + row.notes if row.notes else ''}"
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


ROUNDED_RUNGS: tuple[str, ...] = ("always", "when_needed")
"""`always` fits every rounded-edge variant of the ladder; `when_needed` first selects among
the sharp variants and adds the rounded ones only when the chosen sharp variant does not
describe the data (`rounding_needed`): a rounded fit compiles several times longer."""


def select_model(
    observations: Observations | Problem,
    spectral: Spectral | None = None,
    ladder: tuple[Variant, ...] = DEFAULT_LADDER,
    *,
    criterion: str = "bic",
    threshold: float = DEFAULT_THRESHOLD,
    force: str | Variant | None = None,
    model_error: bool = False,
    rounded_rungs: str = "always",
    fixed: Params = DEFAULTS,
    priors: Priors | None = None,
    aperture: model.Aperture | None = None,
    resolution: int | None = None,
    options: LeastSquaresOptions | None = None,
    on_variant: Callable[[str], None] | None = None,
    kernels: tuple[str, ...] = ("gaussian",),
    work_budget_gflop: float | None = None,
    **option_overrides: Any,
) -> Selection:
    """Fit every variant of `ladder` and choose the simplest the data support (module doc).

    `kernels` (the lab model's facets, `stairfit.model.LAB_KERNELS`): with more than one, each
    is first fitted with one probe variant (`choose_kernel`), and the ladder then uses the
    kernel the same rule prefers (the first listed wins a tie: list the simplest first).

    Variants are fitted from simple to rich, each also started from the optimum of every
    fitted parent (the variants with one optional feature fewer), so that none ends worse than
    its parent. `force` (a variant or a ladder name) skips the comparison and fits only that
    variant (a rounded one started from its sharp counterpart's optimum). `model_error=True`
    frees `model_error_frac` in every variant. `rounded_rungs` (`ROUNDED_RUNGS`) says when the
    rounded-edge variants are fitted. `options` (and keywords naming its fields, e.g.
    `solver`, `max_steps`, `sigma_starts_rad`) set each least-squares fit; failures are
    recorded in the table with their `Status`, and warnings of the chosen fit are emitted while
    those of the others are only recorded in their results. `on_variant(name)` is called after
    each variant's fit (for progress bars). `work_budget_gflop`: no further variant of the
    ladder is started once its fits have done this much work (solver steps, every start and
    refit, each weighted by `step_gflop`; counted after the kernel probes; those left are
    listed as not tried): work, not time, so that the same data give the same choice on any
    machine, busy or not. A variant that adds nothing over its parent (`Status.ADDS_NOTHING`)
    is not scored and its children are not tried.
    """
    if criterion not in CRITERIA:
        raise FitInputError(f"criterion = {criterion!r}; choose one of {', '.join(CRITERIA)}")
    if not threshold >= 0:
        raise FitInputError(f"threshold = {threshold!r}; give a non-negative number")
    if rounded_rungs not in ROUNDED_RUNGS:
        raise FitInputError(
            f"rounded_rungs = {rounded_rungs!r}; choose one of {', '.join(ROUNDED_RUNGS)}"
        )
    problem = as_problem(observations, spectral, fixed=fixed, priors=priors, aperture=aperture,
                         resolution=resolution)  # fmt: skip
    opts = (options or LeastSquaresOptions()).updated(**option_overrides)
    opts = opts._replace(on_failure="flag", emit_warnings=False)
    if len(ladder) == 0:
        raise FitInputError("the ladder is empty; give at least one variant")
    if work_budget_gflop is not None and not work_budget_gflop > 0:
        raise FitInputError(
            f"work_budget_gflop = {work_budget_gflop!r}; give a positive number of Gflop"
        )
    facets = None
    if len(kernels) > 1:
        settings = _Settings(opts, model_error, on_variant or (lambda name: None))
        facets = choose_kernel(problem, ladder, kernels, criterion, threshold, settings)
    # the budget is the ladder's: the kernel probes decide what the ladder fits, so they run whole
    kernel = facets.kernel if facets is not None else kernels[0]
    ladder = tuple(v._replace(kernel=kernel) for v in ladder)
    probes = facets.fits if facets is not None else ()
    if force is not None:
        forced = _find(force, ladder)
        sel = _forced(problem, forced._replace(kernel=kernel), model_error, criterion, threshold,
                      opts, probes)  # fmt: skip
        return _with_facets(sel, facets)
    opts = _Settings(opts, model_error, on_variant or (lambda name: None), work_budget_gflop,
                     probes)  # fmt: skip
    sel = _select_ladder(problem, ladder, rounded_rungs, criterion, threshold, opts)
    if facets is not None:
        sel, facets = _recheck_kernel(problem, sel, facets, kernels, criterion, threshold, opts)
    return _with_facets(sel, facets)


def _recheck_kernel(
    problem: Problem,
    sel: Selection,
    facets: Facets,
    kernels: tuple[str, ...],
    criterion: str,
    threshold: float,
    settings: _Settings,
) -> tuple[Selection, Facets]:
    """When the kernel probe misfits and the ladder chose another variant, the kernels are
    compared again at the chosen variant (each started from the chosen optimum): a misfitting
    probe ranks kernels by how they hide a missing feature, not by the facets' shape (a
    sharp-edged probe of rounded GGX facets preferred Gaussian facets). The better kernel
    (beyond `threshold`) replaces the chosen fit."""
    probe_rows = [r for r in facets.rows if r.name.startswith(f"{facets.probe} (")]
    probe_misfits = any(r.status == Status.MISFITS for r in probe_rows)
    if sel.chosen == facets.probe or not probe_misfits:
        return sel, facets
    chosen = sel.fit.requested
    settled = _kernel_settled(sel.fit, facets, probe_rows)
    if settled is not None:
        return sel, facets._replace(reason=f"{facets.reason}; {settled}")
    scored = {facets.kernel: _criterion(sel.fit, criterion)}
    fits, rows = {facets.kernel: sel.fit}, []
    for kernel in (k for k in kernels if k != facets.kernel):
        v = _ladder_variant(sel.fit)._replace(kernel=kernel)
        t0 = time.perf_counter()
        try:
            fit = _fit_variant(problem, v, settings, (sel.fit,))
        except FitError as err:
            rows.append(not_fitted_row(v._replace(name=f"{chosen.name} ({kernel} facets)"),
                                       Status.NOT_FITTED, str(err)))  # fmt: skip
            continue
        named = v._replace(name=f"{chosen.name} ({kernel} facets)")
        rows.append(_row(fit, named, math.nan, time.perf_counter() - t0))
        c = _criterion(fit, criterion) if fit.success else None
        if c is not None and math.isfinite(c):
            scored[kernel], fits[kernel] = c, fit
    best = min(scored, key=lambda k: scored[k])
    keep = scored[facets.kernel] is not None and scored[best] >= scored[facets.kernel] - threshold
    kernel = facets.kernel if keep else best
    crit = "BIC" if criterion == "bic" else "-2 ln Z"
    others = ", ".join(f"{k} {scored[k] - scored[kernel]:+.3g}" for k in scored if k != kernel)
    reason = (
        f"{facets.reason}; compared again at {chosen.name!r} because the probe misfits: "
        f"{kernel} facets, {crit} relative to it: {others}"
    )
    facets = facets._replace(kernel=kernel, rows=facets.rows + tuple(rows), reason=reason)
    if keep:
        return sel, facets
    fit = fits[kernel]
    new_fits = {**sel.fits, sel.chosen: fit}
    old_chosen = next(r for r in sel.table if r.name == sel.chosen)
    old_best = scored[facets.kernel] - old_chosen.delta  # the ladder's lowest criterion
    shift = min(old_best, scored[kernel]) - old_best  # <= 0: the deltas' new origin
    table = tuple(
        dataclasses.replace(_row(fit, _ladder_variant(fit), 0.0, fit.elapsed_s), name=r.name,
                            delta=scored[kernel] - old_best - shift)
        if r.name == sel.chosen
        else dataclasses.replace(r, delta=r.delta - shift)
        for r in sel.table
    )  # fmt: skip
    return dataclasses.replace(sel, fit=fit, fits=new_fits, table=table,
                               assessment=describe_fit(fit)), facets  # fmt: skip


RECHECK_FACTOR = 10.0
"""The kernels are not compared again at the chosen variant when, at the probe, every other
kernel's `-2 log L` exceeds the chosen kernel's by more than this many times what the chosen
variant's added features gained the chosen kernel there: to overturn the choice another kernel
would have to gain more than `RECHECK_FACTOR + 1` times as much from the same features
(docs/fitting.md §10)."""


def _kernel_settled(fit: FitResult, facets: Facets, probe_rows: list[ComparisonRow]) -> str | None:
    """Why comparing the kernels again at the chosen variant (`fit`) cannot change the choice
    (`RECHECK_FACTOR`), or None when it could (or the probe's numbers are missing)."""
    probe = [f for f in facets.fits if f.requested.name.startswith(f"{facets.probe} (")]
    margins = [r.delta for r in probe_rows if not r.name.endswith(f"({facets.kernel} facets)")]
    if not probe or not margins or not all(math.isfinite(d) for d in margins):
        return None
    gain = max(2.0 * (fit.log_likelihood - probe[-1].log_likelihood), 0.0)
    margin = min(margins)
    if not margin > RECHECK_FACTOR * gain:
        return None
    return (
        f"not compared again at {fit.requested.name!r}: at the probe every other kernel is "
        f"{margin:.3g} worse, more than {RECHECK_FACTOR:g} x the {gain:.3g} that variant's "
        "added features gained there"
    )


KERNEL_PROBE = "sharp+floor"
"""The variant every facet kernel is fitted with before the ladder (`choose_kernel`): the
simplest variant with a body reflection, which the lab model's scenes (dark plastics under a
lamp) need, and in which the kernels differ only in their lobes' shape."""

KERNEL_PROBE_ROUNDED = "rounded+floor"
"""The second probe, when every kernel misfits at `KERNEL_PROBE`: a sharp probe of a rounded
staircase ranks the kernels by how they hide the missing arcs, not by the facets' shape (on
Mitsuba's rounded GGX staircase it preferred Gaussian facets by 29 BIC; at this variant GGX
wins by 1240)."""


def choose_kernel(
    problem: Problem,
    ladder: tuple[Variant, ...],
    kernels: tuple[str, ...],
    criterion: str,
    threshold: float,
    settings: _Settings,
) -> Facets:
    """Fit the probe variant (`KERNEL_PROBE`, else the ladder's first) with every kernel and
    choose by the ladder's rule: the lowest criterion, and among those within `threshold` of it
    the first of `kernels` (they have the same number of parameters). When every kernel
    misfits there and the ladder has `KERNEL_PROBE_ROUNDED`, the kernels are fitted again
    with it (each started from its own first probe) and chosen there."""
    probe = next((v for v in ladder if v.name == KERNEL_PROBE), ladder[0])
    facets, fits = _probe_kernels(problem, probe, kernels, criterion, threshold, settings, {})
    rounded = next((v for v in ladder if v.name == KERNEL_PROBE_ROUNDED), None)
    if rounded is None or not all(r.status != Status.OK for r in facets.rows):
        return facets._replace(fits=_chosen(fits, facets.kernel))
    second, fits2 = _probe_kernels(problem, rounded, kernels, criterion, threshold, settings, fits)
    reason = (f"{second.reason}, fitted because every kernel misfits at '{probe.name}' "
              f"({facets.reason})")  # fmt: skip
    return second._replace(
        rows=facets.rows + second.rows,
        reason=reason,
        fits=_chosen(fits, second.kernel) + _chosen(fits2, second.kernel),
    )


def _chosen(fits: dict[str, FitResult], kernel: str) -> tuple[FitResult, ...]:
    """The fit of `kernel` among a probe's fits (none if it did not converge)."""
    return (fits[kernel],) if kernel in fits else ()


def _probe_kernels(
    problem: Problem,
    probe: Variant,
    kernels: tuple[str, ...],
    criterion: str,
    threshold: float,
    settings: _Settings,
    starts: dict[str, FitResult],
) -> tuple[Facets, dict[str, FitResult]]:
    """`probe` fitted with every kernel (each also from `starts[kernel]` and from the optima of
    the kernels fitted before it at this probe), the choice by the ladder's rule, and the
    converged fits by kernel.

    Lobes of the same width differ mostly in their tails, so another kernel's optimum starts
    a kernel near its own: started from the widths alone, a misfitting microfacet probe can run
    off to a flat lobe (roughness and scale both huge) and lose the comparison for it
    (docs/fitting.md §4)."""
    rows, scored, fits = [], {}, {}
    for kernel in kernels:
        v = probe._replace(kernel=kernel, name=f"{probe.name} ({kernel} facets)")
        t0 = time.perf_counter()
        parents = ((starts[kernel],) if kernel in starts else ()) + tuple(fits.values())
        try:
            fit = _fit_variant(problem, v, settings, parents)
        except FitError as err:
            rows.append(not_fitted_row(v, Status.NOT_FITTED, str(err)))
            continue
        rows.append(_row(fit, v, math.nan, time.perf_counter() - t0))
        c = _criterion(fit, criterion) if fit.success else None
        if c is not None and math.isfinite(c):
            scored[kernel], fits[kernel] = c, fit
    if not scored:
        raise FitError("no facet kernel converged: " + "; ".join(r.status_text for r in rows))
    best = min(scored.values())
    chosen = next(k for k in kernels if k in scored and scored[k] <= best + threshold)
    crit = "BIC" if criterion == "bic" else "-2 ln Z"
    others = ", ".join(f"{k} {scored[k] - scored[chosen]:+.3g}" for k in scored if k != chosen)
    reason = (
        f"{chosen} facets: {crit} of '{probe.name}' relative to it: {others}"
        if others
        else f"{chosen} facets: the only kernel whose '{probe.name}' converged"
    ) + ("" if scored[chosen] == best else f" (within {threshold:g} of the best; the simpler)")
    rows = [dataclasses.replace(r, delta=scored.get(k, math.nan) - scored[chosen])
            for r, k in zip(rows, kernels, strict=True)]  # fmt: skip
    return Facets(chosen, probe.name, tuple(rows), reason), fits


def _with_facets(sel: Selection, facets: Facets | None) -> Selection:
    """The selection with its facets record, and the reason saying which and why."""
    if facets is None:
        return sel
    return dataclasses.replace(sel, facets=facets, reason=f"{sel.reason}; {facets.reason}")


class _Settings(NamedTuple):
    """How every variant of a ladder is fitted; `budget_gflop`: no further variant is started
    once the ladder's rows have done this much work (`ladder_work`; None: no limit)."""

    options: LeastSquaresOptions
    model_error: bool
    on_variant: Callable[[str], None]
    budget_gflop: float | None = None
    starts: tuple[FitResult, ...] = ()
    """Fits of the same problem (the chosen kernel's probes) whose optima also start the
    variant of the same name (`_probe_starts`)."""


def _probe_starts(v: Variant, starts: tuple[FitResult, ...]) -> tuple[FitResult, ...]:
    """The fits in `starts` of the variant `v` itself (same free parameters and kernel)."""
    free = v.free | {"model_error_frac"}
    return tuple(f for f in starts
                 if f.requested.kernel == v.kernel and f.requested.free | {"model_error_frac"}
                 == free and f.requested.per_wedge_sigma == v.per_wedge_sigma)  # fmt: skip


def _select_ladder(
    problem: Problem,
    ladder: tuple[Variant, ...],
    policy: str,
    criterion: str,
    threshold: float,
    opts: _Settings,
) -> Selection:
    """The sharp rungs, then (always, or when they do not describe the data) the rounded ones,
    then in the same way the fillet rungs."""
    filleted = tuple(v for v in ladder if _is_filleted(v))
    if filleted:
        return _select_fillets(problem, ladder, filleted, policy, criterion, threshold, opts)
    rounded = tuple(v for v in ladder if _is_rounded(v))
    if not rounded:
        return _choose(ladder, _fit_ladder(problem, ladder, opts), criterion, threshold)
    sharp = tuple(v for v in ladder if not _is_rounded(v))
    runs = _fit_ladder(problem, sharp, opts)
    why = "the preset fits them always"
    if policy == "when_needed" and sharp:
        sel = _choose(sharp, runs, criterion, threshold)
        needed, why = rounding_needed(sel)
        if not needed:
            skipped = {v.name: not_fitted_row(v, Status.NOT_FITTED, "rounding not needed")
                       for v in rounded}  # fmt: skip
            return _with_rounding(
                _choose(ladder, _Runs(runs.fits, {**runs.rows, **skipped}), criterion,
                        threshold),
                Rounding(policy, False, why, len(rounded), 0.0),
            )  # fmt: skip
    t0 = time.perf_counter()
    runs = _fit_ladder(problem, rounded, opts, runs)
    sel = _choose(ladder, runs, criterion, threshold)
    return _with_rounding(sel, Rounding(policy, True, why, len(rounded), time.perf_counter() - t0))


def _with_rounding(sel: Selection, rounding: Rounding) -> Selection:
    """The selection with its rounding record, and the reason saying what happened."""
    what = "were fitted" if rounding.fitted else "were not fitted"
    took = f" (in {rounding.elapsed_s:.0f} s)" if rounding.fitted else ""
    if rounding.fitted and any(r.detail == PROBE_KEPT for r in sel.table):
        took = (
            f" (in {rounding.elapsed_s:.0f} s: the ladder's budget was spent, so the "
            "rungs the kernel probes had fitted are kept)"
        )
    reason = f"{sel.reason}; the rounded variants {what}{took} because {rounding.reason}"
    return dataclasses.replace(sel, rounding=rounding, reason=reason)


def _is_rounded(v: Variant) -> bool:
    return "edge_radius_um" in v.free


def _is_filleted(v: Variant) -> bool:
    return FILLET in v.free


def _select_fillets(
    problem: Problem,
    ladder: tuple[Variant, ...],
    filleted: tuple[Variant, ...],
    policy: str,
    criterion: str,
    threshold: float,
    opts: _Settings,
) -> Selection:
    """The ladder without its fillet rungs (`_select_ladder`), then the fillet rungs: always,
    or (`when_needed`) only when the variant chosen without them misfits (`rounding_needed`'s
    rule). Each fillet rung starts from its fitted parents' optima (a rounded variant's)."""
    rest = tuple(v for v in ladder if not _is_filleted(v))
    base = _select_ladder(problem, rest, policy, criterion, threshold, opts) if rest else None
    fits = dict(base.fits) if base else {}
    rows = {r.name: r for r in base.table} if base else {}
    needed, why = (
        (True, "the ladder has no variant without fillets") if base is None else (False, "")
    )
    if base is not None:
        needed, why = (
            fillet_needed(base)
            if policy == "when_needed"
            else (True, "the preset fits them always")
        )
    rounding = (
        base.rounding
        if base is not None and base.rounding is not None
        else Rounding(policy, False, "the ladder has no rounded variants", 0, 0.0)
    )
    if not needed:
        skipped = {
            v.name: not_fitted_row(v, Status.NOT_FITTED, "fillets not needed") for v in filleted
        }
        sel = _choose(ladder, _Runs(fits, {**rows, **skipped}), criterion, threshold)
        return _with_fillets(
            sel, rounding._replace(fillet_reason=why, fillet_n_variants=len(filleted))
        )
    t0 = time.perf_counter()
    runs = _fit_ladder(problem, filleted, opts, _Runs(fits, rows))
    sel = _choose(ladder, runs, criterion, threshold)
    elapsed = time.perf_counter() - t0
    return _with_fillets(
        sel, rounding._replace(fillet_fitted=True, fillet_reason=why,
                               fillet_n_variants=len(filleted), fillet_elapsed_s=elapsed)
    )  # fmt: skip


def _with_fillets(sel: Selection, rounding: Rounding) -> Selection:
    """The selection with its rounding record (fillets included) and the reason."""
    sel = _with_rounding(sel, rounding) if rounding.n_variants else sel
    sel = dataclasses.replace(sel, rounding=rounding)
    what = "were fitted" if rounding.fillet_fitted else "were not fitted"
    took = f" (in {rounding.fillet_elapsed_s:.0f} s)" if rounding.fillet_fitted else ""
    reason = f"{sel.reason}; the fillet variants {what}{took} because {rounding.fillet_reason}"
    return dataclasses.replace(sel, reason=reason)


def fillet_needed(selection: Selection) -> tuple[bool, str]:
    """Whether the variant chosen without fillets leaves a misfit that fillets could explain:
    the misfit rule of `rounding_needed` (and `describe_fit`) applied to it. Returns (needed,
    the reason in words). docs/fitting.md §4."""
    fit = selection.fit
    a = selection.assessment if selection.assessment is not None else describe_fit(fit)
    if a.misfits:
        return True, (
            f"the best variant without fillets {selection.chosen!r} misfits: it {a.because()}"
        )
    return False, (
        f"the best variant without fillets {selection.chosen!r} describes the data "
        f"({chi2_text(fit.chi2, fit.dof)})"
    )


def rounding_needed(selection: Selection) -> tuple[bool, str]:
    """Whether the chosen sharp variant leaves a misfit that edge rounding could explain: the
    misfit rule of `describe_fit` (a model-error term above the smaller of 1% and twice the
    median relative standard error, or a chi^2 tail probability below `P_VALUE_LIMIT`), the
    rule that also puts MISFIT at the top of the summary. A smaller model-error term is
    reported but does not trigger the rounded fits' compilation: with precise data the term
    is significant at a level no resolvable edge radius changes (measured: 1-2.3e-4 on the
    sharp demo and the independent renderer's sharp photos). Returns (needed, the reason in
    words). docs/fitting.md §4."""
    fit = selection.fit
    a = selection.assessment if selection.assessment is not None else describe_fit(fit)
    if a.misfits:
        return (
            True,
            f"the best sharp variant {selection.chosen!r} misfits: it {a.because()}",
        )
    if a.model_error_frac is not None:
        return False, (
            f"the best sharp variant {selection.chosen!r} describes the data: its model-error "
            f"term ({100 * a.model_error_frac:.2g}% of the model) is within the limit "
            f"{100 * a.model_error_limit:.2g}%, {chi2_text(fit.chi2, fit.dof)}"
        )
    return False, (
        f"the best sharp variant {selection.chosen!r} describes the data (no model-error term "
        f"needed, {chi2_text(fit.chi2, fit.dof)})"
    )


def _forced(
    problem: Problem,
    v: Variant,
    model_error: bool,
    criterion: str,
    threshold: float,
    opts: LeastSquaresOptions,
    probes: tuple[FitResult, ...] = (),
) -> Selection:
    """Fit only `v`, also from the kernel probes' optima (`probes`) of it and of its sharp
    counterpart."""
    v = v.with_free(model_error=True) if model_error else v
    parents: tuple[FitResult, ...] = ()
    if _is_rounded(v):  # start from the sharp counterpart: r near 0 if the data are sharp
        sharp = v._replace(free=v.free - {"edge_radius_um", FILLET})
        parent = fit_least_squares(problem, variant=sharp, options=opts,
                                   start_from=_probe_starts(sharp, probes))  # fmt: skip
        parents = (parent,) if parent.success else ()
    if _is_filleted(v):  # then from the rounded counterpart: r_f near 0 if the data are rounded
        rounded = v._replace(free=v.free - {FILLET})
        parent = fit_least_squares(problem, variant=rounded, options=opts, start_from=parents)
        parents = (parent,) if parent.success else ()
    t0 = time.perf_counter()
    fit = fit_least_squares(problem, variant=v, options=opts,
                            start_from=parents + _probe_starts(v, probes))  # fmt: skip
    if not fit.success:
        raise FitError(f"the forced variant {v.name!r} did not converge: {fit.message}")
    emit(fit.warnings)
    row = _row(fit, v, 0.0, time.perf_counter() - t0)
    return Selection(v.name, fit, (row,), f"{v.name!r} was forced by the caller", criterion,
                     threshold, True, {v.name: fit}, None, describe_fit(fit))  # fmt: skip


class _Runs(NamedTuple):
    """Fits of the ladder so far: converged fits by name and the table row of every variant."""

    fits: dict[str, FitResult]
    rows: dict[str, ComparisonRow]


def parents_of(v: Variant, ladder: tuple[Variant, ...]) -> tuple[Variant, ...]:
    """The variants of `ladder` with exactly one optional feature fewer than `v` (its parents:
    `sharp` for `sharp+floor`; `sharp+floor` and `sharp+delta_n` for `sharp+delta_n+floor`)."""
    mine = set(v.features)
    return tuple(u for u in ladder if set(u.features) < mine and len(mine - set(u.features)) == 1)


def _fit_ladder(
    problem: Problem, ladder: tuple[Variant, ...], settings: _Settings, done: _Runs | None = None
) -> _Runs:
    """Fit `ladder` from simple to rich, each variant also from its fitted parents' optima
    (parents among `done` too); every variant gets a row, failures with their status."""
    fits = dict(done.fits) if done else {}
    rows = dict(done.rows) if done else {}
    known = tuple({v.name: v for v in ladder}.values()) + tuple(
        _ladder_variant(f) for n, f in fits.items() if n not in {v.name for v in ladder}
    )
    for v in sorted(ladder, key=lambda u: len(u.features)):
        skip = _skip_reason(v, known, rows, settings, bool(fits))
        probe = _converged_probe(v, settings.starts) if skip is not None else None
        if probe is not None and not _parents_added_nothing(v, known, rows):
            fits[v.name] = probe  # the budget is spent, but this variant was fitted as a probe
            rows[v.name] = dataclasses.replace(_row(probe, v, math.nan, 0.0), detail=PROBE_KEPT)
            continue
        if skip is not None:
            rows[v.name] = not_fitted_row(v, Status.NOT_FITTED, skip)
            continue
        parents = tuple(fits[u.name] for u in parents_of(v, known) if u.name in fits)
        t0 = time.perf_counter()
        fit = _kept_probe(v, settings, parents)
        kept = fit is not None  # its steps were spent by the kernel probes, not the ladder
        if kept:
            settings.on_variant(v.name)  # a rung done, for the progress bar
        try:
            if fit is None:
                starts = parents + _probe_starts(v, settings.starts)
                fit = _fit_variant(problem, v, settings, starts, _added(v, parents))
        except UnconstrainedError as err:  # a misfit running to a degenerate limit, or no signal
            rows[v.name] = _unconstrained_row(v, err)
            continue
        except FitError as err:
            rows[v.name] = not_fitted_row(v, Status.UNIDENTIFIABLE, str(err))
            continue
        row = _row(fit, v, math.nan, time.perf_counter() - t0)
        row = row if kept else _with_work(row, fit)  # a kept probe's work is not the ladder's
        judged = fit.success or _stopped(fit, v, parents)
        nothing = _adds_nothing(fit, v, parents) if judged else None
        if nothing is not None:
            rows[v.name] = _adds_nothing_row(fit, v, parents, row, nothing)
        elif fit.success:
            fits[v.name] = fit
            rows[v.name] = row
        else:  # its best start's numbers are kept: an upper bound of what the variant reaches
            detail = f"{fit.message.split(':')[0]} after {fit.num_steps} steps"
            rows[v.name] = dataclasses.replace(row, status=Status.NOT_CONVERGED, detail=detail,
                                               bic=math.nan, aic=math.nan,
                                               laplace_log_evidence=None)  # fmt: skip
    return _Runs(fits, rows)


def _skip_reason(
    v: Variant,
    known: tuple[Variant, ...],
    rows: dict[str, ComparisonRow],
    settings: _Settings,
    any_fitted: bool,
) -> str | None:
    """Why `v` is not tried (None: it is): every parent added nothing (the escalation stops
    where each route to a rung passes through one that changed nothing), or the ladder's
    budget is spent (`ladder_work`) and some variant has already converged."""
    if _parents_added_nothing(v, known, rows):
        names = " and ".join(repr(u.name) for u in parents_of(v, known))
        return f"not tried: {names} added nothing"
    budget = settings.budget_gflop
    if any_fitted and budget is not None and ladder_work(rows) >= budget:
        return f"{BUDGET_SPENT} ({budget:g} Gflop of solver work) was spent"
    return None


BUDGET_SPENT = "not tried: the ladder's budget"
"""How the detail of a rung left untried by the ladder's budget begins (`budget_untried`)."""


def budget_untried(sel: Selection) -> tuple[str, ...]:
    """The rungs of `sel` that the ladder's budget left untried, in ladder order."""
    untried = (r for r in sel.table if r.status == Status.NOT_FITTED)
    return tuple(r.name for r in untried if r.detail.startswith(BUDGET_SPENT))


def ladder_work(rows: dict[str, ComparisonRow]) -> float:
    """The work (Gflop) the ladder has done on `rows` (the kernel probes' not counted)."""
    return sum(r.work_gflop for r in rows.values())


def _with_work(row: ComparisonRow, fit: FitResult) -> ComparisonRow:
    """The row with the work of its fit (`FitResult.solver_steps`, `work_gflop`: each solve
    of its refinement at the cost of its own steps)."""
    return dataclasses.replace(row, solver_steps=fit.solver_steps, work_gflop=fit.work_gflop())


def _parents_added_nothing(
    v: Variant, known: tuple[Variant, ...], rows: dict[str, ComparisonRow]
) -> bool:
    """Whether `v` has parents and every one of them added nothing (the escalation stops)."""
    parents = [rows.get(u.name) for u in parents_of(v, known)]
    return bool(parents) and all(r is not None and r.status == Status.ADDS_NOTHING
                                 for r in parents)  # fmt: skip


PROBE_KEPT = "the kernel probe's fit of this variant: the ladder's budget was spent"
"""A ladder row's detail when the budget left no time to fit the variant again, and the chosen
kernel's probe had fitted that very variant (same free parameters and kernel)."""


def _converged_probe(v: Variant, starts: tuple[FitResult, ...]) -> FitResult | None:
    """The best converged fit among the probes of `v` itself (`_probe_starts`), or None."""
    done = [f for f in _probe_starts(v, starts) if f.success]
    return min(done, key=lambda f: f.chi2, default=None)


def _kept_probe(
    v: Variant, settings: _Settings, parents: tuple[FitResult, ...]
) -> FitResult | None:
    """The chosen kernel's converged probe fit of `v` itself, when it is at least as likely as
    every fitted parent (so a refit from the parents' optima could not be needed to keep it
    from ending worse than them); None otherwise. The probe was fitted with the ladder's own
    settings, so fitting it again would repeat its work."""
    probe = _converged_probe(v, settings.starts)
    if probe is None or any(probe.log_likelihood < p.log_likelihood for p in parents):
        return None
    return dataclasses.replace(probe, requested=probe.requested._replace(name=v.name),
                               variant=probe.variant._replace(name=v.name))  # fmt: skip


def _best_parent(parents: tuple[FitResult, ...]) -> FitResult:
    return max(parents, key=lambda f: f.log_likelihood)


def _added(v: Variant, parents: tuple[FitResult, ...]) -> frozenset[str]:
    """The parameters `v` adds over its most likely fitted parent (none without parents)."""
    return frozenset(set(v.free) - set(_best_parent(parents).requested.free)) if parents else (
        frozenset()
    )  # fmt: skip


def _adds_nothing_row(
    fit: FitResult, v: Variant, parents: tuple[FitResult, ...], row: ComparisonRow, why: str
) -> ComparisonRow:
    """The row of a variant that adds nothing: when the parameters it adds were fixed, its fit
    is its most likely parent again, whose numbers it shows (the ladder stops fitting it as
    soon as they are fixed, `fit_least_squares(stop_when_fixed=...)`)."""
    best = _best_parent(parents)
    if _stopped(fit, v, parents):
        row = dataclasses.replace(_row(best, v, math.nan, row.elapsed_s), notes=row.notes,
                                  solver_steps=row.solver_steps,  # its own work, not the parent's
                                  work_gflop=row.work_gflop)  # fmt: skip
    return dataclasses.replace(row, status=Status.ADDS_NOTHING, detail=why)


def _stopped(fit: FitResult, v: Variant, parents: tuple[FitResult, ...]) -> bool:
    """Whether the refinement fixed every parameter `v` adds over its most likely parent (so
    the fit is that parent again, converged or not where it stopped)."""
    added = _added(v, parents)
    return bool(added) and added <= fixed_names(fit.warnings)


def _adds_nothing(fit: FitResult, v: Variant, parents: tuple[FitResult, ...]) -> str | None:
    """Why the converged `fit` of `v` is its parent again (None when it adds something): each
    parameter it adds over a parent was fixed on a bound or as unidentified, or `-2 log L`
    falls by less than `GAIN_MIN` below the best parent's."""
    if not parents:
        return None
    best = _best_parent(parents)
    added = _added(v, parents)
    removed = {w.parameter: w.code.replace("_", " ") for w in fit.warnings
               if w.code in FIXING_CODES}  # fmt: skip
    if _stopped(fit, v, parents):
        what = ", ".join(f"{p} {removed[p]}" for p in sorted(added))
        return f"{what}: the fit is {best.requested.name!r} again"
    gain = 2.0 * (fit.log_likelihood - best.log_likelihood)
    if gain < GAIN_MIN:
        return (
            f"-2 log L only {gain:.3g} below {best.requested.name!r} (< {GAIN_MIN:g}): "
            "the added parameters change nothing the data show"
        )
    return None


def _fit_variant(
    problem: Problem,
    v: Variant,
    settings: _Settings,
    parents: tuple[FitResult, ...],
    stop_when_fixed: frozenset[str] = frozenset(),
) -> FitResult:
    """One variant of the ladder, also started from its parents' optima; `stop_when_fixed`:
    see `fit_least_squares`."""
    v_run = v.with_free(model_error=True) if settings.model_error else v
    try:
        return fit_least_squares(problem, variant=v_run, options=settings.options,
                                 start_from=parents, stop_when_fixed=stop_when_fixed)  # fmt: skip
    finally:
        settings.on_variant(v.name)


def _ladder_variant(fit: FitResult) -> Variant:
    """The ladder variant a fit was asked for (without the model-error term all share)."""
    v = fit.requested
    return v._replace(free=v.free - {"model_error_frac"})


def _unconstrained_row(v: Variant, err: UnconstrainedError) -> ComparisonRow:
    """A variant whose width or scale the data cannot constrain: a misfit if its chi^2 is
    improbable (it ran to a degenerate limit), else unidentifiable."""
    if chi2_p_value(err.chi2, err.dof) < P_VALUE_LIMIT:
        detail = (
            f"{chi2_text(err.chi2, err.dof)}; {err.parameter} ran to a degenerate limit where "
            "the data no longer constrain it"
        )
        return not_fitted_row(v, Status.MISFITS, detail, err.chi2, err.dof)
    return not_fitted_row(v, Status.UNIDENTIFIABLE, str(err), err.chi2, err.dof)


def _choose(
    ladder: tuple[Variant, ...], runs: _Runs, criterion: str, threshold: float
) -> Selection:
    """Apply the rule (module doc) to the fitted variants and build the table."""
    fits = {n: f for n, f in runs.fits.items() if n in {v.name for v in ladder}}
    scored = {n: _criterion(f, criterion) for n, f in fits.items()}
    scored = {n: c for n, c in scored.items() if c is not None and math.isfinite(c)}
    if not scored:
        raise FitError(
            "no variant of the ladder converged: "
            + "; ".join(f"{k}: {r.status_text}" for k, r in runs.rows.items())
        )
    best_name = min(scored, key=lambda n: scored[n])
    best = scored[best_name]
    order = {v.name: i for i, v in enumerate(ladder)}
    candidates = [n for n, c in scored.items() if c <= best + threshold]
    chosen = min(candidates, key=lambda n: (fits[n].n_free, round(scored[n], 6), order[n]))
    table = []
    for v in ladder:
        row = runs.rows[v.name]
        c = scored.get(v.name)
        delta = math.nan if c is None or v.name not in fits else c - best
        table.append(dataclasses.replace(row, delta=delta))
    reason = _reason(chosen, best_name, fits, scored, criterion, threshold)
    emit(fits[chosen].warnings)
    return Selection(chosen, fits[chosen], tuple(table), reason, criterion, threshold, False, fits,
                     None, describe_fit(fits[chosen]))  # fmt: skip


def _find(force: str | Variant, ladder: tuple[Variant, ...]) -> Variant:
    if isinstance(force, Variant):
        return force
    for v in ladder:
        if v.name == force:
            return v
    names = ", ".join(v.name for v in ladder)
    raise FitInputError(f"force = {force!r} is not a variant of the ladder; choose one of {names}")


def _row(fit: FitResult, v: Variant, delta: float, elapsed_s: float) -> ComparisonRow:
    notes = ", ".join(dict.fromkeys(f"{w.parameter} {w.code.replace('_', ' ')}"
                                    for w in fit.warnings if w.code in FIXING_CODES))  # fmt: skip
    a = describe_fit(fit)
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
        status=a.status,
        notes=notes,
        detail="; ".join(a.reasons),
        chi2_measurement=a.chi2_measurement,
        dof=fit.dof,
        elapsed_s=elapsed_s,
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
    mine = set(fits[chosen].requested.features)
    simpler = [scored[n] - scored[best] for n in scored
               if set(fits[n].requested.features) < mine]  # fmt: skip
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
