"""Correlated colour channels: imaging measures it, the fit whitens each ROI with it.

A multiplicative texture is shared by R, G and B, so the three means of one ROI err together;
pixel noise is independent per channel. `channel_corr` must tell the two apart, and
`stairfit.pipeline.roi_correlations` must hand the ROI's `corr_*` to the fit (docs/fitting.md
§Correlated channels; the whitening itself: tests/fitting/test_whiten.py).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from stairfit import imaging
from stairfit.imaging import synthetic
from stairfit.pipeline import roi_correlations

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
    def __init__(self, rg: float, rb: float, gb: float) -> None:
        self.corr_rg, self.corr_rb, self.corr_gb = rg, rb, gb


def test_roi_correlations_map_rgb_pairs_to_channel_indices() -> None:
    """R, G, B are channels 0, 1, 2: (R, G) -> corr_01, (R, B) -> corr_02, (G, B) -> corr_12;
    an unknown (NaN) correlation is 0 (independent), values are kept within [-1, 1]."""
    assert roi_correlations(_Row(0.9, 0.8, -0.7)) == {
        "corr_01": 0.9, "corr_02": 0.8, "corr_12": -0.7,
    }  # fmt: skip
    assert roi_correlations(_Row(float("nan"), 1.0 + 1e-12, -0.2)) == {
        "corr_01": 0.0, "corr_02": 1.0, "corr_12": -0.2,
    }  # fmt: skip
