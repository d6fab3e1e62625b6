"""The closed-form sharp lobes (`stairfit.model.sharp_lobes`) against the independent ray tracer.

The tracer (tests/raytrace.py) shares no code with `model/`: it follows rays through an explicit
periodic staircase [conventions §2] and multiplies s and p power by its own Fresnel factors
[conventions §6]. A traced ray belongs to a lobe by the facets it hit [conventions §3]:
`tread` = tread only, `riser` = riser only, `retro` = tread then riser or riser then tread.

Tolerances. Rays cross the top of the profile at evenly spaced points (midpoint rule over one
period); each lobe's rays form one interval of those points, so its traced weight is within
`1 / n_rays` of the exact fraction. With `N_RAYS = 20_000` that is 5e-5, well inside the
required 1e-3 for weights and ratios (ratio error <= weight error, as Fresnel <= 1).
Directions must agree to 0.01 deg; per-ray Fresnel factors are exact, so a lobe's mean Fresnel
factor must agree to rounding (1e-9 relative).

Grazing incidence: at exactly `theta_i = +-90 deg` the beam has zero width and there is no ray
to trace (`trace` refuses it); the limit is checked at `+-(90 - 1e-6) deg` instead.
"""

from __future__ import annotations

import numpy as np
import pytest
from raytrace import Staircase, paths, trace

from stairfit.model import sharp_lobes

WEDGES_DEG = (10.0, 20.0, 30.0, 40.0, 45.0, 60.0)
N_RAYS = 20_000
WEIGHT_TOL = 1e-3
DIRECTION_TOL_DEG = 0.01
LOBE_OF_PATH = {("tread",): 0, ("riser",): 1, ("tread", "riser"): 2, ("riser", "tread"): 2}


def special_angles_deg(beta2_deg: float) -> list[float]:
    """Regime boundaries -beta2, beta1 - beta2, beta1 [conventions §3], exactly and +-0.01 deg
    around them, and +-(90 - 1e-6) deg (grazing, as a limit)."""
    beta1 = 90.0 - beta2_deg
    out = [90.0 - 1e-6, -(90.0 - 1e-6)]
    for b in (-beta2_deg, beta1 - beta2_deg, beta1):
        out += [b, b - 0.01, b + 0.01]
    return [a for a in out if abs(a) < 90.0]


def traced_lobes(beta2_deg: float, theta_i_deg: float, n: complex, n_rays: int) -> dict:
    """Weight, ratio, mean Fresnel and direction range of the three lobes, from the tracer."""
    res = trace(Staircase(beta2_deg), theta_i_deg, n, n_rays=n_rays)
    assert res.n_lost == 0 and res.n_trapped == 0, (beta2_deg, theta_i_deg)
    weight, ratio = np.zeros(3), np.zeros(3)
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for key, st in paths(res).items():
        assert key in LOBE_OF_PATH, f"unexpected path {key} at {beta2_deg=}, {theta_i_deg=}"
        k = LOBE_OF_PATH[key]
        weight[k] += st.weight
        ratio[k] += st.power
        lo[k] = min(lo[k], st.theta_o_min_deg)
        hi[k] = max(hi[k], st.theta_o_max_deg)
    return {"weight": weight, "ratio": ratio, "lo": lo, "hi": hi}


def mismatches(beta2_deg: float, thetas_deg: list[float], n: complex, n_rays: int) -> list[str]:
    """All disagreements between model and tracer over `thetas_deg`, as readable lines."""
    th = np.asarray(thetas_deg, dtype=float)
    model = sharp_lobes(np.deg2rad(th), np.deg2rad(beta2_deg), n)
    m_theta = np.rad2deg(np.asarray(model.theta_o))
    m_weight, m_fresnel = np.asarray(model.weight), np.asarray(model.fresnel)
    m_ratio = np.asarray(model.ratio)
    bad = []
    for i, t in enumerate(th):
        tr = traced_lobes(beta2_deg, float(t), n, n_rays)
        where = f"beta2={beta2_deg:g} theta_i={t!r} n={n}"
        dw = np.abs(tr["weight"] - m_weight[i])
        if np.any(dw > WEIGHT_TOL):
            bad.append(f"{where}: weight traced {tr['weight']} model {m_weight[i]}")
        if np.any(np.abs(tr["ratio"] - m_ratio[i]) > WEIGHT_TOL):
            bad.append(f"{where}: ratio traced {tr['ratio']} model {m_ratio[i]}")
        for k in range(3):
            if tr["weight"][k] == 0:
                continue  # no traced ray: the lobe's nominal direction is not observable
            off = max(abs(tr["lo"][k] - m_theta[i, k]), abs(tr["hi"][k] - m_theta[i, k]))
            if off > DIRECTION_TOL_DEG:
                bad.append(
                    f"{where}: lobe {k} direction {tr['lo'][k]}..{tr['hi'][k]} "
                    f"model {m_theta[i, k]}"
                )
            fresnel = tr["ratio"][k] / tr["weight"][k]
            if abs(fresnel - m_fresnel[i, k]) > 1e-9 * max(m_fresnel[i, k], 1e-300):
                bad.append(f"{where}: lobe {k} Fresnel traced {fresnel} model {m_fresnel[i, k]}")
    return bad


@pytest.mark.parametrize("beta2_deg", WEDGES_DEG)
def test_sharp_lobes_match_raytrace_on_a_grid_with_regime_boundaries(beta2_deg):
    thetas = list(np.arange(-87.5, 90.0, 2.5)) + special_angles_deg(beta2_deg)
    bad = mismatches(beta2_deg, thetas, 1.46, N_RAYS)
    assert not bad, "\n".join(bad[:20])


@pytest.mark.parametrize("n", [1.5 + 0.3j, 1.0001])
@pytest.mark.parametrize("beta2_deg", [10.0, 45.0, 60.0])
def test_sharp_lobes_match_raytrace_for_complex_and_near_unit_index(beta2_deg, n):
    thetas = list(np.arange(-85.0, 90.0, 10.0)) + special_angles_deg(beta2_deg)
    bad = mismatches(beta2_deg, thetas, n, N_RAYS)
    assert not bad, "\n".join(bad[:20])


@pytest.mark.slow
@pytest.mark.parametrize("beta2_deg", WEDGES_DEG)
def test_sharp_lobes_match_raytrace_on_a_fine_grid(beta2_deg):
    # 0.5-degree steps offset from the coarse grid; 10_000 rays keep the weight error <= 1e-4.
    thetas = list(np.arange(-89.75, 90.0, 0.5))
    bad = mismatches(beta2_deg, thetas, 1.46, 10_000)
    assert not bad, "\n".join(bad[:20])
