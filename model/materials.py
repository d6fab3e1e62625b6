"""Refractive-index models (dispersion) and the materials stairfit ships [conventions §7].

A dispersion model maps wavelengths in nanometres to a (possibly complex) refractive index.
The choice is always explicit; see the README's "Materials" section for why the default for PLA
is the paper's constant n = 1.46 rather than the only published PLA dispersion formula.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float


class ConstantIndex(NamedTuple):
    """Wavelength-independent index `n' + i k`."""

    n: float
    k: float = 0.0
    valid_nm: tuple[float, float] = (0.0, float("inf"))

    def __call__(self, wavelength_nm: ArrayLike) -> Array:
        """Index at each wavelength (nm) [conventions §7]."""
        wl = jnp.asarray(wavelength_nm)
        return _complex_if_absorbing(jnp.full_like(wl, self.n), self.k, wl)


class Cauchy(NamedTuple):
    """Cauchy's formula `n = A + B / lambda^2 + C / lambda^4`, lambda in micrometres."""

    a: float
    b_um2: float = 0.0
    c_um4: float = 0.0
    k: float = 0.0
    valid_nm: tuple[float, float] = (380.0, 780.0)

    def __call__(self, wavelength_nm: ArrayLike) -> Array:
        """Index at each wavelength (nm) [conventions §7]."""
        lam2 = (jnp.asarray(wavelength_nm) * 1e-3) ** 2
        n = self.a + self.b_um2 / lam2 + self.c_um4 / lam2**2
        return _complex_if_absorbing(n, self.k, n)


class Sellmeier(NamedTuple):
    """refractiveindex.info "formula 1": `n^2 = 1 + c0 + sum_i B_i / (1 - (C_i / lambda)^2)`.

    `b` are the dimensionless B_i, `c_um` the resonance wavelengths C_i in micrometres.
    """

    c0: float
    b: tuple[float, ...]
    c_um: tuple[float, ...]
    k: float = 0.0
    valid_nm: tuple[float, float] = (380.0, 780.0)

    def __call__(self, wavelength_nm: ArrayLike) -> Array:
        """Index at each wavelength (nm) [conventions §7]."""
        lam = jnp.asarray(wavelength_nm) * 1e-3
        n2 = 1.0 + self.c0
        for b_i, c_i in zip(self.b, self.c_um, strict=True):
            n2 = n2 + b_i / (1.0 - (c_i / lam) ** 2)
        n = jnp.sqrt(n2)
        return _complex_if_absorbing(n, self.k, n)


class Tabulated(NamedTuple):
    """Measured `n`, `k` at given wavelengths (nm), linearly interpolated, held at the ends."""

    wavelength_nm: tuple[float, ...]
    n: tuple[float, ...]
    k: tuple[float, ...] | None = None

    @property
    def valid_nm(self) -> tuple[float, float]:
        """The tabulated range; outside it the end values are held."""
        return (min(self.wavelength_nm), max(self.wavelength_nm))

    def __call__(self, wavelength_nm: ArrayLike) -> Array:
        """Index at each wavelength (nm) [conventions §7]."""
        wl = jnp.asarray(wavelength_nm)
        xp = jnp.asarray(self.wavelength_nm, dtype=wl.dtype)
        n = jnp.interp(wl, xp, jnp.asarray(self.n, dtype=wl.dtype))
        if self.k is None or not any(self.k):
            return n
        k = jnp.interp(wl, xp, jnp.asarray(self.k, dtype=wl.dtype))
        return n + 1j * k


Dispersion = ConstantIndex | Cauchy | Sellmeier | Tabulated


class PerChannel(NamedTuple):
    """One index per camera channel, in channel order (R, G, B), each constant across its
    channel's band [conventions §7, §8]: for indices measured or fitted channel by channel.

    Not a dispersion model (it has no wavelength dependence of its own): the fit reads it per
    channel (`index_per_channel`), and pictures over wavelength use `along_wavelength`.
    `k` is empty (no absorption) or one extinction coefficient per channel.
    """

    n: tuple[float, ...]
    k: tuple[float, ...] = ()

    def values(self) -> Array:
        """(n_channels,) the complex index `n + i k` per channel (real when `k` is empty or 0)."""
        n = jnp.asarray(self.n, dtype=float)
        if not any(self.k):
            return n
        return n + 1j * jnp.asarray(self.k, dtype=float)

    def along_wavelength(self, effective_nm: ArrayLike) -> Tabulated:
        """A wavelength model through each channel's value at its effective wavelength (linear
        between them, held beyond): for figures over the spectrum only."""
        eff = np.asarray(effective_nm, float)
        if eff.shape != (len(self.n),):
            raise ValueError(f"need one effective wavelength per channel ({len(self.n)})")
        order = np.argsort(eff)
        n = np.asarray(self.n, float)[order]
        k = tuple(np.asarray(self.k, float)[order].tolist()) if any(self.k) else None
        return Tabulated(tuple(eff[order].tolist()), tuple(n.tolist()), k)


def index_per_channel(
    index: Dispersion | PerChannel, wavelength_nm: ArrayLike
) -> Float[Array, "channels K"]:
    """The index each channel sees at its wavelength samples `wavelength_nm` (n_channels, K)
    [conventions §7]: a dispersion model evaluated there, or a `PerChannel` value per row
    (ValueError when its length is not the number of channels)."""
    wl = jnp.asarray(wavelength_nm)
    if not isinstance(index, PerChannel):
        return index(wl)
    if len(index.n) != wl.shape[0] or (index.k and len(index.k) != len(index.n)):
        raise ValueError(
            f"a per-channel index needs one value per camera channel ({wl.shape[0]}, in R, G, "
            f"B order); got n = {list(index.n)}" + (f", k = {list(index.k)}" if index.k else "")
        )
    return jnp.broadcast_to(index.values()[:, None], wl.shape)


def _complex_if_absorbing(n: Array, k: float, like: Array) -> Array:
    """Return `n` real when `k == 0` (faster Fresnel), else `n + i k`."""
    if k == 0.0:
        return n
    return n + 1j * jnp.asarray(k, dtype=like.dtype)


def refractive_index(
    dispersion: Dispersion, wavelength_nm: ArrayLike, delta_n: ArrayLike = 0.0
) -> Float[Array, "..."]:
    """`n(lambda) + delta_n` [conventions §7]: the learnable offset shifts the real part only."""
    return dispersion(wavelength_nm) + jnp.asarray(delta_n)


# --- checks ---------------------------------------------------------------------------------


def index_problem(
    dispersion: Dispersion,
    wavelength_nm: ArrayLike,
    delta_n: float = 0.0,
    values: ArrayLike | None = None,
) -> str | None:
    """Why `dispersion + delta_n` is not a physical index at `wavelength_nm`, or None.

    Physical means [conventions §6, §7]: finite, `Re n > 1`, `k >= 0` at every wavelength;
    tabulated wavelengths strictly increasing (linear interpolation needs them sorted); no
    Sellmeier resonance `C_i` (where n^2 diverges) inside the span of the wavelengths.
    `values`, when given, are `dispersion(wavelength_nm)` already evaluated (e.g. by a compiled
    call), so that the check adds no evaluation of its own.
    """
    wl = np.atleast_1d(np.asarray(wavelength_nm, dtype=float))
    if isinstance(dispersion, Tabulated):
        table = np.asarray(dispersion.wavelength_nm, dtype=float)
        if not (np.all(np.isfinite(table)) and np.all(np.diff(table) > 0)):
            return "the tabulated wavelengths must increase strictly; sort the table"
    if isinstance(dispersion, Sellmeier):
        for b_i, c_i in zip(dispersion.b, dispersion.c_um, strict=True):
            pole = abs(c_i) * 1e3
            if b_i != 0 and wl.min() <= pole <= wl.max():
                return (
                    f"has a Sellmeier pole (C = {c_i:g} um) at {pole:g} nm, inside the "
                    f"wavelengths used ({wl.min():g}-{wl.max():g} nm), where n is infinite or NaN"
                )
    n = np.asarray(dispersion(wl) if values is None else values).reshape(wl.shape) + delta_n
    bad = ~np.isfinite(n) | ~(np.real(n) > 1.0) | (np.imag(n) < 0)
    if np.any(bad):
        k = int(np.argmax(bad))
        return (
            f"gives n({wl[k]:g} nm) = {complex(n[k]):.4g}; need a finite index with Re n > 1 "
            f"and k >= 0 at every wavelength used ({wl.min():g}-{wl.max():g} nm)"
        )
    return None


def extrapolated(dispersion: Dispersion, wavelength_nm: ArrayLike) -> np.ndarray:
    """Which of `wavelength_nm` lie outside the model's validity range `valid_nm` (bool array).

    Outside it a formula is extrapolated and a table is held at its end values.
    """
    wl = np.asarray(wavelength_nm, dtype=float)
    lo, hi = dispersion.valid_nm
    return (wl < lo) | (wl > hi)


# --- datasets -------------------------------------------------------------------------------

PLA_PAPER_CONSTANT = ConstantIndex(n=1.46)
"""PLA as in the paper (Pranovich et al. 2020, Sec. 3): "a representative value of n = 1.46"."""

PLA_BODUROV_2016 = Sellmeier(c0=0.0, b=(0.9809,), c_um=(0.2123719,), valid_nm=(405.0, 635.0))
"""PLA (PDLA film, 45 um on glass, 24 C), single-term Sellmeier, valid 405-635 nm.

Source: I. Bodurov, I. Vlaeva, A. Viraneva, T. Yovcheva, S. Sainov, "Modified design of a laser
refractometer", Nanosci. Nanotechnol. 16, 31-33 (2016), as encoded in the refractiveindex.info
database (M. N. Polyanskiy, Sci. Data 11, 94 (2024); entry
`organic/(C3H4O2)n - polylactic acid/nk/Bodurov.yml`, CC0): "formula 1", coefficients
`0 0.9809 0.2123719`. n(550 nm) = 1.4672. Its implied Abbe number (about 11.5) is implausibly low
for a plastic; outside 405-635 nm it is an extrapolation.
"""

MATERIALS: dict[str, Dispersion] = {
    "pla": PLA_PAPER_CONSTANT,
    "pla-constant": PLA_PAPER_CONSTANT,
    "pla-bodurov2016": PLA_BODUROV_2016,
}
"""Named dispersion models. `pla` is `pla-constant`, the paper's choice."""


def get_material(name: str) -> Dispersion:
    """Look up a named dispersion model; a clear error lists the known names."""
    try:
        return MATERIALS[name.lower()]
    except KeyError:
        known = ", ".join(sorted(MATERIALS))
        raise ValueError(f"unknown material {name!r}; known materials: {known}") from None
