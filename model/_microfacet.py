"""Microfacet distributions of a rough facet: GGX and Beckmann, with Smith shadowing-masking.

A rough facet is a surface whose micro-normals `m` scatter about its normal `n` with the
density `D(m)` (per steradian of `m`, normalised so that the integral of `D (m . n)` over the
hemisphere is 1), and whose micro-surface shadows and masks itself by Smith's `G1`
[conventions §12]. `alpha` is the roughness: GGX's width (Trowbridge-Reitz), Beckmann's RMS
slope. The definitions are Walter et al. 2007 ("Microfacet models for refraction through rough
surfaces"); they are the ones Mitsuba 3 uses (`include/mitsuba/render/microfacet.h`), except
that Beckmann's `G1` is the exact Smith form here (erf), not a rational approximation.

Everything takes cosines relative to the facet normal, so no frame is built; every function is
finite, with finite gradients, for cosines in [-1, 1] and `alpha > 0`.
"""

from __future__ import annotations

import jax.numpy as jnp
from jax.scipy.special import erf, erfc
from jaxtyping import Array, ArrayLike, Float

from ._shapes import same_rank

DISTRIBUTIONS: tuple[str, ...] = ("ggx", "beckmann")
"""The microfacet distributions `ndf` and `smith_g1` know [conventions §12]."""

_TINY = 1e-12


ROUGHNESS_ANGLE_MAX_RAD = 1.5
"""The largest roughness angle (rad, 86 deg; the width prior's upper end, `alpha = tan(1.5) =
14`, a lobe flat over the hemisphere): beyond it `roughness_alpha` holds. `tan` has period pi,
so without the hold a fit could leave through the pole into the next branch, where a width of
`12 pi + 0.06` rad is the same surface as 0.06 rad and would be reported as 2163 deg."""


def roughness_alpha(width_rad: ArrayLike) -> Float[Array, "..."]:
    """A microfacet distribution's `alpha` from the roughness angle the fit and the reports use
    (its width slot, shared with the Gaussian kernel's sigma): `alpha = tan(width)`, the
    width being the angle whose tangent is the micro-slopes' scale (Beckmann: their RMS), held
    at `ROUGHNESS_ANGLE_MAX_RAD` so that `alpha` grows monotonically with the width. `alpha`
    is the number a renderer takes (Mitsuba's `alpha`) [conventions §12]."""
    return jnp.tan(jnp.minimum(jnp.asarray(width_rad), ROUGHNESS_ANGLE_MAX_RAD))


def _check(kind: str) -> None:
    if kind not in DISTRIBUTIONS:
        raise ValueError(f"microfacet distribution {kind!r}: use one of {', '.join(DISTRIBUTIONS)}")


def ndf(cos_m: ArrayLike, alpha: ArrayLike, kind: str = "ggx") -> Float[Array, "..."]:
    """Density `D(m)` (1/sr) of micro-normals at angle `acos(cos_m)` from the facet normal.

    GGX: `alpha^2 / (pi ((alpha^2 - 1) c^2 + 1)^2)`; Beckmann:
    `exp(-tan^2 / alpha^2) / (pi alpha^2 c^4)`, `c = cos_m`. Zero for `c <= 0` (a micro-normal
    facing away) [conventions §12].
    """
    _check(kind)
    c, a = same_rank(cos_m, alpha)
    up = c > 0.0
    c_safe = jnp.where(up, jnp.clip(c, _TINY, 1.0), 1.0)
    c2 = c_safe * c_safe
    a2 = a * a
    if kind == "ggx":
        d = a2 / (jnp.pi * ((a2 - 1.0) * c2 + 1.0) ** 2)
    else:
        tan2 = (1.0 - c2) / c2
        d = jnp.exp(-tan2 / a2) / (jnp.pi * a2 * c2 * c2)
    return jnp.where(up, d, 0.0)


def smith_lambda(cos_v: ArrayLike, alpha: ArrayLike, kind: str = "ggx") -> Float[Array, "..."]:
    """Smith's `Lambda` of a direction at `acos(cos_v)` from the facet normal (`cos_v > 0`).

    GGX: `(sqrt(1 + alpha^2 tan^2) - 1) / 2`; Beckmann, with `a = 1 / (alpha tan)`:
    `(exp(-a^2) / (a sqrt(pi)) - erfc(a)) / 2`. 0 at normal incidence, growing without bound
    towards grazing [conventions §12].
    """
    _check(kind)
    c, a = same_rank(cos_v, alpha)
    c = jnp.clip(c, _TINY, 1.0)
    tan2 = (1.0 - c * c) / (c * c)
    if kind == "ggx":
        # (sqrt(1 + x) - 1) / 2 written as x / (2 (sqrt(1 + x) + 1)): no cancellation near 0
        x = a * a * tan2
        return x / (2.0 * (jnp.sqrt(1.0 + x) + 1.0))
    flat = tan2 <= 0.0
    tan_safe = jnp.sqrt(jnp.where(flat, 1.0, tan2))
    aa = 1.0 / (a * tan_safe)
    big = aa > 6.0  # Lambda < 1e-17: the two terms cancel to nothing
    aa_safe = jnp.where(big, 1.0, aa)
    lam = 0.5 * (jnp.exp(-aa_safe * aa_safe) / (aa_safe * jnp.sqrt(jnp.pi)) - erfc(aa_safe))
    return jnp.where(flat | big, 0.0, lam)


def smith_g1(
    cos_v: ArrayLike, cos_vm: ArrayLike, alpha: ArrayLike, kind: str = "ggx"
) -> Float[Array, "..."]:
    """Smith's shadowing-masking `G1 = 1 / (1 + Lambda)` of a direction `v` for micro-normal
    `m`: `cos_v = v . n`, `cos_vm = v . m`. Zero when `v` sees the back of the facet or of the
    micro-facet (`cos_v <= 0` or `cos_vm <= 0`) [conventions §12]."""
    cos_v, cos_vm, alpha = same_rank(cos_v, cos_vm, alpha)
    seen = (cos_v > 0.0) & (cos_vm > 0.0)
    g = 1.0 / (1.0 + smith_lambda(jnp.where(seen, cos_v, 1.0), alpha, kind))
    return jnp.where(seen, g, 0.0)


def slope_marginal(x: ArrayLike, alpha: ArrayLike, kind: str = "ggx") -> Float[Array, "..."]:
    """Density of one component of a micro-normal's slope (`tan` of its tilt along one axis):
    GGX `(1 + x^2 / alpha^2)^(-3/2) / (2 alpha)` (Student's t with two degrees of freedom),
    Beckmann `exp(-x^2 / alpha^2) / (alpha sqrt(pi))`; each integrates to 1 over the real line
    [conventions §12]."""
    _check(kind)
    x, alpha = same_rank(x, alpha)
    u = x / alpha
    if kind == "ggx":
        return (1.0 + u * u) ** -1.5 / (2.0 * alpha)
    return jnp.exp(-u * u) / (alpha * jnp.sqrt(jnp.pi))


def slope_cdf(x: ArrayLike, alpha: ArrayLike, kind: str = "ggx") -> Float[Array, "..."]:
    """Probability that one slope component of a micro-normal is below `x`: the integral of
    `slope_marginal`, GGX `(1 + u / sqrt(1 + u^2)) / 2`, Beckmann `(1 + erf(u)) / 2`,
    `u = x / alpha` [conventions §12]."""
    _check(kind)
    x, alpha = same_rank(x, alpha)
    u = x / alpha
    if kind == "ggx":
        return 0.5 * (1.0 + u / jnp.sqrt(1.0 + u * u))
    return 0.5 * (1.0 + erf(u))
