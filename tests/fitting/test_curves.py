"""The report's model curves (issue 41): `fit_per_wedge.png` draws the fitted model as a dense
curve over the viewing angle, not as a polyline through the measured views.

Checked: a curve has many more points than its wedge's views; at every measured view it is
the fitted value (to rounding, in-plane; by construction through the mean geometry, lab); between
the views it is the model, checked against `fitting.model_radiance` (which evaluates
`stairfit.model` directly, not the fit's forward); the figure draws those curves.
"""

from __future__ import annotations

from types import SimpleNamespace

import jax.numpy as jnp
import numpy as np
import pytest
from matplotlib.backends.backend_agg import FigureCanvasAgg

from stairfit import fitting
from stairfit.fitting._lab import lab_data, lab_grid

DEG = np.pi / 180
WEDGES_DEG = (10.0, 30.0, 60.0)
VIEWS_DEG = (-60.0, -30.0, 0.0, 25.0, 50.0)
LIGHTS_DEG = (20.0, -35.0)


@pytest.fixture(scope="module")
def in_plane_fit() -> fitting.FitResult:
    """A sharp fit of simulated rows: three wedges, five views at each of two light angles, a
    view spread that differs from row to row (interpolated between the views by the curves)."""
    spectral = fitting.spectral_setup("pla", sampling="effective")
    views = [v for _ in LIGHTS_DEG for v in VIEWS_DEG]
    lights = [li for li in LIGHTS_DEG for _ in VIEWS_DEG]
    design = fitting.Design(WEDGES_DEG, tuple(lights), tuple(views))
    truth = fitting.Params(sigma_rad=5 * DEG, scale=1e5, floor=40.0)
    sim = fitting.simulate_observations(truth, design, spectral, seed=3)
    spread = np.random.default_rng(4).uniform(0.4, 1.0, sim.n_rows)
    obs = fitting.Observations.from_arrays(**{**sim._asdict(), "view_spread": spread})
    return fitting.fit_least_squares(obs, spectral, variant=fitting.variant("sharp+floor", "floor"))


def test_in_plane_curves_are_dense_and_pass_through_the_fitted_values(in_plane_fit):
    fit = in_plane_fit
    obs = fit.problem.observations
    curves = fitting.model_curves(fit)
    assert len(curves) == len(WEDGES_DEG) * len(LIGHTS_DEG) * 3  # wedges x lights x channels
    for c in curves:
        assert c.rows.size == len(VIEWS_DEG)
        assert c.theta_o_rad.size >= 20 * c.rows.size  # 0.5 deg over 110 deg: 221 points
        at = np.searchsorted(c.theta_o_rad, obs.theta_o_rad[c.rows])
        np.testing.assert_allclose(c.value[at], fit.model[c.rows], rtol=1e-12)
        assert not c.mean_geometry and c.ratio_range == (1.0, 1.0)


def test_in_plane_curves_between_the_views_are_the_model(in_plane_fit):
    """Midway between two views the curve is the model there (with the view spread
    interpolated), evaluated by `fitting.model_radiance`, not a straight line."""
    fit = in_plane_fit
    obs = fit.problem.observations
    light = [c for c in fitting.model_curves(fit) if abs(c.theta_i_rad + 35 * DEG) < 1e-9]
    curve = next(c for c in light if c.wedge == 1 and c.channel == 1)
    # the 30-deg wedge's tread lobe leaves at -35 + 60 = 25 deg: between the views 0 and 25
    views = obs.theta_o_rad[curve.rows]
    order = np.argsort(views)
    j = int(np.argmin(np.abs(curve.theta_o_rad - 12.5 * DEG)))
    theta = curve.theta_o_rad[j]
    spread = np.interp(theta, views[order], obs.view_spread[curve.rows][order])
    row = fitting.Observations.from_arrays(
        theta_i_rad=[curve.theta_i_rad], theta_o_rad=theta, beta2_rad=WEDGES_DEG[1] * DEG,
        layer_um=150.0, wedge_index=1, channel_index=1, value=1.0, stderr=1.0,
        view_spread=spread,
    )  # fmt: skip
    # model_radiance wants every wedge index up to 1: a single row of wedge 1 has n_wedges 2
    params = fit.params._replace(sigma_rad=fit.params.sigma_rad[:2])
    direct = fitting.model_radiance(params, row, fit.problem.spectral,
                                    aperture=fit.problem.aperture)  # fmt: skip
    np.testing.assert_allclose(curve.value[j], direct[0], rtol=1e-10)
    linear = np.interp(theta, views[order], fit.model[curve.rows][order])
    assert abs(curve.value[j] / linear - 1) > 0.01  # the lobe between the views shows


def test_fit_per_wedge_draws_the_dense_curves(in_plane_fit):
    from stairfit.report import fit_per_wedge

    fit = in_plane_fit
    obs = fit.problem.observations
    wedges = tuple(SimpleNamespace(name=f"w{b:g}", angle_deg=b) for b in WEDGES_DEG)
    outcome = SimpleNamespace(
        selection=SimpleNamespace(fit=fit, chosen="sharp+floor"),
        observations=SimpleNamespace(
            data=obs, labels=[SimpleNamespace(theta_o_deg=t / DEG) for t in obs.theta_o_rad]
        ),
        scene=SimpleNamespace(specimen=SimpleNamespace(wedges=wedges)),
    )
    fig = fit_per_wedge(outcome)
    FigureCanvasAgg(fig).draw()
    for k in range(len(WEDGES_DEG)):
        lines = [ln for ln in fig.axes[k].get_lines() if len(ln.get_xdata()) > 100]
        assert len(lines) == len(LIGHTS_DEG) * 3, k  # one curve per light angle and channel
        styles = {ln.get_linestyle() for ln in lines}
        assert len(styles) == len(LIGHTS_DEG)  # the two light angles are told apart
        for ln in lines:  # every measured view of the wedge lies on one of its curves
            x, y = np.asarray(ln.get_xdata()), np.asarray(ln.get_ydata())
            assert np.all(np.diff(x) > 0) and np.all(np.isfinite(y)) and np.all(y > 0)
        rows = np.flatnonzero(obs.wedge_index == k)
        for r in rows:
            hits = [np.interp(obs.theta_o_rad[r] / DEG, ln.get_xdata(), ln.get_ydata())
                    for ln in lines]  # fmt: skip
            assert np.min(np.abs(np.array(hits) / fit.model[r] - 1)) < 1e-12


def _face(vec: np.ndarray, b2: float) -> np.ndarray:
    """Base-frame vectors in the face frame (conventions §11), written here from the text."""
    c, s = np.cos(b2), np.sin(b2)
    return np.stack([vec[..., 0] * c + vec[..., 2] * s, vec[..., 1],
                     -vec[..., 0] * s + vec[..., 2] * c], -1)  # fmt: skip


def _lab_rows() -> tuple[fitting.LabGeometry, np.ndarray, np.ndarray]:
    """Wedges along y under a near lamp, seen from a pinhole at 900 mm: 2 x 2 face points per
    face, one key per photo and wedge; (geometry, each key's in-plane light and view angles)."""
    w_i, w_o, irr, wedge, ti, to = [], [], [], [], [], []
    lamp = 500.0 * np.array([-np.sin(20 * DEG), 0.0, np.cos(20 * DEG)])
    for view in VIEWS_DEG:
        cam = 900.0 * np.array([np.sin(view * DEG), 0.0, np.cos(view * DEG)])
        for k, (b, y) in enumerate(zip(WEDGES_DEG, (-40.0, 0.0, 40.0), strict=True)):
            b2 = b * DEG
            u, v = np.meshgrid([-5.0, 5.0], [-5.0, 5.0], indexing="ij")
            pts = np.stack([u.ravel(), y + v.ravel(), (u.ravel() + 8) * np.tan(b2)], -1)
            d = np.linalg.norm(lamp - pts, axis=-1)
            wi = _face((lamp - pts) / d[:, None], b2)
            wo = _face((cam - pts) / np.linalg.norm(cam - pts, axis=-1)[:, None], b2)
            if wo[:, 2].min() < 0.1:
                continue
            w_i.append(wi)
            w_o.append(wo)
            irr.append((500.0 / d) ** 2)
            wedge.append(k)
            mi, mo = wi.mean(0), wo.mean(0)
            ti.append(np.arctan2(-mi[0], mi[2]))
            to.append(np.arctan2(mo[0], mo[2]))
    g = len(w_i)
    keys = np.repeat(np.arange(g), 3)
    geo = fitting.LabGeometry(np.array(w_i), np.array(w_o), np.full((g, 4), 0.25),
                              np.array(irr), np.array(wedge), keys)  # fmt: skip
    return geo, np.repeat(ti, 3), np.repeat(to, 3)


def test_lab_curves_follow_the_mean_geometry_through_the_fitted_values():
    """A lab fit (GGX facets under a near lamp): the curve passes through the fitted values at
    the views and the mean geometry is within 5% of each row's full node average (the scale
    factors of the curve, `ratio_range`: 0.985-1.017 here)."""
    geo, ti, to = _lab_rows()
    spectral = fitting.spectral_setup("pla", sampling="effective")
    ld = lab_data(geo, np.asarray(WEDGES_DEG) * DEG, np.full(3, 150.0), geo.key.size,
                  (np.asarray(spectral.n_base), np.asarray(spectral.weights)))  # fmt: skip
    sp, body = lab_grid(jnp.full(ld.b2.shape, 4 * DEG), 0.0, ld, "ggx")
    ch = np.tile(np.arange(3), geo.key.size // 3)
    value = np.asarray(2e5 * sp[geo.key, ch] + 30.0 * body[geo.key, ch])
    obs = fitting.Observations.from_arrays(
        theta_i_rad=ti, theta_o_rad=to, beta2_rad=np.asarray(WEDGES_DEG)[geo.wedge][geo.key] * DEG,
        layer_um=150.0, wedge_index=geo.wedge[geo.key], channel_index=ch,
        value=value * (1 + 0.005 * np.random.default_rng(5).normal(size=value.shape)),
        stderr=0.005 * value + 0.5,
    )  # fmt: skip
    problem = fitting.prepare(obs, spectral, lab=geo)
    fit = fitting.fit_least_squares(problem, variant=fitting.variant("sharp+floor", "floor")
                                    ._replace(kernel="ggx"))  # fmt: skip
    curves = fitting.model_curves(fit)
    assert len(curves) == len(WEDGES_DEG) * 3
    for c in curves:
        at = np.searchsorted(c.theta_o_rad, obs.theta_o_rad[c.rows])
        np.testing.assert_allclose(c.value[at], fit.model[c.rows], rtol=1e-12)
        assert c.theta_o_rad.size >= 20 * c.rows.size
        assert c.mean_geometry and 0.95 < c.ratio_range[0] <= c.ratio_range[1] < 1.05, c
