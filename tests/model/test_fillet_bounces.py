"""How many times a ray reflects on the staircase with tip arcs and fillets (issue 15).

docs/rounded.md §1: no bound holds over the whole domain (rays parallel to a facet creep along
the fillet), but `fillet_bounce_bound(theta_i, beta2) = 4 + pi / (4 delta)`, with `delta` the
angle between the incident direction and the nearer facet, bounds every ray the independent
tracer (tests/raytrace.py) follows, over wedges 10-80 deg, tip and fillet radii up to the
largest that fit, and angles of incidence to +-89.9 deg. Also the range helper's errors.
"""

from __future__ import annotations

import numpy as np
import pytest
from raytrace import Staircase, trace

from stairfit import model

DEG = np.pi / 180
L1 = 150.0
# (r_tip, r_f) as fractions of min(l1, l2): small, medium, both large, fillet alone, fillet
# at its bound beside a small tip
RADII = [(0.1, 0.1), (0.2, 0.4), (0.5, 0.5), (0.0, 0.5), (0.05, 0.95)]


def _angles(beta2_deg: float, step: float) -> list[float]:
    """theta_i (deg) on a grid, 1 and 3 deg from both facet-grazing angles, and near grazing."""
    b1 = 90.0 - beta2_deg
    near = [a + d for a in (b1, -beta2_deg) for d in (-3.0, -1.0, 1.0, 3.0)]
    grid = [float(a) for a in np.arange(-89.0, 89.5, step)]
    return [a for a in [*grid, *near, -89.9, 89.9] if abs(a) < 90.0]


def _check_bound(beta2_deg: float, step: float, n_rays: int) -> float:
    """Trace the grid; assert no ray exceeds the bound; return the largest count / bound."""
    cap = min(L1, L1 / np.tan(beta2_deg * DEG))
    worst = 0.0
    for tip, fil in RADII:
        st = Staircase(beta2_deg, L1, tip * cap, fil * cap)
        for ti in _angles(beta2_deg, step):
            bound = float(model.fillet_bounce_bound(ti * DEG, beta2_deg * DEG))
            if not np.isfinite(bound) or bound > 1e3:
                continue  # at (or within 0.05 deg of) a facet-grazing angle: no finite claim
            res = trace(st, ti, None, n_rays=n_rays, max_bounces=int(bound) + 2)
            assert res.n_lost == 0
            most = int(res.n_bounces.max())
            assert res.n_trapped == 0 and most <= bound, (beta2_deg, tip, fil, ti, most, bound)
            worst = max(worst, most / bound)
    return worst


@pytest.mark.parametrize("beta2_deg", [10, 30, 45, 60, 80])
def test_no_ray_exceeds_the_bounce_bound(beta2_deg):
    worst = _check_bound(beta2_deg, step=8.0, n_rays=2000)
    assert worst > 0.3  # the grid reaches rays that come near the bound: the check has teeth


@pytest.mark.slow
@pytest.mark.parametrize("beta2_deg", [10, 20, 30, 40, 45, 50, 60, 70, 80])
def test_no_ray_exceeds_the_bounce_bound_dense(beta2_deg):
    _check_bound(beta2_deg, step=2.0, n_rays=10_000)


def test_bounces_grow_like_one_over_the_angle_to_a_facet():
    """The bound is not a constant: the most reflections grow as theta_i approaches a facet's
    direction (the 1 / delta of the creeping rays, docs/rounded.md §1)."""
    st = Staircase(30.0, L1, 5.0, 60.0)
    most = {}
    for d in (5.0, 0.5):
        most[d] = int(trace(st, 60.0 - d, None, n_rays=20_000, max_bounces=400).n_bounces.max())
    assert most[0.5] > 4 * most[5.0], most
    # at the facet-grazing angles themselves (up to rounding of the radians): no finite bound
    assert model.fillet_bounce_bound(60 * DEG, 30 * DEG) > 1e12
    assert model.fillet_bounce_bound(-30 * DEG, 30 * DEG) > 1e12


def test_sharp_and_rounded_profiles_need_at_most_two():
    """Without a fillet the bound is not needed: two reflections (docs/rounded.md §1)."""
    for b2 in (10, 45, 80):
        cap = min(L1, L1 / np.tan(b2 * DEG))
        for ti in (-60.0, -20.0, 0.0, 40.0, 80.0):
            assert trace(Staircase(b2, L1, 0.5 * cap), ti, None, n_rays=2000).n_bounces.max() <= 2


def test_max_fillet_radius_leaves_room_for_the_tips():
    assert float(model.max_fillet_radius(30 * DEG, L1, 30.0)) == pytest.approx(120.0)
    assert float(model.max_fillet_radius(60 * DEG, L1, 30.0)) == pytest.approx(
        L1 / np.sqrt(3) - 30.0
    )


@pytest.mark.parametrize(
    ("tip", "fil", "words"),
    [
        (30.0, -1.0, ["fillet_radius_um = -1 um is negative", ">= 0"]),
        (30.0, 60.0, ["beta2 = 60 deg", "layer_um = 150", "edge_radius_um = 30", "r_f <= 56.6"]),
        (90.0, 0.0, ["edge_radius_um = 90 um does not fit"]),
    ],
)
def test_check_fillet_radius_names_wedge_layer_and_bound(tip, fil, words):
    with pytest.raises(ValueError) as err:
        model.check_fillet_radius(60 * DEG, L1, tip, fil)
    message = str(err.value)
    assert "\n" not in message
    for w in words:
        assert w in message, message
    model.check_fillet_radius(60 * DEG, L1, 30.0, 56.6)  # at the bound: accepted


def test_each_ray_takes_the_independent_tracers_path():
    """Ray by ray against the independent tracer (which also searches the neighbouring cells):
    the model's tracer, which tests only the five primitives of a ray's groove (docs/rounded.md
    §11, "the groove"), reflects each ray as often and sends it the same way, over wedges
    10-80 deg, the radii above and angles of incidence to +-89 deg and 1 deg from the
    facet-grazing ones. Both start ray `j` at the midpoint of stratum `j` of the ray front at
    the top of the tip arcs. At most 1 ray in 1000 may differ (a ray that meets a tangency can
    go either way by rounding); measured: none."""
    from stairfit.model._fillet import _trace

    n_rays, bounces = 400, 16
    cases, ours_in = [], []
    for b2 in (10.0, 30.0, 60.0, 80.0):
        cap = min(L1, L1 / np.tan(b2 * DEG))
        angles = [*np.arange(-89.0, 89.5, 22.0), 89.0 - b2, 91.0 - b2, 1.0 - b2, -1.0 - b2]
        for tip, fil in RADII:
            for ti in angles:
                cases.append(trace(Staircase(b2, L1, tip * cap, fil * cap), float(ti), None,
                                   n_rays=n_rays, max_bounces=bounces))  # fmt: skip
                ours_in.append((ti * DEG, b2 * DEG, L1, tip * cap, fil * cap))
    args = (np.array(a) for a in zip(*ours_in, strict=True))
    ours = _trace(*args, rays=n_rays, bounces=bounces)
    n_ours = np.sum(np.asarray(ours.hit), axis=-1)
    esc_ours = np.asarray(ours.escaped)
    theta_ours = np.rad2deg(np.asarray(ours.theta_o))
    differ = 0
    for i, res in enumerate(cases):
        assert res.n_lost == 0
        same = (res.escaped == esc_ours[i]) & np.where(
            res.escaped,
            (res.n_bounces == n_ours[i]) & (np.abs(res.theta_o_deg - theta_ours[i]) < 1e-7),
            True,
        )
        differ += int(np.sum(~same))
    total = len(cases) * n_rays
    assert differ <= total // 1000, (differ, total)
    assert sum(int(np.sum(r.n_bounces >= 3)) for r in cases) > 1000  # multi-bounce paths met
