"""The refractive index outside its validity range: one warning line, shared by fit and predict.

Non-physical indices (NaN, Re n <= 1, k < 0, a Sellmeier pole, unsorted tables) are errors,
checked where the index is read (`model.materials.index_problem`). Using a dispersion model
outside its stated validity range `valid_nm` is a warning, not an error: the index there is
still checked to be physical, extrapolating a smooth formula a few tens of nanometres is common
practice, and the camera bands of every fit span 380-780 nm, so an error would make a material
such as `pla-bodurov2016` (valid 405-635 nm) unusable. The warning names the range, the
wavelengths that are extrapolated and, for a fit, the share of the channels' spectral weight
there, so that the user can choose a constant index or a measured table instead.
"""

from __future__ import annotations

import warnings
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from .errors import StairfitWarning

if TYPE_CHECKING:
    from stairfit.model.materials import Dispersion


def extrapolation_warning(
    dispersion: Dispersion,
    name: str,
    wavelength_nm: ArrayLike,
    weights: ArrayLike | None = None,
    user: str = "the fit",
) -> str | None:
    """Warn (and return the message) when `wavelength_nm` leaves `dispersion.valid_nm`.

    `weights` (same shape as the wavelengths, e.g. a fit's channel weights) give the share of
    the spectral weight at extrapolated wavelengths; wavelengths with zero weight are ignored.
    Returns None, without a warning, when every wavelength used is inside the range.
    """
    from stairfit.model import materials

    wl = np.asarray(wavelength_nm, dtype=float)
    w = np.broadcast_to(np.asarray(1.0 if weights is None else weights, float), wl.shape)
    used = w > 0
    outside = materials.extrapolated(dispersion, wl) & used
    if not outside.any():
        return None
    lo, hi = dispersion.valid_nm
    n = np.real(np.asarray(dispersion(wl[outside])))
    tabulated = isinstance(dispersion, materials.Tabulated)
    how = "held at its end values" if tabulated else "extrapolated"
    share = ""
    if weights is not None:
        share = f" ({100 * w[outside].sum() / w[used].sum():.0f}% of the channels' spectral weight)"
    sides = [
        f"{_span(a, 'g')} nm" for a in (wl[outside & (wl < lo)], wl[outside & (wl > hi)]) if a.size
    ]
    message = (
        f"{name} is valid over {lo:g}-{hi:g} nm; {user} uses {wl[used].min():g}-"
        f"{wl[used].max():g} nm, so at {' and '.join(sides)}{share} the index is {how} "
        f"(n = {_span(n)} there); choose a constant index or a measured table if that matters"
    )
    warnings.warn(message, StairfitWarning, stacklevel=2)
    return message


def _span(x: np.ndarray, spec: str = ".4g") -> str:
    """`min-max` of an array, or the one value when they are equal."""
    lo, hi = format(x.min(), spec), format(x.max(), spec)
    return lo if lo == hi else f"{lo}-{hi}"
