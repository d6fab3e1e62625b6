"""Importance sampling of the staircase's reflectance: a mixture of its three lobes and a cosine
hemisphere, with the exact density of the mixture (so that an estimator weighting each sample
by value / density is unbiased whatever the mixture's fit to the value).

Directions are drawn in the coordinates of conventions §11: the projected angle `theta'` across
the layer lines and the component `t` along them, in which `d omega = d theta' d t` exactly, so
a density in `(theta', t)` is a density per steradian. Each lobe draws `theta'` and `t`
independently from a Student's t with two degrees of freedom (the heavy-tailed slope marginal of
GGX, conventions §12) truncated to `[-90, 90] deg` and `[-1, 1]`, about the lobe's direction of
conventions §3 (`theta_o = theta_i + 2 beta2` for the tread, `theta_i - 2 beta1` for the riser,
`-theta_i` for the two-bounce path; `t_o = -t_i`, docs/model.md §7.1). The cosine hemisphere
covers the body, the rounded edges' broad lobes and the tails.

`given` is the direction the density is conditioned on: the viewer (Mitsuba's `si.wi` in its
radiance mode) when the light is drawn (`draw="light"`), or the light when the viewer is.
"""

from __future__ import annotations

import functools

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ._material import Material, clamp_beta2_deg

COSINE_SHARE = 0.25
"""The cosine hemisphere's share of the mixture (before the lobes' weights are normalised)."""
MIN_SCALE = 0.02
"""The smallest spread (rad, and in `t`) of a lobe's proposal, for nearly sharp facets."""


def _student_cdf(x: NDArray) -> NDArray:
    return 0.5 + x / (2.0 * np.sqrt(2.0 + x * x))


def _student_quantile(u: NDArray) -> NDArray:
    y = np.clip(2.0 * u - 1.0, -1.0 + 1e-15, 1.0 - 1e-15)
    return y * np.sqrt(2.0 / (1.0 - y * y))


def _student_pdf(x: NDArray) -> NDArray:
    return (2.0 + x * x) ** -1.5


def _truncated(centre: NDArray, scale: NDArray, lo: float, hi: float) -> tuple[NDArray, NDArray]:
    """`(F(a), F(b) - F(a))` of the standardised bounds of a truncated Student's t."""
    fa = _student_cdf((lo - centre) / scale)
    fb = _student_cdf((hi - centre) / scale)
    return fa, np.maximum(fb - fa, 1e-300)


def _split(w: NDArray, draw: str) -> tuple[NDArray, NDArray]:
    """`(theta', t)` of unit vectors: the light's projected incidence angle
    (`atan2(-x, z)`) or the viewer's (`atan2(x, z)`) [conventions §11]."""
    sign = -1.0 if draw == "light" else 1.0
    return np.arctan2(sign * w[..., 0], np.maximum(w[..., 2], 0.0)), w[..., 1]


def _join(theta: NDArray, t: NDArray, draw: str) -> NDArray:
    sign = -1.0 if draw == "light" else 1.0
    c = np.sqrt(np.clip(1.0 - t * t, 0.0, 1.0))
    return np.stack([sign * c * np.sin(theta), t, c * np.cos(theta)], axis=-1)


class Mixture:
    """The mixture for one material, wedge angle and conditioning direction(s)."""

    def __init__(self, material: Material, beta2_deg: ArrayLike, given: NDArray, draw: str):
        if draw not in ("light", "view"):
            raise ValueError(f"draw {draw!r}: 'light' or 'view'")
        b = np.radians(clamp_beta2_deg(beta2_deg))
        given = np.asarray(given, float)
        b = np.broadcast_to(b, given.shape[:-1])
        other = "view" if draw == "light" else "light"
        theta_g, t_g = _split(given, other)
        beta1 = np.pi / 2 - b
        if draw == "light":  # the light that each lobe sends to the viewer
            centres = np.stack([theta_g - 2 * b, theta_g + 2 * beta1, -theta_g], axis=-1)
            lit = centres
        else:  # where each lobe sends the given light
            centres = np.stack([theta_g + 2 * b, theta_g - 2 * beta1, -theta_g], axis=-1)
            lit = np.repeat(theta_g[..., None], 3, axis=-1)
        ok = np.abs(lit) < np.pi / 2
        weights = _lobe_weights(np.where(ok, lit, 0.0), np.repeat(b[..., None], 3, axis=-1))
        weights = np.where(ok & (np.abs(centres) < np.pi / 2 + 0.3), weights, 0.0)
        width = material.model_width(np.degrees(b))
        spread = width if material.kernel == "gaussian" else 2.0 * width
        self.scale = np.maximum(spread, MIN_SCALE)[..., None] * np.array([1.0, 1.0, 1.4])
        all_w = np.concatenate([weights, np.full((*weights.shape[:-1], 1), COSINE_SHARE)], -1)
        self.weights = all_w / all_w.sum(axis=-1, keepdims=True)
        self.centre = np.clip(centres, -np.pi / 2, np.pi / 2)
        self.t_centre = -t_g
        self.draw = draw

    def sample(self, u_choice: NDArray, u: NDArray) -> tuple[NDArray, NDArray]:
        """Directions `(..., 3)` and their densities (1/sr) from uniform variates `u_choice`
        `(...)` (which component) and `u` `(..., 2)`."""
        cdf = np.cumsum(self.weights, axis=-1)
        k = np.minimum(np.sum(u_choice[..., None] > cdf, axis=-1), 3)
        lobe = np.minimum(k, 2)
        centre = np.take_along_axis(self.centre, lobe[..., None], -1)[..., 0]
        scale = np.take_along_axis(self.scale, lobe[..., None], -1)[..., 0]
        fa, mass = _truncated(centre, scale, -np.pi / 2, np.pi / 2)
        theta = centre + scale * _student_quantile(fa + u[..., 0] * mass)
        ga, tmass = _truncated(self.t_centre, scale, -1.0, 1.0)
        t = self.t_centre + scale * _student_quantile(ga + u[..., 1] * tmass)
        lobe_dir = _join(np.clip(theta, -np.pi / 2, np.pi / 2), np.clip(t, -1.0, 1.0), self.draw)
        r = np.sqrt(u[..., 0])
        phi = 2.0 * np.pi * u[..., 1]
        cos_dir = np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(1.0 - r * r)], axis=-1)
        out = np.where((k == 3)[..., None], cos_dir, lobe_dir)
        return out, self.pdf(out)

    def pdf(self, w: NDArray) -> NDArray:
        """The mixture's density (1/sr) of directions `w` `(..., 3)`, 0 below the surface."""
        w = np.asarray(w, float)
        theta, t = _split(w, self.draw)
        up = w[..., 2] > 0.0
        _, mass = _truncated(self.centre, self.scale, -np.pi / 2, np.pi / 2)
        _, tmass = _truncated(self.t_centre[..., None], self.scale, -1.0, 1.0)
        p_theta = _student_pdf((theta[..., None] - self.centre) / self.scale) / (self.scale * mass)
        p_t = _student_pdf((t[..., None] - self.t_centre[..., None]) / self.scale) / (
            self.scale * tmass
        )
        lobes = np.sum(self.weights[..., :3] * p_theta * p_t, axis=-1)
        cosine = self.weights[..., 3] * np.maximum(w[..., 2], 0.0) / np.pi
        return np.where(up, lobes + cosine, 0.0)


@functools.cache
def _weights_program():
    import jax

    from stairfit import model

    def f(theta, beta2):  # noqa: ANN001
        w = model.lobe_weights(theta, beta2)  # (..., 3 lights, 3 lobes)
        return w[..., 0, 0], w[..., 1, 1], w[..., 2, 2]

    return jax.jit(f)


def _lobe_weights(theta: NDArray, beta2: NDArray) -> NDArray:
    """The sharp staircase's geometric weight of lobe k for light at `theta[..., k]`
    (`stairfit.model.lobe_weights`, conventions §3): `(..., 3)`."""
    import jax

    with jax.enable_x64(True):
        out = _weights_program()(np.asarray(theta, float), np.asarray(beta2, float))
    return np.stack([np.asarray(o) for o in out], axis=-1)
