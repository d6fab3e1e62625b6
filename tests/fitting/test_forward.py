"""The fitting layer's forward model, transforms and priors against independent references.

The fitting forward evaluates the model on a (key, view, channel) grid and differentiates it
with a custom JVP; here it is compared with `stairfit.model.band_density` (values), with plain
autodiff of that function and with finite differences (Jacobians) [conventions §4, §8, §9].
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import zoo
from scipy import integrate

from stairfit import fitting, model
from stairfit.fitting import _forward, _params, _problem

DEG = np.pi / 180


def _scene(material: object = "pla-bodurov2016", sampling: str = "full") -> tuple:
    spec = zoo.full(material) if sampling == "full" else zoo.effective(material)
    truth = fitting.Params(sigma_rad=np.array([0.05, 0.1, 0.2]), delta_n=0.03, scale=1.7,
                           floor=0.004)  # fmt: skip
    obs = zoo.scene(truth, zoo.mixed_design(), spec, seed=0).obs
    return spec, obs, truth


def _plain_values(x: jax.Array, obs: fitting.Observations, spec: fitting.Spectral,
                  aperture: model.Aperture | None) -> jax.Array:  # fmt: skip
    """The same radiance straight from `stairfit.model` for physical parameters
    x = (sigma per wedge..., delta_n, scale, floor)."""
    n_w = obs.n_wedges
    sigma = x[:n_w][obs.wedge_index]
    n = jnp.asarray(spec.n_base)[obs.channel_index] + x[n_w]
    w = jnp.asarray(spec.weights)[obs.channel_index]
    dens = model.band_density(obs.theta_i_rad, obs.theta_o_rad, obs.beta2_rad, n, w, sigma,
                              aperture)  # fmt: skip
    return model.radiance(dens, obs.theta_i_rad, obs.theta_o_rad, x[n_w + 1], x[n_w + 2])


@pytest.mark.parametrize(
    ("material", "sampling", "aperture"),
    [
        ("pla-bodurov2016", "full", None),
        ("pla", "effective", model.Aperture(0.02, 0.03, 3)),
        (model.materials.ConstantIndex(1.55, k=0.02), "effective", None),
    ],
)
def test_fitting_forward_matches_model_band_density(material, sampling, aperture):
    spec, obs, _ = _scene(material, sampling)
    prob = _problem.prepare(obs, spec, aperture=aperture)
    v = fitting.variant("all", "delta_n", "floor", per_wedge_sigma=True)
    fs = _problem.spec_for(v, prob)
    static, data = prob.static_for(fs), prob.arrays_for(fs)
    lay = prob.layout
    x_phys = np.array([0.05, 0.1, 0.2, 0.03, 1.7, 0.004])
    z = np.zeros(lay.size)
    z[1:4] = np.log(x_phys[:3])
    z[lay.slot("delta_n")] = x_phys[3]
    z[lay.slot("scale")] = np.log(x_phys[4])
    z[lay.slot("floor")] = x_phys[5]
    z = jnp.asarray(z)
    ours = jax.jit(lambda zz: _forward.model_values(zz, static, data)[0])(z)
    plain = jax.jit(lambda x: _plain_values(x, obs, spec, aperture))
    ref = plain(jnp.asarray(x_phys))
    np.testing.assert_allclose(ours, ref, rtol=1e-12, atol=1e-15)

    # Jacobian with respect to the physical parameters: custom JVP vs plain autodiff.
    def ours_of_x(x: jax.Array) -> jax.Array:
        zz = z.at[1:4].set(jnp.log(x[:3]))
        zz = zz.at[lay.slot("delta_n")].set(x[3]).at[lay.slot("scale")].set(jnp.log(x[4]))
        zz = zz.at[lay.slot("floor")].set(x[5])
        return _forward.model_values(zz, static, data)[0]

    j_ours = jax.jit(jax.jacfwd(ours_of_x))(jnp.asarray(x_phys))
    j_ref = jax.jit(jax.jacfwd(plain))(jnp.asarray(x_phys))
    np.testing.assert_allclose(j_ours, j_ref, rtol=1e-9, atol=1e-12 * float(np.abs(j_ref).max()))
    # and against central finite differences (an independent check of the derivative itself)
    h = 1e-6 * np.maximum(np.abs(x_phys), 1e-2)
    for k in range(x_phys.size):
        e = np.zeros_like(x_phys)
        e[k] = h[k]
        fd = (np.asarray(plain(x_phys + e)) - np.asarray(plain(x_phys - e))) / (2 * h[k])
        np.testing.assert_allclose(j_ours[:, k], fd, rtol=1e-5, atol=1e-7 * np.abs(fd).max())


def test_fitting_forward_grid_shares_geometry_between_channels():
    # 4 photos x 3 wedges x 3 channels = 36 rows, but only 4 x 3 = 12 distinct (theta_i, wedge,
    # theta_o) views, each evaluated for all channels at once; the standard scene (one theta_i,
    # 19 views, 6 wedges) has 114 views for 342 rows.
    # (the keys are padded to a shape bucket, `_problem.bucket`: the real ones are those the
    # rows name)
    spec, obs, _ = _scene()
    d = _problem.prepare(obs, spec).data
    assert obs.n_rows == 36
    assert (int(np.max(d.r_key)) + 1) * d.r_to.shape[1] == 12
    std = zoo.standard(fitting.Params(), seed=0, spec=spec).obs
    assert std.n_rows == 342
    d = _problem.prepare(std, spec).data
    assert (int(np.max(d.r_key)) + 1) * d.r_to.shape[1] == 114


def test_transforms_round_trip_and_jacobian():
    kinds = _params.Layout(2).kinds
    r_max = 86.6
    x = np.array([0.1, 0.05, 0.2, 0.03, 12.0, 2.5, 0.004, 0.05, 30.0])  # last: r_f <= 74.6
    r = x[kinds.index("sin")]
    z = np.array([_params.from_physical(xi, k, r_max, r) for xi, k in zip(x, kinds, strict=True)])
    back = np.asarray(_params.to_physical(jnp.asarray(z), kinds, r_max))
    np.testing.assert_allclose(back, x, rtol=1e-12)
    # dx/dz (the full matrix: the fillet's bound moves with the edge radius) and log|det| against
    # autodiff of the forward transform
    jac = np.asarray(jax.jacfwd(lambda zz: _params.to_physical(zz, kinds, r_max))(jnp.asarray(z)))
    np.testing.assert_allclose(np.abs(np.diag(jac)), np.abs(_params.dx_dz(z, kinds, r_max, r)),
                               rtol=1e-12)  # fmt: skip
    free = np.ones(len(kinds), bool)
    np.testing.assert_allclose(_params.dx_matrix(z, kinds, r_max, free, r), jac, rtol=1e-12,
                               atol=1e-15)  # fmt: skip
    assert jac[kinds.index("sin_rest"), kinds.index("sin")] < 0  # a larger tip leaves less room
    logj = np.asarray(_params.log_abs_jacobian(jnp.asarray(z), kinds, r_max))
    expected = np.log(np.abs(np.diag(jac)))
    expected[kinds.index("abs")] -= np.log(2.0)  # two-to-one map: density of z is p(|z|) / 2
    np.testing.assert_allclose(logj, expected, rtol=1e-12)
    # triangular: the log-determinant is the sum of the diagonal's (abs aside)
    _, logdet = np.linalg.slogdet(jac)
    np.testing.assert_allclose(logdet, np.sum(expected) + np.log(2.0), rtol=1e-12)


def test_fillet_transform_fits_beside_a_fixed_edge_radius():
    kinds = _params.Layout(1).kinds
    k_r, k_f = kinds.index("sin"), kinds.index("sin_rest")
    free = np.ones(len(kinds), bool)
    free[k_r] = False
    x_fixed = np.zeros(len(kinds))
    x_fixed[k_r] = 60.0
    z = jnp.zeros(len(kinds)).at[k_f].set(np.pi / 2)  # the top of the fillet's range
    x = np.asarray(_params.to_physical(z, kinds, 86.6, (jnp.asarray(free), jnp.asarray(x_fixed))))
    assert x[k_r] == 60.0
    np.testing.assert_allclose(x[k_f], 86.6 - 60.0, rtol=1e-12)


def test_sine_transform_reaches_both_bounds_at_finite_z():
    r = _params.to_physical(jnp.array([-np.pi / 2, np.pi / 2]), ("sin", "sin"), 40.0)
    np.testing.assert_allclose(r, [0.0, 40.0], atol=1e-12)
    assert not bool(_params.in_support(jnp.array([-1.6]), ("sin",)))
    assert bool(_params.in_support(jnp.array([-1.5]), ("sin",)))


@pytest.mark.parametrize(
    ("prior", "lo", "hi"),
    [
        (fitting.Normal(0.0, 0.1), -2.0, 2.0),
        (fitting.HalfNormal(0.3), 0.0, 5.0),
        (fitting.Uniform(0.0, 37.0), 0.0, 37.0),
        (fitting.LogUniform(1e-3, 1.5), 1e-3, 1.5),
    ],
)
def test_priors_are_normalised(prior, lo, hi):
    f = lambda x: float(np.exp(prior.log_pdf(x)))  # noqa: E731
    points = np.geomspace(lo, hi, 12)[1:-1] if lo > 0 else None
    total, _ = integrate.quad(f, lo, hi, points=points, limit=200)
    assert total == pytest.approx(1.0, rel=1e-6)
    assert float(prior.log_pdf(hi + 10.0)) < -1e3 or not np.isfinite(prior.log_pdf(hi + 10.0))


def test_prior_includes_transform_jacobian():
    # With a log transform and a log-uniform prior on x, the density of z = ln x is uniform:
    # log p(z) = log p(x) + log|dx/dz| = -ln x - ln ln(hi/lo) + ln x = const.
    prior = fitting.LogUniform(1e-3, 1.5)
    zs = np.log([0.002, 0.05, 1.0])
    jac = [float(_params.log_abs_jacobian(jnp.array([z]), ("log",), 1.0)[0]) for z in zs]
    vals = [float(prior.log_pdf(np.exp(z))) + j for z, j in zip(zs, jac, strict=True)]
    np.testing.assert_allclose(vals, -np.log(np.log(1.5 / 1e-3)), rtol=1e-12)


@pytest.mark.slow  # the rounded model's Jacobian takes about half a minute to compile (XLA)
def test_fitting_rounded_forward_matches_model_and_finite_differences():
    # The fitting layer evaluates the rounded model on a (theta_i, wedge, channel) x view grid
    # with a three-direction custom JVP; compare with `predict` (row by row, straight from
    # stairfit.model.brdf_rounded) and with central differences.
    design = fitting.Design((20.0, 45.0), (20.0,) * 5, tuple(np.linspace(-60, 60, 5)))
    truth = fitting.Params(sigma_rad=6 * DEG, delta_n=0.02, scale=1.3, edge_radius_um=20.0)
    obs, spec, _ = zoo.scene(truth, design, zoo.effective(), seed=0)
    prob = _problem.prepare(obs, spec)
    fs = _problem.spec_for(fitting.variant("r", "delta_n", "edge_radius_um"), prob)
    static, data = prob.static_for(fs), prob.arrays_for(fs)
    assert static.rounded
    lay = prob.layout
    z = np.zeros(lay.size)
    z[0] = np.log(truth.sigma_rad)
    z[lay.slot("delta_n")] = truth.delta_n
    z[lay.slot("scale")] = np.log(truth.scale)
    z[lay.slot("edge_radius_um")] = np.arcsin(2 * truth.edge_radius_um / prob.r_max_um - 1)
    f = jax.jit(lambda zz: _forward.model_values(zz, static, data)[0])
    np.testing.assert_allclose(
        f(jnp.asarray(z)), fitting.model_radiance(truth, obs, spec), rtol=1e-10
    )
    jac = np.asarray(jax.jit(jax.jacfwd(f))(jnp.asarray(z)))
    for k in (0, lay.slot("delta_n"), lay.slot("edge_radius_um")):
        h = 1e-5
        e = np.zeros_like(z)
        e[k] = h
        fd = (np.asarray(f(jnp.asarray(z + e))) - np.asarray(f(jnp.asarray(z - e)))) / (2 * h)
        np.testing.assert_allclose(jac[:, k], fd, rtol=1e-4, atol=1e-6 * np.abs(fd).max())
