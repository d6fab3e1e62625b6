"""Accuracy that follows the data (issue 13; `stairfit.pipeline.refine`): after the fit, the
preset's numerical error at the optimum against the `accurate` preset's knobs
(`fitting.numerical_error`, one evaluation); when it exceeds `fitting.ACCURACY_LIMIT` (0.2
measurement standard errors, rms over the rows), the chosen variant is fitted again with the
accurate knobs, started from its optimum — or, with the `fast` preset, a warning says so.
docs/fitting.md §3 ("Numerical error at the optimum").
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from ._memory import first_line, is_out_of_memory
from .fit_setup import fit_setup
from .presets import PRESETS, Preset

if TYPE_CHECKING:
    from stairfit import fitting, model

    from .fit_setup import Material
    from .scene import Scene

DEG = np.pi / 180
REFERENCE = "accurate"
"""The preset whose knobs (5 nm spectral sampling, aperture nodes, rounded resolution, fillet
rays) are the converged reference."""


CHI2_ROSE = 1.05
"""A refit whose chi^2 exceeds the preset fit's by this factor says that the reference itself
is not converged there (a finer model should not describe the data worse)."""

CHI2_ROSE_NOTE = (
    "chi^2 rose, so the accurate knobs are not converged for these data either: a lobe at the "
    "horizon, or a light interval holding two kinks of the lobe weights or one close to its "
    "end, converges slowly (docs/fitting.md §3, light nodes across a kink)"
)


FILLET_NOT_REFITTED = (
    "a filleted variant is not refitted automatically: with the accurate knobs (5 nm sampling, "
    "4096 rays) a refit of a photo folder takes many minutes; rerun with --preset accurate to "
    "refine it"
)
"""The filleted variants' exception to the refit (docs/fitting.md §3): a wait of many minutes
is not started without the user asking for it."""


class AccuracyCheck(NamedTuple):
    """What the check found and did: `preset`; `error` (a `fitting.NumericalError` of the
    preset's fit, None when the preset is the reference); `action` (`none`, `warned`,
    `refitted`, `refit failed`); `elapsed_s` of the refit; `message` in words."""

    preset: str
    error: fitting.NumericalError | None
    action: str
    elapsed_s: float
    message: str

    def record(self) -> dict[str, object]:
        """results.json's `accuracy`."""
        e = self.error
        return {
            "preset": self.preset,
            "reference": REFERENCE,
            "rms_over_stderr": None if e is None else e.rms,
            "max_over_stderr": None if e is None else e.max,
            "of_peak": None if e is None else e.of_peak,
            "limit": None if e is None else e.limit,
            "exceeds": None if e is None else e.exceeds,
            "action": self.action,
            "refit_s": self.elapsed_s,
            "message": self.message,
        }


LAB_NOT_CHECKED = (
    "not checked: the lab model evaluates every face's nodes exactly and its spectral samples "
    "without approximation, so the presets' knobs (aperture nodes, spectral sampling) do not "
    "apply to it"
)
"""The accuracy check's sentence for a fit of the lab model."""


def check_accuracy(
    scene: Scene,
    observations: fitting.Observations,
    selection: fitting.Selection,
    preset: Preset,
    index: Material | None = None,
) -> tuple[fitting.Selection, AccuracyCheck]:
    """The selection (its chosen fit refined when needed) and what the check did (module doc);
    `index`: the scene's index when the fit built it already."""
    from stairfit import fitting

    if preset.name == REFERENCE:
        return selection, AccuracyCheck(preset.name, None, "none", 0.0,
                                        "the accurate preset is its own reference")  # fmt: skip
    if selection.fit.problem is not None and selection.fit.problem.lab is not None:
        return selection, AccuracyCheck(preset.name, None, "none", 0.0, LAB_NOT_CHECKED)
    ref = PRESETS[REFERENCE]
    reference = fit_setup(scene, ref, index)
    spectral = reference.spectral
    resolution = fitting.Resolution(ref.rounded_resolution, ref.fillet_rays)
    knobs = _Knobs(reference.aperture, resolution)
    error = fitting.numerical_error(selection.fit, spectral, **knobs._asdict())
    if not error.exceeds:
        return selection, AccuracyCheck(preset.name, error, "none", 0.0, error.sentence())
    if preset.name == "fast":
        message = f"{error.sentence()}; fast does not refine: rerun with --preset balanced"
        return selection, AccuracyCheck(preset.name, error, "warned", 0.0, message)
    if fitting.FILLET in selection.fit.requested.free:
        return selection, AccuracyCheck(preset.name, error, "warned", 0.0,
                                        f"{error.sentence()}; {FILLET_NOT_REFITTED}")  # fmt: skip
    return _refit(selection, observations, spectral, knobs, preset, error)


class _Knobs(NamedTuple):
    """The reference's quadrature knobs, as `numerical_error` and `fit_least_squares` take them."""

    aperture: model.Aperture
    resolution: fitting.Resolution


def _refit(
    selection: fitting.Selection, observations: fitting.Observations, spectral: fitting.Spectral,
    knobs: _Knobs, preset: Preset, error: fitting.NumericalError,
) -> tuple[fitting.Selection, AccuracyCheck]:  # fmt: skip
    """The chosen variant fitted again with the reference knobs, from its own optimum."""
    from stairfit import fitting

    t0 = time.perf_counter()
    try:
        fit = fitting.fit_least_squares(
            observations, spectral, selection.fit.requested, start_from=(selection.fit,),
            sigma_starts_rad=tuple(s * DEG for s in preset.sigma_starts_deg),
            on_failure="flag", emit_warnings=False, **knobs._asdict(),
        )  # fmt: skip
    except (MemoryError, RuntimeError) as err:  # XLA's allocation failures are RuntimeErrors
        if not is_out_of_memory(err):
            raise
        elapsed = time.perf_counter() - t0
        message = (
            f"{error.sentence()}; the refit with the accurate knobs ran out of memory "
            f"({first_line(err)}), so the {preset.name} fit is kept: its numerical error is "
            "above the limit (rerun on a machine with more memory, or fit fewer photos)"
        )
        return selection, AccuracyCheck(preset.name, error, "refit failed", elapsed, message)
    elapsed = time.perf_counter() - t0
    if not fit.success:
        message = f"{error.sentence()}; the refit with the accurate knobs failed ({fit.message})"
        return selection, AccuracyCheck(preset.name, error, "refit failed", elapsed, message)
    refined = selection.with_fit(fit)
    message = (
        f"{error.sentence()}; {selection.chosen!r} was fitted again with the accurate preset's "
        f"knobs in {elapsed:.0f} s (chi^2 {selection.fit.chi2:.5g} -> {fit.chi2:.5g}); the "
        "parameters, the posterior and the figures are the refined fit's"
    )
    if fit.chi2 > CHI2_ROSE * selection.fit.chi2:
        message += f"; {CHI2_ROSE_NOTE}"
    return refined, AccuracyCheck(preset.name, error, "refitted", elapsed, message)
