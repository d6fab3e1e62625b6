"""Accuracy that follows the data (issue 13): the numerical error of a fit's model at its
optimum, against a converged reference, in units of the measurement standard errors.

A preset's knobs (spectral sampling, aperture nodes, the rounded model's resolution, the fillet
correction's rays) trade accuracy for speed; an error that is small at 2% noise can be many
standard errors when a large photo averages the noise down. `numerical_error` evaluates the
model once more at the fitted parameters with the reference knobs (`model_radiance`,
`stairfit.model` directly) and compares it with the fitted model row by row. docs/fitting.md
§3 ("Numerical error at the optimum").
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from stairfit import model

from ._forward import Resolution, measurement_whitened
from ._observations import Spectral
from ._result import FitResult
from ._simulate import model_radiance

ACCURACY_LIMIT = 0.2
"""The fit's numerical error is too large when the rms over the used rows of
`(model - reference) / stderr` exceeds this: a bias of 0.2 standard errors per row adds about
4% to chi^2 and moves no parameter by more than a fraction of its standard error."""


class NumericalError(NamedTuple):
    """The fitted model against a reference evaluation at the same parameters, over the used
    rows: `rms` and `max` of `(model - reference) / stderr` (whitened with the ROI's
    measurement covariance for correlated rows, so that `rms^2 x rows` is the chi^2 the
    difference alone would add), `of_peak`: the largest
    `|model - reference|` over the largest reference value, the `limit` that `rms` is compared
    with, and `elapsed_s` of the reference evaluation."""

    rms: float
    max: float
    of_peak: float
    limit: float
    elapsed_s: float

    @property
    def exceeds(self) -> bool:
        """True when the rms error exceeds `limit` (the preset is too coarse for the data)."""
        return not self.rms <= self.limit

    def sentence(self) -> str:
        """One line for summaries: the number and what it means."""
        verdict = "exceeds" if self.exceeds else "is within"
        return (
            f"numerical error of the model at the optimum: rms {self.rms:.3g} (max {self.max:.3g}) "
            f"measurement standard errors, {100 * self.of_peak:.2g}% of the peak at most; "
            f"{verdict} the limit {self.limit:g}"
        )


def numerical_error(
    fit: FitResult,
    reference: Spectral,
    *,
    aperture: model.Aperture | None = None,
    resolution: int | Resolution | None = None,
    limit: float = ACCURACY_LIMIT,
) -> NumericalError:
    """`fit.model` against `model_radiance(fit.params, ...)` with the reference spectral setup
    `reference`, `aperture` and `resolution` (the rounded model's, or a `Resolution` with the
    fillet correction's rays too) (module doc); one evaluation."""
    import time

    if fit.problem is None:
        raise ValueError("the fit holds no observations (FitResult.problem is None)")
    obs = fit.problem.observations
    t0 = time.perf_counter()
    ref = model_radiance(fit.params, obs, reference, aperture=aperture, resolution=resolution)
    elapsed = time.perf_counter() - t0
    use = np.asarray(obs.use, bool)
    full = np.asarray(fit.model, float) - ref
    diff = full[use]
    z = np.asarray(measurement_whitened(full, fit.problem.data, fit.problem.correlated))[use]
    peak = float(np.max(np.abs(ref[use])))
    return NumericalError(
        rms=float(np.sqrt(np.mean(z**2))),
        max=float(np.max(np.abs(z))),
        of_peak=float(np.max(np.abs(diff)) / peak) if peak > 0 else 0.0,
        limit=float(limit),
        elapsed_s=elapsed,
    )
