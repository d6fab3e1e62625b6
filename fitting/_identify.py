"""What least squares may report: the covariance, the active set, the identifiability rule.

After each multi-start solve (`_core.fit_core`), a free parameter whose optimum lies on its
bound is fixed there, and one the data do not constrain is fixed at its default; the fit is then
repeated (`_least_squares.fit_least_squares`). The rules are in docs/fitting.md §3.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from ._core import MODEL_ERROR_RISE, CoreFit, model_error_rise
from ._errors import FitWarning, UnconstrainedError
from ._params import LOG, SIN, SIN_REST, Parameter, dx_dz
from ._problem import FreeSpec, Problem

IDENTIFIABILITY_THRESHOLD = 0.5
"""A free parameter is *unidentified* when its standard error exceeds this fraction of its
prior's standard deviation (for log-uniform priors: the sd of ln x), i.e. the data shrink the
prior by less than a factor of two; or when it takes part (`PARTICIPATION`) in a direction of
the Fisher information with relative eigenvalue below `DEGENERACY_EIGENVALUE`."""

DEGENERACY_EIGENVALUE = 1e-12
"""Relative eigenvalue (of the correlation-normalised Fisher matrix) below which the
information is numerically singular."""

ZERO_INFORMATION = 1e-30
"""A free parameter's Fisher diagonal below this fraction of the largest is zero to rounding
(its derivative is rounding noise). The diagonals carry the parameters' units: a floor in
radiance units (about 1e5) against widths in radians has about 1e-12 of their information at
equal relative precision, so only a rounding-level fraction says "none"."""

PARTICIPATION = 0.2
"""A parameter takes part in a singular direction when its component in the (normalised)
eigenvector is at least this fraction of the largest component."""

FIX_ORDER: tuple[tuple[str, bool], ...] = (
    ("model_error_frac", False),
    ("fillet_radius_um", False),
    ("edge_radius_um", False),
    ("floor", False),
    ("delta_n", False),
    ("sigma_rad", True),  # a wedge's own width
    ("sigma_rad", False),  # the shared width
    ("scale", False),
)
"""When several parameters are unidentified, the first in this order, `(param, per wedge)`, is
fixed first (and the fit repeated): optional refinements go before the essential width and
scale."""

BOUND_TOL = 1e-3
"""A sine slot with `|cos z| < BOUND_TOL` (the radius within `2.5e-7 r_max` of a bound), or a
model-error fraction whose term is below `BOUND_TOL` of every row's stderr, is on its bound."""

NEAR_BOUND = 0.05
"""An edge radius below this fraction of r_max is tested against the sharp model (r = 0) by a
likelihood ratio: with a sine transform the delta method is unreliable next to the bound."""

PROFILE_DELTA = 1.0
"""The bound is kept when `-2 log L` rises by less than this when the parameter is fixed on it
(the bound lies inside the 68% profile-likelihood interval)."""


# --- covariance ---------------------------------------------------------------------------------


class Covariance(NamedTuple):
    """The inverse Fisher information of the free slots: `z` (unconstrained, or None when the
    information is singular), its `fisher_diag`, and the positions (in free-slot order) of the
    parameters that take part in a singular direction."""

    z: np.ndarray | None
    fisher_diag: np.ndarray
    degenerate: tuple[int, ...]


def covariance(core: CoreFit) -> Covariance:
    """Covariance in `z` of the free slots through an eigen-decomposition of the
    correlation-normalised Fisher matrix (docs/fitting.md §3, "Covariance")."""
    slots = core.free_slots
    fisher = core.ev.fisher[np.ix_(slots, slots)]
    diag = np.diag(fisher).copy()
    if not np.all(np.isfinite(fisher)):
        return Covariance(None, diag, ())
    scale = np.sqrt(np.where(diag > 0, diag, 1.0))
    zero = diag <= ZERO_INFORMATION * max(float(diag.max(initial=0.0)), 1e-300)
    lam, vec = np.linalg.eigh(fisher / np.outer(scale, scale))
    lam_max = max(float(lam.max(initial=0.0)), 1e-300)
    singular: set[int] = set(np.flatnonzero(zero).tolist())
    for k in np.flatnonzero(lam < DEGENERACY_EIGENVALUE * lam_max):
        v = np.abs(vec[:, k])
        singular |= set(np.flatnonzero(v >= PARTICIPATION * v.max()).tolist())
    if singular:
        return Covariance(None, diag, tuple(sorted(singular)))
    cov_norm = (vec / lam) @ vec.T
    return Covariance(cov_norm / np.outer(scale, scale), diag, ())


# --- identifiability ----------------------------------------------------------------------------


class Unidentified(NamedTuple):
    """A free parameter the data do not constrain, and why (a clause for the warning)."""

    parameter: Parameter
    reason: str


def _stderr_vs_prior(p: Parameter, se_z: float, d: float, x: float) -> tuple[float, float, str]:
    """(standard error in the prior's space, the prior's sd there, the space's name)."""
    space, width = p.prior.width()
    if space == "log":
        se = se_z if p.transform == LOG else se_z * abs(d) / max(abs(x), 1e-300)
    else:
        se = se_z * abs(d)
    return se, width, space


SIGNIFICANT = 3.0
"""A parameter in the prior's linear space whose value lies this many standard errors from its
default (0 for delta_n, the floor, the edge radius and the model error) is constrained by the
data however wide its error bar is next to the prior: a grossly misfitting variant can need a
model error of 50% +- 10%, which is not "unidentified"."""


def _significant(problem: Problem, p: Parameter, core: CoreFit, se: float, space: str) -> bool:
    """`|value - default| / stderr >= SIGNIFICANT` (linear-space parameters only)."""
    if space != "linear" or p.param == "sigma_rad" or not se > 0:
        return False
    default = float(getattr(problem.fixed, p.param))
    return abs(float(core.ev.x[p.slot]) - default) >= SIGNIFICANT * se


def unidentified(problem: Problem, core: CoreFit, threshold: float) -> Unidentified | None:
    """The parameter to fix next, or None when every free one is constrained."""
    params = problem.parameters(core.spec)
    slots = core.free_slots
    cov = covariance(core)
    candidates: dict[int, str] = {}
    for i in cov.degenerate:
        candidates[int(slots[i])] = (
            "the Fisher information is singular along it, so the data cannot separate it "
            "from the other parameters"
        )
    if cov.z is not None:
        r = float(core.ev.x[problem.layout.slot("edge_radius_um")])
        d = dx_dz(core.z, problem.layout.kinds, problem.r_max_um, r)
        for i, k in enumerate(slots):
            se_z = math.sqrt(max(cov.z[i, i], 0.0))
            se, width, space = _stderr_vs_prior(params[k], se_z, d[k], core.ev.x[k])
            if se > threshold * width and not _significant(problem, params[k], core, se, space):
                candidates[int(k)] = (
                    f"its standard error ({se:.3g}{' in ln' if space == 'log' else ''}) exceeds "
                    f"{threshold:g} x the prior's sd ({width:.3g})"
                )
    if not candidates:
        return None

    def priority(k: int) -> tuple[int, int]:
        p = params[k]
        return FIX_ORDER.index((p.param, p.wedge is not None)), -k

    k = min(candidates, key=priority)
    return Unidentified(params[k], candidates[k])


def apply_fix(
    problem: Problem, spec: FreeSpec, fix: Unidentified, core: CoreFit
) -> tuple[FreeSpec, FitWarning]:
    """Fix an unidentified parameter at its default; an unidentified per-wedge width is fixed
    at the geometric mean of the other fitted widths (or joins the shared width if other wedges
    use it). The shared width or the scale cannot be fixed: `UnconstrainedError`."""
    p = fix.parameter
    if p.param == "sigma_rad" and p.wedge is not None:
        return _fix_wedge_width(problem, spec, fix, core)
    if p.param in ("sigma_rad", "scale"):
        dof = problem.observations.n_used - int(core.free_slots.size)
        raise UnconstrainedError(
            f"the data cannot constrain {p.param}: {fix.reason}; the observations hold no "
            "usable signal for the model (check angles, wedge indices and values)",
            p.param,
            float(core.ev.chi2),
            dof,
        )
    value = getattr(problem.fixed, p.param)
    msg = (
        f"{p.param} is not constrained by the data: {fix.reason}; fixed at its default "
        f"{value:g} instead of being reported with a meaningless error bar"
    )
    return spec._replace(free=spec.free - {p.param}), FitWarning("unidentified", p.param, msg)


def _fix_wedge_width(
    problem: Problem, spec: FreeSpec, fix: Unidentified, core: CoreFit
) -> tuple[FreeSpec, FitWarning]:
    lay, w = problem.layout, fix.parameter.wedge
    label = fix.parameter.label()
    x = core.ev.x
    free = np.asarray(core.data.free)
    source = np.asarray(core.data.sigma_source)
    others = [
        lay.slot("sigma_rad", v)
        for v in spec.own_sigma
        if v != w and free[lay.slot("sigma_rad", v)]
    ]
    if free[lay.slot("sigma_rad")] and np.any(np.delete(source, w) == lay.slot("sigma_rad")):
        msg = f"{label} is not constrained by the data: {fix.reason}; it now shares sigma_rad"
        return spec._replace(own_sigma=spec.own_sigma - {w}), FitWarning("unidentified", label, msg)
    shared = x[lay.slot("sigma_rad")]
    value = float(np.exp(np.mean(np.log(x[others])))) if others else float(shared)
    msg = (
        f"{label} is not constrained by the data: {fix.reason}; fixed at the geometric mean of "
        f"the other wedges' widths, {value:.4g} rad ({np.rad2deg(value):.3g} deg)"
    )
    new = spec._replace(fixed_sigma=(*spec.fixed_sigma, (w, value)))
    return new, FitWarning("unidentified", label, msg)


# --- the active set -----------------------------------------------------------------------------


class BoundFix(NamedTuple):
    """A free parameter whose optimum lies on (or beyond) its bound: the spec with it fixed
    there, the parameter, and the warning (None for the near-bound check, see `on_bound`)."""

    spec: FreeSpec
    param: str
    warning: FitWarning | None


def on_bound(problem: Problem, spec: FreeSpec, core: CoreFit) -> BoundFix | None:
    """Active set: a free parameter whose optimum lies on (or beyond) its bound is fixed there.

    `floor < 0` -> 0; an edge radius at 0 or `r_max`; a model error too small to matter -> 0.
    An edge radius below `NEAR_BOUND x r_max` returns the spec with `r = 0` and no warning: the
    caller refits there and keeps the bound when the likelihood ratio says the data cannot tell
    it apart.
    """
    found = _bound_found(problem, spec, core)
    if found is None:
        return None
    name, value, why = found
    new = spec.fixing(name, value)
    if why is None:
        return BoundFix(new, name, None)
    msg = f"{name} is fixed on its bound {value:g} ({why}); the fit was repeated without it"
    return BoundFix(new, name, FitWarning("at_bound", name, msg))


def _bound_found(
    problem: Problem, spec: FreeSpec, core: CoreFit
) -> tuple[str, float, str | None] | None:
    """(parameter, bound value, why; None = only near the bound) of the first parameter on its
    bound, in the order floor, edge radius, fillet radius, model error."""
    lay, z, x = problem.layout, core.z, core.ev.x
    k = lay.slot("floor")
    if "floor" in spec.free and x[k] < 0.0:
        return "floor", 0.0, f"the unconstrained optimum is negative ({x[k]:.3g})"
    k = lay.slot("edge_radius_um")
    if "edge_radius_um" in spec.free:
        if abs(math.cos(z[k])) < BOUND_TOL:
            at = 0.0 if math.sin(z[k]) < 0 else problem.r_max_um
            return "edge_radius_um", at, f"the optimum is the bound r = {at:.4g} um"
        if x[k] < NEAR_BOUND * problem.r_max_um:
            return "edge_radius_um", 0.0, None
    k = lay.slot("fillet_radius_um")
    if "fillet_radius_um" in spec.free:
        if abs(math.cos(z[k])) < BOUND_TOL and math.sin(z[k]) < 0:
            return "fillet_radius_um", 0.0, "the optimum is the bound r_f = 0 um"
        if abs(math.cos(z[k])) < BOUND_TOL:  # r + r_f = r_max: fixed there, at its value
            return "fillet_radius_um", float(x[k]), "the optimum is the bound r + r_f = r_max"
        if x[k] < NEAR_BOUND * problem.r_max_um:
            return "fillet_radius_um", 0.0, None
    k = lay.slot("model_error_frac")
    if "model_error_frac" in spec.free:
        rel = x[k] * np.abs(core.ev.model) / np.asarray(core.data.stderr)
        if float(np.max(rel * np.asarray(core.data.use))) < BOUND_TOL:
            return "model_error_frac", 0.0, "the data need no model-error term"
        if not core.success:  # the solver stopped short while the term crept to 0
            rise = model_error_rise(core.ev, core.data, float(x[k]))
            if rise < MODEL_ERROR_RISE:
                return (
                    "model_error_frac",
                    0.0,
                    (
                        f"the data need no model-error term: removing it raises -2 log L by "
                        f"{rise:.2g} < {MODEL_ERROR_RISE:g}"
                    ),
                )
    return None


def within_stderr_of_bound(p: Parameter, x: float, se: float) -> bool:
    """A bounded parameter (`ParamInfo.on_bound`) within one standard error of a bound of its
    transform, where a Gaussian error bar is not meaningful."""
    if not p.info.on_bound:
        return False
    return bool(x - p.bounds[0] < se or (p.transform in (SIN, SIN_REST) and p.bounds[1] - x < se))
