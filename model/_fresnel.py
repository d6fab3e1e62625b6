"""Fresnel reflectance of a smooth interface from air, per polarisation [conventions §6]."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from ._shapes import same_rank


class SP(NamedTuple):
    """Power reflectances for s (TE) and p (TM) polarisation, each in [0, 1]."""

    s: Float[Array, "..."]
    p: Float[Array, "..."]


def fresnel_sp(cos_gamma: ArrayLike, n: ArrayLike) -> SP:
    """Fresnel power reflectances at local incidence `gamma` (`cos_gamma` in [0, 1]).

    `n` is the complex relative refractive index `n' + i k` (a real array is allowed)
    [conventions §6]. With `s = sqrt(n^2 - 1 + c^2)` (equal to `n cos(gamma_t)`):
    `r_s = (c - s) / (c + s)` and `r_p = (n^2 c - s) / (n^2 c + s)`. No angle is formed, so there
    is no `arccos` and no `1 / sin` singularity; the square root's argument is bounded away from 0
    for `Re n > 1`, which keeps gradients finite at normal and grazing incidence.
    """
    c, n = same_rank(cos_gamma, n)
    c = jnp.clip(c, 0.0, 1.0)
    if jnp.iscomplexobj(n):
        n2 = n.astype(jnp.result_type(c.dtype, jnp.complex64)) ** 2
    else:  # real n: stay in real arithmetic (about 3x faster); the formulas are the same.
        n2 = n.astype(c.dtype) ** 2
    r_s, r_p = _amplitudes(c, n2)
    return SP(s=_abs2(r_s), p=_abs2(r_p))


@jax.custom_jvp
def _amplitudes(c: Array, n2: Array) -> tuple[Array, Array]:
    """Amplitude reflection coefficients `(r_s, r_p)` from `c = cos(gamma)` and `n2 = n^2`.

    Both are holomorphic in `n2`, so the derivative rule below holds for complex `n` too. The
    rule is the calculus automatic differentiation would do on these lines, rearranged to need
    one extra division instead of four: the Fresnel factors are most of the work of a
    Jacobian (benchmarks/bench_model.py). Checked against autodiff of an independent formula
    in tests/model/test_band_derivatives.py [conventions §6].
    """
    s = jnp.sqrt(n2 - 1.0 + c**2)
    return (c - s) / (c + s), (n2 * c - s) / (n2 * c + s)


@_amplitudes.defjvp
def _amplitudes_jvp(primals: tuple, tangents: tuple) -> tuple:
    """With `s = sqrt(n2 - 1 + c^2)`, `m = n2 c`: `ds = (dn2 + 2 c dc) / 2s`,
    `dr_s = 2 (s dc - c ds) / (c + s)^2`, `dr_p = 2 (s dm - m ds) / (m + s)^2`,
    `dm = c dn2 + n2 dc` (the quotient rule on `(x - s) / (x + s)`)."""
    c, n2 = primals
    dc, dn2 = tangents
    s = jnp.sqrt(n2 - 1.0 + c**2)
    m = n2 * c
    inv_a, inv_b = 1.0 / (c + s), 1.0 / (m + s)
    r_s, r_p = (c - s) * inv_a, (m - s) * inv_b
    ds = (dn2 + 2.0 * c * dc) * (0.5 / s)
    dm = c * dn2 + n2 * dc
    dr_s = 2.0 * (s * dc - c * ds) * inv_a * inv_a
    dr_p = 2.0 * (s * dm - m * ds) * inv_b * inv_b
    return (r_s, r_p), (dr_s, dr_p)


def _abs2(z: Array) -> Array:
    """|z|^2 without the square root of `abs` (whose gradient is undefined at 0)."""
    if jnp.iscomplexobj(z):
        return jnp.real(z) ** 2 + jnp.imag(z) ** 2
    return z * z


def fresnel_unpolarised(cos_gamma: ArrayLike, n: ArrayLike) -> Float[Array, "..."]:
    """Mean of s and p reflectance: the reflectance for unpolarised light [conventions §6]."""
    r = fresnel_sp(cos_gamma, n)
    return 0.5 * (r.s + r.p)
