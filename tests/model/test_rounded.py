"""Physics and numerics of the rounded-edge model (issue 5), without the ray tracer.

Limits (r -> 0 is the sharp model, in value and gradient), conservation (the paths partition the
period; broadening keeps the reflected power), bounds (Fresnel), symmetries (45-degree wedge;
the 30/60 pair stops being mirror images, in the direction of the paper's Sec. 3.3), finite values
and gradients at the extremes, smoothness in r, and the internal premises of the method (class
order of the rays leaving an arc, boundary finder, broadening moments).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from checks import all_finite, generic_direction, jacobian_by_columns

from stairfit import model
from stairfit.model import _rounded

DEG = np.pi / 180
HALF = np.pi / 2
L1 = 150.0

# One compilation per argument shape for the whole module (eager calls would compile and
# dispatch op by op, and new lambdas would recompile). Each program of the rounded model takes
# seconds to compile, so the tests share a few argument shapes: a scalar theta_i with the 73
# viewing angles `_TO` below for `BRDF`, 361 angles of incidence for `PATHS` (`_paths_weight`).
BRDF = jax.jit(model.brdf_rounded, static_argnames=("resolution",))
PATHS = jax.jit(model.rounded_paths, static_argnames=("resolution",))
TOTAL = jax.jit(model.rounded_total, static_argnames=("resolution",))
SHARP = jax.jit(model.brdf)
LOBE_WEIGHTS = jax.jit(model.lobe_weights)
_N_PATHS = 361


def _paths_weight(theta_i, beta2: float, radius: float) -> jax.Array:
    """`rounded_paths(theta_i, beta2, 1.46, L1, radius).weight`, (n_theta_i, n_paths), through
    the one compiled program for 361 angles (padded with normal incidence; each angle's paths
    depend on that angle alone)."""
    ti = np.atleast_1d(np.asarray(theta_i, float))
    padded = np.zeros(_N_PATHS)
    padded[: ti.size] = ti
    return PATHS(jnp.asarray(padded), beta2, 1.46, L1, radius).weight[: ti.size]


# ------------------------------------------------------------------------------------------
# r -> 0: the sharp model
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("beta2_deg", [0.5, 10, 30, 45, 60, 89.5])
@pytest.mark.parametrize("sigma", [1e-6, 1e-3, 5 * DEG, 1.0])
def test_zero_radius_is_the_sharp_model(beta2_deg, sigma):
    b2 = beta2_deg * DEG
    b1 = HALF - b2
    ti = np.array([-HALF, -HALF + 1e-9, -b2, b1 - b2, b1, 0.3, HALF - 1e-9, HALF])
    to = np.linspace(-HALF, HALF, 181)
    t_i, t_o = np.meshgrid(ti, to, indexing="ij")
    rounded = BRDF(t_i, t_o, b2, 1.46, sigma, L1, 0.0)
    sharp = SHARP(t_i, t_o, b2, 1.46, sigma)
    np.testing.assert_allclose(rounded, sharp, rtol=1e-10, atol=1e-12 * float(np.max(sharp)))
    w = _paths_weight(ti, b2, 0.0)
    np.testing.assert_allclose(w[:, :3], LOBE_WEIGHTS(ti, b2), atol=1e-12)
    np.testing.assert_array_equal(w[:, 3:], 0.0)


def _rho(p, to, b2):  # p = (sigma, n, r, theta_i)
    return model.brdf_rounded(p[3], to, b2, p[1], p[0], L1, p[2])


@jax.jit
def _rho_jvp(p, to, b2, dp, dto):
    """rho and its derivative along the tangent `(dp, dto)` of (sigma, n, r, theta_i) and the
    viewing angles: one compiled program for every direction (the tangent is an argument;
    rho at theta_o[k] depends on theta_o[k] only). With the whole Jacobian and d rho / d theta_o
    in the program instead (`jax.jacfwd` and a second `jax.jvp`) it took 5.1 s against 2.8 s to
    trace and compile, and 4.8 ms against 2.0 ms a call."""
    return jax.jvp(lambda q, t: _rho(q, t, b2), (p, to), (dp, dto))


def _value(p, to, b2):
    return _rho_jvp(p, to, b2, jnp.zeros(4), jnp.zeros_like(to))[0]


def _jac(p, to, b2):
    """Jacobian with respect to (sigma, n, r, theta_i), shape (n_theta_o, 4)."""
    return jacobian_by_columns(lambda dp: _rho_jvp(p, to, b2, dp, jnp.zeros_like(to))[1], 4)


def _value_and_d_dr(p, to, b2):
    """rho and d rho / d r in one call."""
    return _rho_jvp(p, to, b2, jnp.array([0.0, 0.0, 1.0, 0.0]), jnp.zeros_like(to))


_JAC_SHARP = jax.jit(jax.jacfwd(lambda p, to, b2: model.brdf(p[3], to, b2, p[1], p[0])))
# 73 viewing angles: the extremes and a grid (one shape, so one compilation of each function)
_TO = jnp.concatenate(
    [jnp.array([-HALF, -HALF + 1e-9, HALF - 1e-9, HALF]), jnp.linspace(-89.0, 89.0, 69) * DEG]
)


@pytest.mark.parametrize("beta2_deg", [10, 30, 45, 60])
def test_value_and_gradient_continuous_as_radius_goes_to_zero(beta2_deg):
    """Gradients with respect to sigma, n, theta_i at r = 0 equal the sharp model's, and at
    r = 1e-6 um they differ from those at r = 0 by O(1e-6 / l1). Away from the kinks of the
    sharp weights (regime boundaries), where a one-sided derivative is ambiguous."""
    b2 = beta2_deg * DEG
    for ti_deg in (-80.0, -beta2_deg + 4.0, 5.0, 90.0 - beta2_deg - 6.0, 88.0 - beta2_deg + 5.0):
        p0 = jnp.array([3 * DEG, 1.46, 0.0, ti_deg * DEG])
        j0 = _jac(p0, _TO, b2)
        js = _JAC_SHARP(p0, _TO, b2)
        scale = float(jnp.max(jnp.abs(js)))
        np.testing.assert_allclose(j0[:, [0, 1, 3]], js[:, [0, 1, 3]], atol=1e-12 * scale)
        j6 = _jac(p0.at[2].set(1e-6), _TO, b2)
        assert float(jnp.max(jnp.abs(j6 - j0))) <= 1e-6 * float(jnp.max(jnp.abs(j0)))
        v6, v0 = _value(p0.at[2].set(1e-6), _TO, b2), _value(p0, _TO, b2)
        assert float(jnp.max(jnp.abs(v6 - v0))) <= 1e-6 * float(jnp.max(v0))
        # d rho / d r at r = 0 against a second-order one-sided difference
        h = 1e-3
        fd = 4 * _value(p0.at[2].set(h), _TO, b2) - _value(p0.at[2].set(2 * h), _TO, b2) - 3 * v0
        fd = fd / (2 * h)
        np.testing.assert_allclose(j0[:, 2], fd, atol=1e-5 * float(jnp.max(jnp.abs(j0[:, 2]))))


@pytest.mark.parametrize("beta2_deg", [10, 30, 45, 60])
def test_radius_derivative_matches_finite_differences(beta2_deg):
    """The boundaries move smoothly with r (they are computed, not sampled): the forward-mode
    derivative equals a central difference across the whole valid range of r."""
    b2 = beta2_deg * DEG
    r_max = float(model.max_edge_radius(b2, L1))
    for radius in (0.05 * r_max, 0.3 * r_max, 0.7 * r_max):
        for ti_deg in (-70.0, -10.0, 20.0, 75.0):
            p = jnp.array([3 * DEG, 1.46, radius, ti_deg * DEG])
            jr = _value_and_d_dr(p, _TO, b2)[1]
            h = 1e-2
            fd = (_value(p.at[2].add(h), _TO, b2) - _value(p.at[2].add(-h), _TO, b2)) / (2 * h)
            np.testing.assert_allclose(jr, fd, atol=2e-4 * float(jnp.max(jnp.abs(jr))) + 1e-12)


def _scan(b2, ti, rs):
    """rho and d rho / d r on a grid of radii, and the trapezoid residual of each step."""
    out = [_value_and_d_dr(jnp.array([3 * DEG, 1.46, r, ti]), _TO, b2) for r in rs]
    v = np.stack([np.asarray(value) for value, _ in out])
    d = np.stack([np.asarray(d_dr) for _, d_dr in out])
    return v, np.diff(v, axis=0) - 0.5 * (d[1:] + d[:-1]) * np.diff(rs)[:, None]


@pytest.mark.parametrize("beta2_deg", [30, 45, 60])
def test_smooth_in_radius_without_jumps(beta2_deg):
    """Scanning r over [0, r_max]: each step's change of rho equals the trapezoid integral of
    d rho / d r up to a residual. The worst step is refined 8-fold: a jump would keep its full
    residual in one sub-step, a smooth (or square-root, where a sub-interval opens) variation
    loses most of it."""
    b2 = beta2_deg * DEG
    rs = np.linspace(0.0, float(model.max_edge_radius(b2, L1)), 41)
    for ti_deg in (-35.0, 15.0, 65.0):
        v, step = _scan(b2, ti_deg * DEG, rs)
        scale = np.max(np.abs(v))
        assert np.max(np.abs(step)) <= 5e-2 * scale, ti_deg
        k = int(np.argmax(np.max(np.abs(step), axis=1)))
        worst = np.max(np.abs(step[k]))
        if worst > 1e-6 * scale:
            _, fine = _scan(b2, ti_deg * DEG, np.linspace(rs[k], rs[k + 1], 9))
            assert np.max(np.abs(fine)) <= 0.25 * worst, (ti_deg, rs[k])


# ------------------------------------------------------------------------------------------
# Extremes
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("beta2_deg", [10, 30, 45, 60])
@pytest.mark.parametrize("sigma", [1e-6, 5 * DEG])
@pytest.mark.parametrize("n", [1.46, 1.0001])
def test_finite_values_and_gradients_at_extremes(beta2_deg, sigma, n):
    b2 = beta2_deg * DEG
    b1 = HALF - b2
    r_max = float(model.max_edge_radius(b2, L1))
    angles = [-HALF, -HALF + 1e-9, -b2, b1 - b2, b1, 0.0, HALF - 1e-9, HALF]
    # the derivative in (sigma, n, r, theta_i) and theta_o along one generic direction: finite
    # exactly when the Jacobian and d rho / d theta_o are (tests/checks.py)
    tangent = generic_direction(5)
    dp, dto = jnp.asarray(tangent[:4]), jnp.full_like(_TO, tangent[4])
    for radius in (0.0, 1e-9, 0.5 * r_max, r_max):
        for ti in angles:
            p = jnp.array([sigma, n, radius, ti])
            v, d = _rho_jvp(p, _TO, b2, dp, dto)
            assert all_finite((v, d)), (radius, ti)
            assert bool(np.all(np.asarray(v) >= 0))


@jax.jit
def _complex_value_and_derivative(q, dq):
    """rho with the complex index `nr + i k`, q = (nr, k, r, theta_i), and its derivative along
    `dq` (with the whole Jacobian, `jax.jacfwd`, the test below took 7.0 s in the suite, now
    4.7 s; most of it is this program's compilation)."""

    def f(q):
        nr, k, r, ti = q
        return model.brdf_rounded(ti, _TO, 30 * DEG, nr + 1j * k, 0.05, L1, r)

    return jax.jvp(f, (q,), (dq,))


def test_complex_index_values_and_gradients():
    """Finite values and derivatives (along one generic direction: tests/checks.py)."""
    dq = jnp.asarray(generic_direction(4))
    for r in (0.0, 40.0, float(model.max_edge_radius(30 * DEG, L1))):
        for ti in (-HALF, -0.3, 0.5, HALF):
            assert all_finite(_complex_value_and_derivative(jnp.array([1.5, 0.3, r, ti]), dq))


# ------------------------------------------------------------------------------------------
# Conservation and bounds
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("beta2_deg", [10, 30, 45, 60, 80])
def test_paths_partition_the_period(beta2_deg):
    b2 = beta2_deg * DEG
    ti = jnp.linspace(-HALF, HALF, 361)
    for frac in (0.01, 0.3, 0.7, 1.0):
        radius = frac * float(model.max_edge_radius(b2, L1))
        w = _paths_weight(ti, b2, radius)
        assert bool(jnp.all(w >= -1e-15))
        # 1e-9: at theta_i = +-90 deg the period's width on the ray front is ~1e-5 um
        np.testing.assert_allclose(jnp.sum(w, axis=-1), 1.0, atol=1e-9)


@pytest.mark.parametrize("beta2_deg", [10, 30, 45, 60])
def test_arc_weight_closed_form_and_cell_size(beta2_deg):
    """In regime B the whole arc is lit; the rays hitting it first span `r (cos u + sin u)`
    of the ray front, `u = beta2 + theta_i`, out of `L cos(theta_i)`. At normal incidence this
    is `(r / l1) sin(beta2) (sin beta2 + cos beta2)`: for one r, the 60-degree cell puts
    sin 60 / sin 30 = 1.73 times more light on its arcs than the 30-degree cell."""
    b2 = beta2_deg * DEG
    radius = 30.0
    ti = jnp.linspace(-b2 + 0.01, HALF - b2 - 0.01, 7)
    w = _paths_weight(ti, b2, radius)
    first_on_arc = jnp.sum(w[:, 3:8], axis=-1)  # the five tip-first lobes
    u = b2 + ti
    expected = radius * (jnp.cos(u) + jnp.sin(u)) / (L1 / jnp.sin(b2) * jnp.cos(ti))
    np.testing.assert_allclose(first_on_arc, expected, rtol=1e-12)


def test_sixty_degree_cell_more_affected_than_thirty():
    """Paper Sec. 3.3: same layer, same edge radius, the finer 60-degree cell is the more
    affected one. Its arcs take sqrt(3) times the share of the 30-degree cell's at normal
    incidence, and its BRDF changes more when the edges are rounded."""
    arc30 = _paths_weight(0.0, 30 * DEG, 30.0)[0, 3:8].sum()
    arc60 = _paths_weight(0.0, 60 * DEG, 30.0)[0, 3:8].sum()
    np.testing.assert_allclose(arc60 / arc30, np.sqrt(3.0), rtol=1e-12)
    to = _TO
    for ti in (0.0, 20 * DEG, -20 * DEG):
        change = {}
        for b in (30, 60):
            sign = 1.0 if b == 30 else -1.0  # compare 60 in the mirrored frame
            rho = [BRDF(sign * ti, sign * to, b * DEG, 1.46, 5 * DEG, L1, r) for r in (0.0, 30.0)]
            change[b] = float(jnp.sum(jnp.abs(rho[1] - rho[0])))
        assert change[60] > 1.3 * change[30], (ti, change)
    # the sharp pair is mirror symmetric, the rounded pair is not
    sharp30 = BRDF(0.0, to, 30 * DEG, 1.46, 5 * DEG, L1, 0.0)
    sharp60 = BRDF(0.0, -to, 60 * DEG, 1.46, 5 * DEG, L1, 0.0)
    np.testing.assert_allclose(sharp30, sharp60, rtol=1e-9, atol=1e-14)
    r30 = BRDF(0.0, to, 30 * DEG, 1.46, 5 * DEG, L1, 30.0)
    r60 = BRDF(0.0, -to, 60 * DEG, 1.46, 5 * DEG, L1, 30.0)
    assert float(jnp.max(jnp.abs(r30 - r60))) > 0.03 * float(jnp.max(r30))


@pytest.mark.parametrize("beta2_deg", [40, 45])
def test_rounded_edges_light_up_minus_80_degrees(beta2_deg):
    """Paper Sec. 3.3: photographs show 'bright intensity scattered towards -80 deg for wedge
    angles around 40 deg', where the sharp model (theta_i = 0) puts almost nothing: the arcs'
    continuum reaches there."""
    b2 = beta2_deg * DEG
    to = _TO.at[0].set(-80 * DEG)
    sharp = float(SHARP(0.0, to, b2, 1.46, 5 * DEG)[0])
    rounded = float(BRDF(0.0, to, b2, 1.46, 5 * DEG, L1, 30.0)[0])
    assert sharp < 1e-20
    assert rounded > 1e-3  # 1/rad; the retroreflection peak is about 0.08 1/rad


@pytest.mark.parametrize("beta2_deg", [10, 30, 45, 60])
def test_total_reflectance_bounded_by_fresnel(beta2_deg):
    """No path reflects more than its first bounce allows: the total is at most the largest
    unpolarised Fresnel factor over every first-bounce local angle on the profile (the whole
    arc's normals `[beta2 - 90 deg, beta2]`, facing the light), and at most 1."""
    b2 = beta2_deg * DEG
    ti = jnp.linspace(-HALF + 1e-3, HALF - 1e-3, 181)
    alpha = jnp.linspace(b2 - HALF, b2, 2001)
    cos_local = jnp.cos(ti[:, None] + alpha[None, :])
    bound = jnp.max(
        jnp.where(cos_local > 0, model.fresnel_unpolarised(jnp.clip(cos_local, 0, 1), 1.46), 0), -1
    )
    for radius in (5.0, 40.0, float(model.max_edge_radius(b2, L1))):
        total = TOTAL(ti, b2, 1.46, L1, radius, resolution=8)
        assert bool(jnp.all(total <= bound * (1 + 1e-6)))
        assert bool(jnp.all(total <= 1.0))


@pytest.mark.parametrize("sigma_deg", [1.0, 5.0, 20.0])
def test_broadening_keeps_the_reflected_power(sigma_deg):
    """Each ray's Gaussian is truncated to the hemisphere and renormalised [conventions §5], so
    the broadened density integrates to the total reflectance."""
    to = jnp.linspace(-HALF, HALF, 20001)
    for b2_deg, ti_deg in ((10, -80), (45, 0), (60, 30), (30, 85)):
        b2 = b2_deg * DEG
        rho = BRDF(ti_deg * DEG, to, b2, 1.46, sigma_deg * DEG, L1, 40.0)
        integral = float(jnp.sum(0.5 * (rho[1:] + rho[:-1]) * jnp.diff(to)))
        total = float(TOTAL(ti_deg * DEG, b2, 1.46, L1, 40.0))
        np.testing.assert_allclose(integral, total, rtol=3e-5)


def test_forty_five_degree_wedge_symmetric():
    to = _TO
    for ti in (-1.2, -0.4, 0.0, 0.3, 1.1):
        a = BRDF(ti, to, 45 * DEG, 1.46, 4 * DEG, L1, 50.0)
        b = BRDF(-ti, -to, 45 * DEG, 1.46, 4 * DEG, L1, 50.0)
        np.testing.assert_allclose(a, b, atol=1e-9 * float(jnp.max(a)))


# ------------------------------------------------------------------------------------------
# Validity range
# ------------------------------------------------------------------------------------------


def test_max_edge_radius():
    np.testing.assert_allclose(model.max_edge_radius(30 * DEG, 150.0), 150.0)
    np.testing.assert_allclose(model.max_edge_radius(60 * DEG, 150.0), 150.0 / np.sqrt(3.0))
    np.testing.assert_allclose(model.max_edge_radius(45 * DEG, 150.0), 150.0)


def test_radius_outside_the_cell_is_a_clear_error():
    with pytest.raises(ValueError, match=r"max_edge_radius.*86\.6"):
        model.brdf_rounded(0.0, 0.0, 60 * DEG, 1.46, 0.1, L1, 90.0)
    with pytest.raises(ValueError, match="negative"):
        model.rounded_total(0.0, 30 * DEG, 1.46, L1, -1.0)
    # inside jax.jit the radius is traced and not checked (a fit bounds it by its transform)
    v = TOTAL(0.0, 30 * DEG, 1.46, L1, 20.0)
    assert np.isfinite(float(v))


# ------------------------------------------------------------------------------------------
# Premises and parts of the method
# ------------------------------------------------------------------------------------------


@jax.jit
def _arc_scan(theta_i, beta2, radius):
    """Boundaries from the fast finder, and the ray class on a fine grid of the lit arc."""
    ti, b, l1, r = _rounded._geom_args(theta_i, beta2, L1, radius)
    k = _rounded._cell(ti, b, l1)
    split = _rounded._split(k, r)
    g = _rounded._arc_geom(k, r)
    lo, hi = split.arc_lo, split.arc_hi
    alpha = jnp.linspace(lo + 1e-9 * (hi - lo), hi - 1e-9 * (hi - lo), 20001)
    return _rounded._arc_boundaries(g, lo, hi), alpha, _rounded._arc_class(g, alpha)


CONFIGS = [
    (b, f, t)
    for b in (10, 30, 45, 60, 80)
    for f in (0.05, 0.4, 1.0)
    for t in (-85, -50, -20, 0, 25, 60, 85)
    if f * L1 <= float(model.max_edge_radius(b * DEG, L1)) + 1e-9
]


@pytest.mark.parametrize(("beta2_deg", "frac", "ti_deg"), CONFIGS)
def test_rays_leaving_the_arc_come_in_a_fixed_order(beta2_deg, frac, ti_deg):
    """Reflected rays of a convex mirror do not cross, so along the lit arc the ray classes
    occur in the order left tread, left tip, escape, right tip, right riser (docs/rounded.md
    §4): the class index never decreases. And the fast boundary finder (12 bisection steps,
    Newton steps, one differentiable Newton step) puts each boundary where the class changes."""
    bounds, alpha, cls = (
        np.asarray(a) for a in _arc_scan(ti_deg * DEG, beta2_deg * DEG, frac * L1)
    )
    assert np.all(np.diff(cls) >= 0)
    for k in range(1, 5):
        below = cls < k
        if below.all():
            ref = alpha[-1]
        elif not below.any():
            ref = alpha[0]
        else:
            ref = alpha[np.flatnonzero(below)[-1]]
        assert abs(bounds[k - 1] - ref) <= 2 * (alpha[1] - alpha[0]), k


@jax.jit
def _moments_fast_and_brute(theta_i, beta2, sigma):
    x, w = (jnp.asarray(a) for a in np.polynomial.legendre.leggauss(400))
    to = jnp.linspace(-HALF, HALF, 181)
    geo = _rounded._geometry(*_rounded._geom_args(theta_i, beta2, L1, 40.0), 4)
    m, h, coef, _ = _rounded._lagrange(geo.panel_lo, geo.panel_hi, geo.nodes.theta_o)
    # panel axes (7, P) lead; explicit unit axes for the quadrature nodes (axis q) and the
    # viewing angles (axis t): the suite forbids implicit rank promotion
    xq, wq = x[None, None, :], w[None, None, :]  # (1, 1, q)
    tq = m[..., None] + h[..., None] * xq  # (7, P, q)
    basis = _rounded._basis(coef[..., None, :, :], xq[..., None])  # (7, P, q, 3)
    kern = model.hemisphere_gaussian(to[:, None, None, None], tq[None], sigma)  # (t, 7, P, q)
    brute = jnp.sum(((h[..., None] * wq)[None] * kern)[..., None] * basis[None], axis=-2)
    ref = jnp.sum(brute * geo.nodes.density[None], axis=(-3, -2, -1))
    panels = (a[None] for a in (geo.panel_lo, geo.panel_hi, m, h))  # a unit axis t
    mom = _rounded._kernel_moments(to, jnp.full_like(to, sigma), *panels)
    wts = jnp.sum(coef[None] * mom[..., None, :], axis=-1)
    return jnp.sum(wts * geo.nodes.density[None], axis=(-3, -2, -1)), ref


def test_broadening_moments_against_brute_force():
    """The erf moments plus the horizon correction reproduce a brute-force convolution of the
    panel interpolants with the exact truncated kernel (400-point Gauss-Legendre per panel)."""
    for b2_deg, ti_deg in ((10, -85), (45, 0), (60, 80)):
        for sigma in (0.5 * DEG, 3 * DEG, 25 * DEG):
            fast, ref = _moments_fast_and_brute(ti_deg * DEG, b2_deg * DEG, sigma)
            assert float(jnp.max(jnp.abs(fast - ref))) <= 1e-5 * float(jnp.max(ref))


def test_error_falls_with_resolution():
    assert _rounded.ROUNDED_RESOLUTION == 4
    args = (_TO, 60 * DEG, 1.46, 2 * DEG, L1, 50.0)
    for ti in (-40 * DEG, 10 * DEG):
        ref = BRDF(ti, *args, resolution=16)
        scale = float(jnp.max(ref))
        e2 = float(jnp.max(jnp.abs(BRDF(ti, *args, resolution=2) - ref)))
        # resolution 4 is the default: the program the other tests of this shape use
        e4 = float(jnp.max(jnp.abs(BRDF(ti, *args) - ref)))
        assert e2 > e4
        assert e4 < 2e-3 * scale  # the default resolution (docs/rounded.md §6)


def test_float32_within_documented_bound():
    """float32 evaluation [conventions §10]: within 1e-3 of max rho of float64 (same rounded
    inputs) for |theta_i| <= 89.9 deg and sigma >= 0.5 deg (docs/rounded.md §7). Closer to
    grazing the arc lobe's width changes like sqrt(cos theta_i) and float32 clamps theta_i
    1.2e-4 rad from +-90 deg."""
    to = np.asarray(_TO[4:])  # at exactly +-pi/2 float32 rounding moves theta_o out of range
    for b2_deg in (10, 45, 60, 89.5):
        b2 = np.float32(b2_deg * DEG)
        radius = min(30.0, float(model.max_edge_radius(b2, L1)))
        for ti_deg in (-89.9, -20.0, 30.0, 85.0):
            for sigma_deg in (0.5, 5.0):
                args32 = [np.float32(ti_deg * DEG), to.astype(np.float32), b2]
                sigma32 = np.float32(sigma_deg * DEG)
                r32 = BRDF(*args32, 1.46, sigma32, L1, radius)
                assert r32.dtype == jnp.float32
                # float64 at the same (float32-rounded) inputs, through the program the other
                # tests use (Python floats, the 73 angles of _TO: the first four dropped after)
                to64 = jnp.concatenate([_TO[:4], args32[1].astype(np.float64)])
                r64 = BRDF(float(args32[0]), to64, float(b2), 1.46, float(sigma32), L1, radius)
                r64 = np.asarray(r64)[4:]
                err = np.max(np.abs(np.asarray(r32, np.float64) - r64))
                assert err <= 1e-3 * np.max(r64), (b2_deg, ti_deg, sigma_deg)
