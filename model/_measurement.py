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
from ._lobes import lobe_directions, lobe_fresnel, lobe_weights
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
        xl, wl = x, w
        if self.light_shape == "disk":
            k = np.arange(1, self.n_nodes + 1)
            xl, wl = (
                np.cos(k * np.pi / (self.n_nodes + 1)),
                np.sin(k * np.pi / (self.n_nodes + 1)) ** 2,
            )
        xi, xo = np.meshgrid(xl, x, indexing="ij")
        ww = np.outer(wl / wl.sum(), w / w.sum())
        return (
            (xi * self.half_width_i_rad).ravel(),
            (xo * self.half_width_o_rad).ravel(),
            ww.ravel(),
        )


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
    aperture: Aperture | None,
    view_spread: ArrayLike = 1.0,
) -> tuple[Array, Array, Array]:
    """Angles of incidence and viewing at the aperture nodes (clipped to the hemisphere); the
    viewing offsets narrowed by `view_spread` (the share of the spread an observation sees)."""
    dtype = jnp.result_type(jnp.asarray(theta_i), jnp.asarray(theta_o))
    aperture = aperture or Aperture()
    di, do, dw = (jnp.asarray(a, dtype) for a in aperture.nodes())
    theta_o = jnp.asarray(theta_o, dtype)
    spread = with_rank(jnp.asarray(view_spread, dtype), theta_o.ndim)[..., None]
    ti = node_angles(jnp.asarray(theta_i, dtype), di)  # (n_obs, n_nodes)
    to = node_angles(theta_o, spread * with_rank(do, theta_o.ndim + 1), aperture.foreshortened)
    return ti, to, dw


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
    ti, _, _ = _aperture_angles(theta_i, theta_i, aperture)
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
    ti, to, _ = _aperture_angles(theta_i, theta_o, aperture, view_spread)
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
    """Band- and aperture-averaged reflectance density (1/rad) for each observation.

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
    _, _, dw = _aperture_angles(theta_i, theta_o, aperture)
    return jnp.sum(ratio * kernel, axis=-1) @ dw


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
