"""The shared checks of tests/checks.py do what the model tests rely on."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from checks import all_finite, generic_direction, jacobian_by_columns


def _f(p: jax.Array) -> jax.Array:
    """Three outputs of four inputs; at p[2] = 0 the derivative in p[2] alone is infinite."""
    return jnp.stack([p[0] * p[1], jnp.sin(p[3]) + jnp.sqrt(p[2]), p[0] ** 2 * p[3]])


_JVP = jax.jit(lambda p, dp: jax.jvp(_f, (p,), (dp,)))


def test_jacobian_by_columns_is_jacfwd():
    p = jnp.array([0.3, -1.2, 0.7, 2.0])
    ours = jacobian_by_columns(lambda dp: _JVP(p, dp)[1], 4)
    np.testing.assert_allclose(ours, jax.jacfwd(_f)(p), rtol=1e-15, atol=0)


def test_a_generic_direction_finds_a_non_finite_jacobian():
    dp = generic_direction(4)
    assert np.all(dp != 0) and len(set(dp)) == 4
    smooth = jnp.array([0.3, -1.2, 0.7, 2.0])
    assert all_finite(jax.jacfwd(_f)(smooth)) and all_finite(_JVP(smooth, dp)[1])
    singular = smooth.at[2].set(0.0)  # d sqrt(p2) / d p2 = inf
    assert not all_finite(jax.jacfwd(_f)(singular))
    assert not all_finite(_JVP(singular, dp)[1])
    # along a direction that misses p2 the derivative is NaN (0 x inf), not finite either
    assert not all_finite(_JVP(singular, np.eye(4)[0])[1])
