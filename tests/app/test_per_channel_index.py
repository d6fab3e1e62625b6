"""One refractive index per camera channel (issue 12): the scene field, its one-line errors, the
fit's spectral setup, and the effective wavelengths written to results.json [conventions §7, §8].
"""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import tomli_w

from stairfit import fitting
from stairfit.errors import UserError
from stairfit.model import materials, spectral
from stairfit.pipeline import fit_setup
from stairfit.presets import PRESETS
from stairfit.report import spectral_record
from stairfit.scene import load_scene

DEG = np.pi / 180
CAMERA = "Nikon 5100 (NPL)"
SCENE = {
    "version": 1,
    "specimen": {
        "layer_um": 150.0,
        "wedges": [{"name": "w30", "angle_deg": 30.0, "roi_px": [[0, 0], [9, 0], [9, 9]]}],
    },
    "light": {"illuminant": "D65"},
    "camera": {"sensitivity": CAMERA},
    "photos": [{"file": "a.dng", "light_deg": 0.0, "view_deg": 10.0}],
}


def _scene_with(tmp_path: Path, index: dict) -> Path:
    data = {**SCENE, "specimen": {**SCENE["specimen"], "index": index}}
    path = tmp_path / "scene.toml"
    path.write_text(tomli_w.dumps(data))
    return path


def test_per_channel_index_reads_in_r_g_b_order(tmp_path):
    scene = load_scene(_scene_with(tmp_path, {"model": "per_channel", "n": [1.47, 1.46, 1.45]}))
    assert scene.specimen.index.build() == materials.PerChannel(n=(1.47, 1.46, 1.45))
    absorbing = {"model": "per_channel", "n": [1.47, 1.46, 1.45], "k": 0.01}
    index = load_scene(_scene_with(tmp_path, absorbing)).specimen.index.build()
    assert index.k == (0.01, 0.01, 0.01)  # one k for every channel


@pytest.mark.parametrize(
    ("index", "field", "message"),
    [
        ({"n": [1.47, 1.46]}, "n", "one index per camera channel, in R, G, B order"),
        ({"n": 1.46}, "n", "one index per camera channel"),
        ({"n": [1.47, 0.9, 1.45]}, "n", "0.9 for channel G; each index must be > 1"),
        ({"n": [1.47, 1.46, 1.45], "k": [0.0, -0.1, 0.0]}, "k", "-0.1 for channel G"),
        ({"n": [1.47, 1.46, 1.45], "k": [0.0, 0.1]}, "k", "3 numbers in R, G, B order"),
        ({"n": [1.47, 1.46, 1.45], "a": 1.0}, "a", "unknown field"),
    ],
)
def test_per_channel_mistakes_are_one_line_errors(tmp_path, index, field, message):
    path = _scene_with(tmp_path, {"model": "per_channel", **index})
    with pytest.raises(UserError) as err:
        load_scene(path)
    text = str(err.value)
    assert text.startswith(f"{path}: specimen.index.{field}"), text
    assert message in text and "\n" not in text


@pytest.mark.parametrize("sampling", ["full", "effective"])
def test_spectral_setup_gives_each_channel_its_own_index(sampling):
    n_rgb = (1.47, 1.46, 1.45)
    per = fitting.spectral_setup(materials.PerChannel(n=n_rgb), CAMERA, "D65", sampling)
    for c, n_c in enumerate(n_rgb):  # the same as a constant index of that channel's value
        const = fitting.spectral_setup(materials.ConstantIndex(n=n_c), CAMERA, "D65", sampling)
        np.testing.assert_array_equal(per.n_base[c], const.n_base[c])
        np.testing.assert_array_equal(per.weights[c], const.weights[c])
        np.testing.assert_array_equal(per.wavelength_nm[c], const.wavelength_nm[c])
    green = fitting.spectral_setup(materials.PerChannel(n=n_rgb), CAMERA, "D65", channels=(1,))
    np.testing.assert_array_equal(green.n_base, 1.46)
    with pytest.raises(fitting.FitInputError, match="one value per camera channel"):
        fitting.spectral_setup(materials.PerChannel(n=(1.47, 1.46)), CAMERA, "D65")


def test_the_fit_model_sees_the_per_channel_index():
    # the fit's forward model of a design's rows, per channel, against a constant index
    design = fitting.standard_design(n_views=3, wedge_deg=(30.0,))
    truth = fitting.Params(sigma_rad=5 * DEG, scale=1.0)
    n_rgb = (1.6, 1.46, 1.3)  # far apart, so that a mixed-up channel cannot pass
    per = fitting.spectral_setup(materials.PerChannel(n=n_rgb), sampling="effective")
    obs = fitting.simulate_observations(truth, design, per, fitting.Noise(0.01), seed=0)
    got = fitting.model_radiance(truth, obs, per)
    for c, n_c in enumerate(n_rgb):
        const = fitting.spectral_setup(materials.ConstantIndex(n=n_c), sampling="effective")
        rows = obs.channel_index == c
        np.testing.assert_allclose(
            got[rows], fitting.model_radiance(truth, obs, const)[rows], rtol=1e-12
        )
    red, blue = got[obs.channel_index == 0], got[obs.channel_index == 2]
    assert np.all(red > 1.5 * blue)  # and the index matters: n = 1.6 reflects far more than 1.3


def test_results_record_the_effective_wavelengths_and_the_index_there():
    cw = spectral.channel_weights(CAMERA, "A")
    disp = materials.PLA_BODUROV_2016
    scene = SimpleNamespace(
        camera=SimpleNamespace(sensitivity=CAMERA, angular_extent_deg=0.0),
        light=SimpleNamespace(illuminant="A", angular_diameter_deg=0.0, shape="uniform"),
        specimen=SimpleNamespace(index=SimpleNamespace(build=lambda: disp)),
    )
    preset = PRESETS["accurate"]  # "full" spectral sampling
    outcome = SimpleNamespace(
        scene=scene, options=SimpleNamespace(preset=preset), setup=fit_setup(scene, preset)
    )
    rec = spectral_record(outcome)
    assert rec["channels"] == ["R", "G", "B"] and rec["illuminant"] == "A"
    np.testing.assert_allclose(rec["effective_wavelength_nm"], cw.effective_nm, atol=5e-4)
    # Sellmeier worked at the effective wavelengths (README "Materials")
    lam_um = cw.effective_nm * 1e-3
    expected = np.sqrt(1 + 0.9809 / (1 - (0.2123719 / lam_um) ** 2))
    np.testing.assert_allclose(rec["index_n"], expected, atol=1e-8)
    np.testing.assert_array_equal(rec["index_k"], 0.0)
    # the Nikon's channels under A sit near 609, 544 and 484 nm (docs/fitting.md table)
    np.testing.assert_allclose(rec["effective_wavelength_nm"], [608.9, 544.3, 484.0], atol=0.05)


def test_figures_draw_a_per_channel_index_through_the_effective_wavelengths(tmp_path):
    from stairfit.report import _along_wavelength

    path = _scene_with(tmp_path, {"model": "per_channel", "n": [1.47, 1.46, 1.45]})
    setup = fit_setup(load_scene(path), PRESETS["balanced"])
    curve = _along_wavelength(SimpleNamespace(setup=setup))
    eff = spectral.channel_weights(CAMERA, "D65").effective_nm  # R > G > B in wavelength
    np.testing.assert_allclose(np.asarray(curve(eff)), [1.47, 1.46, 1.45], rtol=1e-12)
    np.testing.assert_allclose(np.asarray(curve(np.array([380.0, 780.0]))), [1.45, 1.47])


def test_docs_table_of_effective_wavelengths_matches_the_camera_models():
    import re

    from conftest import REPO

    text = (REPO / "docs" / "fitting.md").read_text()
    header = re.search(r"\| camera .*?\| under D65.*\n", text).group(0)
    illuminants = ["D65", *re.findall(r"\| under ([\w-]+)", header)[1:]]
    checked = 0
    for camera in spectral.CAMERAS:
        row = re.search(rf"\| `{re.escape(camera)}`[^|]*\|(.*)\n", text).group(1)
        cells = [c.strip() for c in row.split("|") if c.strip()]
        for ill, cell in zip(illuminants, cells, strict=True):
            doc = [float(x) for x in cell.split("/")]
            eff = spectral.channel_weights(camera, ill).effective_nm
            np.testing.assert_allclose(doc, eff, atol=0.051, err_msg=f"{camera} {ill}")
            checked += 1
    assert checked == 3 * 4
