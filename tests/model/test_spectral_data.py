"""The shipped spectral tables equal colour-science's datasets, and importing the model does not
import colour-science, matplotlib or SciPy (issue 14: cold start) [conventions §8]."""

from __future__ import annotations

import subprocess
import sys

import colour
import numpy as np
import pytest

from stairfit.model import _spectral_data, spectral

# The JSON file holds the shortest round-trip repr of every float64, so the tables are exact
# copies; the tolerance only allows for a future writer that rounds in the last bit.
RTOL = 1e-15


def _assert_same(ours: _spectral_data.Tabulated, wavelengths, values) -> None:
    np.testing.assert_allclose(ours.wavelength_nm, wavelengths, rtol=RTOL, atol=0)
    np.testing.assert_allclose(ours.values, values, rtol=RTOL, atol=0)


def test_cmfs_equal_colour_science():
    cmfs = colour.MSDS_CMFS[_spectral_data.CMFS_NAME]
    _assert_same(
        _spectral_data.tables().cmfs[_spectral_data.CMFS_NAME], cmfs.wavelengths, cmfs.values
    )


def test_every_illuminant_equals_colour_science():
    ours = _spectral_data.tables().illuminants
    assert list(ours) == list(colour.SDS_ILLUMINANTS.keys())
    for name, sd in colour.SDS_ILLUMINANTS.items():
        _assert_same(ours[name], sd.wavelengths, sd.values)


def test_every_camera_equals_colour_science_and_is_listed():
    ours = _spectral_data.tables().cameras
    assert list(ours) == list(colour.MSDS_CAMERA_SENSITIVITIES.keys())
    assert (*colour.MSDS_CAMERA_SENSITIVITIES.keys(), "ideal") == spectral.CAMERAS
    for name, m in colour.MSDS_CAMERA_SENSITIVITIES.items():
        _assert_same(ours[name], m.wavelengths, m.values)


def test_xyz_to_srgb_equals_colour_science():
    rng = np.random.default_rng(4)
    # in gamut, out of gamut (negative and > 1 channels), near black (the linear segment)
    xyz = np.concatenate([rng.uniform(0, 1.2, (200, 3)), rng.uniform(0, 0.004, (50, 3))])
    ref = np.clip(colour.XYZ_to_sRGB(xyz * 0.8, apply_cctf_encoding=True), 0.0, 1.0)
    np.testing.assert_allclose(spectral.xyz_to_srgb(xyz, 0.8), ref, rtol=0, atol=1e-12)


def test_illuminant_names_accept_what_colour_science_accepts():
    ref = spectral.illuminant_spd("LED-B1")
    for spelling in ("led-b1", "ledb1"):  # colour-science's lower-case and canonical keys
        assert colour.SDS_ILLUMINANTS[spelling] is colour.SDS_ILLUMINANTS["LED-B1"]
        np.testing.assert_array_equal(spectral.illuminant_spd(spelling), ref)
    # and spaces or '_' for '-' (a superset, harmless: no two names collide)
    np.testing.assert_array_equal(spectral.illuminant_spd("LED B1"), ref)
    canon = [_spectral_data.canonical(k) for k in _spectral_data.tables().illuminants]
    assert len(set(canon)) == len(canon)
    with pytest.raises(ValueError, match="unknown illuminant"):
        spectral.illuminant_spd("D66")


def test_channel_weights_from_the_tables_match_colour_science_resampled():
    # an independent resampling: colour-science's own SpectralShape alignment (linear
    # interpolation of the 5 nm D65 / camera data onto 380-780 nm at 5 nm: the same samples)
    shape = colour.SpectralShape(380, 780, 5)
    cam = colour.MSDS_CAMERA_SENSITIVITIES["Nikon 5100 (NPL)"].copy().align(shape)
    d65 = colour.SDS_ILLUMINANTS["D65"].copy().align(shape)
    raw = cam.values.T * d65.values
    ref = raw / raw.sum(axis=1, keepdims=True)
    cw = spectral.channel_weights("Nikon 5100 (NPL)", "D65")
    np.testing.assert_allclose(cw.weights, ref, rtol=1e-12, atol=1e-15)


def test_importing_the_model_imports_neither_colour_matplotlib_nor_scipy():
    code = (
        "import sys; from stairfit import model; from stairfit.model import spectral; "
        "spectral.channel_weights('ideal', 'D65'); spectral.xyz_weights('A'); "
        "print(sorted(m for m in ('colour', 'matplotlib', 'scipy') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr
