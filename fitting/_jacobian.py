"""Derivatives of the model radiance with respect to physical parameters (design studies).

For a notebook's question "which photo would teach the most": the Jacobian of the fitted
model at any rows, in physical units, by forward-mode autodiff of the fit's own forward model
(`_forward`), so that it is exactly the derivative the fit's covariance is built from; the
Fisher information of those rows is then `fisher_information(J, sd)` [conventions §9].
"""

from __future__ import annotations

from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from stairfit import model

from ._errors import FitInputError
from ._forward import model_values
from ._observations import Observations, Spectral
from ._params import PARAM_NAMES, Params
from ._problem import FreeSpec, prepare

ParameterKey = tuple[str, int | None]
"""A parameter's identity: `(param, wedge)`, e.g. `("delta_n", None)`, `("sigma_rad", 2)`."""


def _spec(params: Params, keys: Sequence[ParameterKey], n_wedges: int) -> FreeSpec:
    """The free set that makes exactly `keys` free around `params`: with widths given one per
    wedge, every wedge keeps its own width (the requested ones free, the others pinned)."""
    names = {p for p, _ in keys}
    unknown = names - set(PARAM_NAMES)
    if unknown:
        raise FitInputError(f"unknown parameter(s) {sorted(unknown)}; known: {PARAM_NAMES}")
    if np.ndim(params.sigma_rad) == 0:
        return FreeSpec(free=frozenset(names))
    sigma = params.sigma_per_wedge(n_wedges)
    wanted = {w for p, w in keys if p == "sigma_rad" and w is not None}
    pinned = tuple((w, float(sigma[w])) for w in range(n_wedges) if w not in wanted)
    return FreeSpec(frozenset(names), frozenset(range(n_wedges)), (), pinned)


def model_jacobian(
    params: Params,
    observations: Observations,
    spectral: Spectral,
    parameters: Sequence[ParameterKey],
    *,
    aperture: model.Aperture | None = None,
    resolution: int | None = None,
) -> np.ndarray:
    """`d(model radiance) / d(parameter)` at every row of `observations`, `(n_rows, p)`, in the
    physical units of each parameter (per radian for a width) [conventions §9].

    `params` holds every parameter's value (widths one per wedge, or one shared); `parameters`
    lists `(param, wedge)` keys in the column order wanted (`wedge` None except for a wedge's
    own width when `params.sigma_rad` has one per wedge). The model is the fit's forward model
    (sharp, or rounded when `edge_radius_um` is non-zero or asked for); `model_error_frac`
    changes the variance, not the model, so its column is zero. Needs float64.
    """
    problem = prepare(observations, spectral, fixed=params, aperture=aperture,
                      resolution=resolution)  # fmt: skip
    lay = problem.layout
    spec = _spec(params, parameters, lay.n_wedges)
    static = problem.static_for(spec)  # the forward (sharp or rounded) the fit would use
    # Every slot fixed at its physical value; the derivative is taken in those values (no
    # transform: exact at bounds too, e.g. an edge radius of 0).
    data = problem.arrays_for(spec)
    data = data._replace(free=jnp.zeros_like(data.free))

    def radiance(x: jax.Array) -> jax.Array:
        return model_values(jnp.zeros_like(x), static, data._replace(x_fixed=x))[0]

    jac = jax.jit(jax.jacfwd(radiance))(data.x_fixed)
    return np.asarray(jac)[:, [lay.slot(p, w) for p, w in parameters]]
