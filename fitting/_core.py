"""The least-squares engine: solvers, one compiled solve per start, the multi-start.

Everything here works on a prepared `Problem` and a `FreeSpec`; the iteration around it (the
active set and the identifiability rule) is in `_least_squares.py` and `_identify.py`
[conventions §9, §10]; the design is documented in docs/fitting.md §3.
"""

from __future__ import annotations

import functools
import itertools
import math
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jaxtyping import Array

from . import _export
from ._errors import FitError, FitInputError
from ._forward import (
    Data,
    Static,
    cholesky,
    correlated_log_likelihood,
    mean_and_log_variance,
    model_error_variance,
    model_values,
    physical,
    residuals,
    whitened,
)
from ._forward import variance as row_variance
from ._params import from_physical
from ._problem import FreeSpec, Problem
from ._whiten import grouped_fisher, scatter

SOLVERS: tuple[str, ...] = ("lm", "dogleg", "gauss_newton")
"""Least-squares solvers: optimistix LevenbergMarquardt (default), Dogleg, GaussNewton."""


def make_solver(name: str, rtol: float, atol: float) -> optx.AbstractLeastSquaresSolver:
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


def solver_key(solver: optx.AbstractLeastSquaresSolver) -> str:
    """A deterministic description of a `make_solver` solver (part of a program's key)."""
    return f"{type(solver).__name__}(rtol={solver.rtol!r}, atol={solver.atol!r})"


def fisher_information(jacobian: Array, sd: Array, use: Array | None = None) -> Array:
    """Fisher information `J^T diag(use / sd^2) J` of independent Gaussian rows whose means have
    the Jacobian `jacobian` `(n_rows, p)` and whose standard deviations are `sd`; rows with
    `use` False (or 0) carry none. The one home of this matrix: the fit's covariance, the
    model-error term's part of it, and `stairfit.explore`'s design study use it."""
    w = 1.0 / jnp.asarray(sd) ** 2
    if use is not None:
        w = jnp.where(jnp.asarray(use) > 0, w, 0.0)
    jac = jnp.asarray(jacobian)
    return jac.T @ (jac * w[:, None])


class Evaluation(NamedTuple):
    """The fit at one point `z`: per row `model`, whitened residual `resid` and standard
    deviation `sd`; `x` the physical value of every slot; `chi2`, `loglik` (Gaussian, full
    normalisation) and `fisher`, the Fisher information in `z` (every slot)."""

    model: Array
    x: Array
    resid: Array
    sd: Array
    chi2: Array
    loglik: Array
    fisher: Array


def evaluate(z: Array, static: Static, data: Data) -> Evaluation:
    """Model, residuals, chi^2, log L and the Fisher information (in z) at one point.

    Fisher information of independent Gaussian rows with mean `m(z)` and variance `v(z)`:
    `I = sum_rows [grad m grad m^T / v + (1/2) grad ln v grad ln v^T]` (the second term only
    with the model-error term); of correlated groups, `_whiten.grouped_fisher`. Forward-mode
    derivatives (`jax.jacfwd`). With correlated rows, `resid` is each row's component of
    `L^-1 (value - model)` and `sd` the marginal `sqrt(C_ii)`.
    """
    if static.correlated:
        return _evaluate_correlated(z, static, data)
    m, p = model_values(z, static, data)
    var = row_variance(m, p, static, data)
    sd = jnp.sqrt(var)
    r = data.use * (data.value - m) / sd
    loglik = -0.5 * jnp.sum(data.use * (r * r + jnp.log(2.0 * jnp.pi * var)))
    jm, jlv = jax.jacfwd(lambda zz: mean_and_log_variance(zz, static, data))(z)
    fisher = fisher_information(jm, sd, data.use)
    fisher = fisher + fisher_information(jlv, jnp.full_like(sd, math.sqrt(2.0)), data.use)
    x = physical(z, static, data)
    return Evaluation(m, x, r, sd, jnp.sum(r * r), loglik, fisher)


def _evaluate_correlated(z: Array, static: Static, data: Data) -> Evaluation:
    """`evaluate` with rows whitened per group (docs/fitting.md §Correlated channels)."""
    m, p = model_values(z, static, data)
    var = row_variance(m, p, static, data)
    chol = cholesky(model_error_variance(m, p, static), data)
    w = whitened(data.value - m, chol, data)
    jm, jlv = jax.jacfwd(lambda zz: mean_and_log_variance(zz, static, data))(z)
    fisher = grouped_fisher(chol, jm, jlv * var[:, None], data.grp_rows, data.grp_mask)
    r = scatter(w, data.grp_rows, data.value.shape[0])
    loglik = correlated_log_likelihood(w, chol, data)
    x = physical(z, static, data)
    return Evaluation(m, x, r, jnp.sqrt(var), jnp.sum(w * w), loglik, fisher)


def _linear_scale(z0: Array, static: Static, data: Data) -> Array:
    """`z0` with the log-scale slot set to the best scale for the other start values.

    The model is linear in `scale`: `model = scale * A + B` (B the body reflection, e.g.
    `floor * cos(theta_i)` in the plane; the lab model's is its own), so the weighted
    least-squares scale is `sum(w A (v - B)) / sum(w A^2)`, `w = use / stderr^2` (correlated
    rows: the same sums of the whitened `A` and `v - B`, with the measurement covariance
    alone). `A` and `B` come from the model itself at scale 1 and 0. Only applied when the
    scale is free.
    """
    k = static.layout.slot("scale")

    def at_scale(x: float) -> Array:
        d = data._replace(free=data.free.at[k].set(False), x_fixed=data.x_fixed.at[k].set(x))
        return model_values(z0, static, d)[0]

    base = at_scale(0.0)
    a = at_scale(1.0) - base
    if static.correlated:
        chol = cholesky(None, data)
        wa, wb = whitened(a, chol, data), whitened(data.value - base, chol, data)
        num, den = jnp.sum(wa * wb), jnp.sum(wa * wa)
    else:
        w = data.use / data.stderr**2
        num = jnp.sum(w * a * (data.value - base))
        den = jnp.sum(w * a * a)
    ok = (den > 0) & (num > 0)
    scale = jnp.where(ok, num / jnp.where(ok, den, 1.0), 1.0)
    return jnp.where(data.free[k], z0.at[k].set(jnp.log(scale)), z0)


@eqx.filter_jit
def _solve_one(
    z0: Array,
    static: Static,
    data: Data,
    solver: optx.AbstractLeastSquaresSolver,
    max_steps: int,
    with_evaluation: bool = True,
) -> tuple[Array, ...]:
    """One start: linear scale, the optimistix solve, and (`with_evaluation`) the evaluation at
    its optimum, `(z, result codes, steps, *Evaluation)`.

    One compiled function per scene shape, forward variant, solver and `max_steps`; the starts
    run one after another (measured: as fast as vmapping them, and half the compile time).
    """
    z0 = _linear_scale(z0, static, data)
    sol = optx.least_squares(
        residuals, solver, z0, args=(static, data), max_steps=max_steps, throw=False
    )
    codes = _result_codes(sol.result)
    ev = evaluate(sol.value, static, data) if with_evaluation else ()
    return sol.value, codes, sol.stats["num_steps"], *ev


_evaluate = jax.jit(evaluate, static_argnums=1)


def _solve_and_evaluate(
    z0: np.ndarray,
    static: Static,
    data: Data,
    solver: optx.AbstractLeastSquaresSolver,
    max_steps: int,
) -> tuple[Array, Array, Array, Evaluation]:
    """`_solve_one` through the exported-program cache (`_export`). A rounded model's solver
    and evaluation compile as two programs, which together compile faster than one program
    holding both; for the sharp model one program is the cheaper."""
    together = not static.rounded
    key = repr((static, solver_key(solver), max_steps))
    out = _export.call(
        "solve_one",
        lambda z, d: _solve_one(z, static, d, solver, max_steps, together),
        key,
        (jnp.asarray(z0), data),
        tuple,
    )
    z, codes, steps = out[:3]
    if together:
        return z, codes, steps, Evaluation(*out[3:])
    ev = _export.call("evaluate", lambda zz, d: _evaluate(zz, static, d), repr(static),
                      (z, data), lambda leaves: Evaluation(*leaves))  # fmt: skip
    return z, codes, steps, ev


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


DENSER_START_ROUNDS = 2
"""When every width start ends in a clear misfit, the multi-start is repeated from the widths
between them, at most this many times (same compiled program, milliseconds per start). Few
views make the chi^2 surface of sigma narrow: on a 5-view, 0.3 MP demo the basin of the true
6 deg spans less than 5-7 deg, and the starts 1, 4, 12 deg all ended at 2.35 deg (chi^2 7179
for 23 dof)."""
MISFIT_SIGMAS = 5.0
"""A start's chi^2 above `dof + MISFIT_SIGMAS sqrt(2 dof)` is a clear misfit (P < 1e-6)."""


def denser_widths(tried: tuple[float, ...]) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """(all widths, the new ones): the geometric midpoints of `tried`, with half the smallest
    and twice the largest width (rad)."""
    s = sorted(set(tried))
    mids = [math.sqrt(a * b) for a, b in itertools.pairwise(s)]
    new = tuple(sorted({0.5 * s[0], *mids, 2.0 * s[-1]}))
    return tuple(sorted({*s, *new})), new


def _all_misfit(runs: list[StartRun], data: Data) -> bool:
    """Every finite start's chi^2 is a clear misfit (`MISFIT_SIGMAS`)."""
    dof = max(int(np.sum(np.asarray(data.use))) - int(np.sum(np.asarray(data.free))), 1)
    limit = dof + MISFIT_SIGMAS * math.sqrt(2.0 * dof)
    return all(not r.finite or float(r.ev.chi2) > limit for r in runs)


MODEL_ERROR_NEGLIGIBLE = 1e-3
"""A model-error term below this fraction of every row's standard error is on its way to its
bound 0 (`_identify.BOUND_TOL`, the rule that then fixes it there)."""


MODEL_ERROR_RISE = 0.05
"""A model-error term whose removal (the same model, the term set to 0) raises `-2 log L` by
less than this is on its way to its bound 0 even where it is not yet below
`MODEL_ERROR_NEGLIGIBLE` of every stderr: the data cannot tell it from 0 (the profile rule
`_least_squares.PROFILE_DELTA` is 1). Without this rule every start can stand at one optimum
with the term creeping towards 0, above the stderr rule, so that no start meets the tolerance
and a fit the data describe is reported as not converged (docs/fitting.md §4, "Starts that all
miss")."""


def model_error_rise(ev: Evaluation, data: Data, frac: float) -> float:
    """The rise of `-2 log L` when the model-error term `frac` is set to 0 at the same model
    values `ev.model` (NumPy, per ROI group: `C = S R S + diag((frac m)^2)` against `S R S`)."""
    m, v, s = (np.asarray(a, float) for a in (ev.model, data.value, data.stderr))
    rows, mask, corr = (np.asarray(a) for a in (data.grp_rows, data.grp_mask, data.grp_corr))
    real = mask > 0
    sg = np.where(real, s[rows], 1.0)
    rg = np.where(real, v[rows] - m[rows], 0.0)
    eye = np.eye(rows.shape[1])[None]

    def m2logl(f: float) -> float:
        cov = sg[:, :, None] * corr * sg[:, None, :]
        cov = cov + np.where(real, (f * m[rows]) ** 2, 0.0)[:, :, None] * eye
        quad = np.einsum("gi,gi->", rg, np.linalg.solve(cov, rg[..., None])[..., 0])
        return float(quad + np.sum(np.linalg.slogdet(cov)[1]))

    return m2logl(0.0) - m2logl(float(frac))


def _to_model_error_bound(run: StartRun, problem: Problem, spec: FreeSpec, data: Data) -> bool:
    """A finite start that did not meet the tolerance only because its model-error term runs
    to 0 (the variance term is singular there). Such a start competes with the converged ones:
    on a 5-view demo a converged start stuck at sigma = 1 deg with an 11% model-error term
    (-2 log L 273) beat two starts at the truth with the term running to 0 (-2 log L 122); the
    refinement then fixes the term on its bound (`_least_squares._next_step`). On its way to 0:
    below `MODEL_ERROR_NEGLIGIBLE` of every stderr, or its removal raises `-2 log L` by less
    than `MODEL_ERROR_RISE`."""
    if run.converged or not run.finite or "model_error_frac" not in spec.free:
        return False
    f = float(run.ev.x[problem.layout.slot("model_error_frac")])
    rel = f * np.abs(run.ev.model) / np.asarray(data.stderr)
    if float(np.max(rel * np.asarray(data.use))) < MODEL_ERROR_NEGLIGIBLE:
        return True
    return model_error_rise(run.ev, data, f) < MODEL_ERROR_RISE


CONTINUE_ROUNDS = 3
"""The best start that only ran out of steps continues from where it stopped, at most this many
times `max_steps` more (the same compiled program), when no start converged or when it beats
every converged start by `BETTER_BY` (`_short_to_continue`). Why: a small model-error term,
whose log-determinant residual is singular at 0, slows Levenberg-Marquardt, so that `max_steps`
can end every start short of the tolerance although more steps converge."""

BETTER_BY = 1.0
"""A start that ran out of steps but whose `-2 log L` is lower than every converged start's by
more than this (the data can tell the two apart, as `_least_squares.PROFILE_DELTA`) is not
discarded for not converging: the converged starts then sit in a worse optimum, e.g. a
degenerate width and scale with a huge model-error term, while the short start stands at the
truth with its term creeping to 0 (docs/fitting.md §4, "Starts that all miss")."""


def _objective(run: StartRun) -> float:
    """`-2 log L` of a start (the solver's objective; inf when not finite)."""
    return -2.0 * float(run.ev.loglik) if run.finite else math.inf


def _short_to_continue(runs: list[StartRun]) -> int | None:
    """The start to continue: the best (lowest `-2 log L`) of those that ran out of steps, if no
    start converged or it beats every converged one by `BETTER_BY`; else None."""
    short = [i for i, r in enumerate(runs) if r.finite and r.name == "nonlinear_max_steps_reached"]
    if not short:
        return None
    i = min(short, key=lambda k: _objective(runs[k]))
    converged = [_objective(r) for r in runs if r.converged]
    if converged and _objective(runs[i]) >= min(converged) - BETTER_BY:
        return None
    return i


def _continued(
    runs: list[StartRun],
    static: Static,
    data: Data,
    solver: optx.AbstractLeastSquaresSolver,
    max_steps: int,
) -> list[StartRun]:
    """`runs` with the start `_short_to_continue` names continued (`CONTINUE_ROUNDS`)."""
    i = _short_to_continue(runs)
    if i is None:
        return runs
    run = runs[i]
    for _ in range(CONTINUE_ROUNDS):
        more = _run(run.z, static, data, solver, max_steps)
        run = more._replace(steps=run.steps + more.steps)
        if run.converged or run.name != "nonlinear_max_steps_reached" or not run.finite:
            break
    return [*runs[:i], run, *runs[i + 1 :]]


def start_vectors(problem: Problem, spec: FreeSpec, sigmas: tuple[float, ...]) -> np.ndarray:
    """One start per width: widths as given, others from the fixed values or a heuristic
    (radius `r_max / 4`; floor half the 10th percentile of the data; model error 2%)."""
    lay, fixed = problem.layout, problem.fixed
    obs = problem.observations
    z = np.zeros(lay.size)
    x_edge = 0.0  # the edge radius the fillet's transform is bounded by (its slot comes first)
    for p in lay.parameters()[1 + lay.n_wedges :]:  # every parameter but the widths
        x = float(getattr(fixed, p.param))
        if p.param == "edge_radius_um" and x <= 0:
            x = 0.25 * problem.r_max_um
        if p.param == "fillet_radius_um" and x <= 0:
            x = 0.25 * (problem.r_max_um - x_edge)
        if p.param == "floor" and x <= 0:
            v = obs.value[obs.use]
            x = max(0.5 * float(np.percentile(v, 10)), 1e-4 * float(np.max(np.abs(v))), 1e-12)
        if p.param == "model_error_frac" and x <= 0:
            x = 0.02
        if p.param == "edge_radius_um":
            x_edge = x if "edge_radius_um" in spec.free else float(fixed.edge_radius_um)
        z[p.slot] = from_physical(x, p.transform, problem.r_max_um, x_edge)
    out = np.repeat(z[None, :], len(sigmas), axis=0)
    widths = [lay.slot("sigma_rad")] + [lay.slot("sigma_rad", w) for w in range(lay.n_wedges)]
    for i, s in enumerate(sigmas):
        out[i, widths] = math.log(s)
    return out if "sigma_rad" in spec.free else out[:1]


class StartRun(NamedTuple):
    """One start of the multi-start: its optimum `z`, optimistix result `name` and `msg`,
    solver `steps`, the evaluation there (numpy) and whether everything was finite."""

    z: np.ndarray
    name: str
    msg: str
    steps: int
    ev: Evaluation
    finite: bool

    @property
    def converged(self) -> bool:
        """optimistix reported success and the values are finite."""
        return self.name == "successful" and self.finite


class CoreFit(NamedTuple):
    """The best start of one multi-start solve of a variant (`spec`) and its configuration.

    `success`: the chosen start converged; `message`: its optimistix result (with the message
    when it did not); `z`, `steps`, `ev`: its optimum, solver steps, evaluation; `starts_*`:
    every start's width, chi^2 (inf if not finite) and convergence; `total_steps`: the solver
    steps of every start (the solve's work); `static`, `data`: what the solve ran on.
    """

    success: bool
    message: str
    z: np.ndarray
    steps: int
    starts_sigma: tuple[float, ...]
    starts_chi2: tuple[float, ...]
    starts_converged: tuple[bool, ...]
    total_steps: int
    ev: Evaluation
    spec: FreeSpec
    data: Data
    static: Static

    @property
    def free_slots(self) -> np.ndarray:
        """Indices of the free slots of `z`, in slot order (the covariance order)."""
        return np.flatnonzero(np.asarray(self.data.free))


def _run(z0: np.ndarray, static: Static, data: Data, solver: optx.AbstractLeastSquaresSolver,
         max_steps: int) -> StartRun:  # fmt: skip
    z, codes, steps, ev = _solve_and_evaluate(z0, static, data, solver, max_steps)
    ev = Evaluation(*(np.asarray(a) for a in ev))
    z = np.asarray(z)
    name, msg = _result_string(codes)
    finite = bool(np.isfinite(ev.chi2) and np.all(np.isfinite(z)) and np.all(np.isfinite(ev.x)))
    return StartRun(z, name, msg, int(steps), ev, finite)


START_THREADS = 2
"""Threads that solve the starts of a sharp fit side by side (the machine the project targets
has 2 cores). XLA runs a compiled program without holding the interpreter, so two starts
really run at once, with results identical to the bit (tests/fitting/test_starts.py); the
time saved is in benchmarks/results/cold.md (issue 14)."""


def _run_starts(
    z0s: np.ndarray,
    static: Static,
    data: Data,
    solver: optx.AbstractLeastSquaresSolver,
    max_steps: int,
) -> list[StartRun]:
    """`_run` of every start, in order (the same results as one after another: each start is
    its own deterministic program run). The first runs alone (it compiles, or loads, the
    program: two threads would do that twice); a sharp fit's other starts then run in
    `START_THREADS` threads. A rounded fit's starts run one after another: each already keeps
    the cores busy for seconds and holds hundreds of MB."""
    if len(z0s) == 0:
        return []
    first = _run(z0s[0], static, data, solver, max_steps)
    rest = z0s[1:]
    if static.rounded or len(rest) < 2:
        return [first, *(_run(z0, static, data, solver, max_steps) for z0 in rest)]
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(START_THREADS, thread_name_prefix="stairfit-start") as pool:
        return [first, *pool.map(lambda z0: _run(z0, static, data, solver, max_steps), rest)]


class SolveWork(NamedTuple):
    """One multi-start solve's work: its solver steps (every start) and what one step of it
    evaluates (`static`, the data's structure and shapes, the free parameters; not the arrays
    themselves), so that its cost can be counted when asked (`gflop`)."""

    steps: int
    static: Static
    tree: jax.tree_util.PyTreeDef
    shapes: tuple[tuple[tuple[int, ...], str], ...]
    n_free: int

    @classmethod
    def of(cls, steps: int, static: Static, data: Data) -> SolveWork:
        """The work of `steps` steps of the forward model `static` on `data`."""
        leaves, tree = jax.tree_util.tree_flatten(data)
        shapes = tuple((tuple(np.shape(x)), _dtype_name(x)) for x in leaves)
        return cls(steps, static, tree, shapes, int(np.count_nonzero(np.asarray(data.free))))

    def gflop(self) -> float:
        """The solve's work in Gflop: its steps times the cost of one (`step_gflop`)."""
        return self.steps * _residual_gflop(self.static, self.tree, self.shapes) * (1 + self.n_free)


def _dtype_name(x: object) -> str:
    """An array's dtype name without copying it to the host (numpy's rules for scalars)."""
    dtype = getattr(x, "dtype", None)
    return np.dtype(dtype).name if dtype is not None else np.asarray(x).dtype.name


def step_gflop(static: Static, data: Data) -> float:
    """The work of one solver step of this forward model, in Gflop: the floating-point
    operations XLA counts in the residuals (its cost analysis of the lowered program, before
    any machine-specific optimisation) times one plus the free parameters (forward-mode
    Jacobian columns). A machine-independent measure of what a solve costs, so that a budget
    of it (`select_model(work_budget_gflop=...)`) ends a ladder at the same rung on any
    machine; a step of a costlier model (rounded, filleted, microfacet) weighs more, as its
    time does."""
    return SolveWork.of(1, static, data).gflop()


@functools.lru_cache(maxsize=64)
def _residual_gflop(static: Static, tree: jax.tree_util.PyTreeDef,
                    shapes: tuple[tuple[tuple[int, ...], str], ...]) -> float:  # fmt: skip
    """XLA's flop count of `residuals` for this configuration and these array shapes (traced
    and lowered, not compiled; memoised: the ladder asks once per forward model)."""
    data = jax.tree_util.tree_unflatten(tree, [jax.ShapeDtypeStruct(s, d) for s, d in shapes])
    z = jax.ShapeDtypeStruct((static.layout.size,), jnp.float64)
    cost = jax.jit(lambda z, d: residuals(z, (static, d))).lower(z, data).cost_analysis()
    cost = cost[0] if isinstance(cost, (list, tuple)) else cost
    return float(cost.get("flops", 0.0)) / 1e9


def costly_solve(static: Static) -> bool:
    """Whether one solve of this forward model costs seconds rather than a fraction of one: the
    rounded model, and the lab model's microfacet facets (their lobes' quadrature at every
    node). Where a parent's or another kernel's optimum starts such a fit, further width starts
    are not worth their time (docs/fitting.md §4)."""
    return static.rounded or static.lab not in (None, "gaussian")


def fit_core(
    problem: Problem,
    spec: FreeSpec,
    solver: optx.AbstractLeastSquaresSolver,
    max_steps: int,
    sigmas: tuple[float, ...],
    extra: tuple[np.ndarray, ...] = (),
) -> CoreFit:
    """Multi-start solve and evaluation at the best converged start (numpy outputs); raises
    `FitError` when no start gives finite values.

    `extra`: further start vectors (every slot of `z`), e.g. a parent variant's optimum
    (`_least_squares.nested_start`); with them, only the first of the width starts `sigmas` is
    used where a solve is costly (`costly_solve`). The best start is the one
    with the lowest `-2 log L` (the solver's objective; chi^2 when there is no model-error
    term, whose variance term chi^2 alone would ignore)."""
    static, data = problem.static_for(spec), problem.arrays_for(spec)
    z0s = start_vectors(problem, spec, sigmas)
    if extra:
        z0s = np.concatenate([np.stack(extra), z0s[:1] if costly_solve(static) else z0s])
    runs = _run_starts(z0s, static, data, solver, max_steps)
    tried = tuple(sigmas)
    for _ in range(DENSER_START_ROUNDS):  # every start misfits: try the widths between them
        if static.rounded or "sigma_rad" not in spec.free or not _all_misfit(runs, data):
            break
        tried, new = denser_widths(tried)
        z_new = start_vectors(problem, spec, new)
        runs += _run_starts(z_new, static, data, solver, max_steps)
        z0s = np.concatenate([z0s, z_new])
    if not any(r.finite for r in runs):
        raise FitError(
            "least squares produced non-finite values from every start "
            f"({'; '.join(sorted({r.msg for r in runs}))}); check the observations (values, "
            "stderr) and the fixed parameters"
        )
    runs = _continued(runs, static, data, solver, max_steps)
    chi2 = np.array([float(r.ev.chi2) if r.finite else np.inf for r in runs])
    objective = np.array([_objective(r) for r in runs])
    bound = [i for i, r in enumerate(runs) if _to_model_error_bound(r, problem, spec, data)]
    better = _short_to_continue(runs)  # still short after continuing, and still clearly better
    pool = [i for i, r in enumerate(runs) if r.converged] + bound + (
        [better] if better is not None else []
    ) or [i for i, r in enumerate(runs) if r.finite]
    best = runs[min(pool, key=lambda i: objective[i])]
    return CoreFit(
        success=best.converged,
        message=best.name if best.converged else f"{best.name}: {best.msg}",
        z=best.z,
        steps=best.steps,
        starts_sigma=tuple(float(np.exp(z[0])) for z in z0s),
        starts_chi2=tuple(float(c) for c in chi2),
        starts_converged=tuple(r.converged for r in runs),
        total_steps=sum(r.steps for r in runs),
        ev=best.ev,
        spec=spec,
        data=data,
        static=static,
    )
