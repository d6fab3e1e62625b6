"""Each photo's pixel noise: shot and read noise as a function of the raw level.

A raw pixel at `x` DN above black has the variance `read_var + x / gain` (DN^2): Gaussian read
noise and Poisson shot noise of `x gain` electrons (`gain` electrons per DN; the same for every
colour of the mosaic, a property of the sensor at the photo's ISO). The two numbers are fitted
per photo to the white-noise variances of its ROIs (each channel of each ROI gives its mean
level and the variance of its neighbour differences, `_extract.noise_points`, after any fitted
stripes are removed), so that an ROI's noise part rests on the whole photo rather than on its
own pixels alone (docs/imaging.md §Pixel noise). Textures finer than the Bayer tile raise an
ROI's neighbour differences above the sensor's noise; such points are left out of the fit
(more than `OUTLIER` times the model) and the fit repeated.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

OUTLIER = 1.5
"""Points whose variance exceeds the model by this factor are left out of the fit."""

MIN_POINTS = 3
"""A model needs at least this many (ROI, channel) points."""

MIN_SPREAD = 1.3
"""... and levels spanning at least this factor (else read and shot noise cannot be told apart;
the model is then shot noise alone plus the mean read noise it implies)."""


@dataclass(frozen=True)
class NoiseModel:
    """The pixel noise of one photo: variance `read_var_dn2 + x / gain_e_per_dn` at x DN.

    Attributes:
        read_var_dn2: the read-noise variance (DN^2).
        gain_e_per_dn: electrons per DN (inf: no shot noise seen).
        points: the (level, variance) points the model was fitted to.
        used: how many of them were kept.
    """

    read_var_dn2: float
    gain_e_per_dn: float
    points: int = 0
    used: int = 0

    def variance(self, level_dn: float | np.ndarray) -> float | np.ndarray:
        """The variance (DN^2) of one pixel at `level_dn` DN above black."""
        return self.read_var_dn2 + np.maximum(level_dn, 0.0) / self.gain_e_per_dn

    def variance_of_mean(self, channel: int, sum_w2: float, sum_w2x: float) -> float:
        """The variance of `sum_p w_p x_p` for independent pixels: sum w^2 (read + x / gain),
        given sum_p w_p^2 and sum_p w_p^2 x_p (the pixel's value stands for its level: the
        expectation is the same). `channel` is for the interface: the model is the sensor's,
        the same for every colour."""
        del channel
        return float(self.read_var_dn2 * sum_w2 + max(sum_w2x, 0.0) / self.gain_e_per_dn)


def fit_noise_model(points: Sequence[tuple[int, float, float, float]]) -> NoiseModel | None:
    """`read + x / gain` fitted to (channel, level, variance, pixels) points; None when they do
    not fix it (too few points, or a negative shot-noise slope).

    Weighted least squares with weights pixels / variance^2 (the variance of a variance
    estimate is proportional to variance^2 / pixels), refitted without points more than
    OUTLIER times above the model (texture counted as noise) until none is left out.
    """
    pts = np.array([(lv, var, n) for _, lv, var, n in points if lv > 0 and var > 0 and n > 0])
    if len(pts) < MIN_POINTS:
        return None
    keep = np.ones(len(pts), dtype=bool)
    model = None
    for _ in range(len(pts)):
        if keep.sum() < MIN_POINTS:
            break
        model = _weighted_fit(pts[keep])
        if model is None:
            return None
        expected = model.read_var_dn2 + pts[:, 0] / model.gain_e_per_dn
        new = pts[:, 1] <= OUTLIER * expected
        if np.array_equal(new, keep):
            break
        keep = new
    if model is None:
        return None
    return NoiseModel(model.read_var_dn2, model.gain_e_per_dn, len(pts), int(keep.sum()))


def _weighted_fit(pts: np.ndarray) -> NoiseModel | None:
    """read >= 0 and 1 / gain > 0 by weighted least squares on (level, variance, pixels)."""
    level, var, n = pts[:, 0], pts[:, 1], pts[:, 2]
    w = n / var**2
    if level.max() < MIN_SPREAD * level.min():
        # one level: the variance there, split as shot noise with no read noise
        slope = float(np.sum(w * var * level) / np.sum(w * level * level))
        return NoiseModel(0.0, 1.0 / slope) if slope > 0 else None
    design = np.stack([np.ones_like(level), level], axis=1) * np.sqrt(w)[:, None]
    coef = np.linalg.lstsq(design, var * np.sqrt(w), rcond=None)[0]
    read, slope = float(coef[0]), float(coef[1])
    if read < 0:  # no read noise resolved: shot noise alone
        read = 0.0
        slope = float(np.sum(w * var * level) / np.sum(w * level * level))
    if not slope > 0:
        return None
    return NoiseModel(read, 1.0 / slope if math.isfinite(slope) else math.inf)
