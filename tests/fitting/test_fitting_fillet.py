"""The fillet radius in fits (issue 15; docs/fitting.md §2, §4; docs/rounded.md §11).

The fit's filleted forward is the simulator's (`fitting.model_radiance`, which calls
`stairfit.model.brdf_filleted_from_geometry` row by row); its Jacobian agrees with central
differences of the residuals; a fit of data made by the filleted model at known radii
recovers `r_f` within its errors, and on rounded data (`r_f = 0`) the fillet is consistent
with 0; the fillet rungs are gated like the rounded ones.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import zoo
from checks import jacobian_by_columns

from stairfit import fitting, model
from stairfit.fitting import _forward, _params, _problem

DEG = np.pi / 180
TRUTH = fitting.Params(sigma_rad=4 * DEG, edge_radius_um=20.0, fillet_radius_um=15.0, scale=2.0)
FILLET = fitting.FILLET_RUNGS[0]  # rounded+fillet


def _z(problem: _problem.Problem, p: fitting.Params) -> jnp.ndarray:
    """The unconstrained vector of `p` (every slot)."""
    lay = problem.layout
    z = np.zeros(lay.size)
    for rec in lay.parameters():
        x = getattr(p, rec.param)
        x = float(np.asarray(x).reshape(-1)[0]) if rec.param == "sigma_rad" else float(x)
        z[rec.slot] = _params.from_physical(x, rec.transform, problem.r_max_um, p.edge_radius_um)
    return jnp.asarray(z)


@pytest.fixture(scope="module")
def filleted_scene() -> zoo.Scene:
    return zoo.standard(TRUTH, seed=1, noise=0.01)


def test_fit_forward_is_the_simulator_and_its_jacobian_the_differences(filleted_scene):
    """The fit's forward at the truth equals `model_radiance` (an independent path: per
    distinct geometry through the model's public functions, no grid); the forward-mode
    Jacobian of the model values in r and r_f agrees with central differences of them with
    1.5 um steps to 10% (norm over the rows; measured 5-7%, the correction's quadrature noise at
    2048 rays), and in sigma and scale to 1e-6. One compiled program gives the values and the
    derivative along any direction (three programs took 51-73 s of the suite, issue 14); as for
    the rounded model (tests/fitting/test_forward.py), the values, not the residuals, which are
    built from them by the same code for every model (tests/fitting/test_whiten.py)."""
    s = filleted_scene
    problem = _problem.prepare(s.obs, s.spec)
    spec = _problem.spec_for(FILLET, problem)
    static, data = problem.static_for(spec), problem.arrays_for(spec)
    assert static.filleted and static.rounded
    z = _z(problem, TRUTH)
    clean = fitting.model_radiance(TRUTH, s.obs, s.spec)
    values = lambda z: _forward.model_values(z, static, data)[0]  # noqa: E731
    # the values and their derivative along `dz`, an argument: one program for every direction
    # (with the whole Jacobian, jax.jacfwd, it took 10.6 s against 7.5 s to trace and compile)
    both = jax.jit(lambda z, dz: jax.jvp(values, (z,), (dz,)))
    lay = problem.layout
    zero = jnp.zeros(lay.size)
    m = both(z, zero)[0]
    np.testing.assert_allclose(m, clean, rtol=1e-10, atol=0)
    # the fillet shows: against the same program at r_f = 0, the rounded model exactly
    # (tests/model/test_fillet.py; a rounded `model_radiance` would be one more compilation)
    rounded = both(_z(problem, TRUTH._replace(fillet_radius_um=0.0)), zero)[0]
    assert np.max(np.abs(clean - np.asarray(rounded))) > 0.01 * np.max(clean)

    d = _params.dx_dz(np.asarray(z), lay.kinds, problem.r_max_um, TRUTH.edge_radius_um)
    for name, step, tol in (("edge_radius_um", 1.5, 0.1), ("fillet_radius_um", 1.5, 0.1),
                            ("sigma_rad", 1e-4, 1e-6), ("scale", 1e-4, 1e-6)):  # fmt: skip
        k = lay.slot(name)
        h = step / d[k] if name.endswith("_um") else step
        e = jnp.zeros(lay.size).at[k].set(h)
        column = np.asarray(both(z, zero.at[k].set(1.0))[1])
        fd = (np.asarray(both(z + e, zero)[0]) - np.asarray(both(z - e, zero)[0])) / (2 * h)
        err = np.linalg.norm(column - fd) / np.linalg.norm(fd)
        assert err < tol, (name, err)


@pytest.mark.slow
def test_fit_recovers_the_fillet_radius_within_its_errors(filleted_scene):
    s = filleted_scene
    fit = fitting.fit_least_squares(s.obs, s.spec, variant=FILLET)
    assert fit.success, fit.message
    est = {e.name: e for e in fit.estimates}
    for name in ("fillet_radius_um", "edge_radius_um"):
        e = est[name]
        truth = getattr(TRUTH, name)
        assert e.stderr is not None and e.stderr > 0
        assert abs(e.value - truth) < 3 * e.stderr, fit.report()


@pytest.mark.slow
def test_rounded_data_give_a_fillet_consistent_with_zero():
    s = zoo.standard(TRUTH._replace(fillet_radius_um=0.0), seed=2, noise=0.01)
    fit = fitting.fit_least_squares(s.obs, s.spec, variant=FILLET)
    assert fit.success, fit.message
    est = {e.name: e for e in fit.estimates}
    if "fillet_radius_um" in est:  # still free: within three standard errors of 0
        e = est["fillet_radius_um"]
        assert e.value < 3 * e.stderr, fit.report()
    else:  # the active set fixed it on its bound 0
        assert float(fit.params.fillet_radius_um) == 0.0, fit.report()


def test_sharp_data_skip_both_the_rounded_and_the_fillet_rungs():
    s = zoo.standard(fitting.Params(sigma_rad=4 * DEG, scale=2.0), seed=3, noise=0.02)
    ladder = (zoo.LADDER["sharp"], zoo.LADDER["rounded"], FILLET)
    sel = fitting.select_model(s.obs, s.spec, ladder, rounded_rungs="when_needed")
    assert sel.chosen == "sharp", sel.report()
    r = sel.rounding
    assert r is not None and not r.fitted and not r.fillet_fitted and r.fillet_n_variants == 1
    assert "describes the data" in r.fillet_reason and r.fillet_elapsed_s == 0.0
    rows = {row.name: row for row in sel.table}
    assert rows[FILLET.name].status == fitting.Status.NOT_FITTED
    assert "fillet variants were not fitted" in sel.reason


def test_fillet_rungs_are_few_and_nested_on_the_rounded_ones():
    names = [v.name for v in fitting.DEFAULT_LADDER]
    assert names[-2:] == ["rounded+fillet", "rounded+floor+fillet"]
    assert sum("fillet_radius_um" in v.free for v in fitting.DEFAULT_LADDER) == 2
    lad = fitting.DEFAULT_LADDER
    from stairfit.fitting._selection import parents_of

    assert [u.name for u in parents_of(lad[-2], lad)] == ["rounded"]
    assert {u.name for u in parents_of(lad[-1], lad)} == {"rounded+floor", "rounded+fillet"}


def test_a_fixed_fillet_that_does_not_fit_is_a_one_line_error(filleted_scene):
    s = filleted_scene
    with pytest.raises(fitting.FitInputError, match="fillet_radius_um = 80"):
        _problem.prepare(s.obs, s.spec, fixed=TRUTH._replace(fillet_radius_um=80.0))


def test_a_fillet_rung_also_starts_with_the_parent_radius_shared_by_tip_and_fillet():
    """`fillet_split_start` (docs/fitting.md §4): from a rounded parent at r_p, a start at r =
    r_f = r_p / 2 with every other slot the parent's (the nested start keeps r_f at 0, where a
    2 MP x 9-view folder with r = 30, r_f = 40 um ended at r = 54, r_f = 0); none from a parent
    that fitted fillets itself or whose radius is 0. No compilation: the start is arithmetic."""
    from types import SimpleNamespace

    from stairfit.fitting._least_squares import fillet_split_start, nested_start

    s = zoo.standard(TRUTH, seed=1, noise=0.01)
    problem = _problem.prepare(s.obs, s.spec)
    lay, r_max = problem.layout, problem.r_max_um
    r_p = 0.6 * r_max
    parent_p = TRUTH._replace(edge_radius_um=r_p, fillet_radius_um=0.0)
    z_parent = np.asarray(_z(problem, parent_p)) + 0.01  # fitted slots: kept bit for bit
    free = tuple(lay.slot(n) for n in ("sigma_rad", "edge_radius_um", "scale"))
    parent = SimpleNamespace(params=parent_p, free_slots=free, z=z_parent)
    z = fillet_split_start(problem, parent)
    k_r, k_f = lay.slot("edge_radius_um"), lay.slot("fillet_radius_um")
    r = r_max * (1 + np.sin(z[k_r])) / 2
    r_f = (r_max - r) * (1 + np.sin(z[k_f])) / 2
    np.testing.assert_allclose([r, r_f], [r_p / 2, r_p / 2], rtol=1e-12)
    nested = nested_start(problem, parent)
    others = [k for k in range(lay.size) if k not in (k_r, k_f)]
    np.testing.assert_array_equal(z[others], nested[others])
    assert z[lay.slot("scale")] == z_parent[lay.slot("scale")]
    # a parent with the fillet free, or without a radius: nothing to share
    assert (
        fillet_split_start(problem, SimpleNamespace(**{**vars(parent), "free_slots": (*free, k_f)}))
        is None
    )
    flat = parent_p._replace(edge_radius_um=0.0)
    assert fillet_split_start(problem, SimpleNamespace(**{**vars(parent), "params": flat})) is None


def test_the_correction_summed_over_chunks_of_rays_is_the_one_pass_sum(monkeypatch):
    """`_fillet_impl` sums over chunks of rays (`lax.scan`) when one pass would hold more than
    `FILLET_CHUNK_BYTES` (the accurate knobs asked XLA for 99 GB on a 2 MP x 9-view folder;
    now 2.9 GB): its value, its forward-mode derivatives in the widths and `delta_n` and its
    values at a stack of other rays (as the grid's JVP takes them for `r` and `r_f`, under
    `vmap`) equal the one-pass ones to rounding, here with 64 rays in chunks of 8 (budget
    forced down). Only the contraction is compiled (the rays traced once, outside): the whole
    grid's value + Jacobian twice took 54-66 s of the suite. The chunk size is the largest
    divisor of the ray count within the budget."""
    assert _forward._ray_chunk(4096, 1000, budget=64_000) == 64
    assert _forward._ray_chunk(4096, 10, budget=64_000) == 4096  # fits: one pass
    assert _forward._ray_chunk(96, 1000, budget=40_000) == 32  # a divisor, not 40
    assert _forward._ray_chunk(7, 10**9, budget=1) == 1
    s = zoo.standard(TRUTH, seed=1, noise=0.01)
    g = _forward._grid(_problem.prepare(s.obs, s.spec).data)
    sigma_k = jnp.full(g.r_ti.shape, 4 * DEG)
    cfg = (model.Aperture(), None, 64, 16)  # (aperture, resolution, rays, bounces)
    r = jnp.broadcast_to(TRUTH.edge_radius_um, g.g_ti.shape)
    rf = jnp.broadcast_to(TRUTH.fillet_radius_um, g.g_ti.shape)
    stack = lambda a: jnp.stack([a, a])  # noqa: E731
    # compiled: eagerly, each of its operations compiles as a program of its own (this test
    # took 13.6 s that way, 9.3 s so)
    trace = jax.jit(model.fillet_rays, static_argnames=("rays", "bounces"))
    rays = trace(g.g_ti, g.g_b2, g.g_layer, r, rf, rays=64, bounces=16)
    r_moved = jnp.stack([1.1 * r, 0.9 * r])
    moved = trace(*map(stack, (g.g_ti, g.g_b2, g.g_layer)), r_moved, stack(rf),
                  rays=64, bounces=16)  # fmt: skip

    def make() -> Callable:  # a fresh function each time: the chunk size is chosen in tracing
        def both(x: jnp.ndarray, dx: jnp.ndarray) -> tuple[jnp.ndarray, ...]:
            f = lambda x: _forward._fillet_impl(sigma_k * jnp.exp(x[0]), x[1], rays, cfg, g)  # noqa: E731
            at = jax.vmap(lambda rr: _forward._fillet_impl(sigma_k, x[1], rr, cfg, g))(moved)
            return *jax.jvp(f, (x,), (dx,)), at

        return both

    def outputs(program: Callable) -> tuple[np.ndarray, ...]:
        """Value, Jacobian (column by column through the one program: tests/checks.py) and
        the values at the other rays."""
        value, _, at = program(x, jnp.zeros(2))
        return value, jacobian_by_columns(lambda dx: program(x, dx)[1], 2), at

    x = jnp.array([0.0, 0.0])
    scans = str(jax.make_jaxpr(make())(x, x)).count("scan[")
    one = outputs(jax.jit(make()))
    per_ray = _forward._fillet_bytes_per_ray(g, g.r_to.shape[-1], g.r_n.size, 8)
    monkeypatch.setattr(_forward, "FILLET_CHUNK_BYTES", 8 * per_ray)
    assert _forward._ray_chunk(64, per_ray, budget=8 * per_ray) == 8
    assert str(jax.make_jaxpr(make())(x, x)).count("scan[") >= scans + 2  # value and vmap chunked
    chunked = outputs(jax.jit(make()))
    for a, b in zip(one, chunked, strict=True):
        np.testing.assert_allclose(b, a, rtol=1e-12, atol=1e-15 * float(np.max(np.abs(a))))
    assert float(np.max(np.abs(one[0]))) > 0 and float(np.max(np.abs(one[2][0] - one[2][1]))) > 0
