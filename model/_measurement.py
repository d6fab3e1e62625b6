"""From the BRDF to what a camera records: spectral bands, finite apertures, radiance.

[conventions §8, §9]. Everything is evaluated only where the scene needs it: at the observed
angles, and at the wavelength samples each observation's channel sees.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._broadening import hemisphere_gaussian
from ._lobes import lobe_directions, lobe_fresnel, lobe_weight_kinks, lobe_weights
from ._shapes import same_rank, with_rank

COS_THETA_O_FLOOR = float(np.cos(np.deg2rad(89.9)))
"""`cos(theta_o)` is floored here in the radiance conversion [conventions §9]."""


LIGHT_SHAPES: tuple[str, ...] = ("uniform", "disk")
"""How a finite light's in-plane offsets are distributed (`Aperture.light_shape`)."""


class Aperture(NamedTuple):
    """Finite angular extent of the light and of the viewed patch [conventions §9].

    The density is averaged over `theta_i +- half_width_i_rad` and uniformly over
    `theta_o +- half_width_o_rad`, with `n_nodes` nodes along each (so `n_nodes**2`
    evaluations; `n_nodes = 1` is a point evaluation). Over the light, `light_shape` "uniform"
    weighs every in-plane offset alike (Gauss-Legendre: a light that is a bar across the plane
    of incidence, or a square), "disk" weighs them as a round light's in-plane marginal, the
    semicircle `sqrt(1 - x^2)` (Gauss-Chebyshev of the second kind: its variance is 3/4 of the
    uniform one's). A light of diameter `D` at distance `d` has `half_width_i = atan(D / 2d)`;
    a wedge face seen across a length `L` at distance `d` spans about
    `half_width_o = atan(L cos(theta_o) / 2d)`. With `foreshortened`, `half_width_o_rad` is
    that spread seen face-on (`atan(L / 2d)`) and every observation uses it times
    `cos(theta_o)` (`node_angles`); without, the same spread at every `theta_o`.

    `nodes()` gives the same offsets for every row; the light's nodes of a row are placed by
    `light_nodes`, which keeps these offsets on rows whose light interval holds no kink of the
    lobe weights and splits the interval at the kink on the others.
    """

    half_width_i_rad: float = 0.0
    half_width_o_rad: float = 0.0
    n_nodes: int = 1
    foreshortened: bool = False
    light_shape: str = "uniform"

    def nodes(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Offsets in theta_i, offsets in theta_o, and weights (sum 1), each (n_nodes**2,)."""
        if self.n_nodes == 1:
            return np.zeros(1), np.zeros(1), np.ones(1)
        if self.light_shape not in LIGHT_SHAPES:
            raise ValueError(f"Aperture.light_shape {self.light_shape!r}: use one of "
                             f"{', '.join(LIGHT_SHAPES)}")  # fmt: skip
        x, w = np.polynomial.legendre.leggauss(self.n_nodes)
        xl, wl = _plain_light_rule(self.n_nodes, self.light_shape)
        xi, xo = np.meshgrid(xl, x, indexing="ij")
        ww = np.outer(wl / wl.sum(), w / w.sum())
        return (
            (xi * self.half_width_i_rad).ravel(),
            (xo * self.half_width_o_rad).ravel(),
            ww.ravel(),
        )


def _plain_light_rule(n: int, shape: str) -> tuple[np.ndarray, np.ndarray]:
    """The light's offsets `x` in [-1, 1] and weights (sum 1) of `Aperture.nodes` (one axis)."""
    if shape == "disk":
        k = np.arange(1, n + 1)
        x, w = np.cos(k * np.pi / (n + 1)), np.sin(k * np.pi / (n + 1)) ** 2
    else:
        x, w = np.polynomial.legendre.leggauss(n)
    return x, w / w.sum()


def _piece_rule(m: int, shape: str, end: str) -> tuple[np.ndarray, np.ndarray]:
    """Gauss rule on [-1, 1] for one piece of a split light interval, `m` nodes (may be 0):
    Gauss-Legendre for a uniform light; for a disk, Gauss-Jacobi with the square root of the
    end of [-1, 1] the piece touches (`end` "right": `(1-y)^(1/2)`, "left": `(1+y)^(1/2)`)."""
    if m == 0:
        return np.zeros(0), np.zeros(0)
    if shape != "disk":
        return np.polynomial.legendre.leggauss(m)
    alpha, beta = (0.5, 0.0) if end == "right" else (0.0, 0.5)
    import scipy.special  # only for a round light's split pieces: not at import (startup)

    y, w = scipy.special.roots_jacobi(m, alpha, beta)
    return np.asarray(y), np.asarray(w)


def _nearest_kink(theta_i: Array, beta2: Array, half_width: float) -> tuple[Array, Array]:
    """(the kink nearest `theta_i` strictly inside its light interval, as the offset `x` in
    (-1, 1), or 0 where none is; whether one is). The kinks are the lobe weights'
    (`lobe_weight_kinks`) and the hemisphere's edges `+-pi/2`, where `node_angles` clips."""
    hw = jnp.asarray(half_width, theta_i.dtype)
    hw_safe = jnp.where(hw > 0, hw, 1.0)
    edges = jnp.broadcast_to(
        jnp.asarray([-jnp.pi / 2, jnp.pi / 2], theta_i.dtype), (*theta_i.shape, 2)
    )
    kinks = jnp.concatenate([lobe_weight_kinks(beta2), edges], axis=-1)
    x = (kinks - theta_i[..., None]) / hw_safe
    inside = (jnp.abs(x) < 1.0) & (hw > 0)
    dist = jnp.where(inside, jnp.abs(x), jnp.inf)
    j = jnp.argmin(dist, axis=-1)
    k = jnp.take_along_axis(x, j[..., None], axis=-1)[..., 0]
    has = jnp.any(inside, axis=-1)
    return jnp.where(has, k, 0.0), has


SPLIT_SIDE_TOL = 1e-4
"""With an odd node count the longer piece of a split interval gets the extra node; for a kink
within this fraction of the half-width of the middle (`|k| <= SPLIT_SIDE_TOL`) the right-hand
piece always gets it, so that a kink at the middle up to rounding (a light centred on the
horizon, `theta_i = pi/2` in float32 and float64) gets the same rule in every precision (with
`k > 0` alone float32 and float64 put the extra node on opposite sides there: 4% apart;
tests/model/test_properties_extra.py)."""

TINY_DISK_PIECE = 1e-3
"""A disk piece `[-1, k]` with `1 + k` below this keeps its Gauss-Jacobi mass: its exact mass
(a difference of numbers near `pi/4`) would lose its digits, and the cofactor is constant
there to `1e-3` anyway."""


def _exact_disk_pieces(
    kp: Array, x_long: Array, w_long: Array, x_short: Array, w_short: Array
) -> tuple[tuple[Array, Array], tuple[Array, Array]]:
    """Each disk piece's weights scaled to its exact semicircle mass, and a one-node piece's
    node moved to its exact centroid (the one-point Gauss rule of the weight): exact for
    constants and, on one-node pieces, for linear functions. Masses and first moments in
    closed form, `int sqrt(1-x^2) dx = (x sqrt(1-x^2) + asin x) / 2`,
    `int x sqrt(1-x^2) dx = -(1-x^2)^(3/2) / 3`; `kp` in (-1, 0]."""
    exact = (1.0 + kp) > TINY_DISK_PIECE  # the short piece's exact mass is accurate
    root = jnp.sqrt(1.0 - kp * kp)  # > 0: |kp| < 1 where a row is split, 0 elsewhere
    prim = 0.5 * (kp * root + jnp.arcsin(kp))
    moment = root**3 / 3.0  # first moment of [k, 1]; minus that of [-1, k]
    m_long, m_short = jnp.pi / 4 - prim, prim + jnp.pi / 4
    w_long = w_long * m_long / jnp.sum(w_long, axis=-1, keepdims=True)
    scale_short = m_short / jnp.sum(w_short, axis=-1, keepdims=True)
    w_short = w_short * jnp.where(exact, scale_short, 1.0)
    if x_long.shape[-1] == 1:
        x_long = moment / m_long
    if x_short.shape[-1] == 1:
        x_short = jnp.where(exact, -moment / m_short, x_short)
    return (x_long, w_long), (x_short, w_short)


def _split_light_rule(k: Array, n: int, shape: str) -> tuple[Array, Array]:
    """Offsets (..., n) and weights (sum 1) of a light interval [-1, 1] split at `x = k`.

    Each piece has its own Gauss rule, `ceil(n/2)` nodes on the longer piece and `floor(n/2)`
    on the shorter: Gauss-Legendre for a uniform light, and for a disk (weight
    `sqrt(1-x) sqrt(1+x)`) Gauss-Jacobi with the root of the piece's outer end, the other root
    (smooth on that piece) evaluated at the nodes. Built for `k <= 0` (longer piece `[k, 1]`)
    and mirrored where `k > 0` (the weight is even). `|k| < 1`: no division by zero, and the
    roots are of positive numbers (the smooth one's argument is at least `1 + k` resp. 1).
    """
    sgn = jnp.where(k > SPLIT_SIDE_TOL, -1.0, 1.0)
    kp = (sgn * k)[..., None]  # the split in the mirrored frame, <= SPLIT_SIDE_TOL
    y_long, w_long = (
        with_rank(jnp.asarray(a, k.dtype), kp.ndim)
        for a in _piece_rule((n + 1) // 2, shape, "right")
    )
    y_short, w_short = (
        with_rank(jnp.asarray(a, k.dtype), kp.ndim) for a in _piece_rule(n // 2, shape, "left")
    )
    h_long, h_short = 0.5 * (1.0 - kp), 0.5 * (1.0 + kp)
    x_long = kp + h_long * (1.0 + y_long)  # on [k, 1]
    x_short = -1.0 + h_short * (1.0 + y_short)  # on [-1, k]
    if shape == "disk":
        wl = h_long**1.5 * w_long * jnp.sqrt(1.0 + x_long)
        ws = h_short**1.5 * w_short * jnp.sqrt(1.0 - x_short)
        (x_long, wl), (x_short, ws) = _exact_disk_pieces(kp, x_long, wl, x_short, ws)
    else:
        wl, ws = h_long * w_long, h_short * w_short
    x = jnp.concatenate([x_long, x_short], axis=-1)
    w = jnp.concatenate([wl, ws], axis=-1)
    return sgn[..., None] * x, w / jnp.sum(w, axis=-1, keepdims=True)


def light_nodes(
    theta_i: ArrayLike, beta2: ArrayLike, aperture: Aperture | None = None
) -> tuple[Float[Array, "... n_nodes"], Float[Array, "... n_nodes"]]:
    """Angles of incidence and weights (sum 1 per row) at a row's aperture nodes, laid out like
    `Aperture.nodes()` (the light index outer, the viewing index inner: the viewing offsets
    are `nodes()[1]`) and clipped to the hemisphere [conventions §3, §9]. The one home of the
    light's node placement: the sharp and the rounded model, the fit's grid and the synthetic
    data all place their light nodes here.

    Where the light's interval `theta_i +- half_width_i_rad` holds a kink of the lobe weights
    (`lobe_weight_kinks`, or the hemisphere's edge), a rule with the same offsets on every row
    converges like `1 / n^2` (benchmarks/results/aperture.md); there the interval is split at
    the kink (the one nearest `theta_i`) and each piece gets its own Gauss rule
    (`_split_light_rule`). Rows without a kink inside keep `Aperture.nodes()`'s rule. Both use
    `n_nodes` light nodes. Finite values and gradients everywhere, including a half-width of 0
    and a kink exactly at the interval's end (that row keeps the plain rule).
    """
    aperture = aperture or Aperture()
    theta_i, beta2 = same_rank(theta_i, beta2)
    theta_i, beta2 = jnp.broadcast_arrays(theta_i, beta2)
    n = aperture.n_nodes
    _, do, dw = aperture.nodes()  # validates the shape; view offsets and product weights
    if n == 1:
        x, wl = jnp.zeros((*theta_i.shape, 1), theta_i.dtype), jnp.ones_like(theta_i)[..., None]
    else:
        x0, w0 = (
            with_rank(jnp.asarray(a, theta_i.dtype), theta_i.ndim + 1)
            for a in _plain_light_rule(n, aperture.light_shape)
        )
        k, has = _nearest_kink(theta_i, beta2, aperture.half_width_i_rad)
        xs, ws = _split_light_rule(k, n, aperture.light_shape)
        x = jnp.where(has[..., None], xs, x0)
        wl = jnp.where(has[..., None], ws, w0)
    n_view = do.size // n
    wv = with_rank(
        jnp.asarray(np.asarray(dw).reshape(n, n_view).sum(axis=0), theta_i.dtype), wl.ndim + 1
    )
    offsets = jnp.repeat(x * aperture.half_width_i_rad, n_view, axis=-1)
    weights = (wl[..., :, None] * wv).reshape(*wl.shape[:-1], n * n_view)
    return node_angles(theta_i, offsets), weights


def node_angles(
    theta: ArrayLike, offsets: ArrayLike, foreshortened: bool = False
) -> Float[Array, "... n_nodes"]:
    """Angles at the aperture nodes, `theta + offset` on a new last axis, clipped to the
    hemisphere `[-pi/2, pi/2]` (a node beyond grazing sees the horizon) [conventions §1, §9].

    With `foreshortened` (viewing angles of a `foreshortened` aperture), the offsets are the
    spread seen face-on and are scaled by `cos(theta)`: a face of fixed size seen obliquely
    spans a smaller range of angles.

    The one home of that clip: the sharp and the rounded model, the fit's evaluation grid and
    the synthetic data all place their aperture nodes with it.
    """
    theta = jnp.asarray(theta)
    node = with_rank(jnp.asarray(offsets, theta.dtype), theta.ndim + 1)
    if foreshortened:
        node = node * jnp.cos(theta)[..., None]
    half = jnp.pi / 2
    return jnp.clip(theta[..., None] + node, -half, half)


def _aperture_angles(
    theta_i: ArrayLike,
    theta_o: ArrayLike,
    beta2: ArrayLike,
    aperture: Aperture | None,
    view_spread: ArrayLike = 1.0,
) -> tuple[Array, Array, Array]:
    """Angles of incidence (`light_nodes`) and viewing at the aperture nodes (clipped to the
    hemisphere), and the nodes' weights per row; the viewing offsets narrowed by `view_spread`
    (the share of the spread an observation sees)."""
    dtype = jnp.result_type(jnp.asarray(theta_i), jnp.asarray(theta_o))
    aperture = aperture or Aperture()
    _, do, _ = aperture.nodes()
    do = jnp.asarray(do, dtype)
    theta_o = jnp.asarray(theta_o, dtype)
    spread = with_rank(jnp.asarray(view_spread, dtype), theta_o.ndim)[..., None]
    ti, dw = light_nodes(jnp.asarray(theta_i, dtype), jnp.asarray(beta2, dtype), aperture)
    to = node_angles(theta_o, spread * with_rank(do, theta_o.ndim + 1), aperture.foreshortened)
    return ti, to, dw


def view_conversion(theta_o: ArrayLike, theta_o_nodes: ArrayLike) -> Array:
    """`cos(theta_o) / cos(theta_o_node)`, both floored at `COS_THETA_O_FLOOR`: the weight of a
    viewing node's density in an aperture average [conventions §9].

    `radiance` converts a density at the patch centre's `theta_o`; each pixel of a patch
    converts its own at its own angle (`1 / cos(theta_o_node)`). Weighting each node's density
    by this factor makes `radiance(band_density(...), theta_i, theta_o, ...)` the patch's mean
    radiance. 1 at a point aperture. `theta_o` broadcasts against `theta_o_nodes`.
    """
    cos_o = jnp.maximum(jnp.cos(jnp.asarray(theta_o)), COS_THETA_O_FLOOR)
    return cos_o / jnp.maximum(jnp.cos(jnp.asarray(theta_o_nodes)), COS_THETA_O_FLOOR)


def band_ratio(
    theta_i: ArrayLike,
    beta2: ArrayLike,
    n: ArrayLike,
    spectral_weight: ArrayLike,
    aperture: Aperture | None = None,
) -> Float[Array, "n_obs n_nodes 3"]:
    """Reflectance ratio of each lobe, band-averaged, at each aperture node [conventions §4, §8].

    Geometry does not depend on wavelength and the ratio is linear in the Fresnel factors, so
    the Fresnel factors are averaged over the band first. Shapes as in `band_density`.
    """
    theta_i, beta2 = same_rank(theta_i, beta2)
    ti, _, _ = _aperture_angles(theta_i, theta_i, beta2, aperture)
    dtype = ti.dtype
    b2 = jnp.asarray(beta2)[..., None]
    fresnel = lobe_fresnel(ti[..., None], b2[..., None], jnp.asarray(n)[..., None, :])
    band_fresnel = jnp.einsum("ok,onkl->onl", jnp.asarray(spectral_weight, dtype), fresnel)
    return lobe_weights(ti, b2) * band_fresnel


def band_kernel(
    theta_i: ArrayLike,
    theta_o: ArrayLike,
    beta2: ArrayLike,
    sigma: ArrayLike,
    aperture: Aperture | None = None,
    view_spread: ArrayLike = 1.0,
) -> Float[Array, "n_obs n_nodes 3"]:
    """Broadening density (1/rad) of each lobe at each aperture node [conventions §5]."""
    theta_i, theta_o, beta2, sigma = same_rank(theta_i, theta_o, beta2, sigma)
    ti, to, _ = _aperture_angles(theta_i, theta_o, beta2, aperture, view_spread)
    b2 = jnp.asarray(beta2)[..., None]
    return hemisphere_gaussian(
        to[..., None], lobe_directions(ti, b2), jnp.asarray(sigma)[..., None, None]
    )


def band_density(
    theta_i: ArrayLike,
    theta_o: ArrayLike,
    beta2: ArrayLike,
    n: ArrayLike,
    spectral_weight: ArrayLike,
    sigma: ArrayLike,
    aperture: Aperture | None = None,
    view_spread: ArrayLike = 1.0,
) -> Float[Array, " n_obs"]:
    """Band- and aperture-averaged reflectance density (1/rad) for each observation: over the
    viewing nodes, each node's density weighted by `view_conversion`, so that `radiance` at
    `theta_o` gives the patch's mean radiance [conventions §9].

    `theta_i`, `theta_o`, `beta2`, `sigma` have shape `(n_obs,)` (or broadcast to it);
    `n` and `spectral_weight` have shape `(n_obs, n_lambda)`: the index (delta_n included) at
    the wavelength samples the observation's channel sees, and the channel's normalised weights
    there (rows sum to 1; one column with weight 1 is the one-effective-wavelength
    approximation) [conventions §4, §8]. `aperture` (default: a point) averages over the finite
    sizes of light and patch; `view_spread` (per observation, default 1) narrows the patch's
    viewing spread to the share its ROI sees [conventions §9]. Angles in radians
    [conventions §1].
    """
    theta_i, theta_o, beta2, sigma = same_rank(theta_i, theta_o, beta2, sigma)
    ratio = band_ratio(theta_i, beta2, n, spectral_weight, aperture)
    kernel = band_kernel(theta_i, theta_o, beta2, sigma, aperture, view_spread)
    _, to, dw = _aperture_angles(theta_i, theta_o, beta2, aperture, view_spread)
    dw = dw * view_conversion(jnp.asarray(theta_o)[..., None], to)
    return jnp.sum(jnp.sum(ratio * kernel, axis=-1) * dw, axis=-1)


def radiance(
    density: ArrayLike,
    theta_i: ArrayLike,
    theta_o: ArrayLike,
    scale: ArrayLike,
    floor: ArrayLike = 0.0,
) -> Float[Array, " n_obs"]:
    """Relative radiance a camera records from a density [conventions §9].

    `scale * cos(theta_i) * rho / cos(theta_o) + floor * cos(theta_i)`: `scale` is light
    intensity x camera gain x out-of-plane spread, `floor` a Lambertian body reflection. The
    `cos(theta_o)` is floored at `cos(89.9 deg)`.
    """
    density, theta_i, theta_o, scale, floor = same_rank(density, theta_i, theta_o, scale, floor)
    cos_i = jnp.cos(theta_i)
    cos_o = jnp.maximum(jnp.cos(theta_o), COS_THETA_O_FLOOR)
    return scale * cos_i * density / cos_o + floor * cos_i
