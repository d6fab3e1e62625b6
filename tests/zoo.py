"""The fitting tests' problem zoo: the scenes they fit and the solvers they fit them with.

One place for the synthetic scenes (spectral setup x design x truth x noise x seed) that the
tests in tests/fitting/ share, in the spirit of
optimistix's tests/helpers.py: a test names a scene and a truth instead of building its own.
Every scene is `fitting.simulate_observations` of a known truth, i.e. data from
`stairfit.model` directly, not from the fitting layer's forward [conventions §1, §9].
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
import pytest

from stairfit import fitting

DEG = np.pi / 180

SOLVERS: tuple[str, ...] = fitting.SOLVERS
"""Every least-squares solver (`lm` first: the default the others are compared with)."""

LADDER: dict[str, fitting.Variant] = {v.name: v for v in fitting.DEFAULT_LADDER}
"""The default ladder's variants by name (`sharp`, `sharp+delta_n`, ...)."""

SHARP_LADDER: tuple[fitting.Variant, ...] = tuple(
    v for v in fitting.DEFAULT_LADDER if "edge_radius_um" not in v.free
)
"""The ladder without the rounded-edge variants (each rounded fit costs tens of seconds of
compilation; the slow tests cover them)."""


# --- spectral setups ----------------------------------------------------------------------


def grey(material: str = "pla") -> fitting.Spectral:
    """One grey (green) channel at its effective wavelength (K = 1): the cheapest setup."""
    return fitting.spectral_setup(material, sampling="effective", channels=(1,))


def effective(material: object = "pla", channels: Sequence[int] | None = None) -> fitting.Spectral:
    """Three camera channels (or `channels`), one effective wavelength each (K = 1)."""
    return fitting.spectral_setup(material, sampling="effective", channels=channels)


def full(material: object = "pla-bodurov2016") -> fitting.Spectral:
    """Three channels at every 5 nm (K = 81), a dispersive material by default."""
    return fitting.spectral_setup(material, sampling="full")


# --- designs ----------------------------------------------------------------------------------


def small_design(n_views: int = 9) -> fitting.Design:
    """2 wedges (20, 45 deg) x `n_views` views over -80..80 deg x one channel, theta_i 20 deg."""
    return fitting.Design((20.0, 45.0), (20.0,) * n_views, tuple(np.linspace(-80, 80, n_views)),
                          channels=(0,))  # fmt: skip


def one_wedge_design(
    wedge_deg: float, theta_i_deg: float, views_deg: Sequence[float] | None = None
) -> fitting.Design:
    """One wedge seen from `views_deg` (default 15 views over -80..80 deg), one channel."""
    views = tuple(np.linspace(-80, 80, 15) if views_deg is None else views_deg)
    return fitting.Design((float(wedge_deg),), (float(theta_i_deg),) * len(views), views,
                          channels=(0,))  # fmt: skip


def mixed_design() -> fitting.Design:
    """3 wedges (10, 30, 60 deg), 4 photos with different lights and views (one at 89 deg):
    every grid layout and both regimes of the fitting forward's evaluation grid."""
    return fitting.Design(
        wedge_deg=(10.0, 30.0, 60.0),
        theta_i_deg=(20.0, 20.0, -35.0, 50.0),
        theta_o_deg=(-70.0, 5.0, 40.0, 89.0),
    )


# --- scenes -----------------------------------------------------------------------------------


class Scene(NamedTuple):
    """Synthetic observations, their spectral setup and the truth they were made from."""

    obs: fitting.Observations
    spec: fitting.Spectral
    truth: fitting.Params


def scene(
    truth: fitting.Params,
    design: fitting.Design,
    spec: fitting.Spectral,
    noise: float | fitting.Noise = 0.02,
    seed: int = 0,
) -> Scene:
    """`truth` seen through `design` with `noise` (a relative error, or a `fitting.Noise`)."""
    noise = noise if isinstance(noise, fitting.Noise) else fitting.Noise(noise)
    return Scene(fitting.simulate_observations(truth, design, spec, noise, seed), spec, truth)


def small(truth: fitting.Params, seed: int, noise: float = 0.02) -> Scene:
    """`small_design` in one grey channel: the calibration studies' scene (18 rows)."""
    return scene(truth, small_design(), grey(), noise, seed)


def standard(
    truth: fitting.Params,
    seed: int,
    noise: float = 0.02,
    spec: fitting.Spectral | None = None,
) -> Scene:
    """The standard scene (6 wedges x 19 views x the setup's channels; default three channels
    at one effective wavelength each)."""
    spec = effective() if spec is None else spec
    design = fitting.standard_design(channels=tuple(range(spec.n_channels)))
    return scene(truth, design, spec, noise, seed)


# --- the posterior tests' scene (tests/fitting/test_posterior.py, test_chain.py) --------------

POSTERIOR_TRUTH = fitting.Params(sigma_rad=8 * DEG, delta_n=0.02, scale=1.0, floor=0.003)
"""The truth of the posterior tests' small scene."""

POSTERIOR_VARIANT = fitting.variant("dn_floor", "delta_n", "floor")
"""The variant the posterior tests sample: width, index offset, scale and floor free."""


def posterior_scene(seed: int) -> tuple[fitting.Observations, fitting.Spectral]:
    """`small` of `POSTERIOR_TRUTH`: its observations and spectral setup."""
    s = small(POSTERIOR_TRUTH, seed)
    return s.obs, s.spec


def posterior_fit(seed: int = 21) -> fitting.FitResult:
    """The least-squares fit of `POSTERIOR_VARIANT` to `posterior_scene(seed)`."""
    obs, spec = posterior_scene(seed)
    return fitting.fit_least_squares(obs, spec, POSTERIOR_VARIANT)


def short_chain(fit: fitting.FitResult, **kw: object) -> fitting.posterior.PosteriorResult:
    """A fixed-length chain of `fit` (tau_factor so large that it never counts as converged),
    with the max_steps warning that this implies checked. The posterior (and emcee) is imported
    here, not by every test that uses the zoo."""
    from stairfit.fitting import posterior

    with pytest.warns(fitting.ConvergenceWarning, match="max_steps"):
        return posterior.sample_posterior(fit, chunk_steps=100, tau_factor=1e9, **kw)  # type: ignore[arg-type]
