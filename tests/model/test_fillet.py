"""The filleted staircase (issue 15; docs/rounded.md §11), without the reference tracer.

At `r_f = 0` the correction is exactly 0, in value and in every derivative, and the whole is the
rounded model to the last bit; values and forward-mode Jacobians are finite over the whole
domain (r_f -> 0 and at its bound, r_tip -> 0, grazing incidence, n -> 1, wedges near 0 and 90
deg); d/d r_f agrees with central differences; broadening keeps the power of the correction; the
result converges as the ray count grows.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from checks import all_finite, generic_direction, jacobian_by_columns

from stairfit import model
from stairfit.model import _fillet

DEG = np.pi / 180
HALF = np.pi / 2
L1 = 150.0
# enough for the properties here; accuracy: tests/validation/test_fillet_vs_raytrace.py
RAYS = 512
_TO = jnp.linspace(-HALF, HALF, 37)
_EDGES = jnp.linspace(-HALF, HALF, 91)


def _brdf(p, b2, rays=RAYS):
    """p = (sigma, n, r_tip, r_f, theta_i, l1)."""
    sg, n, r, rf, ti, l1 = p
    return model.brdf_filleted(ti, _TO, b2, n, sg, l1, r, rf, rays=rays)


def _rounded(p, b2):
    sg, n, r, _, ti, l1 = p
    return model.brdf_rounded(ti, _TO, b2, n, sg, l1, r)


def _correction(p, b2):
    """The fillet correction alone, T(r, r_f) - T(r, 0) (private: the exactness check)."""
    sg, n, r, rf, ti, l1 = p
    args = _fillet._args(ti, _TO, b2, n, sg, l1, r, rf)
    ti, to, b, n, sg, l1, r, rf = args
    static = _fillet._Static("brdf", RAYS, model.FILLET_BOUNCES)
    return _fillet._filleted(static, jnp.zeros(()), ti, b, l1, r, rf, n, to, sg)


def _three(p, b2):
    return _brdf(p, b2), _rounded(p, b2), _correction(p, b2)


# Few compiled programs, each shared by several tests (the filleted model's compilation is
# most of this file's time, issue 14): the filleted and the rounded model and the correction
# alone, with their derivatives along a tangent `dp` that is an argument, in one program.
# Jacobians are taken column by column through it (`jacobian_by_columns`): the program with
# the whole Jacobian (`jax.jacfwd`) took 12.4 s to compile against 8.4 s, and 12 ms a call
# against 7.5 ms.
_ALL = jax.jit(lambda p, b2, dp: jax.jvp(lambda q: _three(q, b2), (p,), (dp,)))


def _values_and_jacobians(p, b2):
    """(filleted, rounded, correction) and their Jacobians in p, shape (37, 6)."""
    values, _ = _ALL(p, b2, jnp.zeros(6))
    jacobians = jacobian_by_columns(lambda dp: _ALL(p, b2, dp)[1], 6)
    return values, jacobians


@pytest.mark.parametrize("beta2_deg", [10, 30, 60])
@pytest.mark.parametrize("theta_i_deg", [-70.0, -20.0, 0.0, 40.0])
def test_zero_fillet_is_the_rounded_model_in_value_and_gradient(beta2_deg, theta_i_deg):
    """The correction is exactly 0 with exactly 0 derivatives; the whole, in one compiled
    program with the rounded model, is equal to it to the last bit. (Separately compiled, the
    rounded model itself differs from its eager run by up to 1e-8 relative at small values.)"""
    b2 = beta2_deg * DEG
    p = jnp.array([0.05, 1.46, 30.0, 0.0, theta_i_deg * DEG, L1])
    (v, v0, c), (j, j0, dc) = _values_and_jacobians(p, b2)
    # to the last bit: the two models' values come out of one program that also carries their
    # derivatives, where XLA fuses the two copies of the rounded model differently (1 ulp
    # seen; in the earlier program with `jax.jacfwd`'s Jacobians they were bit-identical);
    # that the correction is exactly 0 is asserted bitwise below
    np.testing.assert_allclose(v, v0, rtol=1e-15, atol=0)
    keep = [0, 1, 2, 4, 5]  # every parameter but r_f (which the rounded model does not have)
    # the Jacobians are two differently structured programs: equal to the last bits (the
    # correction's own derivative is checked to be exactly 0 below)
    np.testing.assert_allclose(j[:, keep], j0[:, keep], rtol=1e-12, atol=0)
    if theta_i_deg == 0:  # at -70, -20 (10 deg wedge), 40 (10, 60 deg) a shadow covers the
        assert bool(jnp.any(j[:, 3] != 0))  # corner; elsewhere r_f acts, already at 0
    np.testing.assert_array_equal(c, 0.0)
    np.testing.assert_array_equal(dc[:, keep], 0.0)


# one compiled program for both pairs (each compared in the same program, as in the test
# above; eagerly the four calls took 31 s), the three wedges on their own axis
_BINNED_TOTAL = jax.jit(lambda ti, b2: (
    model.filleted_binned(ti, _EDGES, b2, 1.46, L1, 5.0, 0.0, rays=RAYS),
    model.rounded_binned(ti, _EDGES, b2, 1.46, L1, 5.0),
    model.filleted_total(ti, b2, 1.46, L1, 5.0, 0.0, rays=RAYS),
    model.rounded_total(ti, b2, 1.46, L1, 5.0),
))  # fmt: skip


def test_zero_fillet_binned_and_total_are_the_rounded_ones():
    ti = jnp.array([-1.0, -0.3, 0.0, 0.6, 1.3])[None, :]
    b2 = jnp.array([10 * DEG, 45 * DEG, 80 * DEG])[:, None]
    binned, binned0, total, total0 = _BINNED_TOTAL(ti, b2)
    # to the last bit but one: compiled together, XLA fuses the two sums differently (1 ulp
    # seen); that the correction itself is exactly 0 is asserted bitwise above
    np.testing.assert_allclose(binned, binned0, rtol=1e-14, atol=0)
    np.testing.assert_allclose(total, total0, rtol=1e-14, atol=0)


@pytest.mark.parametrize("beta2_deg", [0.5, 30, 60, 89.5])
def test_finite_values_and_gradients_at_extremes(beta2_deg):
    """Values and derivatives finite, values non-negative. The derivative is the one along a
    direction with every component non-zero (`generic_direction`): it is finite exactly when
    every column of the Jacobian is, and costs one call of the program instead of six."""
    b2 = beta2_deg * DEG
    b1 = HALF - b2
    cap = float(min(L1, L1 / np.tan(b2)))
    angles = [-HALF, -HALF + 1e-9, -b2, b1 - b2, b1, 0.0, HALF - 1e-9, HALF]
    dp = jnp.asarray(generic_direction(6))
    for r in (0.0, 1e-9, 0.3 * cap):
        for rf in (0.0, 1e-9, 0.5 * (cap - r), cap - r):
            for ti in angles:
                for n in (1.46, 1.0001):
                    p = jnp.array([0.05, n, r, rf, ti, L1])
                    (v, _, _), (dv, _, _) = _ALL(p, b2, dp)  # the program compiled above
                    assert all_finite((v, dv)), (r, rf, ti, n)
                    assert bool(np.all(np.asarray(v) >= 0)), (r, rf, ti, n)


def _t5(p: jax.Array) -> jax.Array:
    """The filleted total at p = (theta_i, beta2, l1, r, r_f), 4096 rays (the slopes below are
    differences)."""
    return model.filleted_total(p[0], p[1], 1.46, p[2], p[3], p[4], rays=4096)


# the value and its derivative along `dp` in one program (a tangent given as data: one
# compilation serves every direction; the whole Jacobian, where needed, column by column)
_TJ5 = jax.jit(lambda p, dp: jax.jvp(_t5, (p,), (dp,)))
_D_RF = np.eye(5)[4]  # the direction of r_f


def _value5(p: jax.Array) -> jax.Array:
    return _TJ5(p, jnp.zeros(5))[0]


def _jac5(p: jax.Array) -> np.ndarray:
    return jacobian_by_columns(lambda dp: _TJ5(p, dp)[1], 5)


def _total(rf: float, ti: float, b2: float) -> float:
    """The filleted total at tip radius 30 um."""
    return float(_value5(jnp.array([ti, b2, L1, 30.0, rf])))


def _d_total(rf: float, ti: float, b2: float) -> float:
    """Its derivative in r_f (the model's difference, docs §11)."""
    return float(_TJ5(jnp.array([ti, b2, L1, 30.0, rf]), jnp.asarray(_D_RF))[1])


@pytest.mark.parametrize(
    ("beta2_deg", "theta_i_deg"), [(30, 0.0), (30, 40.0), (60, -20.0), (45, 20.0)]
)
def test_fillet_derivative_matches_the_slope_of_the_value(beta2_deg, theta_i_deg):
    """d/d r_f (a difference of step 0.01 min(l1, l2), docs §11) against the slope of the value
    over a window four to eight times wider: 3% (the curvature over the window is below that;
    the per-ray derivative this replaced was off by up to 70%)."""
    b2, ti = beta2_deg * DEG, theta_i_deg * DEG
    for rf in (15.0, 40.0):
        h = 4.0
        slope = (_total(rf + h, ti, b2) - _total(rf - h, ti, b2)) / (2 * h)
        np.testing.assert_allclose(_d_total(rf, ti, b2), slope, rtol=0.03)


def test_fillet_derivative_one_sided_at_the_ends():
    b2 = 60 * DEG
    rf_max = float(model.max_fillet_radius(b2, L1, 30.0))
    # At the upper bound the flat riser vanishes and the slope changes fast (one-sided slopes
    # over 0.5, 1.5 and 2 um differ by 20%), hence 15% there.
    for rf, other, tol in ((0.0, 2.0, 0.05), (rf_max, rf_max - 2.0, 0.15)):
        slope = (_total(rf, 0.3, b2) - _total(other, 0.3, b2)) / (rf - other)
        np.testing.assert_allclose(_d_total(rf, 0.3, b2), slope, rtol=tol)


def test_broadening_keeps_the_reflected_power():
    """The correction's Gaussians are truncated and renormalised per ray, so the broadened
    density integrates to the total, as for the rounded model (3e-5 there)."""
    to = jnp.linspace(-HALF, HALF, 4001)
    both = jax.jit(lambda ti: (
        jnp.trapezoid(model.brdf_filleted(ti, to, 30 * DEG, 1.46, 0.05, L1, 30.0, 15.0,
                                          rays=RAYS), to),
        model.filleted_total(ti, 30 * DEG, 1.46, L1, 30.0, 15.0, rays=RAYS),
    ))  # fmt: skip
    for ti in (-0.5, 0.0, 0.7):
        np.testing.assert_allclose(*both(ti), rtol=1e-4)


@pytest.mark.slow  # three ray counts, three compilations (12 s); accuracy at the default
def test_correction_converges_with_the_ray_count():  # count: validation/test_fillet_vs_raytrace.py
    """Doubling the rays changes the total by less and less; 2048 (the default) against
    16384 within 1e-4 of the total (docs/rounded.md §11 has the table)."""
    ti, b2 = 40 * DEG, 30 * DEG
    totals = {
        k: float(model.filleted_total(ti, b2, 1.46, L1, 30.0, 15.0, rays=k))
        for k in (256, 2048, 16384)
    }
    ref = totals[16384]
    assert abs(totals[2048] - ref) < abs(totals[256] - ref) + 1e-12
    assert abs(totals[2048] - ref) < 1e-4 * ref


def test_fillet_increases_total_as_in_the_issue():
    """Issue 15's tracer figures (30-degree wedge, l1 150 um, tip 30 um, fillet 15 um,
    n = 1.46): total up 6.7% at theta_i = 0 and 11.5% at 40 deg; the model within 0.3%. The
    program of the derivative tests (4096 rays); its `r_f = 0` is the rounded total exactly
    (`test_zero_fillet_binned_and_total_are_the_rounded_ones`)."""
    for ti, up in ((0.0, 0.067), (40.0, 0.115)):
        ratio = _total(15.0, ti * DEG, 30 * DEG) / _total(0.0, ti * DEG, 30 * DEG)
        assert ratio - 1 == pytest.approx(up, abs=0.003)


@pytest.mark.slow  # two compilations (15 s); float32 is for figures, not fits (docs §10)
def test_float32_stays_float32_and_close():
    args = (0.3, 30 * DEG, 1.46, L1, 30.0, 15.0)
    f64 = model.filleted_total(*args)
    f32 = model.filleted_total(*(np.float32(a) for a in args))
    assert f32.dtype == jnp.float32
    np.testing.assert_allclose(float(f32), float(f64), rtol=1e-3)


@pytest.mark.parametrize(
    ("beta2_deg", "theta_i_deg", "tip", "fil"),
    [
        (30, 0.0, 30.0, 15.0),
        (30, 40.0, 30.0, 15.0),
        (60, -20.0, 10.0, 30.0),
        (45, 20.0, 20.0, 40.0),
    ],
)
def test_jacobian_matches_central_differences(beta2_deg, theta_i_deg, tip, fil):
    """The whole Jacobian (theta_i, beta2, l1, r, r_f) of the total against central differences
    of other steps than the model's (0.5 deg, 1.5 um, 1 um): 4%, the correction's quadrature
    noise (measured worst 3.1%, in theta_i; the pathwise derivative was 10x off there)."""
    p = np.array([theta_i_deg * DEG, beta2_deg * DEG, L1, tip, fil])
    steps = np.array([0.5 * DEG, 0.5 * DEG, 1.5, 1.0, 1.0])
    jac = np.asarray(_jac5(jnp.asarray(p)))
    for k, h in enumerate(steps):
        e = np.eye(5)[k] * h
        fd = (float(_value5(jnp.asarray(p + e))) - float(_value5(jnp.asarray(p - e)))) / (2 * h)
        np.testing.assert_allclose(jac[k], fd, rtol=0.04, err_msg=str(k))
