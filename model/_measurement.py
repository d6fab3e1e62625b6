"""From the BRDF to what a camera records: spectral bands, finite apertures, radiance.

[conventions §8, §9]. Everything is evaluated only where the scene needs it: at the observed
angles, and at the wavelength samples each observation's channel sees.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._broadening import hemisphere_gaussian
from ._lobes import lobe_directions, lobe_fresnel, lobe_weights

COS_THETA_O_FLOOR = float(np.cos(np.deg2rad(89.9)))
"""`cos(theta_o)` is floored here in the radiance conversion [conventions §9]."""


class Aperture(NamedTuple):
    """Finite angular extent of the light and of the viewed patch [conventions §9].

    The density is averaged uniformly over `theta_i +- half_width_i_rad` and
    `theta_o +- half_width_o_rad` with `n_nodes` Gauss-Legendre nodes along each (so
    `n_nodes**2` evaluations; `n_nodes = 1` is a point evaluation). A light of diameter `D` at
    distance `d` has `half_width_i = atan(D / 2d)`; a wedge face seen across a length `L` at
    distance `d` spans about `half_width_o = atan(L cos(theta_o) / 2d)`. With `foreshortened`,
    `half_width_o_rad` is that spread seen face-on (`atan(L / 2d)`) and every observation uses
    it times `cos(theta_o)` (`view_offsets`); without, the same spread at every `theta_o`.
    """

    half_width_i_rad: float = 0.0
    half_width_o_rad: float = 0.0
    n_nodes: int = 1
    foreshortened: bool = False

    def nodes(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Offsets in theta_i, offsets in theta_o, and weights (sum 1), each (n_nodes**2,)."""
        if self.n_nodes == 1:
            return np.zeros(1), np.zeros(1), np.ones(1)
        x, w = np.polynomial.legendre.leggauss(self.n_nodes)
        xi, xo = np.meshgrid(x, x, indexing="ij")
        ww = np.outer(w, w) / 4.0
        return (
            (xi * self.half_width_i_rad).ravel(),
            (xo * self.half_width_o_rad).ravel(),
            ww.ravel(),
        )


def view_offsets(aperture: Aperture, theta_o: ArrayLike, offsets: ArrayLike) -> Array:
    """The aperture's viewing-angle offsets at `theta_o` (broadcast): `offsets`, times
    `cos(theta_o)` for a `foreshortened` aperture (a face of fixed size seen obliquely spans a
    smaller range of angles). `theta_o` carries the trailing axes of `offsets`' broadcast."""
    offsets = jnp.asarray(offsets)
    if not aperture.foreshortened:
        return offsets
    return offsets * jnp.cos(jnp.asarray(theta_o))


def _aperture_angles(
    theta_i: ArrayLike, theta_o: ArrayLike, aperture: Aperture | None
) -> tuple[Array, Array, Array]:
    """Angles of incidence and viewing at the aperture nodes (clipped to the hemisphere)."""
    dtype = jnp.result_type(jnp.asarray(theta_i), jnp.asarray(theta_o))
    aperture = aperture or Aperture()
    di, do, dw = (jnp.asarray(a, dtype) for a in aperture.nodes())
    half = jnp.pi / 2
    ti = jnp.clip(jnp.asarray(theta_i)[..., None] + di, -half, half)  # (n_obs, n_nodes)
    to_nominal = jnp.asarray(theta_o)[..., None]
    to = jnp.clip(to_nominal + view_offsets(aperture, to_nominal, do), -half, half)
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
) -> Float[Array, "n_obs n_nodes 3"]:
    """Broadening density (1/rad) of each lobe at each aperture node [conventions §5]."""
    ti, to, _ = _aperture_angles(theta_i, theta_o, aperture)
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
) -> Float[Array, " n_obs"]:
    """Band- and aperture-averaged reflectance density (1/rad) for each observation.

    `theta_i`, `theta_o`, `beta2`, `sigma` have shape `(n_obs,)` (or broadcast to it);
    `n` and `spectral_weight` have shape `(n_obs, n_lambda)`: the index (delta_n included) at
    the wavelength samples the observation's channel sees, and the channel's normalised weights
    there (rows sum to 1; one column with weight 1 is the one-effective-wavelength
    approximation) [conventions §4, §8]. `aperture` (default: a point) averages over the finite
    sizes of light and patch. Angles in radians [conventions §1].
    """
    ratio = band_ratio(theta_i, beta2, n, spectral_weight, aperture)
    kernel = band_kernel(theta_i, theta_o, beta2, sigma, aperture)
    _, _, dw = _aperture_angles(theta_i, theta_o, aperture)
    return jnp.sum(ratio * kernel, axis=-1) @ dw


class BandDerivatives(NamedTuple):
    """`band_density` and its derivatives for each observation [conventions §4, §5, §8].

    `d_sigma` is per radian of a uniform change of `sigma`; `d_delta_n` is with respect to a
    uniform offset added to every entry of `n` (the fitted index offset, conventions §7).
    """

    density: Float[Array, " n_obs"]
    d_sigma: Float[Array, " n_obs"]
    d_delta_n: Float[Array, " n_obs"]


def band_density_derivatives(
    theta_i: ArrayLike,
    theta_o: ArrayLike,
    beta2: ArrayLike,
    n: ArrayLike,
    spectral_weight: ArrayLike,
    sigma: ArrayLike,
    aperture: Aperture | None = None,
) -> BandDerivatives:
    """`band_density` with its derivatives in `sigma` and a uniform index offset, in one pass.

    The density is `sum(ratio * kernel) @ node_weight` over lobes and aperture nodes, where
    only `band_ratio` depends on the index and only `band_kernel` on `sigma`. Each factor is
    differentiated by one forward-mode `jax.jvp` and the product rule combines them, so the
    Fresnel factors, by far the largest part of the work, are evaluated once with their
    derivative instead of once per parameter.
    Arguments as in `band_density`; the result equals `jax.jacfwd` of `band_density` to
    rounding (tests/test_band_derivatives.py).
    """
    n = jnp.asarray(n)
    sigma = jnp.asarray(sigma)
    ratio, d_ratio = jax.jvp(
        lambda nn: band_ratio(theta_i, beta2, nn, spectral_weight, aperture),
        (n,),
        (jnp.ones_like(n),),
    )
    kernel, d_kernel = jax.jvp(
        lambda s: band_kernel(theta_i, theta_o, beta2, s, aperture),
        (sigma,),
        (jnp.ones_like(sigma),),
    )
    _, _, dw = _aperture_angles(theta_i, theta_o, aperture)
    return BandDerivatives(
        density=jnp.sum(ratio * kernel, axis=-1) @ dw,
        d_sigma=jnp.sum(ratio * d_kernel, axis=-1) @ dw,
        d_delta_n=jnp.sum(d_ratio * kernel, axis=-1) @ dw,
    )


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
    cos_i = jnp.cos(jnp.asarray(theta_i))
    cos_o = jnp.maximum(jnp.cos(jnp.asarray(theta_o)), COS_THETA_O_FLOOR)
    return jnp.asarray(scale) * cos_i * jnp.asarray(density) / cos_o + jnp.asarray(floor) * cos_i
