"""Spectral sampling, camera channels and colour [conventions §8].

The CIE data, illuminants and camera sensitivities are colour-science's, shipped with stairfit
as package data (`model/_spectral_data.py`: importing colour-science would also import
matplotlib and SciPy; nothing is downloaded). They are turned into plain weight matrices here,
so that everything downstream is a differentiable JAX contraction over wavelength.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from . import _spectral_data

VISIBLE_NM = np.arange(380.0, 781.0, 5.0)
"""The default spectral grid: 380-780 nm every 5 nm (81 samples) [conventions §8]."""

CAMERAS: tuple[str, ...] = ("Nikon 5100 (NPL)", "Sigma SDMerill (NPL)", "ideal")
"""Camera sensitivity sets: colour-science's measured ones (`_spectral_data`, the names of its
`MSDS_CAMERA_SENSITIVITIES`; tests/model/test_spectral_data.py keeps the two lists equal) plus an
ideal Gaussian RGB camera."""

IDEAL_RGB_CENTRES_NM = (600.0, 540.0, 460.0)
IDEAL_RGB_FWHM_NM = 60.0
"""The ideal camera: Gaussian R, G, B bands (centres and full width at half maximum, nm)."""


def illuminant_spd(name: str, wavelength_nm: NDArray = VISIBLE_NM) -> NDArray:
    """Relative spectral power of a CIE illuminant (any of colour-science's SDS_ILLUMINANTS,
    compared as `_spectral_data.canonical` names) on a grid."""
    try:
        sd = _spectral_data.lookup(_spectral_data.tables().illuminants, name)
    except KeyError:
        raise ValueError(
            f"unknown illuminant {name!r}; try one of: D65, A, D50, E, FL2, LED-B1"
        ) from None
    return _resample(sd.wavelength_nm, sd.values, wavelength_nm)


def camera_sensitivities(name: str, wavelength_nm: NDArray = VISIBLE_NM) -> NDArray:
    """(3, n_lambda) R, G, B spectral sensitivities of a named camera (see `CAMERAS`)."""
    if name == "ideal":
        sigma = IDEAL_RGB_FWHM_NM / (2.0 * np.sqrt(2.0 * np.log(2.0)))
        centres = np.asarray(IDEAL_RGB_CENTRES_NM)[:, None]
        return np.exp(-0.5 * ((wavelength_nm[None, :] - centres) / sigma) ** 2)
    try:
        msds = _spectral_data.lookup(_spectral_data.tables().cameras, name)
    except KeyError:
        raise ValueError(f"unknown camera {name!r}; known cameras: {', '.join(CAMERAS)}") from None
    return np.stack(
        [_resample(msds.wavelength_nm, msds.values[:, c], wavelength_nm) for c in range(3)]
    )


class ChannelWeights(NamedTuple):
    """How each channel samples a spectrum [conventions §8].

    `weights` (n_channels, n_lambda) sums to 1 along wavelength, so `weights @ rho(lambda)` is
    the band-weighted mean reflectance a channel sees; `wavelength_nm` is the grid.
    """

    weights: NDArray
    wavelength_nm: NDArray

    @property
    def effective_nm(self) -> NDArray:
        """One effective wavelength per channel: the weighted mean wavelength."""
        return self.weights @ self.wavelength_nm

    def collapsed(self) -> ChannelWeights:
        """The cheap approximation: each channel evaluated at its effective wavelength only."""
        return ChannelWeights(np.eye(len(self.weights)), self.effective_nm)


def channel_weights(
    camera: str, illuminant: str, wavelength_nm: NDArray = VISIBLE_NM
) -> ChannelWeights:
    """Normalised sensitivity x illuminant weights for each camera channel [conventions §8]."""
    raw = camera_sensitivities(camera, wavelength_nm) * illuminant_spd(illuminant, wavelength_nm)
    return ChannelWeights(raw / raw.sum(axis=1, keepdims=True), np.asarray(wavelength_nm, float))


def xyz_weights(illuminant: str, wavelength_nm: NDArray = VISIBLE_NM) -> NDArray:
    """(3, n_lambda) weights such that `weights @ rho(lambda)` is CIE 1931 XYZ of the reflected
    light with a perfect white reflector at Y = 1 [conventions §8]."""
    cmfs = _spectral_data.tables().cmfs[_spectral_data.CMFS_NAME]
    xyz_bar = np.stack(
        [_resample(cmfs.wavelength_nm, cmfs.values[:, c], wavelength_nm) for c in range(3)]
    )
    raw = xyz_bar * illuminant_spd(illuminant, wavelength_nm)
    return raw / raw[1].sum()


def xyz_to_srgb(xyz: NDArray, exposure: float = 1.0) -> NDArray:
    """Display sRGB (gamma-encoded, clipped to [0, 1]) of XYZ scaled by `exposure`.

    Only for pictures (the edge of the program): not differentiable, no chromatic adaptation,
    so light under illuminant A looks warm, as in the paper's Fig. 7. The IEC 61966-2-1 matrix
    and encoding; equal to colour-science's `XYZ_to_sRGB` (tests/model/test_spectral_data.py).
    """
    matrix = _spectral_data.tables().srgb_matrix_xyz_to_rgb
    linear = np.clip((np.asarray(xyz, float) * exposure) @ matrix.T, 0.0, 1.0)
    return srgb_encode(linear)


def srgb_encode(linear: NDArray) -> NDArray:
    """The sRGB transfer function (IEC 61966-2-1) of linear values in [0, 1]."""
    lin = np.asarray(linear, float)
    low = lin <= 0.0031308
    safe = np.where(low, 1.0, lin)  # no power of a negative or zero on the untaken branch
    return np.where(low, 12.92 * lin, 1.055 * safe ** (1 / 2.4) - 0.055)


def _resample(x: NDArray, y: NDArray, at: NDArray) -> NDArray:
    """Linear interpolation, zero outside the tabulated range (no extrapolation of data)."""
    return np.interp(at, np.asarray(x, float), np.asarray(y, float), left=0.0, right=0.0)
