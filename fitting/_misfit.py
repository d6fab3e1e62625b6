"""Does a fit describe the data? Status words, the chi^2 tail, the model-error test, residuals.

A fit *misfits* when its chi^2 is improbable under its own error model, or when it needed a
fractional model-error term larger than the measurement errors can hide (`MODEL_ERROR_LIMIT`,
or twice the median relative standard error of the data, whichever is smaller). The residual
pattern (per wedge and per photo, with the measurement errors alone) says where. The rules are
in docs/fitting.md §4 ("Status words") [conventions §9].
"""

from __future__ import annotations

import enum
import math
from typing import NamedTuple

import jax
import numpy as np
from jaxtyping import Array

from ._forward import measurement_whitened
from ._result import FitResult

P_VALUE_LIMIT = 1e-3
"""A chi^2 whose upper tail probability is below this does not describe the data."""

MODEL_ERROR_LIMIT = 0.01
"""A model-error term above 1% of the model (or above `MODEL_ERROR_NOISE_FACTOR` x the median
relative standard error, if smaller) is a misfit that the term hides."""

MODEL_ERROR_NOISE_FACTOR = 2.0
"""See `MODEL_ERROR_LIMIT`: with precise data even a small model error dominates the errors."""


class Status(enum.StrEnum):
    """What became of one variant of the ladder (the words of the comparison table)."""

    OK = "ok"
    """Converged, and describes the data."""
    MISFITS = "misfits"
    """Converged (or ran to a degenerate limit), and does not describe the data."""
    UNIDENTIFIABLE = "unidentifiable"
    """The data cannot constrain an essential parameter (a width, the scale), and the fit does
    not misfit: the observations hold too little signal for this variant."""
    NOT_CONVERGED = "did not converge"
    """No start met the solver's tolerance within `max_steps`."""
    NOT_FITTED = "not fitted"
    """Skipped on purpose (e.g. rounded rungs that the data did not need)."""
    ADDS_NOTHING = "adds nothing"
    """Converged, but what it adds over its parent ended on a bound, was unidentified or
    changed `-2 log L` by less than `GAIN_MIN`: it is its parent again, so it is not scored
    and the ladder does not escalate from it."""


def chi2_p_value(chi2: float, dof: int) -> float:
    """Upper tail probability of chi^2 with `dof` degrees of freedom (`dof` at least 1)."""
    if not math.isfinite(chi2):
        return math.nan
    return float(_gammaincc(0.5 * max(int(dof), 1), 0.5 * max(float(chi2), 0.0)))


@jax.jit
def _gammaincc(a: Array, x: Array) -> Array:
    """`jax.scipy.special.gammaincc` as one compiled program (eagerly, each call dispatched its
    conversions and the incomplete gamma function as separate programs)."""
    from jax.scipy.special import gammaincc

    return gammaincc(a, x)


def p_text(p: float) -> str:
    """`p = 0.023`, `p = 1.1e-40`, `p < 1e-300` (an underflow)."""
    if not math.isfinite(p):
        return "p = n/a"
    return "p < 1e-300" if p <= 0.0 else f"p = {p:.2g}"


def chi2_text(chi2: float, dof: int) -> str:
    """`chi^2 = 3.59e+04 for 340 dof, p < 1e-300`."""
    return f"chi^2 = {chi2:.4g} for {dof} dof, {p_text(chi2_p_value(chi2, dof))}"


class ResidualGroup(NamedTuple):
    """Residuals of one wedge or one photo, with the measurement errors alone: `label`, used
    rows `n`, `mean` and `rms` of `(value - model) / stderr`, and the range of
    `model / value` over its rows (`ratio_min`, `ratio_max`)."""

    label: str
    n: int
    mean: float
    rms: float
    ratio_min: float
    ratio_max: float


class Assessment(NamedTuple):
    """Whether a fit describes the data (`describe_fit`).

    `status` (`Status.OK` or `Status.MISFITS`); `reasons`: why it misfits, in words (empty if
    it does not); `chi2` (with the fit's own error model, model-error term included), its `dof`
    and `p_value`; `chi2_measurement`: chi^2 with the measurement errors alone (the model-error
    term removed; equal to `chi2` without one); `model_error_frac` (None when not fitted) and
    the `model_error_limit` it is compared with; `median_rel_stderr` of the used rows; the
    residual pattern `by_wedge`, `by_photo`; `pattern`: one line describing it.
    """

    status: Status
    reasons: tuple[str, ...]
    chi2: float
    dof: int
    p_value: float
    chi2_measurement: float
    model_error_frac: float | None
    model_error_limit: float
    median_rel_stderr: float
    by_wedge: tuple[ResidualGroup, ...]
    by_photo: tuple[ResidualGroup, ...]
    pattern: str

    @property
    def misfits(self) -> bool:
        """True when the fit does not describe the data."""
        return self.status == Status.MISFITS

    def because(self) -> str:
        """The reasons as a predicate of "it": `needs a model-error term of 14% > 0.17%; has
        chi^2 = 247.3 for 150 dof, p = 9.7e-07`."""
        return "; ".join(r if r.startswith("needs") else f"has {r}" for r in self.reasons)

    def headline(self) -> str:
        """One sentence for the top of a summary (empty when the fit describes the data)."""
        if not self.misfits:
            return ""
        limit = (
            f" (the limit is the smaller of {100 * MODEL_ERROR_LIMIT:g}% and "
            f"{MODEL_ERROR_NOISE_FACTOR:g} x the median relative standard error, "
            f"{100 * self.median_rel_stderr:.2g}%)"
            if self.model_error_frac is not None and self.model_error_frac > self.model_error_limit
            else ""
        )
        return (
            f"MISFIT: the model does not describe the data: it {self.because()}{limit}; "
            f"chi^2 = {self.chi2_measurement:.4g} with the measurement errors alone, "
            f"{self.chi2:.4g} with the model-error term, for {self.dof} dof. {self.pattern}"
        )


def _groups(
    keys: np.ndarray, labels: dict[int, str], z: np.ndarray, ratio: np.ndarray
) -> tuple[ResidualGroup, ...]:
    out = []
    for k in np.unique(keys):
        sel = keys == k
        out.append(
            ResidualGroup(
                labels.get(int(k), str(int(k))),
                int(sel.sum()),
                float(np.mean(z[sel])),
                float(np.sqrt(np.mean(z[sel] ** 2))),
                float(np.min(ratio[sel])),
                float(np.max(ratio[sel])),
            )
        )
    return tuple(out)


def _pattern(by_wedge: tuple[ResidualGroup, ...], ratio: np.ndarray) -> str:
    """One line: where the residuals are largest and how far the model is from the data."""
    if not by_wedge:
        return ""
    worst = max(by_wedge, key=lambda g: g.rms)
    best = min(by_wedge, key=lambda g: g.rms)
    sign = "above" if worst.mean < 0 else "below"
    return (
        f"Residuals (measurement errors alone) are largest on wedge {worst.label} (rms "
        f"{worst.rms:.3g}, the model mostly {sign} the data) and smallest on wedge {best.label} "
        f"(rms {best.rms:.3g}); model / measured spans {np.min(ratio):.3g}-{np.max(ratio):.3g}."
    )


def measurement_residuals(fit: FitResult) -> np.ndarray:
    """Per row of the fit's observations, the residual with the measurement errors alone (the
    model-error term left out): `(value - model) / stderr` for independent rows, the row's
    component of `L0^-1 (value - model)` with the ROI's measurement covariance `S R S = L0 L0^T`
    for correlated ones (docs/fitting.md §Correlated channels); 0 for rows not fitted."""
    problem = fit.problem
    if problem is None:
        return np.zeros(0)
    resid = np.asarray(problem.observations.value, float) - np.asarray(fit.model, float)
    return np.asarray(measurement_whitened(resid, problem.data, problem.correlated))


def describe_fit(fit: FitResult) -> Assessment:
    """Whether `fit` describes its data (module doc), with the residual pattern."""
    obs = fit.problem.observations if fit.problem is not None else None
    use = np.zeros(0, bool) if obs is None else np.asarray(obs.use, bool)
    value = np.zeros(0) if obs is None else np.asarray(obs.value, float)
    stderr = np.ones(0) if obs is None else np.asarray(obs.stderr, float)
    model = np.asarray(fit.model, float)
    z = measurement_residuals(fit)[use]
    chi2_meas = float(np.sum(z**2))
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(value[use] != 0, model[use] / value[use], np.nan)
        rel = np.abs(stderr[use] / value[use])
    ratio = ratio[np.isfinite(ratio)] if np.any(np.isfinite(ratio)) else np.array([np.nan])
    median_rel = float(np.nanmedian(rel)) if rel.size else math.nan
    limit = min(MODEL_ERROR_LIMIT, MODEL_ERROR_NOISE_FACTOR * median_rel)
    f = fit.estimate("model_error_frac").value if "model_error_frac" in fit.variant.free else None
    p = chi2_p_value(fit.chi2, fit.dof)
    reasons = []
    if f is not None and f > limit:
        reasons.append(f"needs a model-error term of {100 * f:.3g}% > {100 * limit:.2g}%")
    if p < P_VALUE_LIMIT:
        reasons.append(chi2_text(fit.chi2, fit.dof))
    wedge_deg = {} if fit.problem is None else dict(enumerate(fit.problem.wedge_deg))
    w_labels = {k: f"{k} ({d:g} deg)" for k, d in wedge_deg.items()}
    wedges = np.asarray(obs.wedge_index)[use] if obs is not None else np.zeros(0, int)
    photos = np.asarray(obs.photo_index)[use] if obs is not None else np.zeros(0, int)
    full_ratio = np.where(value[use] != 0, model[use] / np.where(value[use] != 0, value[use], 1), 1)
    by_wedge = _groups(wedges, w_labels, z, full_ratio)
    by_photo = _groups(photos, {}, z, full_ratio)
    return Assessment(
        status=Status.MISFITS if reasons else Status.OK,
        reasons=tuple(reasons),
        chi2=float(fit.chi2),
        dof=int(fit.dof),
        p_value=p,
        chi2_measurement=chi2_meas,
        model_error_frac=f,
        model_error_limit=limit,
        median_rel_stderr=median_rel,
        by_wedge=by_wedge,
        by_photo=by_photo,
        pattern=_pattern(by_wedge, ratio),
    )
