"""The outcome of a least-squares fit: `Estimate` per free parameter and `FitResult`.

[conventions §9]; every attribute is documented in the class docstrings and docs/fitting.md §6.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np

from ._core import CoreFit, SolveWork
from ._errors import FitWarning
from ._identify import covariance, within_stderr_of_bound
from ._params import (
    Parameter,
    Params,
    Variant,
    dx_matrix,
    log_prior_split,
    parameter_label,
    split_priors,
)
from ._problem import FreeSpec, Problem

_log_prior_z = jax.jit(log_prior_split, static_argnums=(1, 3))
"""`log_prior_z` as one compiled program per layout and free slots with their priors' kinds
(evaluated op by op it dispatched about 50 small programs per fitted variant); the priors'
numbers are data (`split_priors`)."""


@dataclass(frozen=True)
class Estimate:
    """One fitted parameter.

    `param` (a name of `fitting.PARAMETERS`) and `wedge` (the wedge of a per-wedge width, else
    None) identify it; `value` in `unit`; `stderr` (delta-method standard error from the
    covariance; None when the covariance could not be determined); `at_bound` (the value lies
    within one standard error of a bound of its transform, where Gaussian error bars are not
    meaningful); `wedge_deg` (the wedge angle of a per-wedge width, for the label). `name` is
    the human-readable label (`sigma_rad`, `sigma_rad[2: 30 deg]`, `delta_n`), for display.
    """

    param: str
    wedge: int | None
    value: float
    stderr: float | None
    unit: str
    at_bound: bool = False
    wedge_deg: float | None = None

    @property
    def name(self) -> str:
        """The display label (`parameter_label`)."""
        return self.label()

    def label(self, name: str | None = None) -> str:
        """The display label, optionally under another `name` (e.g. `sigma_deg`)."""
        return parameter_label(name or self.param, self.wedge, self.wedge_deg)


@dataclass(frozen=True)
class FitResult:
    """The outcome of one least-squares fit (immutable; `report()` prints it).

    Attributes:
        variant: the variant as finally fitted (unidentified parameters removed).
        requested: the variant that was asked for.
        params: every physical parameter at the optimum (fixed ones at their fixed values);
            `sigma_rad` is one value per wedge.
        estimates: the free parameters, with standard errors, in covariance order.
        names: `tuple(e.name for e in estimates)` (display labels).
        covariance: physical-unit covariance of the free parameters (delta method from the
            inverse Fisher information); None if it cannot be determined.
        correlation: the correlation matrix; None with `covariance`.
        covariance_z: the covariance in the unconstrained coordinates; None likewise.
        chi2: sum of squared whitened residuals over used rows.
        log_likelihood: maximised Gaussian log-likelihood (full normalisation).
        n_used, n_rows: rows fitted / rows in the table; `excluded_rows` the others' indices;
            `n_saturated` how many of those were saturated.
        n_free: number of free parameters; `dof = n_used - n_free`; `reduced_chi2`.
        bic: `-2 log L + n_free ln(n_used)`; aic: `-2 log L + 2 n_free`.
        success: True when the chosen start converged (optimistix `successful`).
        message: optimistix's result name (and message when not successful).
        num_steps: solver steps of the chosen start; `starts_sigma_rad`, `starts_chi2`,
            `starts_converged`: every start of the multi-start.
        solver: solver name (`lm`, `dogleg`, `gauss_newton`).
        warnings: structured warnings (also emitted with `warnings.warn`).
        unidentified: labels of parameters fixed because the data did not constrain them.
        model: model value per row; residuals: whitened residuals per row (0 when excluded);
            uncertainty: per-row standard deviation used (stderr with the model-error term).
        z: the optimum in the unconstrained coordinates (every slot; used by the posterior).
        free_slots: indices of the free slots of `z`, in covariance order.
        elapsed_s: wall time of the fit (compilation included on a first call).
        solves: every solve of the fit (its refinement's refits included) with its solver
            steps (every start): `solver_steps` adds them up, `work_gflop()` weighs each by
            the cost of one of its steps, a measure of the fit's work that is the same on every
            machine.
        problem: the prepared problem (observations, spectral setup, priors, options).
        spec: the final free set (with parameters fixed on bounds); used by the posterior.
    """

    variant: Variant
    requested: Variant
    params: Params
    estimates: tuple[Estimate, ...]
    covariance: np.ndarray | None
    correlation: np.ndarray | None
    covariance_z: np.ndarray | None
    chi2: float
    log_likelihood: float
    n_used: int
    n_rows: int
    excluded_rows: tuple[int, ...]
    n_saturated: int
    n_free: int
    dof: int
    reduced_chi2: float
    bic: float
    aic: float
    success: bool
    message: str
    num_steps: int
    starts_sigma_rad: tuple[float, ...]
    starts_chi2: tuple[float, ...]
    starts_converged: tuple[bool, ...]
    solver: str
    warnings: tuple[FitWarning, ...]
    unidentified: tuple[str, ...]
    model: np.ndarray = field(repr=False)
    residuals: np.ndarray = field(repr=False)
    uncertainty: np.ndarray = field(repr=False)
    z: np.ndarray = field(repr=False)
    free_slots: tuple[int, ...] = field(repr=False)
    elapsed_s: float = 0.0
    solves: tuple[SolveWork, ...] = field(default=(), repr=False)
    problem: Problem | None = field(default=None, repr=False)
    spec: FreeSpec | None = field(default=None, repr=False)

    @property
    def solver_steps(self) -> int:
        """The solver steps of every start of every solve of the fit."""
        return sum(s.steps for s in self.solves)

    def work_gflop(self) -> float:
        """The fit's work in Gflop: every solve's steps at the cost of one of its steps
        (`fitting.step_gflop`; counted when asked: it lowers each forward model once)."""
        return sum(s.gflop() for s in self.solves)

    @property
    def parameters(self) -> tuple[Parameter, ...]:
        """The free parameters' records (`fitting.Parameter`), in covariance order."""
        if self.problem is None or self.spec is None:
            return ()
        records = self.problem.parameters(self.spec)
        return tuple(records[k] for k in self.free_slots)

    @property
    def laplace_log_evidence(self) -> float | None:
        """Laplace approximation of the log evidence with the priors, or None without a
        covariance: `log L + log prior(z) + (k/2) ln 2 pi + (1/2) ln det C_z` (the prior in
        the unconstrained coordinates includes `log |dx/dz|`)."""
        if self.covariance_z is None or self.problem is None:
            return None
        k = len(self.free_slots)
        spec = tuple((p.slot, p.prior) for p in self.parameters)
        lay = self.problem.layout
        d = self.problem.arrays_for(self.spec) if self.spec is not None else None
        fixed = None if d is None else (d.free, d.x_fixed)  # a fixed r bounds a free r_f
        z = jnp.asarray(self.z)
        r_max = self.problem.r_max_um
        log_prior = float(_log_prior_z(z, tuple(lay.kinds), r_max, *split_priors(spec), fixed))
        logdet = float(np.linalg.slogdet(self.covariance_z)[1])
        return self.log_likelihood + log_prior + 0.5 * k * math.log(2 * math.pi) + 0.5 * logdet

    @property
    def names(self) -> tuple[str, ...]:
        """Display labels of the free parameters, in covariance order."""
        return tuple(e.name for e in self.estimates)

    @property
    def values(self) -> np.ndarray:
        """Fitted values of the free parameters (physical units)."""
        return np.array([e.value for e in self.estimates])

    @property
    def stderrs(self) -> np.ndarray | None:
        """Standard errors of the free parameters, or None without a covariance."""
        if self.covariance is None:
            return None
        return np.sqrt(np.diag(self.covariance))

    def index(self, param: str, wedge: int | None = None) -> int:
        """Position of the free parameter `(param, wedge)` in `estimates` (covariance order)."""
        for i, e in enumerate(self.estimates):
            if (e.param, e.wedge) == (param, wedge):
                return i
        label = parameter_label(param, wedge)
        raise KeyError(f"{label!r} is not a free parameter of this fit ({', '.join(self.names)})")

    def estimate(self, param: str, wedge: int | None = None) -> Estimate:
        """The estimate of the free parameter `param` (of wedge `wedge`'s own width)."""
        return self.estimates[self.index(param, wedge)]

    def report(self) -> str:
        """A plain-text summary: status, goodness of fit, parameters, correlations, warnings."""
        lines = [
            f"least-squares fit of variant {self.variant.name!r} ({self.solver})",
            f"  status: {'converged' if self.success else 'NOT CONVERGED'} ({self.message}) "
            f"after {self.num_steps} steps; best of {len(self.starts_chi2)} starts "
            f"({sum(self.starts_converged)} converged)",
            f"  rows: {self.n_used} used of {self.n_rows}; {len(self.excluded_rows)} excluded "
            f"({self.n_saturated} saturated)",
            f"  chi2 = {self.chi2:.4g}, dof = {self.dof}, reduced chi2 = {self.reduced_chi2:.4g}; "
            f"log L = {self.log_likelihood:.6g}, BIC = {self.bic:.6g}, AIC = {self.aic:.6g}",
            f"  {'parameter':<28} {'value':>13} {'stderr':>11}  unit",
            *(_estimate_line(e) for e in self.estimates),
        ]
        fixed = [
            n
            for n in ("delta_n", "edge_radius_um", "floor", "model_error_frac")
            if n not in self.variant.free
        ]
        if fixed:
            lines.append(
                "  fixed: " + ", ".join(f"{n} = {getattr(self.params, n):.4g}" for n in fixed)
            )
        lines.append(self._correlation_line())
        lines += [f"  warning ({w.code}): {w.message}" for w in self.warnings]
        return "\n".join(line for line in lines if line)

    def _correlation_line(self) -> str:
        if self.correlation is None:
            return "  covariance: could not be determined"
        pairs = [
            f"{self.names[i]}/{self.names[j]} = {self.correlation[i, j]:+.2f}"
            for i in range(len(self.names))
            for j in range(i + 1, len(self.names))
            if abs(self.correlation[i, j]) > 0.5
        ]
        return "  correlations |r| > 0.5: " + "; ".join(pairs) if pairs else ""


def _estimate_line(e: Estimate) -> str:
    """One parameter of `FitResult.report` (widths also in degrees)."""
    se = "n/a" if e.stderr is None else f"{e.stderr:.4g}"
    extra = ""
    if e.param == "sigma_rad":
        sd = "" if e.stderr is None else f" +- {np.rad2deg(e.stderr):.3g}"
        extra = f"  ({np.rad2deg(e.value):.4g}{sd} deg)"
    flag = "  [at bound]" if e.at_bound else ""
    return f"  {e.name:<28} {e.value:>13.6g} {se:>11}  {e.unit}{extra}{flag}"


# --- assembling the result --------------------------------------------------------------------


def _physical_covariance(
    problem: Problem, core: CoreFit
) -> tuple[np.ndarray | None, np.ndarray | None, np.ndarray | None]:
    """(covariance in z, physical covariance (delta method), correlation), or Nones when the
    fit did not converge or the information is singular."""
    if not core.success:
        return None, None, None
    cov_z = covariance(core).z
    if cov_z is None:
        return None, None, None
    slots = core.free_slots
    lay = problem.layout
    r = float(core.ev.x[lay.slot("edge_radius_um")])
    free = np.zeros(lay.size, bool)
    free[slots] = True
    d = dx_matrix(np.asarray(core.z), lay.kinds, problem.r_max_um, free, r)[np.ix_(slots, slots)]
    cov = d @ cov_z @ d.T
    sd = np.sqrt(np.diag(cov))
    return cov_z, cov, cov / np.outer(sd, sd)


def _estimates(
    params: tuple[Parameter, ...], core: CoreFit, cov: np.ndarray | None
) -> tuple[tuple[Estimate, ...], list[FitWarning]]:
    """One `Estimate` per free slot, and an `at_bound` warning for each one within a standard
    error of its bound."""
    x = core.ev.x
    estimates, records = [], []
    for i, k in enumerate(core.free_slots):
        p = params[k]
        se = None if cov is None else float(math.sqrt(max(cov[i, i], 0.0)))
        at_bound = se is not None and within_stderr_of_bound(p, float(x[k]), se)
        if at_bound:
            records.append(
                FitWarning(
                    "at_bound",
                    p.label(),
                    f"{p.label()} = {x[k]:.3g} +- {se:.3g} is within one standard error of a "
                    "bound; its Gaussian error bar is not meaningful (use the posterior)",
                )
            )
        estimates.append(Estimate(p.param, p.wedge, float(x[k]), se, p.unit, at_bound, p.wedge_deg))
    return tuple(estimates), records


def _fitted_variant(requested: Variant, spec: FreeSpec) -> Variant:
    """The variant as finally fitted: the spec's free set, per-wedge widths if any are left, and
    the requested facet kernel."""
    own = spec.own_sigma - {w for w, _ in spec.fixed_sigma}
    return Variant(requested.name, frozenset(spec.free), bool(own) and "sigma_rad" in spec.free,
                   requested.kernel)  # fmt: skip


def _fitted_params(problem: Problem, core: CoreFit) -> Params:
    """Every physical parameter at the optimum (widths one per wedge), as Python floats."""
    p = problem.layout.unpack(core.ev.x, np.asarray(core.data.sigma_source))
    return Params(np.asarray(p.sigma_rad, float), *(float(v) for v in p[1:]))


def make_result(
    problem: Problem,
    requested: Variant,
    core: CoreFit,
    solver: str,
    records: list[FitWarning],
    unidentified: list[str],
    t0: float,
    solves: tuple[SolveWork, ...] | None = None,
) -> FitResult:
    """Assemble the immutable result from the last core fit (`core.spec` is the final spec);
    `solves`: every solve that led to it (default: `core` alone)."""
    obs, ev = problem.observations, core.ev
    cov_z, cov, corr = _physical_covariance(problem, core)
    estimates, bound_records = _estimates(problem.parameters(core.spec), core, cov)
    records = [*records, *bound_records]
    if not core.success:
        records.append(
            FitWarning(
                "not_converged",
                None,
                f"least squares did not converge ({core.message}); no covariance is reported",
            )
        )
    n_used, k = obs.n_used, int(core.free_slots.size)
    chi2, loglik = float(ev.chi2), float(ev.loglik)
    return FitResult(
        variant=_fitted_variant(requested, core.spec),
        requested=requested,
        params=_fitted_params(problem, core),
        estimates=estimates,
        covariance=cov,
        correlation=corr,
        covariance_z=cov_z,
        chi2=chi2,
        log_likelihood=loglik,
        n_used=n_used,
        n_rows=obs.n_rows,
        excluded_rows=tuple(int(i) for i in obs.excluded_rows),
        n_saturated=int(np.count_nonzero(obs.saturated)),
        n_free=k,
        dof=n_used - k,
        reduced_chi2=chi2 / max(n_used - k, 1),
        bic=-2.0 * loglik + k * math.log(n_used),
        aic=-2.0 * loglik + 2.0 * k,
        success=core.success,
        message=core.message,
        num_steps=core.steps,
        starts_sigma_rad=core.starts_sigma,
        starts_chi2=core.starts_chi2,
        starts_converged=core.starts_converged,
        solver=solver,
        warnings=tuple(records),
        unidentified=tuple(unidentified),
        model=ev.model,
        residuals=ev.resid,
        uncertainty=ev.sd,
        z=np.asarray(core.z),
        free_slots=tuple(int(s) for s in core.free_slots),
        elapsed_s=time.perf_counter() - t0,
        solves=(SolveWork.of(core.total_steps, core.static, core.data),) if solves is None
        else solves,
        problem=problem,
        spec=core.spec,
    )
