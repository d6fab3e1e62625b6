"""Synthetic observations from known parameters: for tests, the demo and calibration studies.

The generator evaluates `stairfit.model` directly (`band_density` + `radiance`, or the
rounded-edge model), not the fitting layer's own forward, so that a fit recovering the truth
also checks the fitting layer's transforms and bookkeeping [conventions §1, §8, §9].
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from stairfit import model

from ._errors import FitInputError
from ._forward import Resolution, light_nodes, resolution_parts
from ._observations import Observations, Spectral
from ._params import Params, clamp_index

STANDARD_WEDGES_DEG: tuple[float, ...] = (10.0, 20.0, 30.0, 40.0, 45.0, 60.0)
"""The paper's six wedges (Pranovich et al. 2020, Fig. 9)."""


class Design(NamedTuple):
    """What a synthetic scene measures.

    `wedge_deg`: wedge angles `beta2` [conventions §2]; `layer_um`: layer thickness;
    `theta_i_deg`, `theta_o_deg`: one entry per photo, in the wedge-face frame
    [conventions §1] (every wedge of a photo is seen at the same angles); `channels`: the
    channel indices of the spectral setup measured in every photo.
    """

    wedge_deg: tuple[float, ...]
    theta_i_deg: tuple[float, ...]
    theta_o_deg: tuple[float, ...]
    layer_um: float = 150.0
    channels: tuple[int, ...] = (0, 1, 2)


def standard_design(
    theta_i_deg: float = 20.0,
    n_views: int = 19,
    view_range_deg: tuple[float, float] = (-81.0, 81.0),
    wedge_deg: Sequence[float] = STANDARD_WEDGES_DEG,
    layer_um: float = 150.0,
    channels: Sequence[int] = (0, 1, 2),
) -> Design:
    """The standard scene: 6 wedges (10-60 deg) x 19 viewing angles x 3 channels.

    The light is fixed (`theta_i_deg` in the face frame for every photo); the photos view at
    `n_views` angles evenly spaced over `view_range_deg` (-81 to 81 deg every 9 deg by default;
    exactly grazing views are left out because `cos(theta_o)` is floored there
    [conventions §9]).
    """
    views = np.linspace(view_range_deg[0], view_range_deg[1], n_views)
    return Design(
        wedge_deg=tuple(float(w) for w in wedge_deg),
        theta_i_deg=tuple(float(theta_i_deg) for _ in views),
        theta_o_deg=tuple(float(v) for v in views),
        layer_um=float(layer_um),
        channels=tuple(int(c) for c in channels),
    )


class Noise(NamedTuple):
    """Gaussian measurement noise: `stderr = sqrt((relative * value)^2 + absolute^2)`.

    `absolute = None` means `1e-3 x` the largest noiseless value of the scene (a camera's noise
    floor); the row's `stderr` is reported exactly, and `value = truth + stderr * N(0, 1)`.
    """

    relative: float = 0.02
    absolute: float | None = None


def model_radiance(
    params: Params,
    observations: Observations,
    spectral: Spectral,
    *,
    aperture: model.Aperture | None = None,
    resolution: int | Resolution | None = None,
) -> np.ndarray:
    """Model relative radiance at every row of `observations` for physical `params`.

    `band_density` + `radiance` of `stairfit.model` [conventions §8, §9], or the rounded-edge
    model when `params.edge_radius_um > 0`, the filleted model (`stairfit.model.brdf_filleted`,
    docs/rounded.md §11) when `params.fillet_radius_um > 0` (micrometres, `r + r_f <=
    min(l1, l2)` on every row's wedge, else a one-line ValueError from
    `stairfit.model.check_fillet_radius`). Evaluated at every row, used or not. `resolution`:
    the rounded model's, or a `Resolution` (also the fillet correction's rays).
    """
    obs = observations
    resolution, fillet_rays = resolution_parts(resolution)
    sigma = params.sigma_per_wedge(obs.n_wedges)[obs.wedge_index]
    n = clamp_index(np.asarray(spectral.n_base)[obs.channel_index] + params.delta_n)
    w = np.asarray(spectral.weights)[obs.channel_index]
    ti, to = jnp.asarray(obs.theta_i_rad), jnp.asarray(obs.theta_o_rad)
    if float(params.fillet_radius_um) > 0.0:
        dens = _filleted_rows(params, obs, n, w, sigma, aperture, resolution, fillet_rays)
    elif float(params.edge_radius_um) > 0.0:
        dens = _rounded_rows(params, obs, n, w, sigma, aperture, resolution)
    else:
        dens = _band_density(
            ti, to, jnp.asarray(obs.beta2_rad), n, w, sigma, aperture, obs.view_spread
        )
    return np.asarray(model.radiance(dens, ti, to, params.scale, params.floor))


def _rounded_rows(
    params: Params,
    obs: Observations,
    n: Array,
    w: np.ndarray,
    sigma: np.ndarray,
    aperture: model.Aperture | None,
    resolution: int | None,
) -> np.ndarray:
    """Rounded-model band density per row, straight from `stairfit.model.brdf_rounded`."""
    ap = aperture or model.Aperture()
    _, do, _ = ap.nodes()
    ti, dw = light_nodes(obs.theta_i_rad, obs.beta2_rad, ap)  # (N, M) each
    ti = ti[..., None]  # (N, M, 1)
    spread = np.asarray(obs.view_spread)[:, None] * do  # the ROI's share of the view spread
    to = model.node_angles(obs.theta_o_rad, spread, ap.foreshortened)[..., None]
    res = model.ROUNDED_RESOLUTION if resolution is None else resolution
    r = float(params.edge_radius_um)
    model.check_edge_radius(obs.beta2_rad, obs.layer_um, r)  # a one-line ValueError (not in jit)
    rho = _brdf_rounded(
        ti,
        to,
        obs.beta2_rad[:, None, None],
        n[:, None, :],
        sigma[:, None, None],
        obs.layer_um[:, None, None],
        r,
        res,
    )  # (N, M, K)
    dw = np.asarray(dw) * np.asarray(model.view_conversion(obs.theta_o_rad[:, None], to[..., 0]))
    return np.einsum("nk,nmk,nm->n", w, np.asarray(rho), dw)


def _filleted_rows(
    params: Params,
    obs: Observations,
    n: Array,
    w: np.ndarray,
    sigma: np.ndarray,
    aperture: model.Aperture | None,
    resolution: int | None,
    fillet_rays: int | None = None,
) -> np.ndarray:
    """Filleted-model band density per row, straight from `stairfit.model.brdf_filleted`:
    the rays are traced once per distinct (theta_i node, wedge, layer) (`fillet_geometry`),
    each row then finishes with `brdf_filleted_from_geometry` at its views, index and width."""
    ap = aperture or model.Aperture()
    _, do, _ = ap.nodes()
    ti, dw = light_nodes(obs.theta_i_rad, obs.beta2_rad, ap)  # (N, M) each
    spread = np.asarray(obs.view_spread)[:, None] * do
    to = np.asarray(model.node_angles(obs.theta_o_rad, spread, ap.foreshortened))  # (N, M)
    dw = np.asarray(dw) * np.asarray(model.view_conversion(obs.theta_o_rad[:, None], to))
    res = model.ROUNDED_RESOLUTION if resolution is None else resolution
    keys = np.stack([obs.theta_i_rad, obs.beta2_rad, obs.layer_um], axis=1)
    _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.ravel()
    r, rf = float(params.edge_radius_um), float(params.fillet_radius_um)
    model.check_fillet_radius(obs.beta2_rad, obs.layer_um, r, rf)  # a one-line ValueError
    geo = _fillet_geometry(
        jnp.asarray(ti)[first][:, :, None, None],
        obs.beta2_rad[first][:, None, None, None],
        obs.layer_um[first][:, None, None, None],
        r,
        rf,
        res,
        model.FILLET_RAYS if fillet_rays is None else fillet_rays,
    )  # (G, M, 1, 1): one geometry per distinct row geometry and light node
    out = np.zeros(obs.n_rows)
    for g in range(first.size):
        rows = np.flatnonzero(inverse == g)
        geo_g = jax.tree_util.tree_map(lambda a, g=g: a[g], geo)
        rho = _filleted_from_geometry(
            geo_g, to[rows].T[:, :, None], jnp.asarray(n)[rows][None], sigma[rows][None, :, None]
        )  # (M, rows, K)
        out[rows] = np.einsum("nk,mnk,nm->n", w[rows], np.asarray(rho), np.asarray(dw)[rows])
    return out


_band_density = jax.jit(model.band_density, static_argnums=6)
"""`stairfit.model.band_density` as one compiled program per aperture (evaluated op by op it
dispatched about 60 small programs, e.g. in every fit's accuracy check)."""
_brdf_rounded = jax.jit(
    lambda ti, to, b, n, sigma, l1, r, res: model.brdf_rounded(
        ti, to, b, n, sigma, l1, r, resolution=res
    ),
    static_argnums=7,
)
"""`stairfit.model.brdf_rounded` as one compiled program: evaluated op by op it compiled about
500 small programs on a new scene (tens of seconds of a forced rounded fit's accuracy check)."""
_fillet_geometry = jax.jit(
    lambda ti, b, l1, r, rf, res, rays: model.fillet_geometry(
        ti, b, l1, r, rf, resolution=res, rays=rays
    ),
    static_argnums=(5, 6),
)
_filleted_from_geometry = jax.jit(model.brdf_filleted_from_geometry)


def design_observations(design: Design) -> Observations:
    """The noiseless table skeleton of a design (value 0, stderr 1), one row per
    photo x wedge x channel."""
    n_photos = len(design.theta_o_deg)
    if len(design.theta_i_deg) != n_photos:
        raise FitInputError("design: theta_i_deg and theta_o_deg need one entry per photo")
    photo, wedge, chan = np.meshgrid(
        np.arange(n_photos),
        np.arange(len(design.wedge_deg)),
        np.arange(len(design.channels)),
        indexing="ij",
    )
    photo, wedge, chan = photo.ravel(), wedge.ravel(), chan.ravel()
    return Observations.from_arrays(
        theta_i_rad=np.deg2rad(np.asarray(design.theta_i_deg))[photo],
        theta_o_rad=np.deg2rad(np.asarray(design.theta_o_deg))[photo],
        beta2_rad=np.deg2rad(np.asarray(design.wedge_deg))[wedge],
        layer_um=np.full(photo.size, design.layer_um),
        wedge_index=wedge,
        channel_index=np.asarray(design.channels)[chan],
        value=np.zeros(photo.size),
        stderr=np.ones(photo.size),
        photo_index=photo,
    )


def simulate_observations(
    truth: Params,
    design: Design,
    spectral: Spectral,
    noise: Noise | None = None,
    seed: int = 0,
    *,
    aperture: model.Aperture | None = None,
    resolution: int | None = None,
) -> Observations:
    """Synthetic measurements: the model at `truth` plus Gaussian noise with the stated stderr.

    Deterministic for a given `seed` (a `numpy.random.Generator`); `noise` defaults to
    `Noise()` (2% relative). The returned table is validated like measured data.
    """
    noise = noise or Noise()
    skeleton = design_observations(design)
    clean = model_radiance(truth, skeleton, spectral, aperture=aperture, resolution=resolution)
    absolute = 1e-3 * float(np.max(np.abs(clean))) if noise.absolute is None else noise.absolute
    stderr = np.sqrt((noise.relative * clean) ** 2 + absolute**2)
    if not np.all(stderr > 0):
        raise FitInputError("noise: relative and absolute are both zero; give a positive noise")
    rng = np.random.default_rng(seed)
    value = clean + stderr * rng.standard_normal(clean.shape)
    return Observations.from_arrays(**{**skeleton._asdict(), "value": value, "stderr": stderr})
