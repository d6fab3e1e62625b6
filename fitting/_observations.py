"""The observation table a fit consumes, and the spectral setup of its channels.

One row per photo x wedge x channel [conventions §1, §8, §9]. Angles are in radians here; a
table in degrees is converted at the edge (`Observations.from_rows` accepts `*_deg` keys).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from stairfit.model import materials as _materials
from stairfit.model import spectral as _spectral

from ._errors import FitInputError

HALF_PI = np.pi / 2
ANGLE_TOL_RAD = 1e-9
"""Angles may exceed +-90 deg by this much (rounding of a degree value) and are then clipped."""

_FLOAT_FIELDS = ("theta_i_rad", "theta_o_rad", "beta2_rad", "layer_um", "value", "stderr")
_INT_FIELDS = ("wedge_index", "channel_index", "photo_index", "roi_index")
CORR_FIELDS = ("corr_01", "corr_02", "corr_12")
"""The pairwise error correlations of a group's channels (0, 1), (0, 2), (1, 2)."""
CORR_TOL = 1e-9
"""Rows of one group must agree on their correlations to this much."""
_BOOL_FIELDS = ("use", "saturated")


class Observations(NamedTuple):
    """Measured relative radiance, one row per photo x wedge x channel (an immutable pytree).

    * `theta_i_rad`, `theta_o_rad`: angles of incidence and observation in the wedge-face frame
      [conventions §1], radians, in [-pi/2, pi/2].
    * `beta2_rad`: the wedge angle of the row's wedge [conventions §2]; `layer_um`: its layer
      thickness `l1` in micrometres.
    * `wedge_index` (0 .. n_wedges-1), `channel_index` (row of the spectral setup),
      `photo_index` (bookkeeping only).
    * `value`: relative radiance [conventions §9]; `stderr`: its standard error (> 0).
    * `use`: False excludes the row from every fit; `saturated` records why (True = the camera
      clipped). Saturated rows are *excluded*, not treated as censored (docs/fitting.md).
    * `roi_index`: rows with the same `roi_index >= 0` (one photo x wedge: its channels) have
      correlated errors; -1 (the default) = independent. `corr_01`, `corr_02`, `corr_12`: the
      correlations of the errors of the group's channel 0 and 1, 0 and 2, 1 and 2 rows (the
      same on every row of the group; default 0). The fit whitens each group with
      `C = S R S (+ model error)` (docs/fitting.md §Correlated channels).
    * `view_spread`: the row's viewing-angle spread as a multiple (>= 0) of the aperture's
      (default 1) [conventions §9]: the eroded ROI's share of its face's (< 1: the ROI is
      narrower than its face), or for an ROI placed through a pinhole its own spread over the
      scene's (above 1 for a face longer along its slope than the scene's extent assumes;
      docs/imaging.md §Viewing spread).

    Build it with `Observations.from_arrays` or `Observations.from_rows`, which validate.
    """

    theta_i_rad: NDArray
    theta_o_rad: NDArray
    beta2_rad: NDArray
    layer_um: NDArray
    wedge_index: NDArray
    channel_index: NDArray
    value: NDArray
    stderr: NDArray
    use: NDArray
    photo_index: NDArray
    saturated: NDArray
    roi_index: NDArray
    corr_01: NDArray
    corr_02: NDArray
    corr_12: NDArray
    view_spread: NDArray

    @property
    def n_rows(self) -> int:
        """Number of rows, used or not."""
        return int(self.value.shape[0])

    @property
    def n_used(self) -> int:
        """Number of rows that enter the fit."""
        return int(np.count_nonzero(self.use))

    @property
    def n_wedges(self) -> int:
        """Number of wedges (1 + the largest `wedge_index`)."""
        return int(self.wedge_index.max()) + 1

    @property
    def wedge_beta2_rad(self) -> NDArray:
        """The wedge angle of each wedge, `(n_wedges,)`."""
        out = np.full(self.n_wedges, np.nan)
        out[self.wedge_index] = self.beta2_rad
        return out

    @property
    def wedge_layer_um(self) -> NDArray:
        """The layer thickness of each wedge, `(n_wedges,)`."""
        out = np.full(self.n_wedges, np.nan)
        out[self.wedge_index] = self.layer_um
        return out

    @property
    def excluded_rows(self) -> NDArray:
        """Indices of the rows that do not enter the fit."""
        return np.flatnonzero(~self.use)

    @classmethod
    def from_arrays(
        cls,
        *,
        theta_i_rad: ArrayLike,
        theta_o_rad: ArrayLike,
        beta2_rad: ArrayLike,
        layer_um: ArrayLike,
        wedge_index: ArrayLike,
        channel_index: ArrayLike,
        value: ArrayLike,
        stderr: ArrayLike,
        use: ArrayLike | None = None,
        photo_index: ArrayLike | None = None,
        saturated: ArrayLike | None = None,
        roi_index: ArrayLike | None = None,
        corr_01: ArrayLike | None = None,
        corr_02: ArrayLike | None = None,
        corr_12: ArrayLike | None = None,
        view_spread: ArrayLike | None = None,
    ) -> Observations:
        """Validated observations from equal-length 1-D arrays (scalars broadcast).

        `use` defaults to all True; `saturated` rows are always excluded (`use` set False);
        `roi_index` defaults to -1 (independent rows), the correlations to 0, `view_spread`
        to 1. Raises `FitInputError` naming the row, the field and the fix for: an empty table,
        mismatched lengths, non-finite or out-of-range angles, a wedge angle outside (0, 90)
        deg, a non-positive layer, NaN values or non-positive/NaN standard errors in used rows,
        inconsistent wedge geometry, a table in which every row is excluded, and groups
        (`roi_index`) with a channel outside 0-2 or twice, or with correlations that are not
        finite, outside [-1, 1] or differ between the group's rows.
        """
        fields: dict[str, ArrayLike | None] = {
            "theta_i_rad": theta_i_rad,
            "theta_o_rad": theta_o_rad,
            "beta2_rad": beta2_rad,
            "layer_um": layer_um,
            "wedge_index": wedge_index,
            "channel_index": channel_index,
            "value": value,
            "stderr": stderr,
            "use": use,
            "photo_index": photo_index,
            "saturated": saturated,
            "roi_index": roi_index,
            "corr_01": corr_01,
            "corr_02": corr_02,
            "corr_12": corr_12,
            "view_spread": view_spread,
        }
        return _validate(cls(**_columns(fields)))

    @classmethod
    def from_rows(cls, rows: Sequence[Mapping[str, object]]) -> Observations:
        """Validated observations from a list of dict rows (e.g. a parsed CSV table).

        Each row needs `theta_i_rad` or `theta_i_deg`, `theta_o_rad` or `theta_o_deg`,
        `beta2_rad` or `beta2_deg` (or `wedge_deg`), `layer_um`, `wedge_index`,
        `channel_index`, `value`, `stderr`; optional `use`, `photo_index`, `saturated`,
        `roi_index`, `corr_01`, `corr_02`, `corr_12`, `view_spread`. Other keys are ignored.
        Degrees are converted to radians here [conventions §1].
        """
        if len(rows) == 0:
            raise FitInputError(_EMPTY)
        aliases = {
            "theta_i_rad": ("theta_i_deg",),
            "theta_o_rad": ("theta_o_deg",),
            "beta2_rad": ("beta2_deg", "wedge_deg"),
        }
        cols: dict[str, list[object]] = {}
        required = ("layer_um", "wedge_index", "channel_index", "value", "stderr")
        for i, row in enumerate(rows):
            for key, alts in aliases.items():
                if key in row:
                    cols.setdefault(key, []).append(row[key])
                    continue
                for alt in alts:
                    if alt in row:
                        cols.setdefault(key, []).append(np.deg2rad(_as_float(row[alt], i, alt)))
                        break
                else:
                    raise FitInputError(
                        f"observation row {i} has no {key!r} (nor {' / '.join(alts)}); add the "
                        "column to the measurement table"
                    )
            for key in required:
                if key not in row:
                    raise FitInputError(
                        f"observation row {i} has no {key!r}; add the column to the "
                        "measurement table"
                    )
                cols.setdefault(key, []).append(row[key])
            for key, default in _OPTIONAL_DEFAULTS:
                cols.setdefault(key, []).append(row.get(key, default))
        return cls.from_arrays(**{k: np.asarray(v, dtype=object) for k, v in cols.items()})


_OPTIONAL_DEFAULTS: tuple[tuple[str, object], ...] = (
    ("use", True),
    ("photo_index", 0),
    ("saturated", False),
    ("roi_index", -1),
    *((k, 0.0) for k in CORR_FIELDS),
    ("view_spread", 1.0),
)
"""Optional columns of `from_rows` and their defaults."""

_EMPTY = (
    "the observation table is empty: give at least one row (photo x wedge x channel) with "
    "value and stderr"
)


def _row_count(fields: Mapping[str, ArrayLike | None]) -> int:
    """The common length of the array columns (scalars broadcast); `FitInputError` if there is
    none, if it is 0, or if the columns disagree."""
    lengths = {k: np.size(v) for k, v in fields.items() if v is not None and np.ndim(v) > 0}
    if not lengths:
        raise FitInputError(_EMPTY)
    n = max(lengths.values())
    bad = {k: m for k, m in lengths.items() if m != n}
    if bad:
        raise FitInputError(
            f"observation columns have different lengths ({bad}, others {n}); every column "
            "needs one entry per row"
        )
    if n == 0:
        raise FitInputError(_EMPTY)
    return n


def _columns(fields: Mapping[str, ArrayLike | None]) -> dict[str, NDArray]:
    """Every column as a typed 1-D array of the common length; defaults for the optional ones
    (`use` True, `photo_index` 0, `saturated` False, `roi_index` -1, correlations 0);
    saturated rows are not used."""
    n = _row_count(fields)
    arrays: dict[str, NDArray] = {}
    for k in (*_FLOAT_FIELDS, *CORR_FIELDS):
        data = fields[k] if fields[k] is not None or k not in CORR_FIELDS else 0.0
        arrays[k] = _column(k, data, n, float)
    spread = fields.get("view_spread")
    arrays["view_spread"] = _column("view_spread", 1.0 if spread is None else spread, n, float)
    for k in _INT_FIELDS:
        default = {"photo_index": 0, "roi_index": -1}.get(k)
        arrays[k] = _column(k, fields[k] if fields[k] is not None else default, n, int)
    use, saturated = fields["use"], fields["saturated"]
    arrays["use"] = _column("use", True if use is None else use, n, bool)
    arrays["saturated"] = _column("saturated", False if saturated is None else saturated, n, bool)
    arrays["use"] = arrays["use"] & ~arrays["saturated"]
    return arrays


def _as_float(x: object, row: int, field: str) -> float:
    try:
        return float(x)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise FitInputError(
            f"observation row {row}: {field} = {x!r} is not a number; fix the measurement table"
        ) from None


def _column(name: str, data: ArrayLike | None, n: int, dtype: type) -> NDArray:
    """One column as a 1-D array of length n; a clear error for missing or non-numeric data."""
    if data is None:
        raise FitInputError(f"the observation column {name!r} is missing; give one entry per row")
    arr = np.asarray(data)
    if arr.ndim == 0:
        arr = np.full(n, arr.item())
    try:
        if dtype is bool:
            ok = arr.dtype.kind in "biu" or (
                arr.dtype == object
                and all(isinstance(v, bool | np.bool_) or v in (0, 1) for v in arr.tolist())
            )
            if not ok:
                raise ValueError
            out = np.asarray(arr.astype(bool), dtype=bool)
        elif dtype is int:
            f = arr.astype(float)
            if np.any(~np.isfinite(f)) or np.any(f != np.round(f)):
                raise ValueError
            out = f.astype(np.int64)
        else:
            out = arr.astype(float)
    except (TypeError, ValueError):
        kind = {bool: "booleans", int: "whole numbers", float: "numbers"}[dtype]
        bad = _first_bad(arr, dtype)
        raise FitInputError(
            f"observation row {bad}: {name} = {arr[bad]!r} is invalid; the column must hold {kind}"
        ) from None
    return out


def _first_bad(arr: NDArray, dtype: type) -> int:
    for i, x in enumerate(arr):
        if dtype is bool and not (isinstance(x, bool | np.bool_) or x in (0, 1)):
            return i
        try:
            f = float(x)
            if dtype is int and (not np.isfinite(f) or f != round(f)):
                return i
        except (TypeError, ValueError):
            return i
    return 0


def _fail(obs: Observations, field: str, rows: NDArray, what: str, fix: str) -> None:
    """Raise `FitInputError` naming the first bad row (its photo, wedge, channel), the field,
    its value, how many more rows are bad, and the fix."""
    i = int(rows[0])
    more = f" (and {rows.size - 1} more rows)" if rows.size > 1 else ""
    val = getattr(obs, field)[i]
    raise FitInputError(
        f"observation row {i} (photo {obs.photo_index[i]}, wedge {obs.wedge_index[i]}, "
        f"channel {obs.channel_index[i]}): {field} = {val!r} {what}{more}; {fix}"
    )


def _check_rows(obs: Observations, used: NDArray) -> None:
    """Angles, wedge angle, layer, indices, value and stderr of every used row."""
    for field in ("theta_i_rad", "theta_o_rad"):
        x = getattr(obs, field)[used]
        bad = used[~np.isfinite(x) | (np.abs(x) > HALF_PI + ANGLE_TOL_RAD)]
        if bad.size:
            _fail(obs, field, bad, "is outside [-90, 90] deg",
                  "angles are in radians in the wedge-face frame [conventions §1]; convert "
                  "degrees with np.deg2rad or exclude the row")  # fmt: skip
    b2 = obs.beta2_rad[used]
    bad = used[~np.isfinite(b2) | (b2 <= 0.0) | (b2 >= HALF_PI)]
    if bad.size:
        _fail(obs, "beta2_rad", bad, "is outside (0, 90) deg", "give the wedge angle in radians")
    lay = obs.layer_um[used]
    bad = used[~np.isfinite(lay) | (lay <= 0.0)]
    if bad.size:
        _fail(obs, "layer_um", bad, "is not a positive length", "give the layer thickness in um")
    for field in ("wedge_index", "channel_index"):
        bad = np.flatnonzero(getattr(obs, field) < 0)
        if bad.size:
            _fail(obs, field, bad, "is negative", "indices count from 0")
    bad = used[~np.isfinite(obs.value[used])]
    if bad.size:
        _fail(obs, "value", bad, "is not a finite number",
              "fix the measurement or set use=False for the row")  # fmt: skip
    spread = obs.view_spread[used]
    bad = used[~np.isfinite(spread) | (spread < 0.0)]
    if bad.size:
        _fail(obs, "view_spread", bad, "is not a finite multiple >= 0",
              "it is the row's viewing-angle spread over the aperture's (1 = the whole face); "
              "fix the measurement table")  # fmt: skip
    se = obs.stderr[used]
    bad = used[~np.isfinite(se) | (se <= 0.0)]
    if bad.size:
        _fail(obs, "stderr", bad, "must be a finite standard error > 0",
              "fix the measurement table (a zero or missing uncertainty cannot be weighted) or "
              "set use=False for the row")  # fmt: skip


def _check_wedges(obs: Observations, used: NDArray) -> None:
    """One geometry per wedge: every used row of a wedge agrees on beta2 and layer thickness."""
    for field in ("beta2_rad", "layer_um"):
        col = getattr(obs, field)
        for w in np.unique(obs.wedge_index[used]):
            rows = used[obs.wedge_index[used] == w]
            vals = col[rows]
            if np.ptp(vals) > 1e-9 * max(1.0, np.abs(vals).max()):
                _fail(obs, field, rows[vals != vals[0]],
                      f"differs from the other rows of wedge {w} ({vals[0]!r})",
                      "each wedge_index must describe one wedge")  # fmt: skip


def _check_groups(obs: Observations, used: NDArray) -> None:
    """Rows of one group (`roi_index >= 0`, used): channels 0-2 at most once each; in groups of
    more than one used row, the same finite correlations in [-1, 1] on every row."""
    grouped = used[obs.roi_index[used] >= 0]
    if grouped.size == 0:
        return
    fix = "rows with the same roi_index are the channels (0, 1, 2) of one ROI; fix roi_index"
    bad = grouped[obs.channel_index[grouped] > 2]
    if bad.size:
        _fail(obs, "channel_index", bad, "is above 2 in a group of correlated rows", fix)
    order = np.lexsort((obs.channel_index[grouped], obs.roi_index[grouped]))
    g = grouped[order]
    same = (obs.roi_index[g][1:] == obs.roi_index[g][:-1]) & (
        obs.channel_index[g][1:] == obs.channel_index[g][:-1]
    )
    if np.any(same):
        _fail(obs, "channel_index", g[1:][same], "appears twice in its roi_index group", fix)
    ids, counts = np.unique(obs.roi_index[g], return_counts=True)
    multi = g[np.isin(obs.roi_index[g], ids[counts > 1])]  # groups of more than one used row
    for field in CORR_FIELDS:
        col = getattr(obs, field)
        bad = multi[~np.isfinite(col[multi]) | (np.abs(col[multi]) > 1.0)]
        if bad.size:
            _fail(obs, field, bad, "is not a correlation in [-1, 1]",
                  "give the ROI's measured channel correlation, or 0 if it is unknown")  # fmt: skip
        first: dict[int, float] = {}
        for i in multi:
            first.setdefault(int(obs.roi_index[i]), float(col[i]))
        ref = np.array([first[int(obs.roi_index[i])] for i in multi])
        bad = multi[np.abs(col[multi] - ref) > CORR_TOL]
        if bad.size:
            _fail(obs, field, bad, "differs from the other rows of its roi_index group",
                  "every row of one ROI carries the same correlations")  # fmt: skip


def _loose_zero(col: NDArray, loose: NDArray) -> NDArray:
    """A correlation column with 0 where no group reads it (`loose`) or it is not finite."""
    return np.where(loose | ~np.isfinite(col), 0.0, col)


def _sanitised(obs: Observations) -> Observations:
    """Angles clipped to the hemisphere; unused rows given finite, harmless values (their
    wedge's geometry, value 0, stderr 1, no group) so that no NaN can reach a derivative
    through a masked branch; the original values are not needed by any fit. Correlations that
    no group reads (ungrouped or unused rows) are set to 0."""
    unused = ~obs.use
    loose = unused | (obs.roi_index < 0)
    clipped = obs._replace(
        theta_i_rad=np.clip(obs.theta_i_rad, -HALF_PI, HALF_PI),
        theta_o_rad=np.clip(obs.theta_o_rad, -HALF_PI, HALF_PI),
        roi_index=np.where(unused, -1, obs.roi_index),
        **{k: _loose_zero(getattr(obs, k), loose) for k in CORR_FIELDS},
    )
    if not np.any(unused):
        return clipped
    used = obs.use
    w_beta2 = np.zeros(obs.n_wedges)
    w_layer = np.ones(obs.n_wedges)
    w_beta2[obs.wedge_index[used]] = obs.beta2_rad[used]
    w_layer[obs.wedge_index[used]] = obs.layer_um[used]
    w_beta2[w_beta2 == 0] = np.pi / 4
    return clipped._replace(
        theta_i_rad=np.where(unused, 0.0, clipped.theta_i_rad),
        theta_o_rad=np.where(unused, 0.0, clipped.theta_o_rad),
        beta2_rad=np.where(unused, w_beta2[obs.wedge_index], obs.beta2_rad),
        layer_um=np.where(unused, w_layer[obs.wedge_index], obs.layer_um),
        value=np.where(unused, 0.0, obs.value),
        stderr=np.where(unused, 1.0, obs.stderr),
        view_spread=np.where(unused, 1.0, obs.view_spread),
    )


def _validate(obs: Observations) -> Observations:
    """Check every field; return the observations with unused rows sanitised (`_sanitised`)."""
    used = np.flatnonzero(obs.use)
    if used.size == 0:
        n_sat = int(np.count_nonzero(obs.saturated))
        raise FitInputError(
            f"all {obs.n_rows} observation rows are excluded ({n_sat} saturated, "
            f"{obs.n_rows - n_sat} flagged use=False); nothing is left to fit — re-expose the "
            "saturated photos or un-flag rows"
        )
    _check_rows(obs, used)
    _check_wedges(obs, used)
    _check_groups(obs, used)
    return _sanitised(obs)


# --- spectral setup -------------------------------------------------------------------------


class Spectral(NamedTuple):
    """What each channel sees [conventions §7, §8]: `(n_channels, K)` arrays.

    `n_base` is the material's index at the channel's wavelength samples (without `delta_n`;
    complex if absorbing), `weights` the channel's normalised weights there (rows sum to 1),
    `wavelength_nm` the samples. `K = 81` is full 5 nm sampling; `K = 1` is one effective
    wavelength per channel (weight 1) — a speed/accuracy knob.
    """

    n_base: NDArray
    weights: NDArray
    wavelength_nm: NDArray

    @property
    def n_channels(self) -> int:
        """Number of channels."""
        return int(self.weights.shape[0])

    @property
    def n_samples(self) -> int:
        """Wavelength samples per channel (K)."""
        return int(self.weights.shape[1])


def spectral_setup(
    material: str | _materials.Dispersion | _materials.PerChannel = "pla",
    camera: str = "ideal",
    illuminant: str = "D65",
    sampling: str = "full",
    channels: Sequence[int] | None = None,
) -> Spectral:
    """The spectral setup for a fit [conventions §7, §8].

    `material` is a name from `stairfit.model.MATERIALS`, a dispersion model, or one index per
    camera channel (`materials.PerChannel`, constant across each band); `camera` and
    `illuminant` name a sensitivity set and a CIE illuminant (`stairfit.model.spectral`).
    `sampling="full"` keeps every 5 nm sample (K = 81); `"effective"` collapses each channel to
    its weighted mean wavelength (K = 1). `channels` selects camera channels (e.g. `(1,)` for a
    single green/grey channel); the observations' `channel_index` counts within the selection.
    """
    if sampling not in ("full", "effective"):
        raise FitInputError(f"sampling = {sampling!r}; use 'full' (5 nm) or 'effective' (K = 1)")
    try:
        disp = _materials.get_material(material) if isinstance(material, str) else material
        cw = _spectral.channel_weights(camera, illuminant)
    except ValueError as exc:
        raise FitInputError(str(exc)) from None
    if sampling == "effective":
        wl = cw.effective_nm[:, None]
        weights = np.ones_like(wl)
    else:
        wl = np.broadcast_to(cw.wavelength_nm, cw.weights.shape).copy()
        weights = np.asarray(cw.weights, float)
    try:  # a dispersion model at each sample, or a per-channel index per row
        n_base = np.asarray(_materials.index_per_channel(disp, wl))
    except ValueError as exc:
        raise FitInputError(str(exc)) from None
    if channels is not None:
        idx = np.asarray(channels, dtype=int)
        if idx.ndim != 1 or idx.size == 0 or idx.min() < 0 or idx.max() >= weights.shape[0]:
            raise FitInputError(
                f"channels = {channels!r}; choose camera channels from 0 .. {weights.shape[0] - 1}"
            )
        n_base, weights, wl = n_base[idx], weights[idx], wl[idx]
    return Spectral(n_base=n_base, weights=weights, wavelength_nm=wl)


def check_compatible(obs: Observations, spec: Spectral) -> None:
    """Raise `FitInputError` when a used row names a channel the spectral setup lacks."""
    used = obs.use
    bad = np.flatnonzero(used & (obs.channel_index >= spec.n_channels))
    if bad.size:
        i = int(bad[0])
        raise FitInputError(
            f"observation row {i}: channel_index = {obs.channel_index[i]} but the spectral setup "
            f"has {spec.n_channels} channel(s); fix channel_index or select more channels in "
            "spectral_setup"
        )
    if spec.weights.shape != spec.n_base.shape:
        raise FitInputError(
            f"spectral setup: n_base {spec.n_base.shape} and weights {spec.weights.shape} must "
            "have the same (n_channels, K) shape"
        )
    if not np.all(np.isfinite(spec.weights)) or np.any(
        np.abs(spec.weights.sum(axis=1) - 1.0) > 1e-6
    ):
        raise FitInputError(
            "spectral setup: every channel's weights must be finite and sum to 1 [conventions §8]"
        )
    if np.any(np.real(spec.n_base) <= 1.0):
        raise FitInputError(
            "spectral setup: the refractive index must have a real part > 1 [conventions §6]"
        )
