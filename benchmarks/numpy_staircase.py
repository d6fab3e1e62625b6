"""A plain, vectorised NumPy implementation of the sharp broadened staircase model.

The baseline that the benchmarks compare JAX against: the same formulas as `stairfit.model`
(paper Eqs. 2-8, conventions §1-§6, §9), written the way one would without JAX. It has no
derivatives, so baselines differentiate it by finite differences. Degrees never appear here.
"""

from __future__ import annotations

import numpy as np
from scipy.special import erf

HALF_PI = np.pi / 2


def fresnel_sp(c: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """s and p power reflectance at local incidence cosine `c` (real n > 1)."""
    c = np.clip(c, 0.0, 1.0)
    n2 = n * n
    s = np.sqrt(n2 - 1.0 + c * c)
    return ((c - s) / (c + s)) ** 2, ((n2 * c - s) / (n2 * c + s)) ** 2


def lobe_geometry(theta_i: np.ndarray, beta2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(directions, weights), each (..., 3) in the lobe order tread, riser, retro."""
    u = beta2 + theta_i
    su, cu = np.sin(u), np.cos(u)
    sb, cb = np.sin(beta2), np.cos(beta2)
    p_r = sb * np.maximum(su, 0) + cb * np.minimum(cu, 0)
    p_t = cb * np.maximum(cu, 0) + sb * np.minimum(su, 0)
    both = (p_r > 0) & (p_t > 0)
    tot = np.where(both, p_r + p_t, 1.0)
    m = np.minimum(p_r, p_t)
    a = u < np.pi / 4
    w_t = np.where(both, (p_t - m) / tot, np.where(a, 1.0, 0.0))
    w_r = np.where(both, (p_r - m) / tot, np.where(a, 0.0, 1.0))
    w_x = np.where(both, 2 * m / tot, 0.0)
    direc = np.stack([theta_i + 2 * beta2, theta_i - 2 * (HALF_PI - beta2), -theta_i], axis=-1)
    return direc, np.stack([w_t, w_r, w_x], axis=-1)


def lobe_fresnel(theta_i: np.ndarray, beta2: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Unpolarised Fresnel factor of each lobe, (..., 3); retro per polarisation product."""
    u = beta2 + theta_i
    ts, tp = fresnel_sp(np.cos(u), n)
    rs, rp = fresnel_sp(np.sin(u), n)
    return np.stack([0.5 * (ts + tp), 0.5 * (rs + rp), 0.5 * (ts * rs + tp * rp)], axis=-1)


def lobes(theta_i: np.ndarray, beta2: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(directions, ratios), each (..., 3) in the lobe order tread, riser, retro."""
    direc, weight = lobe_geometry(theta_i, beta2)
    return direc, weight * lobe_fresnel(theta_i, beta2, n)


def kernel(theta_o: np.ndarray, direc: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """Hemisphere-truncated, renormalised Gaussian of each lobe at theta_o, (..., 3)."""
    mu = np.clip(direc, -HALF_PI, HALF_PI)
    sig = np.asarray(sigma)[..., None]
    r2s = np.sqrt(2.0) * sig
    mass = 0.5 * (erf((HALF_PI - mu) / r2s) - erf((-HALF_PI - mu) / r2s))
    z = (np.asarray(theta_o)[..., None] - mu) / sig
    g = np.exp(-0.5 * z * z) / (np.sqrt(2 * np.pi) * sig * mass)
    return np.where(np.abs(np.asarray(theta_o))[..., None] <= HALF_PI, g, 0.0)


def brdf(
    theta_i: np.ndarray, theta_o: np.ndarray, beta2: np.ndarray, n: np.ndarray, sigma: np.ndarray
) -> np.ndarray:
    """Broadened in-plane reflectance density (1/rad), hemisphere-truncated Gaussians."""
    direc, ratio = lobes(theta_i, beta2, n)
    return np.sum(ratio * kernel(theta_o, direc, sigma), axis=-1)


def band_radiance(
    theta_i: np.ndarray,
    theta_o: np.ndarray,
    beta2: np.ndarray,
    n: np.ndarray,
    spectral_weight: np.ndarray,
    sigma: float,
    scale: float,
    floor: float = 0.0,
) -> np.ndarray:
    """Relative radiance per observation (conventions §9), bands as (n_obs, n_lambda) arrays.

    The same algorithm as `stairfit.model.band_density`: the lobe geometry and the broadening
    once per observation, the Fresnel factors averaged over the band first.
    """
    direc, weight = lobe_geometry(theta_i, beta2)
    fres = lobe_fresnel(theta_i[:, None], beta2[:, None], n)  # (n_obs, n_lambda, 3)
    band_fres = np.einsum("ok,okl->ol", spectral_weight, fres)
    dens = np.sum(weight * band_fres * kernel(theta_o, direc, sigma), axis=-1)
    cos_i = np.cos(theta_i)
    cos_o = np.maximum(np.cos(theta_o), np.cos(np.deg2rad(89.9)))
    return scale * cos_i * dens / cos_o + floor * cos_i
