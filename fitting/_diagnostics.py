"""Posterior convergence diagnostics the field expects, from ArviZ: split R-hat, bulk and tail
effective sample sizes, and the chain as an ArviZ `InferenceData` (netCDF).

emcee's walkers are treated as ArviZ's chains (as `arviz.from_emcee` does): the chain after
burn-in, `(n_steps, n_walkers, p)`, becomes `(chain = walker, draw = step)` per parameter.
Thresholds (Vehtari et al. 2021, "Rank-normalization, folding, and localization: an improved
R-hat", Bayesian Analysis 16, 667): rank-normalised split R-hat below `RHAT_MAX` and bulk and
tail ESS of at least `ESS_MIN`; a parameter outside them gets a `ConvergenceWarning`.
docs/fitting.md §5 ("Diagnostics").
"""

from __future__ import annotations

import re
import warnings
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from stairfit.fileio import atomic_path

from ._errors import FitWarning

RHAT_MAX = 1.01
"""Split R-hat at or above this: the walkers have not mixed (Vehtari et al. 2021)."""

ESS_MIN = 400.0
"""Bulk or tail ESS below this: too few effective draws for reliable intervals (ibid.)."""


def _arviz() -> Any:
    """ArviZ, imported on first use (it imports pandas and xarray); its refactor notice, a
    FutureWarning about versions 1.x, is not ours to show."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)
        import arviz

    return arviz


def variable_names(parameters: tuple[Any, ...], degrees: bool = False) -> tuple[str, ...]:
    """netCDF-safe variable names of the free parameters (`sigma_rad`, `sigma_rad_w2`, `scale`):
    `param`, and for a per-wedge width `_w` and the wedge index; with `degrees`, widths are
    named `sigma_deg` (see `display_factors`)."""
    out = []
    for p in parameters:
        param = "sigma_deg" if degrees and p.param == "sigma_rad" else p.param
        name = param if p.wedge is None else f"{param}_w{p.wedge}"
        out.append(re.sub(r"[^A-Za-z0-9_]", "_", name))
    return tuple(out)


def display_factors(
    parameters: tuple[Any, ...], degrees: bool = False
) -> tuple[np.ndarray, tuple[str, ...]]:
    """Per parameter, the factor from physical values to the file's values and the unit: 1 and
    the parameter's unit, except widths in degrees with `degrees` (files and plots are in
    degrees at the CLI's edge [conventions §1])."""
    factors, units = [], []
    for p in parameters:
        width = degrees and p.param == "sigma_rad"
        factors.append(180.0 / np.pi if width else 1.0)
        units.append("deg" if width else p.unit)
    return np.asarray(factors), tuple(units)


class Diagnostics(NamedTuple):
    """Per parameter (the posterior's order): `rhat` (rank-normalised split R-hat),
    `ess_bulk`, `ess_tail` (ArviZ `ess(method="bulk" / "tail")`), after burn-in."""

    rhat: np.ndarray
    ess_bulk: np.ndarray
    ess_tail: np.ndarray


def _dataset(chain: np.ndarray, names: tuple[str, ...]) -> dict[str, np.ndarray]:
    """`{name: (walker, step)}` from a chain `(n_steps, n_walkers, p)`."""
    return {n: np.ascontiguousarray(chain[:, :, i].T) for i, n in enumerate(names)}


def chain_diagnostics(chain: np.ndarray, burn_in: int) -> Diagnostics:
    """R-hat and bulk / tail ESS of every parameter of `chain` `(n_steps, n_walkers, p)` after
    `burn_in` steps (module doc)."""
    az = _arviz()
    kept = chain[burn_in:]
    p = kept.shape[2]
    if kept.shape[0] < 4:  # R-hat splits every chain in two halves: nothing to compare
        nan = np.full(p, np.nan)
        return Diagnostics(nan, nan.copy(), nan.copy())
    names = tuple(f"x{i}" for i in range(p))
    data = az.convert_to_dataset(_dataset(kept, names))
    rhat = az.rhat(data, method="rank")
    bulk = az.ess(data, method="bulk")
    tail = az.ess(data, method="tail")
    return Diagnostics(
        np.array([float(rhat[n]) for n in names]),
        np.array([float(bulk[n]) for n in names]),
        np.array([float(tail[n]) for n in names]),
    )


def diagnostic_warnings(d: Diagnostics, labels: tuple[str, ...]) -> tuple[FitWarning, ...]:
    """`rhat_high` and `ess_low` warnings for the parameters outside the thresholds."""
    out = []
    for label, r, b, t in zip(labels, d.rhat, d.ess_bulk, d.ess_tail, strict=True):
        if not r < RHAT_MAX:
            out.append(
                FitWarning(
                    "rhat_high",
                    label,
                    f"{label}: split R-hat = {r:.4g} is not below {RHAT_MAX:g}; the walkers have "
                    "not mixed — run a longer chain (resume) before trusting the intervals",
                )
            )
        if not min(b, t) >= ESS_MIN:
            out.append(
                FitWarning(
                    "ess_low",
                    label,
                    f"{label}: effective sample size bulk {b:.0f} / tail {t:.0f} is below "
                    f"{ESS_MIN:g}; the percentiles (the tails most) are noisy — run a longer chain",
                )
            )
    return tuple(out)


def inference_data(
    chain: np.ndarray,
    log_prob: np.ndarray,
    burn_in: int,
    names: tuple[str, ...],
    units: tuple[str, ...],
    attrs: dict[str, Any],
) -> Any:
    """The chain `(n_steps, n_walkers, p)` as an `arviz.InferenceData`: group `posterior`
    (after burn-in) and `warmup_posterior` (the burn-in), variable `names[i]` `(chain = walker,
    draw = step)` with attribute `units[i]`, `sample_stats.lp` the log posterior (also split at
    `burn_in`), and the file attributes `attrs` (labels, seed ...)."""
    az = _arviz()
    lp = np.ascontiguousarray(log_prob.T)
    with warnings.catch_warnings():
        # ArviZ guesses that a group with more chains than draws was passed transposed; a short
        # burn-in (7 steps of 32 walkers for the "laplace" moves) is such a group, correctly.
        warnings.filterwarnings("ignore", "More chains", UserWarning)
        idata = az.from_dict(
            posterior=_dataset(chain[burn_in:], names),
            warmup_posterior=_dataset(chain[:burn_in], names),
            sample_stats={"lp": lp[:, burn_in:]},
            warmup_sample_stats={"lp": lp[:, :burn_in]},
            save_warmup=True,
            attrs=attrs,
        )
    for group in (idata.posterior, idata.warmup_posterior):
        for name, unit in zip(names, units, strict=True):
            group[name].attrs["units"] = unit
    return idata


def write_netcdf(idata: Any, path: str | Path) -> Path:
    """Write an `InferenceData` to `path` (netCDF-4 through h5netcdf, ArviZ's default engine;
    `arviz.from_netcdf(path)` reads it) atomically (`stairfit.fileio.atomic_path`), as the
    chain file is written (`_chain.ChainBackend.save`)."""
    with atomic_path(path) as tmp:
        idata.to_netcdf(str(tmp), engine="h5netcdf")
    return Path(path)
