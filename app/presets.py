"""Quality presets: named settings of every knob that trades accuracy for time.

The knobs and their measured effect are in the README's "Speed and accuracy" section, which the
benchmark `python benchmarks/bench_tradeoff.py` regenerates. `fit` uses `balanced` by default.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

from .errors import UserError


@dataclass(frozen=True)
class Preset:
    """Every accuracy/speed knob of a fit.

    * `spectral`: "effective" (one effective wavelength per camera channel) or "full" (5 nm
      sampling, 81 wavelengths per channel) [conventions §8].
    * `aperture_nodes`: Gauss-Legendre nodes per axis over the angular size of the light and of
      the viewed face (1 = point light, point view) [conventions §9].
    * `rounded_resolution`: quadrature resolution of the rounded-edge model (docs/rounded.md).
    * `diffuse_nodes`: nodes per piece of the broadened diffuse integral (figures).
    * `sigma_starts_deg`: multi-start widths of the least-squares fit.
    * `ladder`: "shared" (one sigma; 8 variants) or "full" (also one sigma per wedge; 16).
    * `posterior_tau_factor`: the chain must be this many autocorrelation times long;
      `posterior_max_steps`: the step limit (then a warning).
    * `float32_figures`: evaluate figures in float32 (fits are always float64).
    """

    name: str
    spectral: str
    aperture_nodes: int
    rounded_resolution: int
    diffuse_nodes: int
    sigma_starts_deg: tuple[float, ...]
    ladder: str
    posterior_tau_factor: float
    posterior_max_steps: int
    float32_figures: bool

    def as_dict(self) -> dict[str, Any]:
        """For results.json."""
        return asdict(self)


PRESETS: dict[str, Preset] = {
    "fast": Preset(
        name="fast",
        spectral="effective",
        aperture_nodes=1,
        rounded_resolution=4,
        diffuse_nodes=4,
        sigma_starts_deg=(2.0, 8.0),
        ladder="shared",
        posterior_tau_factor=20.0,
        posterior_max_steps=4_000,
        float32_figures=True,
    ),
    "balanced": Preset(
        name="balanced",
        spectral="effective",
        aperture_nodes=2,
        rounded_resolution=8,
        diffuse_nodes=6,
        sigma_starts_deg=(1.0, 4.0, 12.0),
        ladder="shared",
        posterior_tau_factor=50.0,
        posterior_max_steps=20_000,
        float32_figures=False,
    ),
    "accurate": Preset(
        name="accurate",
        spectral="full",
        aperture_nodes=4,
        rounded_resolution=16,
        diffuse_nodes=8,
        sigma_starts_deg=(0.5, 2.0, 6.0, 18.0),
        ladder="full",
        posterior_tau_factor=100.0,
        posterior_max_steps=50_000,
        float32_figures=False,
    ),
}


def get_preset(name: str) -> Preset:
    """A preset by name; a clear error lists the others."""
    try:
        return PRESETS[name]
    except KeyError:
        raise UserError(
            f"--preset: unknown preset {name!r}; use one of {', '.join(PRESETS)}"
        ) from None
