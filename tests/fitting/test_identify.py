"""Identifiability: parameters the data cannot constrain are fixed with a warning, not reported
with meaningless error bars, and the warning fires only where it should (docs/fitting.md)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import zoo

from stairfit import fitting

DEG = np.pi / 180
DN = fitting.variant("sharp+delta_n", "delta_n")


def test_delta_n_from_one_grey_channel_single_facet_is_unidentified():
    # One channel, a constant index, and a geometry in which every observation sees the same
    # facet at the same local angle (theta_i = -50 deg on a 30-deg wedge: regime A, only the
    # tread is lit [conventions §3]): delta_n and the scale are exactly degenerate.
    truth = fitting.Params(sigma_rad=6 * DEG, delta_n=0.05, scale=2.0)
    obs, spec, _ = zoo.scene(truth, zoo.one_wedge_design(30.0, -50.0), zoo.grey(), seed=3)
    with pytest.warns(fitting.UnidentifiedParameterWarning, match="delta_n is not constrained"):
        fit = fitting.fit_least_squares(obs, spec, DN)
    assert fit.unidentified == ("delta_n",)
    assert "delta_n" not in fit.names and fit.params.delta_n == 0.0
    assert [w.code for w in fit.warnings] == ["unidentified"]
    assert fit.covariance is not None  # the remaining parameters have honest error bars
    assert abs(fit.params.sigma_rad[0] - truth.sigma_rad) < 3 * fit.estimate("sigma_rad").stderr


def test_delta_n_weakly_constrained_is_fixed_by_the_standard_error_rule():
    # A 45-deg wedge at normal incidence: all local angles are 45 deg; only the ratio of the
    # retro (two reflections) to the direct lobes depends on n, weakly. Without the rule, the
    # fit wanders to an absurd index with no usable covariance.
    truth = fitting.Params(sigma_rad=6 * DEG, scale=2.0)
    obs, spec, _ = zoo.scene(truth, zoo.one_wedge_design(45.0, 0.0), zoo.grey(), seed=3)
    raw = fitting.fit_least_squares(obs, spec, DN, identifiability=False)
    if raw.covariance is not None:
        assert raw.estimate("delta_n").stderr > 0.5 * 0.1  # larger than half the prior's sd
    with pytest.warns(fitting.UnidentifiedParameterWarning, match="delta_n"):
        fit = fitting.fit_least_squares(obs, spec, DN)
    assert "delta_n" not in fit.names


@pytest.mark.parametrize(
    ("material", "channels"), [("pla", (1,)), ("pla", None), ("pla-bodurov2016", None)]
)
def test_no_identifiability_warning_on_the_standard_scene(material, channels):
    # The standard scene sees many local angles: delta_n is constrained even from one grey
    # channel with a constant index, and certainly from three channels.
    truth = fitting.Params(sigma_rad=6 * DEG, delta_n=0.03, scale=1.0, floor=0.002)
    obs, spec, _ = zoo.standard(truth, seed=5, spec=zoo.effective(material, channels))
    variants = [DN, fitting.variant("dnf", "delta_n", "floor"),
                fitting.variant("dnw", "delta_n", "floor", per_wedge_sigma=True)]  # fmt: skip
    for v in variants:
        with warnings.catch_warnings():
            warnings.simplefilter("error", fitting.UnidentifiedParameterWarning)
            fit = fitting.fit_least_squares(obs, spec, v)
        assert fit.unidentified == () and set(fit.variant.free) == set(v.free)


def test_per_wedge_width_without_information_is_fixed():
    # Wedge 0 is only seen in its far tails (|theta_o| >= 72 deg, > 5 sigma from its lobes):
    # its own width is unconstrained; every other wedge keeps its own free width.
    obs, spec, _ = zoo.standard(fitting.Params(sigma_rad=6 * DEG, scale=2.0), seed=3)
    far = (obs.wedge_index == 0) & (np.abs(np.rad2deg(obs.theta_o_rad)) < 70)
    obs = fitting.Observations.from_arrays(**{**obs._asdict(), "use": ~far})
    with pytest.warns(fitting.UnidentifiedParameterWarning, match=r"sigma_rad\[0: 10 deg\]"):
        fit = fitting.fit_least_squares(obs, spec, fitting.variant("w", per_wedge_sigma=True))
    assert len(fit.unidentified) == 1
    assert [(e.param, e.wedge) for e in fit.estimates] == [
        *(("sigma_rad", w) for w in range(1, 6)),
        ("scale", None),
    ]
    others = fit.params.sigma_rad[1:]
    assert fit.params.sigma_rad[0] == pytest.approx(np.exp(np.mean(np.log(others))), rel=1e-9)


def test_selection_does_not_warn_about_variants_it_rejects():
    # In the degenerate scene the delta_n variants lose delta_n; the chosen variant is 'sharp'
    # and no identifiability warning is emitted for the rejected ones.
    truth = fitting.Params(sigma_rad=6 * DEG, scale=2.0)
    obs, spec, _ = zoo.scene(truth, zoo.one_wedge_design(30.0, -50.0), zoo.grey(), seed=4)
    # shared-sigma sharp variants: the rounded rungs cost tens of seconds each to compile and
    # the point here (delta_n collapsing in the rejected variants) does not involve them
    ladder = tuple(v for v in zoo.SHARP_LADDER if not v.per_wedge_sigma)
    with warnings.catch_warnings():
        warnings.simplefilter("error", fitting.UnidentifiedParameterWarning)
        sel = fitting.select_model(obs, spec, ladder)
    assert sel.chosen == "sharp", sel.report()
    dn_row = next(r for r in sel.table if r.name == "sharp+delta_n")
    assert "delta_n unidentified" in dn_row.notes


def _rounded_scene(wedge_deg: float) -> tuple[fitting.Observations, fitting.Spectral]:
    """One wedge, 7 views, one grey channel, 5% noise, a realistic 10 um edge radius."""
    design = zoo.one_wedge_design(wedge_deg, 20.0, np.linspace(-30, 30, 7))
    truth = fitting.Params(sigma_rad=6 * DEG, scale=1.0, edge_radius_um=10.0)
    obs, spec, _ = zoo.scene(truth, design, zoo.grey(), noise=0.05, seed=2)
    return obs, spec


@pytest.mark.slow  # the rounded model's Jacobian takes about a minute to compile (XLA)
def test_edge_radius_with_only_coarse_cells_is_not_reported():
    # A 5-deg wedge: cells of 1.7 mm for 150 um layers. A 10 um edge changes the reflectance
    # by far less than the 5% noise of seven views, so the radius is fixed (on its bound, or
    # as unidentified) with a warning instead of being reported with a meaningless error bar.
    obs, spec = _rounded_scene(5.0)
    with pytest.warns(fitting.FitWarningCategory, match="edge_radius_um"):
        fit = fitting.fit_least_squares(obs, spec, fitting.variant("r", "edge_radius_um"))
    assert "edge_radius_um" not in fit.names
    assert fit.params.edge_radius_um == 0.0


@pytest.mark.slow  # the rounded model's Jacobian takes about a minute to compile (XLA)
def test_edge_radius_on_fine_cells_is_identified():
    # The same scene with a 30-deg wedge (cells of 300 um): the radius is measured, no warning.
    obs, spec = _rounded_scene(30.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error", fitting.FitWarningCategory)
        fit = fitting.fit_least_squares(obs, spec, fitting.variant("r", "edge_radius_um"))
    e = fit.estimate("edge_radius_um")
    assert abs(e.value - 10.0) < 3 * e.stderr and e.stderr < 2.0


def test_a_parameter_in_large_units_is_not_taken_for_one_without_information() -> None:
    """The Fisher diagonals carry the parameters' units: the variant set's Beckmann probe had
    its floor (radiance units, about 2e5) at 9e-13 of the width's diagonal, well conditioned
    (normalised eigenvalues 0.56-1.89), and the old 1e-12 test called it singular, which fixed
    the floor at 0 and left a model-error term of 89%. A column of zeros is still singular."""
    from types import SimpleNamespace

    from stairfit.fitting._identify import covariance

    diag = np.array([2.66e4, 2.14e5, 7.10e3, 1.96e-7, 4.16e4])  # sigma, r, scale, floor, f
    corr = np.full((5, 5), 0.3) + 0.7 * np.eye(5)
    fisher = corr * np.sqrt(np.outer(diag, diag))
    core = SimpleNamespace(free_slots=np.arange(5), ev=SimpleNamespace(fisher=fisher))
    cov = covariance(core)
    assert cov.degenerate == () and cov.z is not None
    assert np.allclose(cov.z @ fisher, np.eye(5), atol=1e-8)
    fisher[3, :] = fisher[:, 3] = 0.0
    assert 3 in covariance(core).degenerate
