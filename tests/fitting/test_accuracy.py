"""Accuracy that follows the data (issue 13): the numerical error of a fit at its optimum,
against a reference evaluated by `stairfit.model` directly, in measurement standard errors.
docs/fitting.md §3 ("Numerical error at the optimum")."""

from __future__ import annotations

import numpy as np
import pytest
import zoo

from stairfit import fitting

DEG = np.pi / 180
MATERIAL = "pla-bodurov2016"  # dispersive: one effective wavelength differs from 5 nm sampling
TRUTH = fitting.Params(sigma_rad=3 * DEG, scale=1.0)


def _spec(sampling: str) -> fitting.Spectral:
    return fitting.spectral_setup(MATERIAL, sampling=sampling, channels=(1,))


def _fit(noise: float) -> fitting.FitResult:
    """The small scene made with 5 nm sampling (relative noise only), fitted with one effective
    wavelength."""
    s = zoo.scene(TRUTH, zoo.small_design(), _spec("full"), fitting.Noise(noise, absolute=1e-12), 3)
    return fitting.fit_least_squares(s.obs, _spec("effective"), fitting.variant("sharp"))


@pytest.fixture(scope="module")
def fits() -> dict[float, fitting.FitResult]:
    return {noise: _fit(noise) for noise in (0.02, 5e-4)}


def test_the_fit_s_own_knobs_reproduce_its_model(fits):
    # the fit's forward (fitting/_forward.py) against stairfit.model row by row: the same numbers
    ne = fitting.numerical_error(fits[0.02], _spec("effective"))
    assert ne.rms < 1e-9 and ne.max < 1e-8 and not ne.exceeds, ne


def test_the_error_grows_as_the_noise_shrinks_and_is_flagged(fits):
    coarse, precise = (fitting.numerical_error(fits[n], _spec("full")) for n in (0.02, 5e-4))
    assert 0 < coarse.of_peak < 0.05  # a small model difference, nearly the same at both fits
    np.testing.assert_allclose(precise.of_peak, coarse.of_peak, rtol=0.2)
    # stderr = noise x value: the same difference is 40x more standard errors at 0.05% noise
    assert 25 < precise.rms / coarse.rms < 60, (coarse, precise)
    assert precise.exceeds and precise.rms > fitting.ACCURACY_LIMIT
    assert "exceeds the limit 0.2" in precise.sentence()
    # recomputed here from the definition
    obs = fits[5e-4].problem.observations
    ref = fitting.model_radiance(fits[5e-4].params, obs, _spec("full"))
    z = (np.asarray(fits[5e-4].model) - ref) / np.asarray(obs.stderr)
    np.testing.assert_allclose(precise.rms, np.sqrt(np.mean(z[np.asarray(obs.use)] ** 2)))
