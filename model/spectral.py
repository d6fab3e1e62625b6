"""Spectral sampling, camera channels and colour [conventions §8].

The CIE data, illuminants and camera sensitivities come from colour-science (shipped with the
pip package; nothing is downloaded). They are turned into plain weight matrices here, once, so
that everything downstream is a differentiable JAX contraction over wavelength.
"""

from __future__ import annotations

from typing import NamedTuple

import colour
import numpy as np
from numpy.typing import NDArray

VISIBLE_NM = np.arange(380.0, 781.0, 5.0)
"""The default spectral grid: 380-780 nm every 5 nm (81 samples) [conventions §8]."""

CAMERAS: tuple[str, ...] = (*colour.MSDS_CAMERA_SENSITIVITIES.keys(), "ideal")
"""Camera sensitivity sets: colour-science's measured ones plus an ideal Gaussian RGB camera."""

IDEAL_RGB_CENTRES_NM = (600.0, 540.0, 460.0)
IDEAL_RGB_FWHM_NM = 60.0
"""The ideal camera: Gaussian R, G, B bands (centres and full width at half maximum, nm)."""


def illuminant_spd(name: str, wavelength_nm: NDArray = VISIBLE_NM) -> NDArray:
    """Relative spectral power of a CIE illuminant (any of colour.SDS_ILLUMINANTS) on a grid."""
    try:
        sd = colour.SDS_ILLUMINANTS[name]
    except KeyError:
        raise ValueError(
            f"unknown illuminant {name!r}; try one of: D65, A, D50, E, FL2, LED-B1"
        ) from None
    return _resample(sd.wavelengths, sd.values, wavelength_nm)


def camera_sensitivities(name: str, wavelength_nm: NDArray = VISIBLE_NM) -> NDArray:
    """(3, n_lambda) R, G, B spectral sensitivities of a named camera (see `CAMERAS`)."""
    if name == "ideal":
        sigma = IDEAL_RGB_FWHM_NM / (2.0 * np.sqrt(2.0 * np.log(2.0)))
        centres = np.asarray(IDEAL_RGB_CENTRES_NM)[:, None]
        return np.exp(-0.5 * ((wavelength_nm[None, :] - centres) / sigma) ** 2)
    try:
        msds = colour.MSDS_CAMERA_SENSITIVITIES[name]
    except KeyError:
        raise ValueError(f"unknown camera {name!r}; known cameras: {', '.join(CAMERAS)}") from None
    return np.stack(
        [_resample(msds.wavelengths, msds.values[:, c], wavelength_nm) for c in range(3)]
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
    cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"]
    xyz_bar = np.stack(
        [_resample(cmfs.wavelengths, cmfs.values[:, c], wavelength_nm) for c in range(3)]
    )
    raw = xyz_bar * illuminant_spd(illuminant, wavelength_nm)
    return raw / raw[1].sum()


def xyz_to_srgb(xyz: NDArray, exposure: float = 1.0) -> NDArray:
    """Display sRGB (gamma-encoded, clipped to [0, 1]) of XYZ scaled by `exposure`.

    Only for pictures (the edge of the program): not differentiable, no chromatic adaptation,
    so light under illuminant A looks warm, as in the paper's Fig. 7.
    """
    rgb = colour.XYZ_to_sRGB(np.asarray(xyz) * exposure, apply_cctf_encoding=True)
    return np.clip(rgb, 0.0, 1.0)


def _resample(x: NDArray, y: NDArray, at: NDArray) -> NDArray:
    """Linear interpolation, zero outside the tabulated range (no extrapolation of data)."""
    return np.interp(at, np.asarray(x, float), np.asarray(y, float), left=0.0, right=0.0)
