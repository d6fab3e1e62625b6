"""The viewing spread an eroded ROI sees (docs/imaging.md §Viewing spread, conventions §9).

An ROI eroded inside its face sees a narrower range of viewing angles than the whole face: the
imaging side measures its share (`view_spread`), the model narrows the aperture's viewing spread
by it, and the simulator renders each face's radiance varying along its in-plane direction.
Checked against closed forms and against a by-hand quadrature, not against the code's own
numbers.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import zoo

from stairfit import fitting, imaging, model
from stairfit.fitting import _forward, _problem
from stairfit.imaging._roi import polygon_axis_variance, view_spread

jax.config.update("jax_enable_x64", True)
DEG = math.pi / 180
# One compiled program per aperture and shape (an eager call compiles each operation alone).
_BAND = jax.jit(model.band_density, static_argnums=6)
_RADIANCE = jax.jit(model.radiance)


def test_polygon_variance_of_a_rectangle_is_its_closed_form() -> None:
    """A w x h rectangle: variance w^2/12 along x, h^2/12 along y, at any position."""
    rect = ((10.0, 20.0), (70.0, 20.0), (70.0, 60.0), (10.0, 60.0))
    assert polygon_axis_variance(rect, np.array([1.0, 0.0])) == pytest.approx(60.0**2 / 12)
    assert polygon_axis_variance(rect, np.array([0.0, 1.0])) == pytest.approx(40.0**2 / 12)
    diag = np.array([1.0, 1.0]) / math.sqrt(2)  # (w^2 + h^2) / 24 along the diagonal
    assert polygon_axis_variance(rect, diag) == pytest.approx((60.0**2 + 40.0**2) / 24)
    assert polygon_axis_variance(tuple(reversed(rect)), np.array([1.0, 0.0])) == pytest.approx(
        300.0
    )


@pytest.mark.parametrize("axis", [(0.0, 1.0), (1.0, 0.0)])
def test_eroded_rectangle_keeps_its_eroded_width(axis: tuple[float, float]) -> None:
    """Eroding a W-wide rectangle by e pixels leaves about (W - 2e) / W of its spread."""
    w, h, e = 120, 80, 8
    rect = ((-0.5 + 30, -0.5 + 40), (w - 0.5 + 30, -0.5 + 40),
            (w - 0.5 + 30, h - 0.5 + 40), (-0.5 + 30, h - 0.5 + 40))  # fmt: skip
    roi = imaging.roi_mask(rect, (200, 220), e, photo="p", wedge="w")
    width = w if axis == (1.0, 0.0) else h
    expected = (width - 2 * e) / width
    assert view_spread(roi, np.array(axis)) == pytest.approx(expected, abs=0.015)
    assert view_spread(imaging.roi_mask(rect, (200, 220), 0, photo="p", wedge="w"),
                       np.array(axis)) == pytest.approx(1.0, abs=0.01)  # fmt: skip


def test_band_density_narrows_the_view_spread_like_a_quadrature_by_hand() -> None:
    """`view_spread` f: the average over theta_o +- f h cos(theta_o), done here with point
    evaluations at Gauss-Legendre nodes, each converted to radiance at its own viewing angle
    (a pixel's radiance is its own density over its own cos theta_o, conventions §9): the
    patch's mean radiance is `radiance` of the aperture's density at the centre's theta_o."""
    ti, b2 = np.full(3, 10 * DEG), np.full(3, 30 * DEG)
    to = np.array([-40.0, 5.0, 35.0]) * DEG
    f = np.array([0.3, 0.7, 1.0])
    n, w = np.full((3, 1), 1.5), np.ones((3, 1))
    sigma = np.full(3, 2 * DEG)
    h = 2.0 * DEG
    ap = model.Aperture(0.0, h, 9, foreshortened=True)
    got = np.asarray(_BAND(ti, to, b2, n, w, sigma, ap, f))
    x, wt = np.polynomial.legendre.leggauss(9)
    nodes = [to + xk * f * h * np.cos(to) for xk in x]
    ref = sum(
        0.5 * wk * np.asarray(_BAND(ti, tk, b2, n, w, sigma)) / np.cos(tk)
        for tk, wk in zip(nodes, wt, strict=True)
    )  # the mean over the patch of density / cos(theta_o): radiance up to its constant factors
    np.testing.assert_allclose(got / np.cos(to), ref, rtol=1e-10)
    point = [_BAND(ti, tk, b2, n, w, sigma) for tk in nodes]
    mean_radiance = sum(
        0.5 * wk * np.asarray(_RADIANCE(d, ti, tk, 1.3, 0.0))
        for d, tk, wk in zip(point, nodes, wt, strict=True)
    )
    np.testing.assert_allclose(_RADIANCE(got, ti, to, 1.3, 0.0), mean_radiance, rtol=1e-10)
    plain = sum(
        0.5 * wk * np.asarray(_BAND(ti, tk, b2, n, w, sigma))
        for tk, wk in zip(nodes, wt, strict=True)
    )
    assert np.max(np.abs(got / plain - 1)) > 1e-6  # the conversion per node is not a no-op
    whole = np.asarray(_BAND(ti, to, b2, n, w, sigma, ap))
    assert abs(got[0] / whole[0] - 1) > 1e-4  # a narrower spread is not the whole face's
    np.testing.assert_allclose(got[2], whole[2], rtol=1e-12)


@pytest.mark.parametrize("grouped", [False, True])
def test_fit_grid_agrees_with_model_radiance_under_spreads(grouped: bool) -> None:
    """The fit's evaluation grid gives `model_radiance`'s values for rows with their own view
    spreads: one per row (two rows of one view and wedge differ, so they need keys of their
    own) or one per ROI (its three channels share it)."""
    spec = zoo.effective("pla")
    truth = fitting.Params(sigma_rad=np.array([0.05, 0.1, 0.2]), delta_n=0.0, scale=1.7,
                           floor=0.004)  # fmt: skip
    obs = zoo.scene(truth, zoo.mixed_design(), spec, seed=0).obs
    rng = np.random.default_rng(3)
    if grouped:
        _, roi = np.unique(np.stack([obs.photo_index, obs.wedge_index], 1), axis=0,
                           return_inverse=True)  # fmt: skip
        spread = rng.uniform(0.4, 1.0, roi.max() + 1)[roi.ravel()]
    else:
        spread = rng.uniform(0.4, 1.0, obs.n_rows)
    obs = obs._replace(view_spread=spread)
    ap = model.Aperture(0.01, 0.03, 5, foreshortened=True)
    prob = _problem.prepare(obs, spec, aperture=ap)
    v = fitting.variant("all", "floor", per_wedge_sigma=True)
    fs = _problem.spec_for(v, prob)
    static, data = prob.static_for(fs), prob.arrays_for(fs)
    lay = prob.layout
    z = np.zeros(lay.size)
    z[1:4] = np.log([0.05, 0.1, 0.2])
    z[lay.slot("scale")] = np.log(1.7)
    z[lay.slot("floor")] = 0.004
    grid = jax.jit(lambda zz: _forward.model_values(zz, static, data)[0])  # eager: op by op
    ours = np.asarray(grid(jnp.asarray(z)))
    ref = fitting.model_radiance(truth, obs, spec, aperture=ap)
    np.testing.assert_allclose(ours, ref, rtol=1e-11)
    whole = fitting.model_radiance(truth, obs._replace(view_spread=np.ones(obs.n_rows)), spec,
                                   aperture=ap)  # fmt: skip
    assert np.max(np.abs(ref / whole - 1)) > 1e-4  # the spreads matter at this aperture


@pytest.mark.parametrize("value", [-0.5, np.nan, np.inf])
def test_observations_refuse_a_negative_or_non_finite_spread(value: float) -> None:
    obs = zoo.scene(fitting.Params(sigma_rad=0.1, scale=1.0), zoo.mixed_design(),
                    zoo.effective("pla"), seed=0).obs  # fmt: skip
    bad = np.ones(obs.n_rows)
    bad[4] = value
    with pytest.raises(fitting.FitInputError, match="view_spread"):
        fitting.Observations.from_arrays(
            **{k: getattr(obs, k) for k in obs._fields if k != "view_spread"}, view_spread=bad
        )


def test_a_spread_above_1_widens_the_rows_viewing_average() -> None:
    """A pinhole-placed ROI may see more than the scene's `angular_extent_deg` (a face longer
    along its slope, docs/imaging.md §Viewing spread): `view_spread = 2` is accepted and is the
    same model as the aperture with twice the viewing half-width."""
    ap = model.Aperture(0.0, np.deg2rad(2.0), 3, foreshortened=True)
    wide = ap._replace(half_width_o_rad=2 * ap.half_width_o_rad)
    sc = zoo.scene(fitting.Params(sigma_rad=0.05, scale=1.0), zoo.mixed_design(),
                   zoo.effective("pla"), seed=0)  # fmt: skip
    obs = sc.obs
    twice = fitting.Observations.from_arrays(
        **{k: getattr(obs, k) for k in obs._fields if k != "view_spread"},
        view_spread=np.full(obs.n_rows, 2.0),
    )
    truth = fitting.Params(sigma_rad=0.05, scale=1.0)
    got = fitting.model_radiance(truth, twice, sc.spec, aperture=ap)
    want = fitting.model_radiance(truth, obs, sc.spec, aperture=wide)
    np.testing.assert_allclose(got, want, rtol=1e-12)
    base = fitting.model_radiance(truth, obs, sc.spec, aperture=ap)
    assert np.max(np.abs(got - base)) > 1e-4 * np.max(base)  # the spread matters here


def test_a_profile_face_renders_its_profile_along_the_face() -> None:
    """`render_photo` with a linear profile from foot to top: the eroded ROI's exact mean is
    the profile's mean over the ROI's share of the face, which `view_spread` measures."""
    from stairfit.imaging import synthetic

    face = ((40.0, 30.0), (140.0, 30.0), (140.0, 150.0), (40.0, 150.0))  # foot at y = 30
    ends = ((90.0, 30.0), (90.0, 150.0))
    prof = np.stack([np.linspace(1000.0, 3000.0, 5)] * 3, axis=1)  # linear in s
    quad = np.stack([1000.0 + 2000.0 * np.linspace(-1, 1, 33) ** 2] * 3, axis=1)  # s^2
    exposure = imaging.Exposure(1.0, 4.0, 100.0)
    for p, mean_of in ((prof, lambda f: 2000.0), (quad, lambda f: 1000.0 + 2000.0 * f**2 / 3)):
        photo = synthetic.render_photo(
            (200, 180), {"w": face}, {"w": p}, exposure, background=(10.0, 10.0, 10.0),
            texture_amplitude=0.0, vignetting=0.0, profile_ends={"w": ends},
        )  # fmt: skip
        roi = imaging.roi_mask(face, (180, 200), 8, photo="p", wedge="w")
        f = view_spread(roi, np.array([0.0, 1.0]))
        assert f == pytest.approx((120 - 16) / 120, abs=0.01)
        # the CFA colours sample different rows (R and B differ by +-0.7% for s^2 at this
        # small size); their mean follows the continuous ROI
        assert float(np.mean(photo.expected["w"])) == pytest.approx(mean_of(f), rel=2e-3)


def test_a_disk_light_weighs_offsets_like_a_round_light() -> None:
    """`light_shape = "disk"`: the in-plane offsets of a round light of radius h have variance
    h^2/4 (a uniform bar: h^2/3) and the nodes integrate the semicircle's moments exactly."""
    h = 0.01
    for n in (3, 5, 7):
        di, _, w = model.Aperture(h, 0.0, n, light_shape="disk").nodes()
        assert float(w.sum()) == pytest.approx(1.0)
        assert float(w @ di**2) == pytest.approx(h**2 / 4, rel=1e-12)
        assert float(w @ di**4) == pytest.approx(h**4 / 8, rel=1e-12)  # E[x^4] = 1/8 on the disk
        du, _, wu = model.Aperture(h, 0.0, n).nodes()
        assert float(wu @ du**2) == pytest.approx(h**2 / 3, rel=1e-12)
    with pytest.raises(ValueError, match="light_shape"):
        model.Aperture(h, 0.0, 3, light_shape="round").nodes()


def test_the_fit_takes_a_pinhole_rois_own_spread() -> None:
    """`stairfit fit`'s row spread: a pinhole-placed ROI's own half-width over the one the
    aperture gives its row, `angular_extent_deg / 2 x cos(theta_o)` (1 deg over 0.5 x 0.5 at 60
    deg: 4); without one, the eroded ROI's share; an undefined share: the whole face."""
    from types import SimpleNamespace

    from stairfit.pipeline import view_spread as _spread

    def row(share: float, half_width: float | None) -> SimpleNamespace:
        return SimpleNamespace(view_spread=share, view_half_width_deg=half_width)

    assert _spread(row(0.8, 1.0), 1.0, 60.0) == pytest.approx(4.0, rel=1e-12)
    assert _spread(row(0.8, None), 1.0, 60.0) == 0.8
    assert _spread(row(0.8, math.nan), 1.0, 60.0) == 0.8
    assert _spread(row(0.8, 1.0), 0.0, 60.0) == 0.8  # no scene extent: nothing to scale
    assert _spread(row(math.nan, None), 1.0, 0.0) == 1.0
