"""A prepared fit problem: observations + spectral setup turned into static, traced arrays.

Preparation runs once per scene; every variant and every start reuses it, and every variant of
the sharp model shares one compilation (see `_forward`).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import numpy as np

from stairfit import model

from ._errors import FitInputError
from ._forward import Data, Resolution, Static, light_nodes, resolution_parts
from ._lab import LabData, LabGeometry, lab_data
from ._observations import Observations, Spectral, check_compatible
from ._params import DEFAULTS, PARAM_NAMES, Layout, Parameter, Params, Priors, Variant
from ._whiten import GroupArrays, group_arrays


def max_edge_radius_um(obs: Observations) -> float:
    """Largest edge radius (um) every used wedge can hold: the smallest
    `stairfit.model.max_edge_radius(beta2, layer_um)` (`min(l1, l2)`) over the used wedges;
    the finest wedge sets the bound shared by all [conventions §2]."""
    used = obs.use
    return float(np.min(np.asarray(model.max_edge_radius(obs.beta2_rad[used], obs.layer_um[used]))))


class FreeSpec(NamedTuple):
    """Which slots are free: parameter names, the wedges that have their own (free) width,
    fixed values that override `Problem.fixed` (a parameter fixed on its bound), per-wedge
    widths fixed at a value (a wedge whose own width the data do not constrain), and the facet
    kernel of the lab model (`stairfit.model.LAB_KERNELS`; only "gaussian" without lab
    geometry)."""

    free: frozenset[str]
    own_sigma: frozenset[int] = frozenset()
    overrides: tuple[tuple[str, float], ...] = ()
    fixed_sigma: tuple[tuple[int, float], ...] = ()
    kernel: str = "gaussian"

    def fixing(self, param: str, value: float) -> FreeSpec:
        """A copy with `param` fixed at `value` (on a bound, or unidentified)."""
        return self._replace(
            free=self.free - {param}, overrides=(*self.overrides, (param, float(value)))
        )


class Problem(NamedTuple):
    """Everything a fit needs, prepared once per scene (observations, spectral setup, options).

    `data` holds the traced arrays (its `free`, `x_fixed` and `sigma_source` are filled per
    variant by `arrays_for`); `fixed` gives the values of fixed parameters; `priors` are
    resolved against the data; `wedge_deg` is for labels only; `lab` the rows' 3-D geometry
    when the scene is fitted with the lab model (`_lab.LabGeometry`), else None.
    """

    observations: Observations
    spectral: Spectral
    layout: Layout
    data: Data
    fixed: Params
    priors: Priors
    r_max_um: float
    aperture: model.Aperture
    resolution: int | Resolution | None
    wedge_deg: np.ndarray
    lab: LabGeometry | None = None

    def static_for(self, spec: FreeSpec) -> Static:
        """The hashable configuration for a variant (which forward, model-error term)."""
        fixed = self.fixed._replace(**dict(spec.overrides))
        filleted = "fillet_radius_um" in spec.free or float(fixed.fillet_radius_um) > 0.0
        rounded = filleted or "edge_radius_um" in spec.free or float(fixed.edge_radius_um) > 0.0
        model_error = "model_error_frac" in spec.free or float(fixed.model_error_frac) > 0.0
        resolution, fillet_rays = resolution_parts(self.resolution)
        return Static(
            layout=self.layout,
            rounded=rounded,
            model_error=model_error,
            correlated=self.correlated,
            aperture=self.aperture,
            resolution=resolution,
            filleted=filleted,
            fillet_rays=fillet_rays,
            lab=None if self.lab is None else spec.kernel,
        )

    @property
    def correlated(self) -> bool:
        """True when some rows share a group with correlated errors (`Observations.roi_index`)."""
        return bool(np.any(np.asarray(self.data.grp_mask).sum(axis=1) > 1))

    def arrays_for(self, spec: FreeSpec) -> Data:
        """The traced arrays for a variant: free mask, fixed values, width tying."""
        source, free = _tying(self.layout, spec)
        arrays = {"free": free, "x_fixed": self._fixed_values(spec), "sigma_source": source}
        return self.data._replace(**jax.device_put(arrays))

    def parameters(self, spec: FreeSpec) -> tuple[Parameter, ...]:
        """One record per slot of `z` for a variant: resolved prior, free flag, the scene's
        `r_max` as the edge radius's upper bound, the wedge angle of each per-wedge width."""
        _, free = _tying(self.layout, spec)
        out = []
        for p in self.layout.parameters():
            radius = p.param in ("edge_radius_um", "fillet_radius_um")
            upper = self.r_max_um if radius else p.bounds[1]
            deg = None if p.wedge is None else float(self.wedge_deg[p.wedge])
            prior = getattr(self.priors, p.param)
            out.append(
                p._replace(bounds=(p.bounds[0], upper), prior=prior, free=bool(free[p.slot]),
                           wedge_deg=deg)
            )  # fmt: skip
        return tuple(out)

    def _fixed_values(self, spec: FreeSpec) -> np.ndarray:
        """Physical value of every slot when fixed (`Problem.fixed`, then the spec's
        overrides and pinned widths; the shared width is the widths' geometric mean)."""
        lay = self.layout
        x = np.zeros(lay.size)
        sigma_w = self.fixed.sigma_per_wedge(lay.n_wedges)
        x[lay.slot("sigma_rad")] = float(np.exp(np.mean(np.log(sigma_w))))
        for w, value in enumerate(sigma_w):
            x[lay.slot("sigma_rad", w)] = value
        for name in PARAM_NAMES[1:]:
            x[lay.slot(name)] = float(getattr(self.fixed, name))
        for name, value in spec.overrides:
            x[lay.slot(name)] = value
        for w, value in spec.fixed_sigma:
            x[lay.slot("sigma_rad", w)] = value
        return x


def _tying(lay: Layout, spec: FreeSpec) -> tuple[np.ndarray, np.ndarray]:
    """(slot holding each wedge's width, free mask of the slots) for a variant.

    Free widths: a wedge with its own width (free, or pinned by `fixed_sigma`) reads its slot,
    the others share slot 0 (free when any wedge uses it). Fixed widths: every wedge keeps its
    own given value.
    """
    free = np.zeros(lay.size, dtype=bool)
    own_slot = np.array([lay.slot("sigma_rad", w) for w in range(lay.n_wedges)], dtype=int)
    if "sigma_rad" not in spec.free:
        source = own_slot
    else:
        pinned = {w for w, _ in spec.fixed_sigma}
        own = spec.own_sigma - pinned
        source = np.where(
            [w in own or w in pinned for w in range(lay.n_wedges)], own_slot, 0
        ).astype(int)
        for w in own:
            free[lay.slot("sigma_rad", w)] = True
        free[lay.slot("sigma_rad")] = bool(np.any(source == 0))
    for name in PARAM_NAMES[1:]:
        free[lay.slot(name)] = name in spec.free
    return source, free


def check_float64() -> None:
    """Fits need float64 [conventions §10]; the library never flips the global flag itself."""
    if not jax.config.read("jax_enable_x64"):
        raise FitInputError(
            "stairfit.fitting needs float64: call jax.config.update('jax_enable_x64', True) "
            "at the start of your program [conventions §10]"
        )


def prepare(
    obs: Observations,
    spectral: Spectral,
    *,
    fixed: Params = DEFAULTS,
    priors: Priors | None = None,
    aperture: model.Aperture | None = None,
    resolution: int | Resolution | None = None,
    lab: LabGeometry | None = None,
) -> Problem:
    """Validate the combination and build the traced arrays (see `Problem`). `lab`: the rows'
    3-D geometry, to fit the lab model (docs/fitting.md §10)."""
    check_float64()
    if not isinstance(obs, Observations):
        raise FitInputError(
            "observations must be an Observations table; build it with "
            "Observations.from_arrays or Observations.from_rows"
        )
    check_compatible(obs, spectral)
    lay = Layout(obs.n_wedges)
    r_max = max_edge_radius_um(obs)
    _check_fixed(fixed, lay.n_wedges, r_max)
    value_max = float(np.max(np.abs(obs.value[obs.use])))
    aperture = aperture or model.Aperture()
    if lab is not None:
        lab = lab.check(obs.n_rows)
    return Problem(
        observations=obs,
        spectral=spectral,
        layout=lay,
        data=_data(obs, spectral, aperture, lay, r_max, lab),
        fixed=fixed,
        priors=(priors or Priors()).resolved(r_max, value_max if value_max > 0 else 1.0),
        r_max_um=r_max,
        aperture=aperture,
        resolution=resolution,
        wedge_deg=np.rad2deg(obs.wedge_beta2_rad),
        lab=lab,
    )


def as_problem(
    observations: Observations | Problem,
    spectral: Spectral | None,
    *,
    fixed: Params = DEFAULTS,
    priors: Priors | None = None,
    aperture: model.Aperture | None = None,
    resolution: int | Resolution | None = None,
) -> Problem:
    """`observations` if it is a prepared `Problem`, else `prepare` of it with the rest."""
    if isinstance(observations, Problem):
        return observations
    if spectral is None:
        raise FitInputError("give the spectral setup (spectral_setup(...)) with observations")
    return prepare(observations, spectral, fixed=fixed, priors=priors, aperture=aperture,
                   resolution=resolution)  # fmt: skip


def _data(
    obs: Observations,
    spectral: Spectral,
    aperture: model.Aperture,
    lay: Layout,
    r_max: float,
    lab: LabGeometry | None = None,
) -> Data:
    """The traced arrays of a scene (per variant, `free`, `x_fixed`, `sigma_source` are
    replaced by `Problem.arrays_for`), moved to the device in one batched transfer."""
    grid = evaluation_grid(obs, np.asarray(spectral.n_base), np.asarray(spectral.weights, float),
                           aperture)  # fmt: skip
    grid = padded_grid(grid)
    corr = np.stack([obs.corr_01, obs.corr_02, obs.corr_12], axis=1)
    groups = padded_groups(group_arrays(obs.use, obs.roi_index, obs.channel_index, corr))
    data = Data(
        theta_i=np.asarray(obs.theta_i_rad, float),
        theta_o=np.asarray(obs.theta_o_rad, float),
        beta2=np.asarray(obs.beta2_rad, float),
        layer_um=np.asarray(obs.layer_um, float),
        value=np.asarray(obs.value, float),
        stderr=np.asarray(obs.stderr, float),
        use=np.asarray(obs.use.astype(float)),
        **{k: np.asarray(v) for k, v in grid.items() if k != "r_layer"},
        free=np.zeros(lay.size, dtype=bool),
        x_fixed=np.zeros(lay.size),
        sigma_source=np.zeros(lay.n_wedges, dtype=int),
        r_max_um=np.asarray(r_max if r_max > 0 else 1.0),
        grp_rows=groups.rows,
        grp_mask=groups.mask,
        grp_corr=groups.corr,
        lab=_lab_arrays(lab, obs, spectral),
    )
    return jax.device_put(data)


def _lab_arrays(lab: LabGeometry | None, obs: Observations, spectral: Spectral) -> LabData:
    """The lab model's traced arrays (`_lab.lab_data`), keys padded to a shape bucket."""
    samples = np.asarray(spectral.n_base), np.asarray(spectral.weights, float)
    size = 0 if lab is None else bucket(lab.weight.shape[0])
    return lab_data(lab, obs.wedge_beta2_rad, obs.wedge_layer_um, obs.n_rows, samples, size)


def bucket(n: int) -> int:
    """`n` rounded up to a shape bucket: a multiple of 8, or of a quarter of the largest power
    of two not above `n` once that is larger (56 for 54, 160 for 130; at most 7 entries or 25%
    more). Scenes of one design whose evaluation keys or groups differ by a few entries (a face
    flagged in one photo, angles that coincide in one scene and not in the other) get arrays of
    one shape, so that one compiled program serves them all (issue 14)."""
    step = max(8, (1 << (max(n, 1).bit_length() - 1)) // 4)
    return -(-max(n, 1) // step) * step


def _pad_rows(a: np.ndarray, size: int) -> np.ndarray:
    """`a` with its last entry (along axis 0) repeated up to `size` entries."""
    extra = size - a.shape[0]
    return a if extra <= 0 else np.concatenate([a, np.repeat(a[-1:], extra, axis=0)])


def padded_grid(grid: dict) -> dict:
    """The evaluation grid with its keys (R) and geometry entries (G) padded to `bucket` sizes
    by copies of their last entry: valid angles, evaluated and never read (no row points at a
    padded key, no key at a padded geometry entry; rows gather from keys, keys from geometry,
    and nothing sums over either)."""
    n_keys, n_geo = grid["r_ti"].shape[0], grid["g_ti"].shape[0]
    out = dict(grid)
    for k in ("r_ti", "r_b2", "r_layer", "r_wedge", "r_geo"):
        out[k] = _pad_rows(np.asarray(grid[k]), bucket(n_keys))
    for k in ("r_to", "r_so"):  # per key `(R, .)`, or one row shared by every key `(1, T)`
        a = np.asarray(grid[k])
        out[k] = _pad_rows(a, bucket(n_keys)) if a.shape[0] == n_keys > 1 else a
    for k in ("g_ti", "g_b2", "g_layer"):
        out[k] = _pad_rows(np.asarray(grid[k]), bucket(n_geo))
    return out


def padded_groups(groups: GroupArrays) -> GroupArrays:
    """The groups padded to a `bucket` count by empty groups (mask 0, row 0, identity
    correlation: the padded slots' convention of `group_arrays`), which whiten to 0 and add
    nothing to any sum."""
    n = groups.rows.shape[0]
    extra = bucket(n) - n
    eye = np.broadcast_to(np.eye(groups.corr.shape[-1]), (extra, *groups.corr.shape[1:]))
    return GroupArrays(
        np.concatenate([groups.rows, np.zeros((extra, groups.rows.shape[1]), groups.rows.dtype)]),
        np.concatenate([groups.mask, np.zeros((extra, groups.mask.shape[1]))]),
        np.concatenate([groups.corr, eye]),
    )


def evaluation_grid(
    obs: Observations, n_base: np.ndarray, weights: np.ndarray, aperture: model.Aperture
) -> dict:
    """Where the model is evaluated: its geometry depends on (theta_i, wedge) only, its
    broadening also on `theta_o`, and only its Fresnel factors on the channel.

    Keys (R) are the distinct (theta_i, wedge) combinations if the full key x view grid (T
    distinct viewing angles) is at most twice as large as the number of distinct (theta_i,
    wedge, theta_o); otherwise those triples, each with its own view (`r_to` per key). Every
    key is evaluated for all channels at once (`r_n`, `r_w`: `(C, K)`), so the broadening is
    shared by the channels; a row reads `[r_key, r_t, r_c]`. The geometry is computed once per
    distinct (theta_i + aperture offset, beta2, layer_um): `g_ti`, `g_b2`, `g_layer`, indexed
    by `r_geo` (key, aperture node).
    """
    channel = np.minimum(np.where(obs.use, obs.channel_index, 0), n_base.shape[0] - 1)
    pair = np.stack([obs.theta_i_rad, obs.wedge_index.astype(float)], axis=1)
    uniq, key = np.unique(pair, axis=0, return_inverse=True)
    views, t_idx = np.unique(obs.theta_o_rad, return_inverse=True)
    spread = np.where(obs.use, obs.view_spread, 1.0)
    triple = np.stack(
        [obs.theta_i_rad, obs.wedge_index.astype(float), obs.theta_o_rad, spread], axis=1
    )
    uniq_v, key_v = np.unique(triple, axis=0, return_inverse=True)
    shared = _shared_spread(key.ravel(), t_idx.ravel(), spread, (uniq.shape[0], views.size))
    if shared is not None and uniq.shape[0] * views.size <= 2 * uniq_v.shape[0]:
        keys, r_key, r_t, r_to = uniq, key.ravel(), t_idx.ravel(), views[None, :]
        r_so = shared
    else:
        keys, r_key = uniq_v, key_v.ravel()
        r_t, r_to, r_so = np.zeros(obs.n_rows, dtype=int), uniq_v[:, 2:3], uniq_v[:, 3:4]
    wedge = keys[:, 1].astype(int)
    b2_w, layer_w = np.zeros(obs.n_wedges), np.ones(obs.n_wedges)
    b2_w[obs.wedge_index] = obs.beta2_rad
    layer_w[obs.wedge_index] = obs.layer_um
    grid = {
        "r_key": r_key,
        "r_t": r_t,
        "r_c": channel,
        "r_ti": keys[:, 0],
        "r_b2": b2_w[wedge],
        "r_layer": layer_w[wedge],
        "r_wedge": wedge,
        "r_n": n_base,
        "r_w": weights,
        "r_to": r_to,
        "r_so": r_so,
    }
    return {**grid, **_geometry_keys(grid, aperture)}


def _shared_spread(
    r_key: np.ndarray, r_t: np.ndarray, spread: np.ndarray, shape: tuple[int, int]
) -> np.ndarray | None:
    """The rows' viewing-spread shares on the shared (key, view) grid, `(R, T)` (1 where no
    row is); None when two rows of one (key, view) differ (they need keys of their own)."""
    grid = np.ones(shape)
    grid[r_key, r_t] = spread
    return grid if np.array_equal(grid[r_key, r_t], spread) else None


def _geometry_keys(grid: dict, aperture: model.Aperture) -> dict:
    """Distinct (theta_i at each aperture node, beta2, layer_um) of the keys: the rounded
    geometry depends on nothing else, so a fit computes it once per entry."""
    r_ti, r_b2 = (np.asarray(grid[k], float) for k in ("r_ti", "r_b2"))
    ti = np.asarray(light_nodes(r_ti, r_b2, aperture)[0])
    shape = ti.shape  # (R, M)
    b2 = np.broadcast_to(np.asarray(grid["r_b2"], float)[:, None], shape)
    layer = np.broadcast_to(np.asarray(grid["r_layer"], float)[:, None], shape)
    combo = np.stack([ti.ravel(), b2.ravel(), layer.ravel()], axis=1)
    uniq, idx = np.unique(combo, axis=0, return_inverse=True)
    return {
        "r_geo": idx.reshape(shape),
        "g_ti": uniq[:, 0],
        "g_b2": uniq[:, 1],
        "g_layer": uniq[:, 2],
    }


def _check_fixed(fixed: Params, n_wedges: int, r_max: float) -> None:
    """Fixed values must be physical: positive widths (one or one per wedge) and scale,
    non-negative floor and model error, an edge radius in `[0, r_max]`."""
    try:
        fixed.sigma_per_wedge(n_wedges)
    except ValueError as exc:
        raise FitInputError(f"fixed parameters: {exc}") from None
    sigma = np.asarray(fixed.sigma_rad, float)
    checks = (
        ("sigma_rad", np.all(np.isfinite(sigma)) and np.all(sigma > 0), "> 0 rad"),
        ("scale", np.isfinite(fixed.scale) and fixed.scale > 0, "> 0"),
        ("floor", np.isfinite(fixed.floor) and fixed.floor >= 0, ">= 0"),
        (
            "model_error_frac",
            np.isfinite(fixed.model_error_frac) and fixed.model_error_frac >= 0,
            ">= 0",
        ),
        ("delta_n", np.isfinite(fixed.delta_n), "finite"),
        ("edge_radius_um", np.isfinite(fixed.edge_radius_um), "finite"),
        ("fillet_radius_um", np.isfinite(fixed.fillet_radius_um), "finite"),
    )
    for name, ok, need in checks:
        if not ok:
            raise FitInputError(
                f"fixed parameter {name} = {getattr(fixed, name)!r} must be {need}; pass a "
                "valid value in Params"
            )
    if not 0.0 <= float(fixed.edge_radius_um) <= r_max:
        raise FitInputError(
            f"fixed edge_radius_um = {fixed.edge_radius_um} is outside [0, r_max = {r_max:.4g}] "
            "um (r_max = the finest wedge's min(l1, l2)); choose a smaller radius"
        )
    rest = r_max - float(fixed.edge_radius_um)
    if not 0.0 <= float(fixed.fillet_radius_um) <= rest:
        raise FitInputError(
            f"fixed fillet_radius_um = {fixed.fillet_radius_um} is outside [0, r_max - "
            f"edge_radius_um = {rest:.4g}] um (tip arc and fillet must fit together on the "
            "finest wedge, r + r_f <= min(l1, l2)); choose a smaller fillet or edge radius"
        )


def spec_for(variant: Variant, problem: Problem) -> FreeSpec:
    """The free set of a variant on this scene (per-wedge widths only for wedges with data)."""
    unknown = variant.free - set(PARAM_NAMES)
    if unknown:
        raise FitInputError(
            f"variant {variant.name!r} frees unknown parameter(s) {sorted(unknown)}; known: "
            f"{', '.join(PARAM_NAMES)}"
        )
    own: frozenset[int] = frozenset()
    if variant.per_wedge_sigma and "sigma_rad" in variant.free:
        obs = problem.observations
        own = frozenset(int(w) for w in np.unique(obs.wedge_index[obs.use]))
    if variant.kernel != "gaussian" and problem.lab is None:
        raise FitInputError(
            f"variant {variant.name!r} has {variant.kernel} facets, which only the lab model "
            "has; give the scene's 3-D geometry (prepare(..., lab=...))"
        )
    return FreeSpec(free=frozenset(variant.free), own_sigma=own, kernel=variant.kernel)
