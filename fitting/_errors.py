"""Errors and structured warnings of the fitting layer.

User mistakes raise `FitInputError` with a message naming the row or field and the fix; a fit
that cannot produce an honest answer raises `FitError`. Things worth knowing that do not stop a
fit are recorded as `FitWarning` records in the result *and* emitted with `warnings.warn` under
one of the warning categories below, so that callers can filter them.
"""

from __future__ import annotations

from typing import Any, NamedTuple, TypeVar

_Options = TypeVar("_Options", bound=tuple)  # a NamedTuple of settings


class FitInputError(ValueError):
    """The observations, the spectral setup or a fit option is invalid (message says the fix)."""


class FitError(RuntimeError):
    """A fit did not converge or produced non-finite values; nothing is reported as success."""


class UnconstrainedError(FitError):
    """An essential parameter (the shared width or the scale) is not constrained by the data.

    `parameter` names it; `chi2` and `dof` are those of the fit where it happened. A grossly
    misfitting variant can run to a degenerate limit (e.g. a width so wide that the model no
    longer depends on it); `select_model` then reports the variant as misfitting, not as
    unidentifiable.
    """

    def __init__(self, message: str, parameter: str, chi2: float, dof: int) -> None:
        super().__init__(message)
        self.parameter, self.chi2, self.dof = parameter, float(chi2), int(dof)


class FitWarningCategory(UserWarning):
    """Base class of every warning the fitting layer emits."""


class UnidentifiedParameterWarning(FitWarningCategory):
    """A free parameter was not constrained by the data and was fixed at its default."""


class BoundaryWarning(FitWarningCategory):
    """A parameter ended at (or numerically next to) a bound of its transform."""


class ConvergenceWarning(FitWarningCategory):
    """A least-squares start or the posterior sampler did not meet its convergence test."""


class FitWarning(NamedTuple):
    """One structured warning recorded in a result.

    `code` is one of `"unidentified"`, `"at_bound"`, `"start_failed"`, `"not_converged"`,
    `"chain_too_short"`, `"low_acceptance"`, `"rhat_high"`, `"ess_low"`; `parameter` names the
    parameter concerned (or is None); `message` is the human-readable sentence also passed to
    `warnings.warn`.
    """

    code: str
    parameter: str | None
    message: str


WARNING_CATEGORIES: dict[str, type[FitWarningCategory]] = {
    "unidentified": UnidentifiedParameterWarning,
    "at_bound": BoundaryWarning,
    "start_failed": ConvergenceWarning,
    "not_converged": ConvergenceWarning,
    "chain_too_short": ConvergenceWarning,
    "low_acceptance": ConvergenceWarning,
    "rhat_high": ConvergenceWarning,
    "ess_low": ConvergenceWarning,
}
"""The `warnings` category used for each `FitWarning.code`."""


def with_overrides(options: _Options, what: str, overrides: dict[str, Any]) -> _Options:
    """`options` (a NamedTuple of settings) with `overrides` replacing fields; an unknown field
    is a `TypeError` naming the `what` options and every valid field, like a bad keyword."""
    unknown = set(overrides) - set(options._fields)
    if unknown:
        raise TypeError(
            f"unknown {what} option(s) {sorted(unknown)}; the options are "
            f"{', '.join(options._fields)}"
        )
    return options._replace(**overrides)


def emit(records: tuple[FitWarning, ...], stacklevel: int = 3) -> None:
    """Pass structured warnings on to `warnings.warn` with their category."""
    import warnings

    for rec in records:
        category = WARNING_CATEGORIES.get(rec.code, FitWarningCategory)
        warnings.warn(rec.message, category, stacklevel=stacklevel)
