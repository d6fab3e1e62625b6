"""The plate's light in the lab model: the share of the lit base plate's radiance that the
staircase reflects into a view (`stairfit.model.plate_reflectance`, docs/model.md §7.7).

Checked two ways that share nothing with its formula: the independent 3-D ray tracer
(tests/raytrace3d.py, reversed view rays, exact s/p, sampled micro-normals), and the model's own
density integrated over the plate's directions (reciprocity). Then the extremes, and the scene
field that switches it on.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from raytrace import Staircase
from raytrace3d import Rough, direction, trace3d

from stairfit import fitting, model
from stairfit.fitting._lab import lab_data, lab_grid

jax.config.update("jax_enable_x64", True)

DEG = math.pi / 180.0


def _traced_share(beta2_deg: float, w_o: np.ndarray, rough: Rough | None, seed: int = 1) -> float:
    """The tracer's share: rays sent from the viewer (reciprocity) that leave the staircase
    below the plate's horizon, their power summed (every number of bounces)."""
    tr = trace3d(Staircase(beta2_deg), w_o, 1.46, rough=rough, n_rays=100_000, seed=seed)
    b = beta2_deg * DEG
    below = tr.w_o @ np.array([math.sin(b), 0.0, math.cos(b)]) < 0.0
    return float(np.sum(tr.power[below]))


@pytest.mark.parametrize(
    ("beta2_deg", "theta_o_deg", "out_deg"),
    [(60.0, -20.0, 0.0), (60.0, 0.0, 0.0), (60.0, 20.0, 8.0), (30.0, -40.0, 0.0),
     (45.0, -10.0, 5.0), (60.0, -45.0, 0.0)],
)  # fmt: skip
def test_a_sharp_staircase_reflects_the_plate_as_the_ray_tracer_finds(
    beta2_deg: float, theta_o_deg: float, out_deg: float
) -> None:
    """Smooth facets: the share equals the tracer's to its sampling noise (1e-3 absolute on
    shares up to 0.03), in and out of the plane of incidence."""
    w_o = direction(theta_o_deg, out_deg)
    want = _traced_share(beta2_deg, w_o, None)
    got = float(model.plate_reflectance(w_o, beta2_deg * DEG, 1.46, 1e-6))
    assert got == pytest.approx(want, abs=1e-3, rel=0.02)


@pytest.mark.parametrize(
    ("kind", "alpha", "beta2_deg", "theta_o_deg"),
    [("ggx", 0.03, 60.0, -20.0), ("ggx", 0.06, 60.0, -20.0), ("ggx", 0.06, 60.0, -45.0),
     ("ggx", 0.06, 30.0, -40.0), ("beckmann", 0.1, 60.0, 0.0), ("ggx", 0.15, 45.0, -20.0),
     ("ggx", 0.15, 30.0, -40.0), ("beckmann", 0.15, 60.0, -20.0)],
)  # fmt: skip
def test_rough_facets_reflect_the_plate_as_the_ray_tracer_finds(
    kind: str, alpha: float, beta2_deg: float, theta_o_deg: float
) -> None:
    """Microfacet facets: within `0.03 + 1.3 alpha` of the tracer's share (relative; 5e-4
    absolute where the share is small). The model takes each lobe's part below the horizon
    from the slope distribution (a reflection turns by twice a micro-normal's in-plane tilt)
    and keeps the sharp lobes' ratios, so it leaves out the rough lobe's tail that the tread
    below intercepts and the micro-surface's masking; the tracer has both, and the model's
    share is high by about `1.2 alpha` for GGX (4% at alpha 0.06, 18-22% at 0.15) and less for
    Beckmann (docs/model.md §7.7)."""
    w_o = direction(theta_o_deg, 0.0)
    want = np.mean([_traced_share(beta2_deg, w_o, Rough(alpha, kind), s) for s in (1, 2)])
    got = float(model.plate_reflectance(w_o, beta2_deg * DEG, 1.46, math.atan(alpha), kind))
    assert abs(got - want) <= max((0.03 + 1.3 * alpha) * want, 5e-4), (got, want)
    assert got >= 0.97 * want  # the approximation errs on the high side only


def test_the_share_is_the_models_own_density_over_the_plates_directions() -> None:
    """Reciprocity: for Gaussian facets the share equals the lab density, reversed, integrated
    over the directions below the plate's horizon, within 2% (a 240 x 480 grid)."""
    b2, sigma = 60.0 * DEG, 3.0 * DEG
    nt, nphi = 240, 480
    th = (np.arange(nt) + 0.5) / nt * (math.pi / 2)
    ph = (np.arange(nphi) + 0.5) / nphi * 2 * math.pi
    tt, pp = np.meshgrid(th, ph, indexing="ij")
    w = np.stack([np.sin(tt) * np.cos(pp), np.sin(tt) * np.sin(pp), np.cos(tt)], -1).reshape(-1, 3)
    dom = (np.sin(tt) * (math.pi / 2 / nt) * (2 * math.pi / nphi)).reshape(-1)
    below = w @ np.array([math.sin(b2), 0.0, math.cos(b2)]) < 0.0
    for theta_o_deg, out_deg in ((-20.0, 0.0), (0.0, 6.0), (20.0, 0.0)):
        w_o = direction(theta_o_deg, out_deg)
        p = np.asarray(model.lab_density_gaussian(w[below], np.broadcast_to(w_o, w[below].shape),
                                                  b2, 1.46, sigma))  # fmt: skip
        integral = float(np.sum(p * w[below][:, 2] / w_o[2] * dom[below]))
        got = float(model.plate_reflectance(w_o, b2, 1.46, sigma))
        assert got == pytest.approx(integral, rel=0.02), theta_o_deg


def test_no_plate_is_seen_from_uphill_of_a_shallow_wedge_nor_through_an_index_of_one() -> None:
    """Zero where nothing reflects the plate: a shallow wedge seen from uphill (its risers face
    away), and `n = 1` (no Fresnel reflection)."""
    w_o = direction(40.0, 0.0)
    assert float(model.plate_reflectance(w_o, 20.0 * DEG, 1.46, 0.01)) < 1e-12
    assert float(model.plate_reflectance(direction(-20.0, 0.0), 60.0 * DEG, 1.0, 0.05)) == 0.0


@pytest.mark.parametrize("kernel", ["gaussian", "ggx", "beckmann"])
def test_the_plates_share_is_finite_with_finite_gradients_at_the_extremes(kernel: str) -> None:
    """Grazing and along-the-layer views, wedges near 0 and 90 deg, widths to 0, n -> 1 (from
    above: exactly 1 at a grazing facet is Fresnel's 0 / 0, as for every lab function)."""

    def share(x: jax.Array, w_o: jax.Array) -> jax.Array:
        b2, width, n = x
        return model.plate_reflectance(w_o, b2, n, width, kernel)

    views = [direction(-89.99, 0.0), direction(89.99, 0.0), direction(0.0, 89.99),
             direction(-20.0, 0.0), np.array([0.0, 0.0, 1.0])]  # fmt: skip
    for b2 in (1e-4, 45.0 * DEG, 90.0 * DEG - 1e-4):
        for width in (0.0, 1e-9, 0.05):
            for n in (1.0 + 1e-9, 1.0001, 1.46):
                for w_o in views:
                    x = jnp.array([b2, width, n])
                    v, g = jax.value_and_grad(share)(x, jnp.asarray(w_o))
                    assert np.isfinite(float(v)) and 0.0 <= float(v) <= 1.0
                    assert np.all(np.isfinite(np.asarray(g))), (b2, width, n, w_o)


def test_a_plate_albedo_adds_its_light_and_zero_leaves_the_model_as_before() -> None:
    """`LabGeometry.plate_albedo`: 0 gives the lab grid without the term; a positive albedo
    adds `albedo / pi (w_i . z_plate)` times the share, per node, to the specular part (what
    `scale` multiplies), and leaves the body alone."""
    b2 = np.array([60.0 * DEG])
    w_i = direction(10.0, 0.0, light=True)[None, None, :]
    w_o = direction(-20.0, 0.0)[None, None, :]
    ones = np.ones((1, 1))
    spectral = (np.full((1, 1), 1.46), np.ones((1, 1)))

    def grid(albedo: float) -> tuple[np.ndarray, np.ndarray]:
        geo = fitting.LabGeometry(w_i, w_o, ones, ones, np.zeros(1, int), np.zeros(1, int),
                                  plate_albedo=albedo)  # fmt: skip
        data = lab_data(geo.check(1), b2, np.array([150.0]), 1, spectral)
        spec, body = lab_grid(jnp.array([math.atan(0.06)]), jnp.zeros(()), data, "ggx")
        return np.asarray(spec), np.asarray(body)

    spec0, body0 = grid(0.0)
    spec3, body3 = grid(0.03)
    tread_normal = np.array([math.sin(b2[0]), 0.0, math.cos(b2[0])])
    share = float(model.plate_reflectance(w_o[0, 0], b2[0], 1.46, math.atan(0.06), "ggx"))
    added = 0.03 / math.pi * float(w_i[0, 0] @ tread_normal) * share
    assert share > 0.01
    assert spec3[0, 0] - spec0[0, 0] == pytest.approx(added, rel=1e-9)
    np.testing.assert_array_equal(body3, body0)
    with pytest.raises(fitting.FitInputError, match="plate_albedo"):
        fitting.LabGeometry(w_i, w_o, ones, ones, np.zeros(1, int), np.zeros(1, int),
                            plate_albedo=1.5).check(1)  # fmt: skip
