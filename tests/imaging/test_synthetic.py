"""The synthetic RAW generator (issue 3), checked on its mosaic directly, not via the decoder."""

from __future__ import annotations

import numpy as np
import pytest

from stairfit import imaging
from stairfit.imaging import synthetic

EXPOSURE = imaging.Exposure(exposure_time_s=1 / 50, f_number=4.0, iso=400)
FACE = {"flat": [(100, 100), (299, 100), (299, 299), (100, 299)]}
BLOCK = (slice(110, 290), slice(110, 290))  # well inside the face, even offsets


def _render(**kw) -> synthetic.SyntheticPhoto:
    args = {
        "background": np.full(3, 500.0) * EXPOSURE.scale,
        "texture_amplitude": 0.0,
        "vignetting": 0.0,
        "seed": 1,
    }
    args.update(kw)
    radiance = args.pop("radiance", {"flat": np.array([1000.0, 3000.0, 2000.0]) * EXPOSURE.scale})
    return synthetic.render_photo((400, 400), FACE, radiance, EXPOSURE, **args)


def test_dn_is_radiance_times_exposure_plus_black() -> None:
    """DN - black = radiance * t * (ISO/100) / N^2, channel by channel, on the RGGB mosaic."""
    sensor = synthetic.SensorModel(black_level=600, gain_e_per_dn=400.0, read_noise_dn=0.0)
    photo = _render(sensor=sensor)  # 400 e-/DN at ISO 100 -> 100 at ISO 400: tiny shot noise
    m = photo.mosaic[BLOCK].astype(np.float64)
    assert m[0::2, 0::2].mean() == pytest.approx(600 + 1000, abs=0.05)  # R
    assert m[0::2, 1::2].mean() == pytest.approx(600 + 3000, abs=0.05)  # G
    assert m[1::2, 0::2].mean() == pytest.approx(600 + 3000, abs=0.05)  # G
    assert m[1::2, 1::2].mean() == pytest.approx(600 + 2000, abs=0.05)  # B
    assert EXPOSURE.scale == pytest.approx(4.0**2 / (0.02 * 4.0))


def test_noise_is_shot_plus_read_plus_quantisation() -> None:
    # gain 2 e-/DN at ISO 100 -> 0.5 e-/DN at ISO 400: var(DN) = S / 0.5 + read^2 + 1/12
    sensor = synthetic.SensorModel(gain_e_per_dn=2.0, read_noise_dn=3.0)
    photo = _render(sensor=sensor)
    g = photo.mosaic[BLOCK][0::2, 1::2].astype(np.float64)  # green, S = 3000 DN
    expected_var = 3000 / 0.5 + 3.0**2 + 1 / 12
    # 8100 pixels: the sample variance is known to 1.6% (1 sigma)
    assert g.var(ddof=1) == pytest.approx(expected_var, rel=0.06)


def test_twelve_bit_white_level_clips() -> None:
    sensor = synthetic.SensorModel(bits=12, black_level=256)
    assert sensor.white == 4095
    photo = _render(sensor=sensor, radiance={"flat": np.full(3, 10_000.0) * EXPOSURE.scale})
    face = photo.mosaic[BLOCK]
    assert face.max() == 4095 and np.all(face == 4095)
    assert photo.mosaic.max() <= 4095
    with pytest.raises(imaging.ImagingError, match="exceeds 4095"):
        synthetic.SensorModel(bits=12, white_level=5000)


def test_cfa_pattern_places_colours() -> None:
    sensor = synthetic.SensorModel(cfa="GRBG", read_noise_dn=0.0, gain_e_per_dn=400.0)
    red_only = {"flat": np.array([2000.0, 0.0, 0.0]) * EXPOSURE.scale}
    photo = _render(sensor=sensor, radiance=red_only, background=np.zeros(3))
    m = photo.mosaic[BLOCK].astype(np.float64) - sensor.black_level
    assert m[0::2, 1::2].mean() == pytest.approx(2000, abs=0.5)  # R sits at (0, 1) in GRBG
    for sub in (m[0::2, 0::2], m[1::2, 0::2], m[1::2, 1::2]):
        assert np.abs(sub).max() <= 1


def test_expectations_without_texture_or_vignetting_are_the_radiance() -> None:
    rad = np.array([1000.0, 3000.0, 2000.0]) * EXPOSURE.scale
    photo = _render()
    assert np.allclose(photo.expected["flat"], rad, rtol=1e-6)
    assert np.allclose(photo.expected_untextured["flat"], rad, rtol=1e-6)


def test_vignetting_follows_the_cos4_law() -> None:
    flat = np.full(3, 1000.0) * EXPOSURE.scale  # the same radiance everywhere, every channel
    photo = _render(vignetting=0.2, keep_field=True, radiance={"flat": flat}, background=flat)
    v = photo.field / flat[0]
    # 1 / (1 + r^2/f^2)^2 about the centre (199.5, 199.5), 1 - 0.2 in the corners
    f2 = 2 * 199.5**2 / (0.8**-0.5 - 1)
    for y, x in [(0, 0), (399, 0), (0, 399), (399, 399), (100, 150), (199, 200)]:
        r2 = (x - 199.5) ** 2 + (y - 199.5) ** 2
        assert v[y, x] == pytest.approx(1 / (1 + r2 / f2) ** 2, rel=1e-5)
    assert v[0, 0] == pytest.approx(0.8, rel=1e-5)


def test_texture_has_the_requested_amplitude_and_mean_one() -> None:
    photo = _render(texture_amplitude=0.03, texture_sigma_px=1.5, keep_field=True)
    rad = np.array([1000.0, 3000.0, 2000.0]) * EXPOSURE.scale
    ratio = photo.field[BLOCK][0::2, 1::2] / rad[1]
    assert ratio.std() == pytest.approx(0.03, rel=0.1)
    assert ratio.mean() == pytest.approx(1.0, abs=0.005)


def test_rendering_is_deterministic_in_the_seed() -> None:
    a, b, c = _render(seed=5), _render(seed=5), _render(seed=6)
    assert np.array_equal(a.mosaic, b.mosaic)
    assert not np.array_equal(a.mosaic, c.mosaic)


def test_markers_need_a_homography() -> None:
    layout = imaging.MarkerLayout({0: [(0, 0), (10, 0), (10, 10), (0, 10)]})
    with pytest.raises(imaging.ImagingError, match="plane_to_image"):
        _render(markers=layout)
