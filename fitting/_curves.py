"""The fitted model between the measured views: dense curves over the viewing angle, evaluated
by the fit's own forward (`_forward.model_values` at the fitted `z`) [conventions §1, §9, §11].

`model_at` evaluates a fit at the rows of another observation table (and, for the lab model,
their 3-D geometry). `model_curves` builds, for every wedge, light angle and channel of a fit,
a grid of viewing angles from its first to its last measured view (every `DENSE_STEP_RAD` and
at each measured view) and evaluates the model there:

* the in-plane model at the row's own light angle, each viewing angle's share of the patch's
  viewing spread interpolated linearly between the measured rows' (so that at a measured view
  the curve is that row's fitted value, to rounding);
* the lab model at the group's mean geometry: the conv-weighted mean direction of its light
  nodes and their irradiance, a view of the nodes' mean component along the layer lines turned
  through the grid, one node per angle. Averaging over a face's nodes changes a value by up to
  a few per cent at a lobe's flank, so the mean-geometry curve is scaled by the ratio of each
  measured row's fitted value to the curve there, interpolated linearly between the views:
  the curve passes through the fitted values and keeps the mean geometry's shape between them.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import numpy as np
from numpy.typing import NDArray

from stairfit import model

from ._errors import FitInputError
from ._forward import model_values
from ._lab import LabGeometry
from ._observations import Observations
from ._problem import prepare
from ._result import FitResult

DENSE_STEP_RAD = float(np.deg2rad(0.5))
"""The grid step of the dense curves (0.5 deg), besides every measured view."""

_GROUP_DECIMALS = 9
"""Light angles (rad) equal to this many decimals belong to one curve."""


class ModelCurve(NamedTuple):
    """The fitted model of one wedge, light angle and channel at `theta_o_rad` (sorted; the
    measured views included): `value` (relative radiance, as `FitResult.model`), `rows` the
    indices of the measured rows on the curve, `mean_geometry` True for a lab fit (its curve is
    the mean geometry's, scaled through the fitted values; `ratio_range` the extreme scale
    factors, (1, 1) for the in-plane model)."""

    wedge: int
    channel: int
    theta_i_rad: float
    theta_o_rad: NDArray
    value: NDArray
    rows: NDArray
    mean_geometry: bool
    ratio_range: tuple[float, float]


def model_at(fit: FitResult, observations: Observations, lab: LabGeometry | None = None) -> NDArray:
    """The fitted model (`fit.z`, its variant and facets) at every row of `observations`, as the
    fit evaluates its own rows (`model_values`): the same spectral setup, aperture, resolution,
    fixed parameters and bound of the edge radius. `observations` must hold every wedge index
    of the fit (unused rows will do); `lab`: their 3-D geometry, needed exactly when the fit
    used the lab model."""
    problem = fit.problem
    if problem is None or fit.spec is None:
        raise FitInputError("model_at: the fit carries no prepared problem; fit it again")
    if (lab is None) != (problem.lab is None):
        need = "needs" if problem.lab is not None else "takes no"
        raise FitInputError(f"model_at: this fit {need} lab geometry for the new rows")
    if observations.n_wedges != problem.observations.n_wedges:
        raise FitInputError(
            f"model_at: the rows have {observations.n_wedges} wedges, the fit "
            f"{problem.observations.n_wedges}; give a row (used or not) for every wedge index"
        )
    new = prepare(observations, problem.spectral, fixed=problem.fixed, aperture=problem.aperture,
                  resolution=problem.resolution, lab=lab)  # fmt: skip
    data = new.arrays_for(fit.spec)._replace(r_max_um=problem.data.r_max_um)
    values = jax.jit(model_values, static_argnums=1)(np.asarray(fit.z), new.static_for(fit.spec),
                                                     data)[0]  # fmt: skip
    return np.asarray(values, float)


class _Group(NamedTuple):
    wedge: int
    theta_i: float
    rows: NDArray  # used rows of the group, every channel


def _groups(obs: Observations) -> list[_Group]:
    """The used rows by wedge and light angle (equal to `_GROUP_DECIMALS`; the group's angle
    is its first row's, exactly)."""
    used = np.flatnonzero(obs.use)
    ti = np.round(obs.theta_i_rad[used], _GROUP_DECIMALS)
    keys = sorted({(int(obs.wedge_index[r]), float(t)) for r, t in zip(used, ti, strict=True)})
    groups = []
    for w, t in keys:
        rows = used[(obs.wedge_index[used] == w) & (ti == t)]
        groups.append(_Group(w, float(obs.theta_i_rad[rows[0]]), rows))
    return groups


def _grid(views: NDArray, step: float) -> NDArray:
    """The measured views and a grid of `step` between the first and the last, sorted."""
    lo, hi = float(views.min()), float(views.max())
    fill = lo + step * np.arange(int(np.floor((hi - lo) / step)) + 1)
    return np.unique(np.concatenate([views, fill]))


def _spread_at(theta: NDArray, views: NDArray, spread: NDArray) -> NDArray:
    """The rows' viewing-spread shares interpolated linearly at `theta` (views averaged where a
    view was measured twice)."""
    uniq, inv = np.unique(views, return_inverse=True)
    mean = np.bincount(inv, spread) / np.bincount(inv)
    return np.interp(theta, uniq, mean)


def _dense_table(obs: Observations, groups: list[_Group], step: float
                 ) -> tuple[Observations, list[tuple[_Group, int, NDArray, slice]]]:  # fmt: skip
    """The observation rows of every curve (one per group x channel x grid angle), plus one
    unused row for every wedge index, and where each curve's rows are."""
    cols: dict[str, list] = {k: [] for k in ("ti", "to", "b2", "layer", "wedge", "ch", "spread")}
    where = []
    for g in groups:
        for c in np.unique(obs.channel_index[g.rows]):
            rows = g.rows[obs.channel_index[g.rows] == c]
            theta = _grid(obs.theta_o_rad[rows], step)
            start = len(cols["ti"])
            spread = _spread_at(theta, obs.theta_o_rad[rows], obs.view_spread[rows])
            for key, v in (
                ("ti", g.theta_i),
                ("b2", obs.beta2_rad[rows[0]]),
                ("layer", obs.layer_um[rows[0]]),
                ("wedge", g.wedge),
                ("ch", c),
            ):
                cols[key].extend([v] * theta.size)  # fmt: skip
            cols["to"].extend(theta)
            cols["spread"].extend(spread)
            where.append((g, int(c), theta, slice(start, start + theta.size)))
    n_dense = len(cols["ti"])
    wb, wl = obs.wedge_beta2_rad, obs.wedge_layer_um
    for w in range(obs.n_wedges):  # every wedge index, so that the layout is the fit's
        for key, v in (
            ("ti", 0.0),
            ("to", 0.0),
            ("b2", wb[w] if np.isfinite(wb[w]) else 0.5),
            ("layer", wl[w] if np.isfinite(wl[w]) else 150.0),
            ("wedge", w),
            ("ch", int(obs.channel_index[0])),
            ("spread", 1.0),
        ):
            cols[key].append(v)  # fmt: skip
    use = np.arange(len(cols["ti"])) < n_dense
    table = Observations.from_arrays(
        theta_i_rad=cols["ti"], theta_o_rad=cols["to"], beta2_rad=cols["b2"],
        layer_um=cols["layer"], wedge_index=np.asarray(cols["wedge"], int),
        channel_index=np.asarray(cols["ch"], int), value=1.0, stderr=1.0, use=use,
        view_spread=cols["spread"],
    )  # fmt: skip
    return table, where


def _mean_geometry(lab: LabGeometry, rows: NDArray, theta: NDArray
                   ) -> tuple[NDArray, NDArray, NDArray, NDArray]:  # fmt: skip
    """One node per angle of `theta` at the mean geometry of the keys of `rows`: the
    weight x irradiance-weighted mean light direction and irradiance, the view turned to each
    angle at the nodes' mean component along the layer lines [conventions §11]."""
    keys = np.unique(lab.key[rows])
    wgt = (lab.weight[keys] * lab.irradiance[keys]).ravel()
    w_i = np.einsum("n,nj->j", wgt, lab.w_i[keys].reshape(-1, 3))
    w_i = w_i / np.linalg.norm(w_i)
    irr = float(np.sum(wgt) / np.sum(lab.weight[keys]))
    t_o = float(np.sum(wgt * lab.w_o[keys].reshape(-1, 3)[:, 1]) / np.sum(wgt))
    w_o = np.asarray(model.face_direction(theta, np.full(theta.shape, t_o)))
    n = theta.size
    return np.broadcast_to(w_i, (n, 3)), w_o, np.ones(n), np.full(n, irr)


def _dense_lab(lab: LabGeometry, table: Observations, where: list) -> LabGeometry:
    """The dense table's lab geometry: one key (one node) per group and grid angle, at the
    group's mean geometry, shared by the group's channels; the unused rows at the end read
    the first key."""
    w_i, w_o, weight, irr, wedge = [], [], [], [], []
    key = np.zeros(table.n_rows, int)
    first: dict[tuple[int, float], tuple[NDArray, int]] = {}  # a group's grid, its first key
    n_keys = 0
    for g, _, theta, sl in where:
        ident = (g.wedge, g.theta_i)
        if ident not in first or not np.array_equal(first[ident][0], theta):
            parts = _mean_geometry(lab, g.rows, theta)
            for acc, part in zip((w_i, w_o, weight, irr), parts, strict=True):
                acc.append(part)
            wedge.append(np.full(theta.size, g.wedge))
            first[ident] = (theta, n_keys)
            n_keys += theta.size
        key[sl] = first[ident][1] + np.arange(theta.size)
    return LabGeometry(
        w_i=np.concatenate(w_i)[:, None, :], w_o=np.concatenate(w_o)[:, None, :],
        weight=np.concatenate(weight)[:, None], irradiance=np.concatenate(irr)[:, None],
        wedge=np.concatenate(wedge).astype(int), key=key,
    )  # fmt: skip


def model_curves(fit: FitResult, step_rad: float = DENSE_STEP_RAD) -> list[ModelCurve]:
    """Dense curves of the fitted model over the viewing angle (see the module text), one per
    wedge, light angle and channel with used rows; one evaluation of the fit's forward."""
    problem = fit.problem
    if problem is None or fit.spec is None:
        raise FitInputError("model_curves: the fit carries no prepared problem; fit it again")
    obs = problem.observations
    table, where = _dense_table(obs, _groups(obs), step_rad)
    lab = None if problem.lab is None else _dense_lab(problem.lab, table, where)
    values = model_at(fit, table, lab)
    curves = []
    for g, c, theta, sl in where:
        rows = g.rows[obs.channel_index[g.rows] == c]
        value = values[sl]
        ratio_range = (1.0, 1.0)
        if lab is not None:
            at = np.searchsorted(theta, obs.theta_o_rad[rows])
            base = value[at]
            ratio = np.where(base > 0, fit.model[rows] / np.where(base > 0, base, 1.0), 1.0)
            value = value * _spread_at(theta, obs.theta_o_rad[rows], ratio)
            ratio_range = (float(ratio.min()), float(ratio.max()))
        curves.append(ModelCurve(g.wedge, c, g.theta_i, theta, value, rows, lab is not None,
                                 ratio_range))  # fmt: skip
    return curves
