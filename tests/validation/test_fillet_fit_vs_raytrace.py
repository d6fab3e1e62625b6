"""A filleted fit of data the model did not make: the independent ray tracer's (issue 15).

The fillet rung's other tests fit data from `stairfit.model` (tests/fitting/test_fitting_fillet.py)
or from stairfit's own photo simulator (tests/app/test_simulate_fillet_render.py): the fit and the
data share the tracer of model/_fillet.py. Here the rows of the standard scene (6 wedges 10-60 deg x
19 views, `theta_i = 20 deg`, one grey channel, `n = 1.46`) get their values from
tests/raytrace.py (true circles, its own intersection code and Fresnel, 100 000 rays per
wedge), broadened here by a Gaussian truncated to the hemisphere written from
[conventions §5] and turned into relative radiance by [conventions §9] (`L = scale
cos(theta_i) rho / cos(theta_o)`). Only the rows' angles come from
`fitting.simulate_observations`. The values are left noiseless, with the standard errors
`fitting.Noise(0.01)` gives (1% of the value and a floor of 1e-3 of the brightest row): what is
tested is the bias of the fit against data made another way, which noise would hide. Measured
with noise (16 draws, a throwaway script): the pulls of `r`, `r_f` and the width have sd 0.91,
1.07 and 1.05 on the tracer's data and the same on the model's with the same draws (means
0.12, -0.37, 0.20 and 0.16, -0.41, 0.21); with 0.2% and a floor of 2e-4, 0.89, 1.04, 1.05 and
0.91, 1.05, 1.04: the data's maker does not show."""

from __future__ import annotations

import math

import numpy as np
import pytest
import zoo
from raytrace import Staircase, trace

from stairfit import fitting

DEG = math.pi / 180
TRUTH = fitting.Params(sigma_rad=4 * DEG, edge_radius_um=20.0, fillet_radius_um=15.0, scale=2.0)
N_RAYS = 100_000
NOISE = 0.01


def _mass(centre: np.ndarray, sigma: float) -> np.ndarray:
    """Mass of N(centre, sigma) inside [-pi/2, pi/2] [conventions §5]."""
    erf = np.vectorize(math.erf)
    s2 = sigma * math.sqrt(2.0)
    return 0.5 * (erf((math.pi / 2 - centre) / s2) - erf((-math.pi / 2 - centre) / s2))


def _density(beta2_deg: float, theta_i_deg: float, theta_o: np.ndarray) -> np.ndarray:
    """rho (1/rad) at `theta_o` (rad): every escaping ray's power spread by the truncated
    Gaussian of width sigma about its direction, each ray carrying 1 / N_RAYS of the light."""
    st = Staircase(beta2_deg, 150.0, TRUTH.edge_radius_um, TRUTH.fillet_radius_um)
    res = trace(st, theta_i_deg, 1.46, n_rays=N_RAYS, max_bounces=200)
    assert res.n_lost == 0 and res.n_trapped == 0
    esc = res.escaped
    centre = np.clip(np.deg2rad(res.theta_o_deg[esc]), -math.pi / 2, math.pi / 2)
    power = res.power[esc] / N_RAYS
    sigma = float(TRUTH.sigma_rad)
    weight = power / (math.sqrt(2 * math.pi) * sigma * _mass(centre, sigma))
    z = (theta_o[:, None] - centre[None, :]) / sigma
    return np.exp(-0.5 * z * z) @ weight


@pytest.fixture(scope="module")
def traced_scene() -> tuple[fitting.Observations, fitting.Spectral]:
    spec = zoo.grey()
    assert np.allclose(np.asarray(spec.n_base), 1.46)  # the index the tracer is given
    design = fitting.standard_design(channels=(0,))
    obs = fitting.simulate_observations(TRUTH, design, spec, fitting.Noise(NOISE), 0)
    ti, to = np.asarray(obs.theta_i_rad), np.asarray(obs.theta_o_rad)
    b2 = np.asarray(obs.beta2_rad)
    rho = np.empty_like(to)
    for wedge in np.unique(b2):
        rows = b2 == wedge
        assert np.allclose(ti[rows], 20 * DEG)
        rho[rows] = _density(float(np.rad2deg(wedge)), 20.0, to[rows])
    clean = TRUTH.scale * np.cos(ti) * rho / np.cos(to)
    # 1% of the value and a floor of 1e-3 of the brightest row, as `fitting.Noise` (a purely
    # relative error makes rows 1e-20 below the peak decide the width's error bar)
    stderr = np.hypot(NOISE * clean, 1e-3 * clean.max())
    return obs._replace(value=clean, stderr=stderr), spec


@pytest.mark.slow
def test_the_fillet_rung_recovers_the_tracers_radii(traced_scene):
    """Every parameter within 0.1 of its standard error (measured: 0.042 or less), and the
    model within the errors of the tracer's values (chi^2 0.004 over 110 degrees of freedom;
    the rows differ by at most 0.3% of their value)."""
    obs, spec = traced_scene
    fit = fitting.fit_least_squares(obs, spec, variant=fitting.FILLET_RUNGS[0])
    assert fit.success, fit.message
    est = {e.name: e for e in fit.estimates}
    for name in ("fillet_radius_um", "edge_radius_um", "sigma_rad", "scale"):
        e, truth = est[name], float(np.asarray(getattr(TRUTH, name)).reshape(-1)[0])
        assert e.stderr is not None and e.stderr > 0
        assert abs(e.value - truth) < 0.1 * e.stderr, (name, e.value, e.stderr, fit.report())
    assert fit.chi2 < 0.05 * fit.dof, fit.report()
