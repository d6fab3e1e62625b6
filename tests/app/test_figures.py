"""stairfit.figures and the report's figure helpers: the fast paths (issue 6) keep the numbers.

The model evaluations of the figures are compared with direct calls of `stairfit.model`; the
layout, PNG and label helpers with values worked out by hand.
"""

from __future__ import annotations

import subprocess
import sys
from types import SimpleNamespace

import jax
import matplotlib.pyplot as plt
import numpy as np
import pytest
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from PIL import Image

from stairfit import figures, fitting, model
from stairfit.model import materials, spectral
from stairfit.report import value_with_errors

DEG = np.pi / 180
THETA_O_DEG = np.arange(-80.0, 81.0, 10.0)


def _direct_spectra(beta2_deg, dispersion, delta_n, sigma_deg):
    """Every wedge and the flat material at every 5 nm wavelength, straight from the model
    (compiled: eager evaluation takes seconds)."""
    n = np.asarray(model.refractive_index(dispersion, spectral.VISIBLE_NM, delta_n))
    to = THETA_O_DEG[:, None] * DEG
    diffuse = jax.jit(model.diffuse_broadened)
    rows = [np.asarray(diffuse(to, b * DEG, n[None, :], sigma_deg * DEG)) for b in beta2_deg]
    rows.append(np.asarray(jax.jit(model.flat_reflectance)(to, n[None, :])))
    return np.stack(rows)


def test_reflected_spectra_of_a_dispersive_material_match_5nm_sampling():
    disp = materials.PLA_BODUROV_2016  # the most dispersive material we ship
    fast = figures.reflected_spectra([10, 60], disp, delta_n=0.01, sigma_deg=5.0)
    ref = _direct_spectra([10, 60], disp, 0.01, 5.0)
    assert fast.shape == ref.shape == (3, THETA_O_DEG.size, spectral.VISIBLE_NM.size)
    # 20 nm nodes + linear interpolation: measured 5e-4 of the peak (sigma 1-20 deg); 4x room
    assert np.abs(fast - ref).max() <= 2e-3 * ref.max()
    for ill in ("D65", "A"):  # and the colours differ by far less than one 8-bit step
        w = spectral.xyz_weights(ill)
        xyz_fast, xyz_ref = fast @ w.T, ref @ w.T
        exposure = 0.9 / xyz_ref[..., 1].max()
        rgb_fast = spectral.xyz_to_srgb(xyz_fast, exposure)
        rgb_ref = spectral.xyz_to_srgb(xyz_ref, exposure)
        assert np.abs(rgb_fast - rgb_ref).max() < 0.5 / 255


def test_reflected_spectra_of_a_constant_absorbing_index_are_exact():
    disp = materials.ConstantIndex(n=1.5, k=0.02)  # complex index, no dispersion
    fast = figures.reflected_spectra([20, 45], disp, sigma_deg=3.0)
    ref = _direct_spectra([20, 45], disp, 0.0, 3.0)
    np.testing.assert_allclose(fast, ref, rtol=1e-12, atol=1e-15)


def test_reflected_spectra_float32_stays_close():
    disp = materials.PLA_PAPER_CONSTANT
    f64 = figures.reflected_spectra([10, 60], disp, sigma_deg=5.0)
    f32 = figures.reflected_spectra([10, 60], disp, sigma_deg=5.0, float32=True)
    # the presets quote a float32 figure error of 3e-3 of the maximum (app/presets.py)
    assert np.abs(f32 - f64).max() <= 3e-3 * f64.max()


@pytest.mark.parametrize(
    ("n", "sigma_deg", "cosine_weighted"), [(1.46, 0.0, False), (1.5 + 0.02j, 5.0, True)]
)
def test_diffuse_curves_are_the_model_per_wedge(n, sigma_deg, cosine_weighted):
    """Paper Fig. 5's curves, all wedges in one compiled program, against the model called
    per wedge (the flat material times cos theta_o where cosine-weighted)."""
    to = np.arange(-90.0, 90.1, 7.5) * DEG
    curves = figures.diffuse_curve_values([10, 45, 60], n, sigma_deg, cosine_weighted, to / DEG)
    assert curves.shape == (4, to.size)
    for k, b in enumerate((10, 45, 60)):
        if sigma_deg > 0:
            ref = jax.jit(model.diffuse_broadened, static_argnums=4)(
                to, b * DEG, n, sigma_deg * DEG, cosine_weighted
            )
        else:
            ref = jax.jit(model.diffuse_sharp, static_argnums=3)(to, b * DEG, n, cosine_weighted)
        np.testing.assert_allclose(curves[k], np.asarray(ref), rtol=1e-12, atol=1e-15)
    flat = np.asarray(model.flat_reflectance(to, n)) * (np.cos(to) if cosine_weighted else 1.0)
    np.testing.assert_allclose(curves[-1], flat, rtol=1e-12, atol=1e-15)
    assert np.all(np.isfinite(curves)) and curves.min() >= 0


@pytest.mark.parametrize(
    ("beta2", "theta_o", "sigma", "name"),
    [([30, 90], [0.0], 0.0, "beta2_deg = 90"), ([0], [0.0], 0.0, "beta2_deg = 0"),
     ([30], [0.0, 95.0], 0.0, "theta_o_deg = 95"), ([30], [np.nan], 0.0, "theta_o_deg = nan"),
     ([30], [0.0], -1.0, "sigma_deg = -1")],
)  # fmt: skip
def test_diffuse_curve_values_refuse_angles_out_of_range(beta2, theta_o, sigma, name):
    """(The model itself returns numbers for a wedge of 95 or 0 deg, so without the check a
    mistyped angle gave a plausible-looking curve.)"""
    with pytest.raises(ValueError, match=rf"{name} is outside its range.*fix the value"):
        figures.diffuse_curve_values(beta2, 1.46, sigma, False, theta_o)


def test_brdf_images_match_model_brdf():
    grid, images = figures.brdf_images([10, 60], 1.5, 4.0, step_deg=5.0)
    np.testing.assert_array_equal(grid, np.arange(-90.0, 91.0, 5.0))
    for k, b in enumerate((10.0, 60.0)):
        ref = np.asarray(
            jax.jit(model.brdf)(grid[:, None] * DEG, grid[None, :] * DEG, b * DEG, 1.5, 4.0 * DEG)
        )
        np.testing.assert_allclose(images[k], ref, rtol=1e-12, atol=1e-15)


def test_refractive_index_helper_matches_the_model_and_takes_unhashable_models():
    lam = np.array([450.0, 550.0, 650.0])
    for disp in (materials.PLA_BODUROV_2016, materials.ConstantIndex(n=1.5, k=0.01)):
        ref = np.asarray(model.refractive_index(disp, lam, 0.02))
        np.testing.assert_allclose(figures.refractive_index(disp, lam, 0.02), ref, rtol=1e-14)
    unhashable = materials.Tabulated(wavelength_nm=[400.0, 700.0], n=[1.5, 1.4])
    with pytest.raises(TypeError):
        hash(unhashable)
    np.testing.assert_allclose(
        figures.refractive_index(unhashable, np.array([400.0, 550.0]), 0.0), [1.5, 1.45]
    )


def test_fixed_layout_keeps_margins_and_gaps_in_inches():
    fig, axes = plt.subplots(2, 2, figsize=(8.0, 5.0))
    figures.fixed_layout(
        fig, 2, 2, left=0.7, right=0.3, bottom=0.5, top=0.4, wspace=1.0, hspace=0.6
    )
    pos = [[ax.get_position() for ax in row] for row in axes]
    plt.close(fig)
    w, h = 8.0, 5.0
    assert pos[0][0].x0 * w == pytest.approx(0.7)
    assert pos[0][1].x1 * w == pytest.approx(w - 0.3)
    assert (pos[0][1].x0 - pos[0][0].x1) * w == pytest.approx(1.0)
    assert pos[1][0].y0 * h == pytest.approx(0.5)
    assert pos[0][0].y1 * h == pytest.approx(h - 0.4)
    assert (pos[0][0].y0 - pos[1][0].y1) * h == pytest.approx(0.6)


@pytest.mark.parametrize(
    ("ylim", "expected"),
    [
        ((2e3, 2e5), {"10⁴", "10⁵"}),
        ((0.005, 0.5), {"10⁻²", "10⁻¹"}),
        ((3e3, 8e3), {"4×10³", "6×10³"}),  # under a decade: the default labels 2-9 x 10^k
    ],
)
def test_log_y_labels_are_plain_text(ylim, expected):
    fig, ax = plt.subplots()
    ax.plot([0, 1], ylim)
    figures.log_y(ax)
    ax.set_ylim(*ylim)
    fig.canvas.draw()
    labels = {t.get_text() for t in ax.get_yticklabels() + ax.get_yticklabels(minor=True)}
    plt.close(fig)
    labels.discard("")
    assert expected <= labels, labels
    assert not any("$" in s for s in labels)  # no mathtext


def test_save_writes_an_opaque_rgb_png_and_closes_the_figure(tmp_path):
    fig, ax = plt.subplots(figsize=(3.0, 2.0))
    ax.plot([0, 1], [0, 1])
    path = figures.save(fig, tmp_path / "sub" / "f.png", dpi=50)
    assert not plt.fignum_exists(fig.number)
    with Image.open(path) as im:
        assert im.format == "PNG" and im.mode == "RGB"
        assert im.size == (150, 100)
        assert im.getpixel((0, 0)) == (255, 255, 255)  # the white figure background


@pytest.mark.parametrize(
    ("args", "text"),
    [
        ((6.000341, 0.000117, 0.000111), "6.00034 +0.00011 -0.00012"),
        ((1999778.2, 113.0, 107.0), "1999778 +107 -113"),
        ((3999.912, 0.133, 0.126), "3999.91 +0.13 -0.13"),
        ((2.5, 0.0, 0.0), "2.5 +0 -0"),  # no spread: no rounding to it
    ],
)
def test_value_with_errors_rounds_to_the_smaller_error(args, text):
    assert value_with_errors(*args) == text


_FROM_SUPERSCRIPT = str.maketrans("⁰¹²³⁴⁵⁶⁷⁸⁹⁻", "0123456789-")


def _label_value(text: str) -> float:
    """Read a PlainLogFormatter label back: `10⁵` -> 1e5, `1.2×10⁵` -> 1.2e5."""
    coeff, _, power = text.rpartition("×")
    assert power.startswith("10"), text
    return float(coeff or 1.0) * 10.0 ** int(power[2:].translate(_FROM_SUPERSCRIPT))


def _visible_labels(ax) -> list[tuple[float, str]]:
    """(location, label) of every labelled y tick inside the view, major and minor."""
    lo, hi = ax.get_ylim()
    ticks = ax.yaxis.get_major_ticks() + ax.yaxis.get_minor_ticks()
    return [
        (t.get_loc(), t.label1.get_text())
        for t in ticks
        if lo <= t.get_loc() <= hi and t.label1.get_visible() and t.label1.get_text()
    ]


def _check_labels(pairs) -> None:
    texts = [text for _, text in pairs]
    assert len(pairs) >= 2, pairs  # a panel shows at least two values
    assert len(set(texts)) == len(texts), texts  # no two ticks share a label
    for loc, text in pairs:  # and each label says where its tick is (4 significant digits)
        assert _label_value(text) == pytest.approx(loc, rel=5e-4), (loc, text)


@pytest.mark.parametrize(
    "ylim", [(1.1e5, 1.9e5), (1.02e5, 1.08e5), (2.5e-3, 7.5e-3), (9e4, 2.2e5), (3e3, 8e3)]
)
def test_log_y_labels_under_a_decade_read_back_as_their_ticks(ylim):
    fig = Figure()
    ax = fig.subplots()
    ax.plot([0, 1], ylim)
    figures.log_y(ax)
    ax.set_ylim(*ylim)
    FigureCanvasAgg(fig).draw()
    _check_labels(_visible_labels(ax))


def test_fit_per_wedge_labels_a_narrow_45_deg_panel_by_its_values():
    # a fake fit outcome, just what fit_per_wedge reads: the 45 deg wedge's radiance spans
    # 1.2-1.8 x 10^5 (issue 12: every tick of that panel read "10⁵")
    from stairfit.report import fit_per_wedge

    theta = np.linspace(-60.0, 60.0, 13)
    values = {0: 1e3 * np.exp(-((theta / 30) ** 2)) + 50.0, 1: 1.5e5 + 3e4 * np.sin(theta * DEG)}
    rows = [(w, c, k) for w in (0, 1) for c in range(3) for k in range(theta.size)]
    value = np.array([values[w][k] * (1 + 0.01 * c) for w, c, k in rows])
    obs = SimpleNamespace(
        wedge_index=np.array([w for w, _, _ in rows]),
        channel_index=np.array([c for _, c, _ in rows]),
        value=value,
        use=np.ones(len(rows), bool),
    )
    fit = SimpleNamespace(model=value, uncertainty=0.01 * value)
    wedges = (
        SimpleNamespace(name="w10", angle_deg=10.0),
        SimpleNamespace(name="w45", angle_deg=45.0),
    )
    outcome = SimpleNamespace(
        selection=SimpleNamespace(fit=fit, chosen="sharp"),
        observations=SimpleNamespace(
            data=obs, labels=[SimpleNamespace(theta_o_deg=theta[k]) for _, _, k in rows]
        ),
        scene=SimpleNamespace(specimen=SimpleNamespace(wedges=wedges)),
    )
    fig = fit_per_wedge(outcome)
    FigureCanvasAgg(fig).draw()
    narrow = fig.axes[1]
    assert narrow.get_title() == "w45 (45 deg)"
    lo, hi = narrow.get_ylim()
    assert hi / lo < 10  # the panel spans less than a decade
    _check_labels(_visible_labels(narrow))


def test_figures_leave_pyplot_and_the_backend_alone(tmp_path):
    # a notebook's backend must survive importing and drawing stairfit's figures (issue 14)
    code = f"""
import matplotlib
matplotlib.use("svg")
import sys
from pathlib import Path
from stairfit import figures, report
fig = figures.brdf_map([30], n=1.46, sigma_deg=5.0, step_deg=10.0)
figures.save(fig, Path({str(tmp_path)!r}) / "map.png", dpi=20)
print(matplotlib.get_backend(), "matplotlib.pyplot" in sys.modules)
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["svg", "False"], out.stdout + out.stderr
    assert (tmp_path / "map.png").stat().st_size > 0


def test_corner_figure_is_not_registered_with_pyplot():
    from stairfit.report import corner_figure, corner_size_in

    rng = np.random.default_rng(0)
    params = tuple(
        fitting.Parameter(name, None, slot, "", fitting.PARAMETERS[0].transform, (0.0, 1.0))
        for slot, name in enumerate(("sigma_rad", "scale"))
    )
    post = SimpleNamespace(
        names=("sigma_rad", "scale"),
        parameters=params,
        samples=rng.normal(size=(400, 2)) * [0.01, 1.0],
    )
    before = plt.get_fignums()
    fig = corner_figure(SimpleNamespace(posterior=post))
    assert plt.get_fignums() == before
    assert len(fig.axes) == 4
    assert tuple(fig.get_size_inches()) == pytest.approx((corner_size_in(2),) * 2)
    assert fig.axes[2].get_xlabel() == "sigma_deg"  # radians shown in degrees
