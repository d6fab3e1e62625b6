"""The 3-D lab model against the independent 3-D ray tracer (issue 40; docs/model.md §7).

`tests/raytrace3d.py` traces rays with 3-D directions over the extruded profile of
`tests/raytrace.py`, draws micro-normals for rough facets and carries two Jones vectors through
every reflection; it shares no code with `stairfit.model`. Checks:

* smooth facets, light out of the plane (wedges 10-80 deg, projected incidence in every regime,
  0-70 deg out of the plane): each traced lobe (rays grouped by their number of bounces and
  direction) carries `lab_lobes(...).ratio` (weights, 3-D Fresnel, the two-bounce s/p turn) to
  the tracer's stratification (within one ray's share of 20 000; measured 0.31 of it),
  and leaves exactly in the lobe's direction (`t_o = -t_i`, projected angle of Eqs. 4-6);
* rough facets (GGX and Beckmann): escaped rays binned in `(theta', t)` (3 deg x 0.05) against
  the model integrated over each bin (Gauss-Legendre, 8 x 8 nodes a bin). Single reflections
  agree to the tracer's noise; the two-bounce path within the bounds of docs/model.md §7.4.

The model's single-reflection part is written here from docs/model.md §7.3 with the model's
own pieces (`lit_fractions`, `facet_normals`, `microfacet_lobe`): `sum_k (L_k / l) V_k D F G /
(4 w_i . z)`; its two-bounce part is `lab_density_microfacet` minus that.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from raytrace import Staircase
from raytrace3d import Rough, direction, trace3d

from stairfit import model
from stairfit.model import _lab

DEG = np.pi / 180
LOBES = jax.jit(model.lab_lobes)

# ------------------------------------------------------------------------------------------
# Smooth facets: the sharp lobes in 3-D
# ------------------------------------------------------------------------------------------

SMOOTH_RAYS = 20_000


def _incidences(beta2_deg: float) -> list[float]:
    """Projected angles of incidence (deg) in regimes A, B (both sides of the boundary between
    'tread larger' and 'riser larger') and C, near their boundaries, up to 85 deg."""
    b1 = 90.0 - beta2_deg
    angles = [-80.0, -beta2_deg - 5.0, -beta2_deg + 5.0, b1 - beta2_deg - 7.0]
    angles += [b1 - beta2_deg + 7.0, b1 - 3.0, b1 + 5.0, 85.0]
    return sorted({float(np.clip(a, -85.0, 85.0)) for a in angles})


def _check_smooth(beta2_deg: float, n: complex, outs: tuple[float, ...]) -> float:
    """Compare every lobe for the incidences of `_incidences` and out-of-plane angles `outs`;
    returns the worst weight error in units of 1 / SMOOTH_RAYS."""
    worst = 0.0
    st = Staircase(beta2_deg)
    for theta in _incidences(beta2_deg):
        for out in outs:
            w_i = direction(theta, out, light=True)
            lobes = LOBES(w_i, beta2_deg * DEG, n)
            ratio, fresnel = np.asarray(lobes.ratio), np.asarray(lobes.fresnel)
            centre = np.asarray(lobes.theta_o)
            tr = trace3d(st, w_i, n, n_rays=SMOOTH_RAYS, seed=1)
            assert np.all(tr.status == 1), "every ray escapes a smooth sharp staircase"
            theta_o = np.arctan2(tr.w_o[:, 0], tr.w_o[:, 2])
            # each reflection keeps the component along the layer lines, mirrored: t_o = -t_i
            np.testing.assert_allclose(tr.w_o[:, 1], -w_i[1], atol=1e-14)
            np.testing.assert_allclose(float(lobes.t_o), -w_i[1], atol=1e-15)
            assert np.all(tr.n_bounces <= 2)
            once = tr.n_bounces == 1
            tread = once & (np.abs(theta_o - centre[0]) < np.abs(theta_o - centre[1]))
            groups = [tread, once & ~tread, tr.n_bounces == 2]
            for k, rays in enumerate(groups):
                # the directions agree exactly (to rounding)
                np.testing.assert_allclose(theta_o[rays], centre[k], atol=1e-12)
                power = float(np.sum(tr.power[rays]))
                # the stratified rays resolve each edge of a lit width to a fraction of one
                # ray: the weight is within one ray's share (measured: 0.31 of it at most)
                err = abs(power - ratio[k]) / max(fresnel[k], 1e-300) * SMOOTH_RAYS
                assert err <= 1.0, (theta, out, model.LOBE_NAMES[k], power, ratio[k])
                worst = max(worst, err)
    return worst


@pytest.mark.parametrize("beta2_deg", [10, 30, 45, 60, 80])
def test_smooth_lobes_match_tracer_out_of_plane(beta2_deg):
    _check_smooth(beta2_deg, 1.46, (0.0, 20.0, 45.0, 70.0))


@pytest.mark.parametrize("beta2_deg", [30, 60])
def test_smooth_lobes_match_tracer_complex_index(beta2_deg):
    _check_smooth(beta2_deg, 1.5 + 0.3j, (0.0, 45.0))


def test_two_bounce_polarisation_turn_is_seen_by_the_tracer():
    """The s/p turn of docs/model.md §7.2 is not a detail the comparison above could miss:
    45 deg out of the plane of a 30-deg wedge, the retroreflection without it (the in-plane
    rule `(R_s R_s' + R_p R_p') / 2` at the 3-D local cosines) would be seven times the traced
    power, and with it the tracer agrees to the stratification."""
    w_i = direction(15.0, 45.0, light=True)
    tr = trace3d(Staircase(30.0), w_i, 1.46, n_rays=SMOOTH_RAYS, seed=1)
    traced = float(np.sum(tr.power[tr.n_bounces == 2]))
    lobes = LOBES(w_i, 30 * DEG, 1.46)
    weight = float(lobes.weight[2])
    c = np.sqrt(1.0 - w_i[1] ** 2)
    u = 30 * DEG + float(model.projected_incidence(w_i).theta)
    tread, riser = model.fresnel_sp(c * np.cos(u), 1.46), model.fresnel_sp(c * np.sin(u), 1.46)
    unturned = weight * 0.5 * float(tread.s * riser.s + tread.p * riser.p)
    assert abs(traced - float(lobes.ratio[2])) <= 1.0 / SMOOTH_RAYS * float(lobes.fresnel[2])
    assert traced < 0.2 * unturned  # measured 0.137 (docs/model.md §7.2)


# ------------------------------------------------------------------------------------------
# Rough facets: binned distributions
# ------------------------------------------------------------------------------------------

TH_EDGES = np.linspace(-90.0, 90.0, 61) * DEG  # projected viewing angle theta', 3 deg
T_EDGES = np.linspace(-1.0, 1.0, 41)  # component along the layer lines t, 0.05
BIN_NODES = 8  # Gauss-Legendre nodes per bin and axis (6 left 3e-3 of the power at alpha 0.03)
ROUGH_RAYS = 200_000
# docs/model.md §7.4's bounds on the two-bounce path (from the light alone), in fractions of
# all reflected power: (L1 distance of the binned distributions, difference of the totals),
# for projected incidence up to 75 deg and beyond (to 85 deg). Measured worst over the slow
# grid (432 cases, ROUGH_RAYS, seeds 1 and 2): 0.129, 0.060; 0.032, 0.027 (median L1 0.006);
# the bounds are those plus about a tenth, for rounding that differs between platforms (the
# rays are seeded).
MULTI_BOUNDS = {75.0: (0.14, 0.066), 85.0: (0.035, 0.03)}


def _multi_bounds(theta: float) -> tuple[float, float]:
    return MULTI_BOUNDS[75.0] if abs(theta) <= 75.0 else MULTI_BOUNDS[85.0]


def _bin_rule(edges: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    x, w = np.polynomial.legendre.leggauss(BIN_NODES)
    mid, half = 0.5 * (edges[1:] + edges[:-1]), 0.5 * np.diff(edges)
    return (mid[:, None] + half[:, None] * x).ravel(), (half[:, None] * w).ravel()


def _single(w_i, w_o, beta2, n, alpha, kind):
    """The single reflections of docs/model.md §7.3: `sum_k (L_k / l) V_k D F G / (4 w_i . z)`,
    `V_k` the smaller of the lit and the visible fraction of facet k."""
    inc, view = model.projected_incidence(w_i), model.projected_view(w_o)
    b = jnp.broadcast_to(beta2, inc.theta.shape)
    visible = jnp.minimum(model.lit_fractions(inc.theta, b), model.lit_fractions(-view.theta, b))
    normals = model.facet_normals(b)
    length = jnp.stack([jnp.cos(b), jnp.sin(b)], axis=-1)
    band = _lab._band(n, None)  # one wavelength sample: the index itself
    lobes = jnp.stack(
        [_lab.microfacet_lobe(w_i, w_o, normals[..., k, :], band, alpha, kind) for k in range(2)],
        -1,
    )
    return jnp.sum(length * visible * lobes, axis=-1) / w_i[..., 2]


@functools.partial(jax.jit, static_argnames=("kind",))
def _model_bins(w_i, beta2, n, alpha, kind):
    """The model's single reflections and two-bounce path integrated over every bin
    (`d omega = d theta' d t`), shapes (60, 40)."""
    th, w_th = _bin_rule(TH_EDGES)
    t, w_t = _bin_rule(T_EDGES)
    grid_th, grid_t = jnp.meshgrid(th, t, indexing="ij")
    w_o = model.face_direction(grid_th, grid_t)
    w_in = jnp.broadcast_to(w_i, w_o.shape)
    full = model.lab_density_microfacet(w_in, w_o, beta2, n, alpha, kind)
    single = _single(w_in, w_o, beta2, n, alpha, kind)
    shape = (TH_EDGES.size - 1, BIN_NODES, T_EDGES.size - 1, BIN_NODES)
    w_th, w_t = w_th.reshape(shape[:2]), w_t.reshape(shape[2:])

    def binned(p):
        return jnp.einsum("iajb,ia,jb->ij", p.reshape(shape), w_th, w_t)

    return binned(single), binned(full - single)


def _traced_bins(tr, rays: np.ndarray) -> np.ndarray:
    theta_o = np.arctan2(tr.w_o[:, 0], tr.w_o[:, 2])
    return np.histogram2d(theta_o, tr.w_o[:, 1], [TH_EDGES, T_EDGES], weights=tr.power * rays)[0]


class RoughComparison:
    """The tracer (two seeds) and the model for one rough case (`theta` its projected
    incidence, deg), in fractions of the traced
    reflected power (seed 1): `single_l1` and `single_noise` (the L1 distance of two seeds'
    single-reflection histograms over sqrt 2: the L1 distance one histogram has from its
    expectation), `single_z` (the difference of the single totals in standard errors),
    `multi_l1` and `multi_total` (the two-bounce path against every ray reflected twice or
    more), `multi_share` (the traced share of those rays)."""

    def __init__(self, kind: str, alpha: float, beta2_deg: float, theta: float, out: float):
        self.theta = theta
        w_i = direction(theta, out, light=True)
        single, multi = (
            np.asarray(a) for a in _model_bins(w_i, beta2_deg * DEG, 1.46, alpha, kind)
        )
        st, rough = Staircase(beta2_deg), Rough(alpha, kind)
        traces = [
            trace3d(st, w_i, 1.46, rough=rough, n_rays=ROUGH_RAYS, seed=seed) for seed in (1, 2)
        ]
        once = [_traced_bins(tr, tr.n_bounces == 1) for tr in traces]
        more = _traced_bins(traces[0], traces[0].n_bounces >= 2)
        total = traces[0].total
        p1 = traces[0].power[traces[0].n_bounces == 1]
        sigma = np.sqrt(max(np.sum(p1**2) - np.sum(p1) ** 2 / ROUGH_RAYS, 1e-300))
        self.single_l1 = np.abs(once[0] - single).sum() / total
        self.single_noise = np.abs(once[0] - once[1]).sum() / total / np.sqrt(2.0)
        self.single_z = (once[0].sum() - single.sum()) / sigma
        self.multi_l1 = np.abs(more - multi).sum() / total
        self.multi_total = (multi.sum() - more.sum()) / total
        self.multi_share = more.sum() / total


# (kind, alpha, beta2, theta_i', out of plane), deg: regimes B (the retroreflection peak of a
# 45-deg wedge, and near its boundaries) and C, in and out of the plane
ROUGH_CASES = [
    ("ggx", 0.03, 30, 20.0, 10.0),
    ("beckmann", 0.15, 45, -40.0, 30.0),
    ("ggx", 0.1, 45, 0.0, 20.0),
    ("beckmann", 0.06, 60, 45.0, 0.0),
    ("beckmann", 0.15, 10, 85.0, 0.0),  # regime C near grazing
]


@pytest.fixture(scope="module", params=ROUGH_CASES, ids=lambda c: "-".join(map(str, c)))
def rough(request) -> RoughComparison:
    return RoughComparison(*request.param)


def test_rough_single_reflections_match_tracer(rough):
    """Single reflections (docs/model.md §7.3, exact for single scattering): the binned
    distribution is as far from the model as one seed's histogram is from another's (the L1
    distance is within twice the two-seed noise estimate; heavy-tailed ray weights make that
    estimate itself scatter, measured ratios 0.65-1.56 over the slow grid) and the totals agree
    to 4 standard errors (measured at most 2.6)."""
    assert rough.single_l1 <= 2.0 * rough.single_noise, (rough.single_l1, rough.single_noise)
    assert abs(rough.single_z) <= 4.0


def test_rough_two_bounce_path_within_its_stated_error(rough):
    """docs/model.md §7.4: the two-bounce path's binned distribution and total differ from
    the rays the tracer reflects two or more times by at most `MULTI_BOUNDS` of all reflected
    power (the worst cases over the slow grid, `test_rough_grid_matches_tracer`)."""
    l1, total = _multi_bounds(rough.theta)
    assert rough.multi_l1 <= l1, rough.multi_l1
    assert abs(rough.multi_total) <= total, rough.multi_total


def _rough_incidences(beta2_deg: float) -> list[float]:
    """Projected angles of incidence (deg) for the rough grid: regimes A, B and C, near their
    boundaries, within 85 deg."""
    b1 = 90.0 - beta2_deg
    angles = [-70.0, -beta2_deg - 10.0, -beta2_deg + 5.0, 0.5 * (b1 - beta2_deg) - 0.5 * beta2_deg]
    angles += [b1 - beta2_deg, b1 - 5.0, b1 + 10.0, 75.0]
    return sorted({float(np.clip(a, -85.0, 85.0)) for a in angles})


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["ggx", "beckmann"])
@pytest.mark.parametrize("alpha", [0.03, 0.08, 0.15])
@pytest.mark.parametrize("beta2_deg", [10, 30, 45, 60, 80])
def test_rough_grid_matches_tracer(kind, alpha, beta2_deg):
    """The two checks above over the grid behind docs/model.md §7.4: every regime, in the
    plane and 45 deg out of it."""
    failed = []
    for out in (0.0, 45.0):
        for theta in _rough_incidences(beta2_deg):
            r = RoughComparison(kind, alpha, beta2_deg, theta, out)
            ok = r.single_l1 <= 2.0 * r.single_noise and abs(r.single_z) <= 4.0
            l1, total = _multi_bounds(theta)
            ok &= r.multi_l1 <= l1 and abs(r.multi_total) <= total
            if not ok:
                failed.append((theta, out, vars(r)))
    assert not failed, failed
