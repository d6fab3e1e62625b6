"""What a fit of a scene needs besides its observations: the material's index, the spectral
setup, the aperture and the channels' effective wavelengths [conventions §7-§9], built once
from the scene and a preset and carried to the accuracy check and the report.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import numpy as np

if TYPE_CHECKING:
    from stairfit import fitting, model
    from stairfit.model.materials import Dispersion, PerChannel

    from .presets import Preset
    from .scene import Scene

    Material = str | Dispersion | PerChannel

DEG = np.pi / 180


class FitSetup(NamedTuple):
    """`index`: the scene's material index (`IndexSpec.build()`, built once); `spectral`: each
    channel's samples and weights for the preset's sampling; `aperture`: the light's and the
    camera's angular extents with the preset's nodes; `effective_nm`: each channel's effective
    wavelength (sensitivity x illuminant weighted mean)."""

    index: Material
    spectral: fitting.Spectral
    aperture: model.Aperture
    effective_nm: np.ndarray


def fit_setup(scene: Scene, preset: Preset, index: Material | None = None) -> FitSetup:
    """The setup of a fit of `scene` with `preset`'s knobs [conventions §8, §9]; `index`: the
    scene's index when already built (the accuracy check's reference setup reuses the fit's)."""
    from stairfit import fitting, model
    from stairfit.model import spectral as spectral_model

    if index is None:
        index = scene.specimen.index.build()
    spectral = fitting.spectral_setup(
        index, scene.camera.sensitivity, scene.light.illuminant, sampling=preset.spectral
    )
    aperture = model.Aperture(
        0.5 * scene.light.angular_diameter_deg * DEG,
        0.5 * scene.camera.angular_extent_deg * DEG,
        preset.aperture_nodes
        if (scene.light.angular_diameter_deg > 0 or scene.camera.angular_extent_deg > 0)
        else 1,
        foreshortened=True,  # angular_extent_deg is the spread seen face-on (docs/scene.md)
        light_shape=scene.light.shape,
    )
    weights = spectral_model.channel_weights(scene.camera.sensitivity, scene.light.illuminant)
    return FitSetup(index, spectral, aperture, np.asarray(weights.effective_nm))
