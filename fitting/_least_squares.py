"""Least squares with optimistix: options, the fit of one variant, and its refinement loop.

Each fit is a multi-start solve (`_core`), then the active set and the identifiability rule
(`_identify`) fix parameters on bounds or unconstrained by the data, one at a time, and refit;
the result is assembled in `_result` [conventions §9, §10]. Design: docs/fitting.md §3.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import numpy as np
import optimistix as optx

from stairfit import model

from ._core import CoreFit, SolveWork, fit_core, make_solver
from ._errors import FitError, FitInputError, FitWarning, emit, with_overrides
from ._identify import IDENTIFIABILITY_THRESHOLD, PROFILE_DELTA, apply_fix, on_bound, unidentified
from ._observations import Observations, Spectral
from ._params import (
    DEFAULTS,
    FILLET,
    PARAM_NAMES,
    SIMPLEST,
    Params,
    Priors,
    Variant,
    from_physical,
)  # fmt: skip
from ._problem import FreeSpec, Problem, as_problem, spec_for
from ._result import FitResult, make_result

DEFAULT_SIGMA_STARTS_RAD: tuple[float, ...] = tuple(float(x) for x in np.deg2rad([1, 3, 10, 30]))
"""Starting widths of the multi-start (log-spaced, 1 to 30 deg): the chi^2 landscape in sigma
is multimodal when lobes overlap."""


class LeastSquaresOptions(NamedTuple):
    """How `fit_least_squares` fits (every field is also a keyword of `fit_least_squares` and
    `select_model`).

    `solver`: `lm` (optimistix LevenbergMarquardt), `dogleg` or `gauss_newton`, with tolerances
    `rtol`, `atol` and at most `max_steps` steps per start; one start per width in
    `sigma_starts_rad`. `identifiability`: fix parameters the data do not constrain (standard
    error above `identifiability_threshold` x the prior's sd, or a singular Fisher direction).
    `on_failure`: `raise` (`FitError` when no start converges) or `flag` (a result with
    `success=False`). `emit_warnings`: also pass the result's warnings to `warnings.warn`.
    """

    solver: str = "lm"
    rtol: float = 1e-8
    atol: float = 1e-8
    max_steps: int = 256
    sigma_starts_rad: tuple[float, ...] = DEFAULT_SIGMA_STARTS_RAD
    identifiability: bool = True
    identifiability_threshold: float = IDENTIFIABILITY_THRESHOLD
    on_failure: str = "raise"
    emit_warnings: bool = True

    def updated(self, **overrides: Any) -> LeastSquaresOptions:
        """A copy with `overrides` (field names; a `TypeError` for an unknown one)."""
        return with_overrides(self, "least-squares", overrides)

    def validated(self) -> LeastSquaresOptions:
        """Self, or `FitInputError` naming the bad option and the fix."""
        if self.on_failure not in ("raise", "flag"):
            raise FitInputError(f"on_failure = {self.on_failure!r}; use 'raise' or 'flag'")
        if self.max_steps < 1:
            raise FitInputError(f"max_steps = {self.max_steps}; give at least 1")
        starts = self.sigma_starts_rad
        if len(starts) == 0 or not all(s > 0 for s in starts):
            raise FitInputError("sigma_starts_rad must hold at least one positive width (rad)")
        return self


def fit_least_squares(
    observations: Observations | Problem,
    spectral: Spectral | None = None,
    variant: Variant = SIMPLEST,
    options: LeastSquaresOptions | None = None,
    *,
    fixed: Params = DEFAULTS,
    priors: Priors | None = None,
    aperture: model.Aperture | None = None,
    resolution: int | None = None,
    start_from: tuple[FitResult, ...] = (),
    stop_when_fixed: frozenset[str] = frozenset(),
    **option_overrides: Any,
) -> FitResult:
    """Fit one model variant by least squares [conventions §9].

    Whitened residuals `(value - model) / uncertainty` over the used rows are minimised with an
    optimistix solver (`throw=False`) from one start per width in `sigma_starts_rad`; the
    lowest chi^2 among converged starts wins. The covariance is the inverse Fisher information
    at the optimum, mapped to physical units by the delta method. With `identifiability`, free
    parameters the data do not constrain (see `IDENTIFIABILITY_THRESHOLD`) are fixed at their
    `fixed` value, one at a time, with a warning, and the fit is repeated.

    `options` (`LeastSquaresOptions`) say how; any of its fields may also be given as a keyword
    (`solver="dogleg"`, `max_steps=64`, ...), overriding `options`. `observations` may be a
    prepared `Problem` (then `spectral`, `fixed`, `priors`, `aperture` and `resolution` come
    from it). With `on_failure="raise"` a fit whose best start did not converge raises
    `FitError`; with `"flag"` it returns a result with `success=False` and no covariance.
    Non-finite optima always raise.

    `start_from`: fits of the same problem (e.g. the variants with one optional feature fewer)
    whose optima are also used as starts (`nested_start`), in every solve of the refinement
    loop: a superset of parameters started at a subset's optimum cannot end worse than it
    (Levenberg-Marquardt only accepts steps that lower the objective).

    `stop_when_fixed`: parameter names; once the refinement has fixed every one of them
    (unidentified or on a bound) it stops, and the result is the fit in which they were found
    so, with their warnings. The model selection asks this of the parameters a variant adds over
    its parent: fixing them makes the fit its parent again, which it already has.
    """
    t0 = time.perf_counter()
    opts = (options or LeastSquaresOptions()).updated(**option_overrides)
    problem = as_problem(observations, spectral, fixed=fixed, priors=priors, aperture=aperture,
                         resolution=resolution)  # fmt: skip
    opts.validated()
    _check_signal(problem)
    solver = make_solver(opts.solver, opts.rtol, opts.atol)
    extra = tuple(nested_start(problem, f) for f in start_from)
    if FILLET in variant.free:
        extra += tuple(z for f in start_from if (z := fillet_split_start(problem, f)) is not None)
    refined = _refine(problem, spec_for(variant, problem), solver, opts, extra, stop_when_fixed)
    result = make_result(problem, variant, refined.core, opts.solver, refined.records,
                         refined.unidentified, t0, refined.solves)  # fmt: skip
    if not result.success and opts.on_failure == "raise":
        raise FitError(
            f"least squares did not converge for variant {variant.name!r} with {opts.solver}: "
            f"{result.message} (best start after {result.num_steps} steps of max_steps = "
            f"{opts.max_steps}); raise max_steps, try another solver, or check the data"
        )
    if opts.emit_warnings:
        emit(result.warnings)
    return result


class _Refined(NamedTuple):
    """The last core fit of the refinement loop, its warnings, the unidentified labels and the
    work of every solve in the loop."""

    core: CoreFit
    records: list[FitWarning]
    unidentified: list[str]
    solves: tuple[SolveWork, ...]


class _Step(NamedTuple):
    """One step of the refinement loop: the spec to fit next (None = done), a core fit that
    already belongs to it (or None), and the warning to record (or None)."""

    spec: FreeSpec | None
    core: CoreFit | None = None
    warning: FitWarning | None = None
    unidentified: str | None = None


def _refine(
    problem: Problem,
    spec: FreeSpec,
    solver: optx.AbstractLeastSquaresSolver,
    opts: LeastSquaresOptions,
    extra: tuple[np.ndarray, ...] = (),
    stop: frozenset[str] = frozenset(),
) -> _Refined:
    """Fit, then fix parameters on bounds or unidentified one at a time and refit, until
    nothing changes (at most `2 x slots + 2` rounds), or until every parameter in `stop` is
    fixed (`fit_least_squares`); `extra` starts go into every solve."""

    spent: list[SolveWork] = []  # every solve, the near-bound checks' included

    def solve(s: FreeSpec) -> CoreFit:
        core = fit_core(problem, s, solver, opts.max_steps, opts.sigma_starts_rad, extra)
        spent.append(SolveWork.of(core.total_steps, core.static, core.data))
        return core

    core = solve(spec)
    records: list[FitWarning] = []
    names: list[str] = []
    checked: set[FreeSpec] = set()
    for _ in range(2 * problem.layout.size + 2):
        step = _next_step(problem, core, checked, opts, solve)
        if step.warning is not None:
            records.append(step.warning)
        if step.unidentified is not None:
            names.append(step.unidentified)
        if step.spec is None or (stop and stop <= fixed_names(records)):
            break
        core = step.core if step.core is not None else solve(step.spec)
    return _Refined(core, records, names, tuple(spent))


FIXING_CODES = ("unidentified", "at_bound")
"""The warning codes of a parameter the refinement fixed (unidentified, or on a bound)."""


def fixed_names(warnings: Sequence[FitWarning]) -> set[str | None]:
    """The parameters the refinement fixed (`FIXING_CODES`), by their warnings."""
    return {w.parameter for w in warnings if w.code in FIXING_CODES}


def _next_step(
    problem: Problem,
    core: CoreFit,
    checked: set[FreeSpec],
    opts: LeastSquaresOptions,
    solve: Callable[[FreeSpec], CoreFit],
) -> _Step:
    """What the refinement loop does after `core`: the active set first, then the
    identifiability rule (see `_refine`)."""
    spec = core.spec
    if not core.success:
        # A model-error term running to 0 (its bound) can keep Levenberg-Marquardt from
        # meeting its tolerance (the variance term is singular there); fixing it on the bound
        # and refitting is what a converged fit would have led to anyway.
        bound = on_bound(problem, spec, core)
        if bound is not None and bound.warning is not None and bound.param == "model_error_frac":
            return _Step(bound.spec, warning=bound.warning)
        if bound is not None and bound.param == "edge_radius_um" and spec not in checked:
            # An edge radius crawling towards 0, where its sine transform is flat, can keep the
            # solver from meeting its tolerance; the profile-likelihood check at the bound
            # decides, as for a converged fit.
            checked.add(spec)
            step = _near_bound_step(core, bound.spec, bound.param, solve)
            return step if step.warning is not None else _Step(None)
        return _Step(None)
    bound = on_bound(problem, spec, core) if spec not in checked else None
    if bound is not None and bound.warning is None:  # near a bound: keep it if the data agree
        checked.add(spec)
        return _near_bound_step(core, bound.spec, bound.param, solve)
    if bound is not None:
        return _Step(bound.spec, warning=bound.warning)
    if not opts.identifiability:
        return _Step(None)
    fix = unidentified(problem, core, opts.identifiability_threshold)
    if fix is None:
        return _Step(None)
    new_spec, rec = apply_fix(problem, spec, fix, core)
    return _Step(new_spec, warning=rec, unidentified=rec.parameter or fix.parameter.label())


def _near_bound_step(
    core: CoreFit, at_bound_spec: FreeSpec, name: str, solve: Callable[[FreeSpec], CoreFit]
) -> _Step:
    """Refit with the parameter on its bound; keep the bound when `-2 log L` rises by less than
    `PROFILE_DELTA` (the bound is inside the 68% profile-likelihood interval)."""
    at_bound = solve(at_bound_spec)
    rise = 2.0 * (float(core.ev.loglik) - float(at_bound.ev.loglik))
    if not (at_bound.success and rise < PROFILE_DELTA):
        return _Step(core.spec, core=core)  # the same fit again; its spec is now checked
    msg = (
        f"{name} is fixed on its bound 0: fixing it there raises -2 log L by only {rise:.3g} "
        f"< {PROFILE_DELTA:g}, so the data cannot tell it from the bound"
    )
    return _Step(at_bound_spec, core=at_bound, warning=FitWarning("at_bound", name, msg))


def _check_signal(problem: Problem) -> None:
    """Refuse data that are consistent with no signal at all: nothing can be fitted to them.

    Under a zero model the whitened sum of squares of the used rows is chi^2 with N degrees of
    freedom; below `N + 3 sqrt(2 N)` (3 standard deviations above its mean) the data do not
    show any signal above their own errors.
    """
    d = problem.data
    use = np.asarray(d.use) > 0
    n = int(use.sum())
    if n == 0:
        return
    chi2_zero = float(np.sum((np.asarray(d.value)[use] / np.asarray(d.stderr)[use]) ** 2))
    if chi2_zero < n + 3.0 * math.sqrt(2.0 * n):
        raise FitError(
            f"the observations hold no usable signal: they are consistent with zero (chi^2 of "
            f"a zero model = {chi2_zero:.4g} for {n} rows); nothing to fit: check the "
            "exposures, the ROIs and the angles"
        )


SIN_NUDGE = 0.05
"""A nested start with the edge radius on a bound of its sine transform (where `dr/dz = 0`,
so no solver could move it) starts `SIN_NUDGE` rad inside it instead: `r = r_max (1 - cos
0.05) / 2 = 6e-4 r_max`, with `dr/dz = 0.025 r_max`."""


def nested_start(problem: Problem, parent: FitResult) -> np.ndarray:
    """A start vector (every slot) at the optimum of `parent`, a fit of the same problem.

    Slots the parent fitted keep its `z`; the others start at the parent's physical values
    (a per-wedge width at the parent's width of that wedge, a parameter the parent fixed at its
    fixed value), an edge or fillet radius on a bound just inside it (`SIN_NUDGE`).
    """
    lay = problem.layout
    p = parent.params
    sigma = np.asarray(p.sigma_rad, float).reshape(-1)
    x = np.zeros(lay.size)
    x[lay.slot("sigma_rad")] = float(np.exp(np.mean(np.log(sigma))))
    for w in range(lay.n_wedges):
        x[lay.slot("sigma_rad", w)] = float(sigma[w] if sigma.size > 1 else sigma[0])
    for name in PARAM_NAMES[1:]:
        x[lay.slot(name)] = float(getattr(p, name))
    r = x[lay.slot("edge_radius_um")]
    z = np.array(
        [from_physical(v, k, problem.r_max_um, r) for v, k in zip(x, lay.kinds, strict=True)]
    )
    for k in (lay.slot("edge_radius_um"), lay.slot("fillet_radius_um")):
        z[k] = float(np.clip(z[k], -0.5 * math.pi + SIN_NUDGE, 0.5 * math.pi - SIN_NUDGE))
    free = list(parent.free_slots)
    z[free] = np.asarray(parent.z)[free]
    return z


def fillet_split_start(problem: Problem, parent: FitResult) -> np.ndarray | None:
    """A second start for a filleted variant from a `parent` without fillets (issue 15): the
    parent's optimum (`nested_start`) with its tip radius `r_p` shared half and half between
    the tip arcs and the fillets, `r = r_f = r_p / 2` (so `r + r_f <= r_max` still holds).

    A rounded fit describes the whole rounded profile with one arc, so on filleted data its
    radius stands for tip and fillet together; from the nested start (`r_f` just off 0) the
    solver can stay on the bound `r_f = 0` with `r` doing the work of both: a 2 MP x 9-view
    simulated folder with `r = 30`, `r_f = 40 um` ended at `r = 54`, `r_f = 0` and a 13.8%
    model-error term (docs/fitting.md §4). None when the parent fitted fillets itself or its
    radius is about 0 (nothing to share: the nested start covers it)."""
    lay = problem.layout
    r_p = float(parent.params.edge_radius_um)
    if lay.slot(FILLET) in parent.free_slots or r_p <= 1e-3 * problem.r_max_um:
        return None
    z = nested_start(problem, parent)
    for name in ("edge_radius_um", FILLET):
        k = lay.slot(name)
        z[k] = from_physical(0.5 * r_p, lay.kinds[k], problem.r_max_um, 0.5 * r_p)
        z[k] = float(np.clip(z[k], -0.5 * math.pi + SIN_NUDGE, 0.5 * math.pi - SIN_NUDGE))
    return z
