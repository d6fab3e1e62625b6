"""Correlated colour channels: imaging measures it, the fit inflates the errors for it.

A multiplicative texture is shared by R, G and B, so the three means of one ROI err together;
pixel noise is independent per channel. `channel_corr` must tell the two apart, and
`stairfit.commands.fit.channel_inflation` must turn it into `sqrt(1 + (m - 1) rho)`
[docs/fitting.md].
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from stairfit import imaging
from stairfit.commands.fit import channel_inflation
from stairfit.imaging import synthetic

EXPOSURE = imaging.Exposure(exposure_time_s=1 / 50, f_number=4.0, iso=400)
FACES = {"a": [(40, 40), (359, 40), (359, 359), (40, 359)]}


def _corr(tmp_path: Path, texture: float, seed: int) -> float:
    photo = synthetic.render_photo(
        (400, 400),
        FACES,
        {"a": np.array([2000.0, 3000.0, 2500.0]) * EXPOSURE.scale},
        EXPOSURE,
        background=np.full(3, 500.0) * EXPOSURE.scale,
        texture_amplitude=texture,
        texture_sigma_px=1.5,
        vignetting=0.0,
        seed=seed,
    )
    frame = imaging.decode_raw(photo.write_dng(tmp_path / f"t{texture}_{seed}.dng"))
    rows = imaging.measure_frame(
        frame, imaging.PhotoSpec(tmp_path / "x.dng", rois=FACES), imaging.ExtractionSettings()
    ).rows
    values = {r.channel_corr for r in rows}
    assert len(values) == 1, "the three rows of one ROI carry the same correlation"
    return values.pop()


def test_texture_makes_channels_correlated(tmp_path: Path) -> None:
    """5% texture (far above the shot noise) -> correlation near 1."""
    rho = np.mean([_corr(tmp_path, 0.05, s) for s in range(3)])
    assert rho > 0.8


def test_pixel_noise_alone_leaves_channels_independent(tmp_path: Path) -> None:
    """No texture: only independent shot and read noise -> correlation near 0."""
    rho = np.mean([_corr(tmp_path, 0.0, s) for s in range(3)])
    assert rho < 0.2


class _Row:
    def __init__(self, photo: str, wedge: str, rho: float, flag: str = "") -> None:
        self.photo, self.wedge, self.channel_corr, self.flag = photo, wedge, rho, flag
        self.value, self.stderr = 1.0, 0.1


def test_inflation_is_exact_for_equicorrelated_channels() -> None:
    """sqrt(1 + (m - 1) rho): the variance of the channel mean of m equicorrelated values."""
    rows = [_Row("p", "w", 0.5) for _ in range(3)] + [_Row("p", "v", float("nan"))] * 3
    rows += [_Row("q", "w", 0.9), _Row("q", "w", 0.9, flag="saturated"), _Row("q", "w", 0.9)]
    f = channel_inflation(rows)
    assert f[("p", "w")] == pytest.approx(np.sqrt(2.0))
    assert f[("p", "v")] == 1.0  # unknown correlation: no inflation
    assert f[("q", "w")] == pytest.approx(np.sqrt(1.9))  # two usable channels
    # the same number from the covariance matrix directly
    cov = 0.5 * np.ones((3, 3)) + 0.5 * np.eye(3)
    var_mean = np.ones(3) @ cov @ np.ones(3) / 9
    assert f[("p", "w")] ** 2 / 3 == pytest.approx(var_mean)
