"""Least squares with optimistix: multi-start, covariance, identifiability, the result object.

[conventions §9, §10]; the design is documented in docs/fitting.md.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jaxtyping import Array

from stairfit import model

from ._errors import FitError, FitInputError, FitWarning, emit
from ._forward import Data, Static, mean_and_log_variance, model_values, residuals, variance
from ._observations import Observations, Spectral
from ._params import (
    DEFAULTS,
    LOG,
    PARAM_UNITS,
    SIMPLEST,
    SIN,
    Params,
    Priors,
    Variant,
    dx_dz,
    from_physical,
    log_abs_jacobian,
    to_physical,
)
from ._problem import FreeSpec, Problem, prepare, rounded_model_available, spec_for

SOLVERS: tuple[str, ...] = ("lm", "dogleg", "gauss_newton")
"""Least-squares solvers: optimistix LevenbergMarquardt (default), Dogleg, GaussNewton."""

DEFAULT_SIGMA_STARTS_RAD: tuple[float, ...] = tuple(float(x) for x in np.deg2rad([1, 3, 10, 30]))
"""Starting widths of the multi-start (log-spaced, 1 to 30 deg): the chi^2 landscape in sigma
is multimodal when lobes overlap."""

IDENTIFIABILITY_THRESHOLD = 0.5
"""A free parameter is *unidentified* when its standard error exceeds this fraction of its
prior's standard deviation (for log-uniform priors: the sd of ln x), i.e. the data shrink the
prior by less than a factor of two; or when it takes part (`PARTICIPATION`) in a direction of
the Fisher information with relative eigenvalue below `DEGENERACY_EIGENVALUE`."""

DEGENERACY_EIGENVALUE = 1e-12
"""Relative eigenvalue (of the correlation-normalised Fisher matrix) below which the
information is numerically singular."""

PARTICIPATION = 0.2
"""A parameter takes part in a singular direction when its component in the (normalised)
eigenvector is at least this fraction of the largest component."""

FIX_PRIORITY: tuple[str, ...] = (
    "model_error_frac",
    "edge_radius_um",
    "floor",
    "delta_n",
    "sigma_wedge",
    "sigma_rad",
    "scale",
)
"""When several parameters are unidentified, the first in this order is fixed first (and the
fit repeated): optional refinements go before the essential width and scale."""


def _solver(name: str, rtol: float, atol: float) -> optx.AbstractLeastSquaresSolver:
    """An optimistix solver by name. Gauss-Newton and Dogleg get a least-squares linear solve
    (fixed slots give zero Jacobian columns, which LM's damping handles by itself)."""
    if name == "lm":
        return optx.LevenbergMarquardt(rtol=rtol, atol=atol)
    linear = lx.AutoLinearSolver(well_posed=False)
    if name == "dogleg":
        return optx.Dogleg(rtol=rtol, atol=atol, linear_solver=linear)
    if name == "gauss_newton":
        return optx.GaussNewton(rtol=rtol, atol=atol, linear_solver=linear)
    raise FitInputError(f"solver = {name!r}; choose one of {', '.join(SOLVERS)}")


def _linear_scale(z0: Array, static: Static, data: Data) -> Array:
    """`z0` with the log-scale slot set to the best scale for the other start values.

    The model is linear in `scale`: `model = scale * A + floor * cos(theta_i)`, so the weighted
    least-squares scale is `sum(w A (v - floor cos)) / sum(w A^2)`, `w = use / stderr^2`. Only
    applied when the scale is free.
    """
    n_wedges = data.sigma_source.shape[0]
    k_scale = n_wedges + 3
    d1 = data._replace(
        free=data.free.at[k_scale].set(False), x_fixed=data.x_fixed.at[k_scale].set(1.0)
    )
    m1, x = model_values(z0, static, d1)
    base = x[n_wedges + 4] * jnp.cos(data.theta_i)
    a = m1 - base
    w = data.use / data.stderr**2
    num = jnp.sum(w * a * (data.value - base))
    den = jnp.sum(w * a * a)
    ok = (den > 0) & (num > 0)
    scale = jnp.where(ok, num / jnp.where(ok, den, 1.0), 1.0)
    return jnp.where(data.free[k_scale], z0.at[k_scale].set(jnp.log(scale)), z0)


def _evaluate(z: Array, static: Static, data: Data) -> dict[str, Array]:
    """Model, residuals, chi^2, log L and the Fisher information (in z) at one point.

    Fisher information of independent Gaussian rows with mean `m(z)` and variance `v(z)`:
    `I = sum_rows [grad m grad m^T / v + (1/2) grad ln v grad ln v^T]` (the second term only
    with the model-error term). Forward-mode derivatives (`jax.jacfwd`).
    """
    m, x = model_values(z, static, data)
    var = variance(m, x, static, data)
    r = data.use * (data.value - m) / jnp.sqrt(var)
    loglik = -0.5 * jnp.sum(data.use * (r * r + jnp.log(2.0 * jnp.pi * var)))
    jm, jlv = jax.jacfwd(lambda zz: mean_and_log_variance(zz, static, data))(z)
    a = jm * (data.use / jnp.sqrt(var))[:, None]
    b = jlv * jnp.sqrt(0.5 * data.use)[:, None]
    fisher = a.T @ a + b.T @ b
    return {
        "model": m,
        "x": x,
        "resid": r,
        "sd": jnp.sqrt(var),
        "chi2": jnp.sum(r * r),
        "loglik": loglik,
        "fisher": fisher,
    }


@eqx.filter_jit
def _solve_one(
    z0: Array, static: Static, data: Data, solver: optx.AbstractLeastSquaresSolver, max_steps: int
) -> tuple[Array, Array, Array, dict[str, Array]]:
    """One start: linear scale, the optimistix solve, and the evaluation at its optimum.

    One compiled function per scene shape, forward variant, solver and `max_steps`; the starts
    run one after another (measured: as fast as vmapping them, and half the compile time).
    """
    z0 = _linear_scale(z0, static, data)
    sol = optx.least_squares(
        residuals, solver, z0, args=(static, data), max_steps=max_steps, throw=False
    )
    return (
        sol.value,
        _result_codes(sol.result),
        sol.stats["num_steps"],
        _evaluate(sol.value, static, data),
    )


_RESULT_NAMES = (
    "successful",
    "nonlinear_max_steps_reached",
    "nonlinear_divergence",
    "nonfinite",
    "singular",
    "breakdown",
    "stagnation",
    "max_steps_reached",
    "conlim",
    "nonfinite_input",
)
_RESULT_ITEMS = tuple(
    (name, getattr(optx.RESULTS, name)) for name in _RESULT_NAMES if hasattr(optx.RESULTS, name)
)
_RESULT_MESSAGES = {
    name: " ".join(optx.RESULTS[item].split()) or name for name, item in _RESULT_ITEMS
}
"""optimistix result names and their one-line messages (looked up once)."""


def _result_codes(result: optx.RESULTS) -> Array:
    """Inside jit: one boolean per name of `_RESULT_ITEMS` (which result this is)."""
    return jnp.stack([result == item for _, item in _RESULT_ITEMS])


def _result_string(codes: np.ndarray) -> tuple[str, str]:
    """(name, one-line message) from `_result_codes`."""
    hits = np.flatnonzero(np.asarray(codes))
    if hits.size == 0:
        return "unknown", "unknown optimistix result"
    name = _RESULT_ITEMS[int(hits[0])][0]
    return name, _RESULT_MESSAGES[name]


@dataclass(frozen=True)
class Estimate:
    """One fitted parameter.

    `name` (e.g. `sigma_rad`, `sigma_rad[2: 30 deg]`, `delta_n`), `value` in `unit`, `stderr`
    (delta-method standard error from the covariance; None when the covariance could not be
    determined), `at_bound` (the value lies within one standard error of a bound of its
    transform, where Gaussian error bars are not meaningful).
    """

    name: str
    value: float
    stderr: float | None
    unit: str
    at_bound: bool = False


@dataclass(frozen=True)
class FitResult:
    """The outcome of one least-squares fit (immutable; `report()` prints it).

    Attributes:
        variant: the variant as finally fitted (unidentified parameters removed).
        requested: the variant that was asked for.
        params: every physical parameter at the optimum (fixed ones at their fixed values);
            `sigma_rad` is one value per wedge.
        estimates: the free parameters, with standard errors, in covariance order.
        names: `tuple(e.name for e in estimates)`.
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
        unidentified: names of parameters fixed because the data did not constrain them.
        model: model value per row; residuals: whitened residuals per row (0 when excluded);
            uncertainty: per-row standard deviation used (stderr with the model-error term).
        z: the optimum in the unconstrained coordinates (every slot; used by the posterior).
        free_slots: indices of the free slots of `z`, in covariance order.
        elapsed_s: wall time of the fit (compilation included on a first call).
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
    problem: Problem | None = field(default=None, repr=False)
    spec: FreeSpec | None = field(default=None, repr=False)

    @property
    def laplace_log_evidence(self) -> float | None:
        """Laplace approximation of the log evidence with the priors, or None without a
        covariance: `log L + log prior(z) + (k/2) ln 2 pi + (1/2) ln det C_z` (the prior in
        the unconstrained coordinates includes `log |dx/dz|`)."""
        if self.covariance_z is None or self.problem is None:
            return None
        k = len(self.free_slots)
        log_prior = _log_prior_z(self.problem, self.z, np.asarray(self.free_slots))
        logdet = float(np.linalg.slogdet(self.covariance_z)[1])
        return self.log_likelihood + log_prior + 0.5 * k * math.log(2 * math.pi) + 0.5 * logdet

    @property
    def names(self) -> tuple[str, ...]:
        """Names of the free parameters, in covariance order."""
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

    def estimate(self, name: str) -> Estimate:
        """The estimate of one free parameter by name."""
        for e in self.estimates:
            if e.name == name:
                return e
        raise KeyError(f"{name!r} is not a free parameter of this fit ({', '.join(self.names)})")

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
        ]
        for e in self.estimates:
            se = "n/a" if e.stderr is None else f"{e.stderr:.4g}"
            extra = ""
            if e.name.startswith("sigma_rad"):
                sd = "" if e.stderr is None else f" +- {np.rad2deg(e.stderr):.3g}"
                extra = f"  ({np.rad2deg(e.value):.4g}{sd} deg)"
            flag = "  [at bound]" if e.at_bound else ""
            lines.append(f"  {e.name:<28} {e.value:>13.6g} {se:>11}  {e.unit}{extra}{flag}")
        fixed = [
            n
            for n in ("delta_n", "edge_radius_um", "floor", "model_error_frac")
            if n not in self.variant.free
        ]
        if fixed:
            lines.append(
                "  fixed: " + ", ".join(f"{n} = {getattr(self.params, n):.4g}" for n in fixed)
            )
        if self.correlation is not None:
            pairs = [
                f"{self.names[i]}/{self.names[j]} = {self.correlation[i, j]:+.2f}"
                for i in range(len(self.names))
                for j in range(i + 1, len(self.names))
                if abs(self.correlation[i, j]) > 0.5
            ]
            if pairs:
                lines.append("  correlations |r| > 0.5: " + "; ".join(pairs))
        else:
            lines.append("  covariance: could not be determined")
        for w in self.warnings:
            lines.append(f"  warning ({w.code}): {w.message}")
        return "\n".join(lines)


def fit_least_squares(
    observations: Observations | Problem,
    spectral: Spectral | None = None,
    variant: Variant = SIMPLEST,
    *,
    fixed: Params = DEFAULTS,
    priors: Priors | None = None,
    solver: str = "lm",
    rtol: float = 1e-8,
    atol: float = 1e-8,
    max_steps: int = 256,
    sigma_starts_rad: tuple[float, ...] = DEFAULT_SIGMA_STARTS_RAD,
    aperture: model.Aperture | None = None,
    resolution: int | None = None,
    identifiability: bool = True,
    identifiability_threshold: float = IDENTIFIABILITY_THRESHOLD,
    on_failure: str = "raise",
    emit_warnings: bool = True,
) -> FitResult:
    """Fit one model variant by least squares [conventions §9].

    Whitened residuals `(value - model) / uncertainty` over the used rows are minimised with an
    optimistix solver (`solver`: `lm`, `dogleg`, `gauss_newton`; `throw=False`) from one start
    per width in `sigma_starts_rad`; the lowest chi^2 among converged starts wins. The
    covariance is the inverse Fisher information at the optimum, mapped to physical units by
    the delta method. With `identifiability=True`, free parameters the data do not constrain
    (see `IDENTIFIABILITY_THRESHOLD`) are fixed at their `fixed` value, one at a time, with a
    warning, and the fit is repeated.

    `observations` may be a prepared `Problem` (then `spectral`, `fixed`, `priors`, `aperture`
    and `resolution` come from it). `on_failure="raise"` raises `FitError` when no start
    converges; `"flag"` returns a result with `success=False` and no covariance instead.
    Non-finite optima always raise.
    """
    t0 = time.perf_counter()
    if isinstance(observations, Problem):
        problem = observations
    else:
        if spectral is None:
            raise FitInputError("give the spectral setup (spectral_setup(...)) with observations")
        problem = prepare(
            observations,
            spectral,
            fixed=fixed,
            priors=priors,
            aperture=aperture,
            resolution=resolution,
        )
    if on_failure not in ("raise", "flag"):
        raise FitInputError(f"on_failure = {on_failure!r}; use 'raise' or 'flag'")
    if max_steps < 1:
        raise FitInputError(f"max_steps = {max_steps}; give at least 1")
    if len(sigma_starts_rad) == 0 or not all(s > 0 for s in sigma_starts_rad):
        raise FitInputError("sigma_starts_rad must hold at least one positive width (rad)")
    _check_signal(problem)
    opt = _solver(solver, rtol, atol)
    spec = spec_for(variant, problem)
    records: list[FitWarning] = []
    unidentified: list[str] = []
    checked: set[FreeSpec] = set()
    core = None
    for _ in range(2 * problem.layout.size + 2):
        if core is None or core["spec"] != spec:
            core = _fit_core(problem, spec, opt, max_steps, sigma_starts_rad)
        if not core["success"]:
            # A model-error term running to 0 (its bound) can keep Levenberg-Marquardt from
            # meeting its tolerance (the variance term is singular there); fixing it on the
            # bound and refitting is what a converged fit would have led to anyway.
            bound = _on_bound(problem, spec, core)
            if (
                bound is not None
                and bound[1] is not None
                and "model_error_frac" in (bound[1].parameter or "")
            ):
                spec = bound[0]
                records.append(bound[1])
                continue
            break
        bound = _on_bound(problem, spec, core) if spec not in checked else None
        if bound is not None:
            new_spec, rec = bound
            if rec is None:  # near a bound: keep the bound only if the data cannot tell
                checked.add(spec)
                at_bound = _fit_core(problem, new_spec, opt, max_steps, sigma_starts_rad)
                rise = 2.0 * (core["eval"]["loglik"] - at_bound["eval"]["loglik"])
                if at_bound["success"] and rise < PROFILE_DELTA:
                    name = new_spec.overrides[-1][0]
                    msg = (
                        f"{name} is fixed on its bound 0: fixing it there raises -2 log L by "
                        f"only {rise:.3g} < {PROFILE_DELTA:g}, so the data cannot tell it from "
                        "the bound"
                    )
                    records.append(FitWarning("at_bound", name, msg))
                    spec, core = new_spec, at_bound
                continue
            spec = new_spec
            records.append(rec)
            continue
        if not identifiability:
            break
        fix = _unidentified(problem, spec, core, identifiability_threshold)
        if fix is None:
            break
        name, reason = fix
        spec, rec = _apply_fix(problem, spec, name, reason, core)
        records.append(rec)
        unidentified.append(rec.parameter or name)
    if core["spec"] != spec:  # the iteration cap was hit right after a change
        core = _fit_core(problem, spec, opt, max_steps, sigma_starts_rad)
    result = _make_result(problem, variant, spec, core, solver, records, unidentified, t0)
    if not result.success and on_failure == "raise":
        raise FitError(
            f"least squares did not converge for variant {variant.name!r} with {solver}: "
            f"{result.message} (best start after {result.num_steps} steps of max_steps = "
            f"{max_steps}); raise max_steps, try another solver, or check the data"
        )
    if emit_warnings:
        emit(result.warnings)
    return result


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


def _start_vectors(problem: Problem, spec: FreeSpec, sigmas: tuple[float, ...]) -> np.ndarray:
    """One start per width: widths as given, others from the fixed values or a heuristic."""
    lay, fixed = problem.layout, problem.fixed
    obs = problem.observations
    kinds = lay.kinds
    z = np.zeros(lay.size)
    for name in ("delta_n", "edge_radius_um", "scale", "floor", "model_error_frac"):
        k = lay.slot(name)
        x = float(getattr(fixed, name))
        if name == "edge_radius_um" and x <= 0:
            x = 0.25 * problem.r_max_um
        if name == "floor" and x <= 0:
            v = obs.value[obs.use]
            x = max(0.5 * float(np.percentile(v, 10)), 1e-4 * float(np.max(np.abs(v))), 1e-12)
        if name == "model_error_frac" and x <= 0:
            x = 0.02
        z[k] = from_physical(x, kinds[k], problem.r_max_um)
    out = np.repeat(z[None, :], len(sigmas), axis=0)
    for i, s in enumerate(sigmas):
        out[i, : 1 + lay.n_wedges] = math.log(s)
    return out


def _fit_core(
    problem: Problem,
    spec: FreeSpec,
    opt: optx.AbstractLeastSquaresSolver,
    max_steps: int,
    sigmas: tuple[float, ...],
) -> dict:
    """Multi-start solve and evaluation at the best converged start (numpy outputs)."""
    static = problem.static_for(spec)
    if static.rounded and not rounded_model_available():
        raise FitInputError(
            "the rounded-edge model (stairfit.model.brdf_rounded) is not available in this "
            "installation; fix edge_radius_um at 0 or choose a sharp variant"
        )
    data = problem.arrays_for(spec)
    z0s = _start_vectors(problem, spec, sigmas)
    if "sigma_rad" not in spec.free:
        z0s = z0s[:1]
    runs = []
    for z0 in z0s:
        z, result, steps, ev = _solve_one(jnp.asarray(z0), static, data, opt, max_steps)
        ev = {k: np.asarray(v) for k, v in ev.items()}
        name, msg = _result_string(result)
        finite = bool(np.isfinite(ev["chi2"]) and np.all(np.isfinite(np.asarray(z))))
        finite = finite and bool(np.all(np.isfinite(ev["x"])))
        runs.append((np.asarray(z), name, msg, int(steps), ev, finite))
    chi2 = np.array([r[4]["chi2"] if r[5] else np.inf for r in runs])
    converged = np.array([r[1] == "successful" and r[5] for r in runs])
    finite = np.array([r[5] for r in runs])
    if not np.any(finite):
        raise FitError(
            "least squares produced non-finite values from every start "
            f"({'; '.join(sorted({r[2] for r in runs}))}); check the observations (values, "
            "stderr) and the fixed parameters"
        )
    pool = np.flatnonzero(converged) if np.any(converged) else np.flatnonzero(finite)
    best = int(pool[np.argmin(chi2[pool])])
    zb, name, msg, steps_b, ev, _ = runs[best]
    start_sigma = tuple(float(np.exp(z[0])) for z in z0s)
    return {
        "success": bool(converged[best]),
        "message": name if converged[best] else f"{name}: {msg}",
        "z": zb,
        "steps": steps_b,
        "starts_sigma": start_sigma,
        "starts_chi2": tuple(float(c) for c in chi2),
        "starts_converged": tuple(bool(c) for c in converged),
        "eval": ev,
        "spec": spec,
        "data": data,
        "static": static,
    }


def _free_slots(problem: Problem, core: dict) -> np.ndarray:
    return np.flatnonzero(np.asarray(core["data"].free))


def _covariance(problem: Problem, core: dict) -> tuple[np.ndarray | None, np.ndarray, list[int]]:
    """(covariance in z or None, Fisher diagonal, slots that dominate singular directions)."""
    slots = _free_slots(problem, core)
    fisher = core["eval"]["fisher"][np.ix_(slots, slots)]
    diag = np.diag(fisher).copy()
    if not np.all(np.isfinite(fisher)):
        return None, diag, []
    scale = np.sqrt(np.where(diag > 0, diag, 1.0))
    zero = diag <= DEGENERACY_EIGENVALUE * max(float(diag.max(initial=0.0)), 1e-300)
    norm = fisher / np.outer(scale, scale)
    lam, vec = np.linalg.eigh(norm)
    lam_max = max(float(lam.max(initial=0.0)), 1e-300)
    singular: set[int] = set()
    for k in np.flatnonzero(lam < DEGENERACY_EIGENVALUE * lam_max):
        v = np.abs(vec[:, k])
        singular |= set(np.flatnonzero(v >= PARTICIPATION * v.max()).tolist())
    degenerate = sorted(singular | set(np.flatnonzero(zero).tolist()))
    if degenerate:
        return None, diag, degenerate
    cov_norm = (vec / lam) @ vec.T
    return cov_norm / np.outer(scale, scale), diag, []


def _param_key(problem: Problem, slot: int) -> str:
    """Name used by `FIX_PRIORITY` for a slot (`sigma_wedge` for a per-wedge width)."""
    lay = problem.layout
    if 1 <= slot <= lay.n_wedges:
        return "sigma_wedge"
    return lay.param_of_slot(slot)


def _prior_of(problem: Problem, slot: int):
    return getattr(problem.priors, problem.layout.param_of_slot(slot))


def _unidentified(
    problem: Problem, spec: FreeSpec, core: dict, threshold: float
) -> tuple[str, str] | None:
    """The parameter to fix next (key, reason), or None when every free one is constrained."""
    slots = _free_slots(problem, core)
    cov_z, _, degenerate = _covariance(problem, core)
    lay = problem.layout
    x = core["eval"]["x"]
    candidates: dict[int, str] = {}
    for i in degenerate:
        candidates[int(slots[i])] = (
            "the Fisher information is singular along it, so the data cannot separate it "
            "from the other parameters"
        )
    if cov_z is not None:
        d = dx_dz(core["z"], lay.kinds, problem.r_max_um)
        for i, k in enumerate(slots):
            space, width = _prior_of(problem, int(k)).width()
            se_z = math.sqrt(max(cov_z[i, i], 0.0))
            if space == "log":
                se = se_z if lay.kinds[k] == LOG else se_z * abs(d[k]) / max(abs(x[k]), 1e-300)
            else:
                se = se_z * abs(d[k])
            if se > threshold * width:
                candidates[int(k)] = (
                    f"its standard error ({se:.3g}{' in ln' if space == 'log' else ''}) exceeds "
                    f"{threshold:g} x the prior's sd ({width:.3g})"
                )
    if not candidates:
        return None

    def priority(k: int) -> tuple[int, float]:
        return (FIX_PRIORITY.index(_param_key(problem, k)), -k)

    k = min(candidates, key=priority)
    key = _param_key(problem, k)
    name = f"sigma_wedge:{k - 1}" if key == "sigma_wedge" else key
    return name, candidates[k]


BOUND_TOL = 1e-3
"""A sine slot with `|cos z| < BOUND_TOL` (the radius within `2.5e-7 r_max` of a bound), or a
model-error fraction whose term is below `BOUND_TOL` of every row's stderr, is on its bound."""


NEAR_BOUND = 0.05
"""An edge radius below this fraction of r_max is tested against the sharp model (r = 0) by a
likelihood ratio: with a sine transform the delta method is unreliable next to the bound."""

PROFILE_DELTA = 1.0
"""The bound is kept when `-2 log L` rises by less than this when the parameter is fixed on it
(the bound lies inside the 68% profile-likelihood interval)."""

BOUNDED = ("edge_radius_um", "floor", "model_error_frac")
"""Parameters with a bound their natural value can sit on (0 for each; r_max for the radius)."""


def _on_bound(
    problem: Problem, spec: FreeSpec, core: dict
) -> tuple[FreeSpec, FitWarning | None] | None:
    """Active set: a free parameter whose optimum lies on (or beyond) its bound is fixed there.

    `floor < 0` -> 0; an edge radius at 0 or `r_max`; a model error too small to matter -> 0.
    Returns the new spec and a warning, or None. An edge radius below `NEAR_BOUND x r_max`
    returns the spec with `r = 0` and no warning: the caller refits there and keeps the bound
    when the likelihood ratio says the data cannot tell it apart (`_bound_check`).
    """
    lay = problem.layout
    z, x = core["z"], core["eval"]["x"]
    data = core["data"]
    found: tuple[str, float, str] | None = None
    if "floor" in spec.free and x[lay.slot("floor")] < 0.0:
        found = (
            "floor",
            0.0,
            f"the unconstrained optimum is negative ({x[lay.slot('floor')]:.3g})",
        )
    k = lay.slot("edge_radius_um")
    if found is None and "edge_radius_um" in spec.free and abs(math.cos(z[k])) < BOUND_TOL:
        at = 0.0 if math.sin(z[k]) < 0 else problem.r_max_um
        found = ("edge_radius_um", at, f"the optimum is the bound r = {at:.4g} um")
    if found is None and "edge_radius_um" in spec.free and x[k] < NEAR_BOUND * problem.r_max_um:
        found = ("edge_radius_um", 0.0, "check")
    k = lay.slot("model_error_frac")
    if found is None and "model_error_frac" in spec.free:
        rel = x[k] * np.abs(core["eval"]["model"]) / np.asarray(data.stderr)
        if float(np.max(rel * np.asarray(data.use))) < BOUND_TOL:
            found = ("model_error_frac", 0.0, "the data need no model-error term")
    if found is None:
        return None
    name, value, why = found
    new = spec._replace(free=spec.free - {name}, overrides=(*spec.overrides, (name, float(value))))
    if why == "check":
        return new, None
    msg = f"{name} is fixed on its bound {value:g} ({why}); the fit was repeated without it"
    return new, FitWarning("at_bound", name, msg)


def _apply_fix(
    problem: Problem, spec: FreeSpec, name: str, reason: str, core: dict
) -> tuple[FreeSpec, FitWarning]:
    """Fix an unidentified parameter; an unidentified per-wedge width is fixed at the geometric
    mean of the other fitted widths (or joins the shared width if other wedges use it)."""
    if name.startswith("sigma_wedge:"):
        w = int(name.split(":")[1])
        lay = problem.layout
        label = lay.label(1 + w, problem.wedge_deg)
        x = core["eval"]["x"]
        free = np.asarray(core["data"].free)
        source = np.asarray(core["data"].sigma_source)
        others = [lay.sigma_slot(v) for v in spec.own_sigma if v != w and free[lay.sigma_slot(v)]]
        if free[0] and np.any(np.delete(source, w) == 0):
            msg = f"{label} is not constrained by the data: {reason}; it now shares sigma_rad"
            return spec._replace(own_sigma=spec.own_sigma - {w}), FitWarning(
                "unidentified", label, msg
            )
        value = float(np.exp(np.mean(np.log(x[others])))) if others else float(x[0])
        msg = (
            f"{label} is not constrained by the data: {reason}; fixed at the geometric mean of "
            f"the other wedges' widths, {value:.4g} rad ({np.rad2deg(value):.3g} deg)"
        )
        new = spec._replace(fixed_sigma=(*spec.fixed_sigma, (w, value)))
        return new, FitWarning("unidentified", label, msg)
    if name in ("sigma_rad", "scale"):
        raise FitError(
            f"the data cannot constrain {name}: {reason}; the observations hold no usable "
            "signal for the model (check angles, wedge indices and values)"
        )
    value = getattr(problem.fixed, name)
    msg = (
        f"{name} is not constrained by the data: {reason}; fixed at its default {value:g} "
        "instead of being reported with a meaningless error bar"
    )
    return spec._replace(free=spec.free - {name}), FitWarning("unidentified", name, msg)


def _make_result(
    problem: Problem,
    requested: Variant,
    spec: FreeSpec,
    core: dict,
    solver: str,
    records: list[FitWarning],
    unidentified: list[str],
    t0: float,
) -> FitResult:
    """Assemble the immutable result from the last core fit."""
    lay = problem.layout
    obs = problem.observations
    ev = core["eval"]
    x = ev["x"]
    slots = _free_slots(problem, core)
    success = core["success"]
    cov_z = None
    if success:
        cov_z, _, _ = _covariance(problem, core)
    d = dx_dz(core["z"], lay.kinds, problem.r_max_um)
    cov = None if cov_z is None else cov_z * np.outer(d[slots], d[slots])
    corr = None
    if cov is not None:
        sd = np.sqrt(np.diag(cov))
        corr = cov / np.outer(sd, sd)
    records = list(records)
    estimates = []
    for i, k in enumerate(slots):
        label = lay.label(int(k), problem.wedge_deg)
        se = None if cov is None else float(math.sqrt(max(cov[i, i], 0.0)))
        at_bound = False
        if se is not None and lay.param_of_slot(int(k)) in BOUNDED:
            at_bound = bool(x[k] < se or (lay.kinds[k] == SIN and problem.r_max_um - x[k] < se))
            if at_bound:
                records.append(
                    FitWarning(
                        "at_bound",
                        label,
                        f"{label} = {x[k]:.3g} +- {se:.3g} is within one standard error of a "
                        "bound; its Gaussian error bar is not meaningful (use the posterior)",
                    )
                )
        unit = PARAM_UNITS[lay.param_of_slot(int(k))]
        estimates.append(Estimate(label, float(x[k]), se, unit, bool(at_bound)))
    if not success:
        records.append(
            FitWarning(
                "not_converged",
                None,
                f"least squares did not converge ({core['message']}); no covariance is reported",
            )
        )
    free_names = set(spec.free)
    fitted = Variant(
        requested.name,
        frozenset(free_names),
        bool(spec.own_sigma - {w for w, _ in spec.fixed_sigma}) and "sigma_rad" in free_names,
    )
    sigma_w = x[np.asarray(core["data"].sigma_source)]
    params = Params(
        sigma_rad=sigma_w,
        delta_n=float(x[lay.slot("delta_n")]),
        edge_radius_um=float(x[lay.slot("edge_radius_um")]),
        scale=float(x[lay.slot("scale")]),
        floor=float(x[lay.slot("floor")]),
        model_error_frac=float(x[lay.slot("model_error_frac")]),
    )
    n_used = obs.n_used
    k = int(slots.size)
    chi2 = float(ev["chi2"])
    loglik = float(ev["loglik"])
    return FitResult(
        variant=fitted,
        requested=requested,
        params=params,
        estimates=tuple(estimates),
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
        success=success,
        message=core["message"],
        num_steps=core["steps"],
        starts_sigma_rad=core["starts_sigma"],
        starts_chi2=core["starts_chi2"],
        starts_converged=core["starts_converged"],
        solver=solver,
        warnings=tuple(records),
        unidentified=tuple(unidentified),
        model=ev["model"],
        residuals=ev["resid"],
        uncertainty=ev["sd"],
        z=np.asarray(core["z"]),
        free_slots=tuple(int(s) for s in slots),
        elapsed_s=time.perf_counter() - t0,
        problem=problem,
        spec=spec,
    )


def _log_prior_z(problem: Problem, z: np.ndarray, slots: np.ndarray) -> float:
    """Log prior density of the free slots in z (physical prior + log |dx/dz|)."""
    lay = problem.layout
    zj = jnp.asarray(z)
    x = np.asarray(to_physical(zj, lay.kinds, problem.r_max_um))
    jac = np.asarray(log_abs_jacobian(zj, lay.kinds, problem.r_max_um))
    total = 0.0
    for k in slots:
        prior = _prior_of(problem, int(k))
        total += float(prior.log_pdf(x[k])) + float(jac[k])
    return total
