"""The lab model in the fit (issue 40): geometry checks, exact band averages, the grid's JVP,
the in-plane limit, and a fit that recovers a microfacet truth and chooses its kernel."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from stairfit import fitting, model
from stairfit.fitting._lab import _lab_impl, distinct_samples, lab_data, lab_grid
from stairfit.fitting._selection import _probe_kernels, _Settings, choose_kernel

WEDGES_DEG = np.array([10.0, 30.0, 45.0, 60.0])


def _face(vec: np.ndarray, b2: float) -> np.ndarray:
    """Base-frame vectors in the face frame (conventions §11), written here from the text."""
    c, s = np.cos(b2), np.sin(b2)
    return np.stack([vec[..., 0] * c + vec[..., 2] * s, vec[..., 1],
                     -vec[..., 0] * s + vec[..., 2] * c], -1)  # fmt: skip


def _lab_scene(lamp_mm: float = 500.0, cam_mm: float = 900.0) -> fitting.LabGeometry:
    """A row of wedges along y under a near lamp, seen from a pinhole about y: 3 x 3 face
    points per face, one node each."""
    ys = np.linspace(-60, 60, WEDGES_DEG.size)
    w_i, w_o, irr, wedge = [], [], [], []
    for light in (0.0, -20.0):
        lamp = lamp_mm * np.array([-np.sin(np.deg2rad(light)), 0, np.cos(np.deg2rad(light))])
        for view in range(-75, 80, 15):
            cam = cam_mm * np.array([np.sin(np.deg2rad(view)), 0, np.cos(np.deg2rad(view))])
            for k, (b, y) in enumerate(zip(WEDGES_DEG, ys, strict=True)):
                b2 = np.deg2rad(b)
                u, v = np.meshgrid(np.linspace(-7, 7, 3), np.linspace(-7, 7, 3), indexing="ij")
                x = u.ravel()
                pts = np.stack([x, y + v.ravel(), (x + 10) * np.tan(b2)], -1)
                to_lamp = lamp - pts
                d = np.linalg.norm(to_lamp, axis=-1)
                wi = _face(to_lamp / d[:, None], b2)
                wo = _face((cam - pts) / np.linalg.norm(cam - pts, axis=-1)[:, None], b2)
                if wi[:, 2].min() < 0.05 or wo[:, 2].min() < 0.1:
                    continue
                w_i.append(wi)
                w_o.append(wo)
                irr.append((lamp_mm / d) ** 2)
                wedge.append(k)
    g = len(w_i)
    weight = np.full((g, 9), 1 / 9)
    key = np.repeat(np.arange(g), 3)
    return fitting.LabGeometry(np.array(w_i), np.array(w_o), weight, np.array(irr),
                               np.array(wedge), key)  # fmt: skip


def test_lab_geometry_refuses_wrong_shapes_and_weights():
    geo = _lab_scene()
    n = geo.key.size
    assert geo.check(n) is geo
    with pytest.raises(fitting.FitInputError, match="key has shape"):
        geo.check(n + 1)
    bad = geo._replace(weight=geo.weight * 1.1)
    with pytest.raises(fitting.FitInputError, match="sum to 1"):
        bad.check(n)
    bad = geo._replace(w_i=np.where(geo.w_i > 0.5, np.nan, geo.w_i))
    with pytest.raises(fitting.FitInputError, match="non-finite"):
        bad.check(n)


def test_distinct_samples_give_the_same_band_averages():
    rng = np.random.default_rng(3)
    n_base = np.stack([np.full(81, 1.46), np.linspace(1.5, 1.48, 81), rng.choice([1.4, 1.6], 81)])
    weights = rng.uniform(size=(3, 81))
    weights /= weights.sum(axis=1, keepdims=True)
    n, w = distinct_samples(n_base, weights)
    assert n.shape == (3, 81) and np.count_nonzero(w[0]) == 1 and np.count_nonzero(w[2]) == 2
    f = lambda x: np.sin(7 * x) + x**3  # noqa: E731
    np.testing.assert_allclose((w * f(n)).sum(1), (weights * f(n_base)).sum(1), rtol=1e-13)


@pytest.fixture(scope="module")
def lab_arrays():
    geo = _lab_scene()
    spec = fitting.spectral_setup("pla")
    samples = (np.asarray(spec.n_base), np.asarray(spec.weights))
    return geo, spec, lab_data(geo, np.deg2rad(WEDGES_DEG), np.full(4, 150.0), geo.key.size,
                               samples)  # fmt: skip


@pytest.mark.parametrize(("kernel", "rounded"), [
    ("ggx", False),
    pytest.param("beckmann", True, marks=pytest.mark.slow),  # the longest compile (CI budget)
    ("gaussian", True),
])  # fmt: skip
def test_lab_grid_jvp_is_the_derivative_of_the_model(lab_arrays, kernel, rounded):
    _, _, ld = lab_arrays
    w = jnp.linspace(0.04, 0.09, ld.b2.shape[0])
    dn, r = jnp.asarray(0.01), jnp.asarray(20.0)
    tw, tdn, tr = jnp.linspace(0.5, 1.5, w.shape[0]), jnp.asarray(0.3), jnp.asarray(0.7)
    radius = r if rounded else None

    def custom(a, b, c):
        return lab_grid(a, b, ld, kernel, c if rounded else None)

    def plain(a, b, c):
        return _lab_impl(a, b, c if rounded else jnp.zeros(()), (kernel, rounded, None), ld)

    args, tangents = (w, dn, r), (tw, tdn, tr)
    v1, t1 = jax.jvp(custom, args, tangents)
    v2, t2 = jax.jvp(plain, args, tangents)
    for a, b in zip((*v1, *t1), (*v2, *t2), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-12 * float(jnp.max(jnp.abs(b))))
    assert radius is None or float(jnp.max(jnp.abs(t1[0]))) > 0


def test_the_rounded_lab_grid_takes_only_the_arcs_broad_lobes_once_per_face(lab_arrays):
    """`lab_grid` evaluates the arcs' panels once per key (at its nodes' mean directions) and
    everything else at every node: against the same nodes each made a key of its own (where
    the mean is the node), every key's specular part within 1% of its radiance with a body
    albedo of 0.02 (measured 0.4%; 40-um tips on 150-um layers,
    Beckmann alpha 0.1; a lamp 500 mm away over faces 14 mm wide). With the flats' weights
    and the arcs' single reflection also taken once per key it was up to 22% off on the
    physically based variant set (docs/model.md §7.6)."""
    geo, spec, ld = lab_arrays
    g, k = geo.weight.shape
    nodes = fitting.LabGeometry(
        geo.w_i.reshape(g * k, 1, 3), geo.w_o.reshape(g * k, 1, 3), np.ones((g * k, 1)),
        (geo.weight * geo.irradiance).reshape(g * k, 1), np.repeat(geo.wedge, k),
        np.repeat(np.arange(g * k), 3),
    )  # fmt: skip
    samples = (np.asarray(spec.n_base), np.asarray(spec.weights))
    ld1 = lab_data(nodes, np.deg2rad(WEDGES_DEG), np.full(4, 150.0), nodes.key.size, samples)
    width, r = np.arctan(0.1), jnp.asarray(40.0)
    per_key, body = lab_grid(jnp.full(ld.b2.shape, width), 0.0, ld, "beckmann", r)
    per_node, _ = lab_grid(jnp.full(ld1.b2.shape, width), 0.0, ld1, "beckmann", r)
    want = np.asarray(per_node)[: g * k].reshape(g, k, -1).sum(axis=1)
    # against the key's radiance with a body albedo of 0.02 (the data's scale)
    total = want + 0.02 / np.pi * np.asarray(body)[:g]
    rel = np.abs(np.asarray(per_key)[:g] - want) / total
    assert rel.max() < 0.01, (rel.max(), np.unravel_index(np.argmax(rel), rel.shape))


def test_in_plane_gaussian_lab_is_the_in_plane_model_times_the_out_of_plane_peak():
    """A distant light and a camera at infinity in the plane: the lab model with Gaussian
    facets is the in-plane model times `line_gaussian(0, 0, sigma)`."""
    rng = np.random.default_rng(0)
    b2 = np.deg2rad(30.0)
    ti, to = rng.uniform(-1.2, 1.2, 12), rng.uniform(-1.3, 1.3, 12)
    w_i = np.stack([-np.sin(ti), 0 * ti, np.cos(ti)], -1)[:, None, :]
    w_o = np.stack([np.sin(to), 0 * to, np.cos(to)], -1)[:, None, :]
    geo = fitting.LabGeometry(w_i, w_o, np.ones((12, 1)), np.ones((12, 1)), np.zeros(12, int),
                              np.arange(12))  # fmt: skip
    spec = fitting.spectral_setup("pla", sampling="effective", channels=(1,))
    ld = lab_data(geo, np.array([b2]), np.array([150.0]), 12,
                  (np.asarray(spec.n_base), np.asarray(spec.weights)))  # fmt: skip
    sigma = np.deg2rad(6.0)
    spec_v, _ = lab_grid(jnp.full(ld.b2.shape, sigma), 0.0, ld, "gaussian")
    rho = model.brdf(ti, to, b2, np.asarray(spec.n_base)[0, 0], sigma)
    expect = rho * np.cos(ti) / np.maximum(np.cos(to), np.cos(np.deg2rad(89.9)))
    expect = expect * model.line_gaussian(0.0, 0.0, sigma)
    np.testing.assert_allclose(np.asarray(spec_v)[:12, 0], expect, rtol=1e-12)


def _lab_observations(lab_arrays, kernel: str, width: float, body_weight: float,
                      rng: np.random.Generator | None = None, **grid) -> fitting.Observations:
    """Rows of the lab scene made by the lab model itself (`3e5 x specular + body_weight x
    body`), errors 0.5% + 0.5, with noise drawn from `rng` (none without it); `grid`: further
    `lab_grid` arguments (e.g. `radius_um`)."""
    geo, _, ld = lab_arrays
    sp, body = lab_grid(jnp.full(ld.b2.shape, width), 0.0, ld, kernel, **grid)
    ch = np.tile(np.arange(3), geo.key.size // 3)
    value = np.asarray(3e5 * sp[geo.key, ch] + body_weight * body[geo.key, ch])
    err = 0.005 * value + 0.5
    noisy = value if rng is None else value + err * rng.normal(size=value.shape)
    return fitting.Observations.from_arrays(
        theta_i_rad=0.0, theta_o_rad=0.0, beta2_rad=np.deg2rad(WEDGES_DEG)[geo.wedge][geo.key],
        layer_um=150.0, wedge_index=geo.wedge[geo.key], channel_index=ch, value=noisy, stderr=err,
    )  # fmt: skip


@pytest.mark.slow  # a recovery fit of its own simulation: about 70 s of the default suite
def test_a_lab_fit_recovers_a_microfacet_truth_and_chooses_its_kernel(lab_arrays):
    """Data made by the lab model itself (GGX facets, alpha = tan(3.4 deg)), 0.5% noise: the
    probe prefers GGX by a wide margin and recovers its width, scale and floor. (The
    independent checks are against the 3-D tracer and Mitsuba; this one checks the fit.)"""
    geo, spec, _ = lab_arrays
    truth = np.deg2rad(3.4)
    obs = _lab_observations(lab_arrays, "ggx", truth, 30.0, np.random.default_rng(11))
    problem = fitting.prepare(obs, spec, lab=geo)
    settings = _Settings(fitting.LeastSquaresOptions(on_failure="flag", emit_warnings=False),
                         False, lambda name: None)  # fmt: skip
    facets = choose_kernel(problem, fitting.DEFAULT_LADDER, ("gaussian", "ggx", "beckmann"),
                           "bic", 2.0, settings)  # fmt: skip
    assert facets.kernel == "ggx"
    # the chosen kernel's probe fit is kept: it starts the ladder's (or a forced) sharp+floor
    assert [(f.requested.kernel, f.success) for f in facets.fits] == [("ggx", True)]
    deltas = {r.name: r.delta for r in facets.rows}
    assert min(v for k, v in deltas.items() if "ggx" not in k) > 100
    fit = fitting.fit_least_squares(problem, variant=fitting.variant("sharp+floor", "floor")
                                    ._replace(kernel="ggx"))  # fmt: skip
    assert fit.variant.kernel == "ggx"  # the fitted variant keeps the requested kernel
    est = {e.param: e for e in fit.estimates}
    for name, value in (("sigma_rad", truth), ("scale", 3e5), ("floor", 30.0)):
        assert abs(est[name].value - value) < 4 * est[name].stderr, name
    assert fit.chi2 / fit.dof < 1.3


def test_each_kernel_is_also_started_from_the_kernels_fitted_before_it(lab_arrays):
    """A microfacet probe started from the widths alone ran off to a flat lobe (alpha and scale
    near 1e26) on the polarised physically based set and lost the kernel comparison for it:
    each kernel's starts include the optima of the kernels fitted before it at the probe."""
    geo, spec, _ = lab_arrays
    obs = _lab_observations(lab_arrays, "ggx", np.deg2rad(3.4), 30.0)
    settings = _Settings(fitting.LeastSquaresOptions(on_failure="flag", emit_warnings=False),
                         False, lambda name: None)  # fmt: skip
    probe = fitting.variant("sharp+floor", "floor")
    _, fits = _probe_kernels(fitting.prepare(obs, spec, lab=geo), probe,
                             ("gaussian", "ggx", "beckmann"), "bic", 2.0, settings, {})  # fmt: skip
    width = {k: float(np.asarray(f.params.sigma_rad).reshape(-1)[0]) for k, f in fits.items()}
    assert set(fits) == {"gaussian", "ggx", "beckmann"}
    assert not np.any(np.isclose(fits["gaussian"].starts_sigma_rad, width["ggx"], rtol=1e-9))
    for later, earlier in (("ggx", "gaussian"), ("beckmann", "gaussian"), ("beckmann", "ggx")):
        assert np.any(np.isclose(fits[later].starts_sigma_rad, width[earlier], rtol=1e-9)), later


@pytest.mark.slow  # three rounded lab fits compile (about a minute each on a loaded machine)
def test_kernels_are_probed_again_rounded_when_the_sharp_probe_misfits(lab_arrays):
    """Rounded GGX facets (r = 25 um on 150 um layers, as the physically based set): the sharp
    probe misfits, so it ranks the kernels by how they hide the missing arcs; the kernels are
    probed again at `rounded+floor`, where GGX must win (issue 40: Mitsuba's rounded GGX
    staircase was fitted with Gaussian facets by the sharp probe alone)."""
    geo, spec, _ = lab_arrays
    truth = np.deg2rad(3.4)
    obs = _lab_observations(lab_arrays, "ggx", truth, 30.0, np.random.default_rng(12),
                            radius_um=25.0)  # fmt: skip
    ladder = (fitting.variant("sharp+floor", "floor"),
              fitting.variant("rounded+floor", "edge_radius_um", "floor"))  # fmt: skip
    sel = fitting.select_model(fitting.prepare(obs, spec, lab=geo), ladder=ladder,
                               kernels=("gaussian", "ggx"))  # fmt: skip
    assert sel.chosen == "rounded+floor" and sel.facets is not None, sel.report()
    assert sel.facets.kernel == "ggx" and sel.fit.requested.kernel == "ggx", sel.facets.reason
    probe = [r for r in sel.facets.rows if r.name.startswith("sharp+floor")]
    assert all(r.status == fitting.Status.MISFITS for r in probe), sel.facets.rows
    assert sel.facets.probe == "rounded+floor", sel.facets.reason  # the second, rounded probe
    assert "every kernel misfits at 'sharp+floor'" in sel.facets.reason, sel.facets.reason
    est = {e.param: e for e in sel.fit.estimates}
    assert abs(est["edge_radius_um"].value - 25.0) < 4 * est["edge_radius_um"].stderr
    assert abs(est["sigma_rad"].value - truth) < 4 * est["sigma_rad"].stderr


@pytest.mark.parametrize("kernel", ["gaussian", "ggx"])
def test_the_linear_scale_start_uses_the_lab_models_own_body_term(lab_arrays, kernel):
    """Every start's scale is solved linearly from the model at scale 1 and 0. The lab model's
    body reflection is not the in-plane `floor x cos(theta_i)`: taking it so put the starts of
    Mitsuba's polarised rounded GGX set so far off (chi^2 8.7e6 at the truth's other values)
    that Levenberg-Marquardt ran to r = 0 and a 1260% model-error term. On noiseless data at
    the truth's width and floor the start's scale must be the truth's."""
    from stairfit.fitting import _core
    from stairfit.fitting._least_squares import spec_for

    geo, spec, _ = lab_arrays
    width = np.deg2rad(3.4)
    obs = _lab_observations(lab_arrays, kernel, width, 3e3)
    fixed = fitting.Params(sigma_rad=width, floor=3e3)
    problem = fitting.prepare(obs, spec, lab=geo, fixed=fixed)
    v = fitting.variant("sharp+floor", "floor")._replace(kernel=kernel)
    s = spec_for(v, problem)
    static, data = problem.static_for(s), problem.arrays_for(s)
    z0 = _core.start_vectors(problem, s, (width,))[0]
    z0[problem.layout.slot("floor")] = 3e3
    z = np.asarray(_core._linear_scale(jnp.asarray(z0), static, data))
    assert np.exp(z[problem.layout.slot("scale")]) == pytest.approx(3e5, rel=1e-9)


def test_a_spent_budget_keeps_the_kernel_probes_fit_of_a_variant(lab_arrays):
    """When the ladder's budget is spent at once (the variant set: every rung
    after the first was "not tried"), a variant the chosen kernel's probe has already fitted is
    taken from that fit instead of being left out; the others stay "not tried"."""
    from stairfit.fitting._selection import PROBE_KEPT

    geo, spec, _ = lab_arrays
    obs = _lab_observations(lab_arrays, "ggx", np.deg2rad(3.4), 30.0, np.random.default_rng(5))
    ladder = tuple(v for v in fitting.DEFAULT_LADDER
                   if fitting.FILLET not in v.free and not v.per_wedge_sigma)  # fmt: skip
    sel = fitting.select_model(fitting.prepare(obs, spec, lab=geo), ladder=ladder,
                               kernels=("gaussian", "ggx"), work_budget_gflop=1e-9,
                               rounded_rungs="when_needed", options=fitting.LeastSquaresOptions(
                                   on_failure="flag", emit_warnings=False))  # fmt: skip
    rows = {r.name: r for r in sel.table}
    assert rows["sharp+floor"].detail == PROBE_KEPT
    assert sel.chosen == "sharp+floor" and sel.fit.variant.kernel == "ggx"
    assert "budget (1e-09 Gflop of solver work) was spent" in rows["sharp+delta_n+floor"].detail
    assert rows["sharp+floor"].work_gflop == 0  # the probes' work is not the ladder's


def test_the_reason_says_when_the_rounded_rungs_were_taken_from_the_kernel_probes() -> None:
    """A ladder whose budget the kernel probes spent took its rounded rungs from their fits in
    no time: the reason says so instead of "fitted (in 0 s)"."""
    from stairfit.fitting import _selection as s

    v = fitting.variant("rounded+floor", "edge_radius_um", "floor")
    row = s.not_fitted_row(v, s.Status.MISFITS, s.PROBE_KEPT)
    sel = s.Selection("rounded+floor", None, (row,), "chosen", "bic", 2.0, False, {})  # type: ignore[arg-type]
    why = "the best sharp variant misfits"
    kept = s._with_rounding(sel, s.Rounding("when_needed", True, why, 4, 0.0)).reason
    assert "budget was spent, so the rungs the kernel probes had fitted are kept" in kept
    plain = dataclasses.replace(sel, table=(s.not_fitted_row(v, s.Status.MISFITS, "x"),))
    fitted = s._with_rounding(plain, s.Rounding("when_needed", True, why, 4, 12.0)).reason
    assert "were fitted (in 12 s) because the best sharp variant misfits" in fitted


def test_the_ladder_keeps_the_chosen_kernels_probe_fit_of_its_own_variant(lab_arrays):
    """The kernel probe fitted `sharp+floor` with the ladder's own settings: when that fit is as
    likely as the rung's fitted parents, the ladder takes it instead of solving it again."""
    geo, spec, _ = lab_arrays
    obs = _lab_observations(lab_arrays, "ggx", np.deg2rad(3.4), 30.0, np.random.default_rng(5))
    ladder = (fitting.variant("sharp"), fitting.variant("sharp+floor", "floor"))
    sel = fitting.select_model(fitting.prepare(obs, spec, lab=geo), ladder=ladder,
                               kernels=("gaussian", "ggx"))  # fmt: skip
    assert sel.facets is not None and sel.facets.kernel == "ggx", sel.report()
    (probe,) = sel.facets.fits
    kept = sel.fits["sharp+floor"]
    assert kept.chi2 == probe.chi2 and kept.log_likelihood >= sel.fits["sharp"].log_likelihood
    assert kept.requested.name == kept.variant.name == "sharp+floor"  # named as the ladder's rung
    assert kept.requested.kernel == "ggx"


def test_the_kernels_are_compared_again_only_where_that_could_change_the_choice() -> None:
    """After a misfitting probe the kernels are fitted again at the chosen variant, unless at
    the probe every other kernel was worse by more than `RECHECK_FACTOR` times what the chosen
    variant's added features gained the chosen kernel (a rule on numbers: fakes suffice)."""
    from types import SimpleNamespace

    from stairfit.fitting import _selection as s

    def fit(name: str, loglik: float) -> SimpleNamespace:
        return SimpleNamespace(requested=SimpleNamespace(name=name), log_likelihood=loglik)

    probe = "rounded+floor"
    rows = [SimpleNamespace(name=f"{probe} (gaussian facets)", delta=1720.0),
            SimpleNamespace(name=f"{probe} (ggx facets)", delta=0.0),
            SimpleNamespace(name=f"{probe} (beckmann facets)", delta=1620.0)]  # fmt: skip
    facets = s.Facets("ggx", probe, (), "", (fit(f"{probe} (ggx facets)", -4127.7),))
    chosen = fit("rounded+delta_n+floor", -4113.7)  # gained 28 in -2 log L
    why = s._kernel_settled(chosen, facets, rows)  # type: ignore[arg-type]
    assert why is not None and "1.62e+03 worse" in why and "the 28 " in why, why
    # a gain a tenth of the margin or more: compared again
    assert s._kernel_settled(fit("rounded+delta_n+floor", -4127.7 + 81.5), facets, rows) is None  # type: ignore[arg-type]
    # a kernel that did not converge at the probe (no margin): compared again
    rows[0] = SimpleNamespace(name=rows[0].name, delta=float("nan"))
    assert s._kernel_settled(chosen, facets, rows) is None  # type: ignore[arg-type]
