"""Gloss units (ISO 2813) of a printed surface from a fit folder's parameters or from given
ones, with uncertainties from the posterior (docs/gloss.md).

`fitted_gloss_model` reads what the gloss depends on from a fit folder (results.json, and
chain.npz when the posterior was sampled); `given_gloss_model` takes it from the user;
`gloss_table` evaluates `stairfit.model.gloss` at every requested surface angle, layer
orientation and glossmeter geometry. Degrees at this edge, radians inside the model
[conventions §1, §13].

Uncertainty: with posterior draws, the gloss of up to `GLOSS_DRAWS` of them (evenly spaced
through the thinned chain) gives its median, 16-84% interval and standard deviation; without
them, the least-squares covariance is carried through the gloss's gradient (the delta
method). Every row says which.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from .errors import UserError

if TYPE_CHECKING:
    import jax
    from jax.typing import ArrayLike

    from stairfit import model as m

    from ._jsontypes import JSONObject, JSONValue

DEG = np.pi / 180

GLOSS_DRAWS = 64
"""The most posterior draws whose gloss is computed: the 16-84% interval of 64 draws is within
about a tenth of a standard deviation of the chain's, at a sixty-fourth of the cost of 4000."""

GLOSS_ANGLES_DEG: tuple[float, ...] = (20.0, 60.0, 85.0)
"""The ISO 2813 geometries, in the order they are reported."""

LAYER_LINES = {0.0: "across (source downhill)", 90.0: "along", 180.0: "across (source uphill)"}
"""How the layer lines lie in the plane of incidence, by the azimuth (deg) [conventions §13]."""


def layer_lines(azimuth_deg: float) -> str:
    """The orientation of the layer lines for an azimuth in degrees: across, along, oblique."""
    a = float(azimuth_deg) % 360.0
    for key, name in LAYER_LINES.items():
        if abs(a - key) < 1e-9 or abs(a - key - 360.0) < 1e-9:
            return name
    if abs(a - 270.0) < 1e-9:
        return "along"
    return f"oblique ({a:g} deg from across)"


@dataclass(frozen=True)
class GlossModel:
    """What the gloss depends on, at the fit's optimum (or as given) and its uncertainty.

    `kind`: the facets ("gaussian", "ggx", "beckmann"); `rounded`: rounded edges are modelled;
    `index_nm`, `index`: the material's refractive index without `delta_n`, sampled in
    wavelength (interpolated linearly between, held outside; `index_at`); `lab`: the scale
    is the lab model's (3-D); False: the in-plane model's, which absorbed the out-of-plane
    density `line_gaussian(0, 0, sigma)` (docs/gloss.md §3). The parameter vector: `keys`
    (`(param, wedge)`), `names` (display labels), `best` (display units: widths in degrees),
    `draws` `(D, P)` posterior draws or None, `covariance` `(P, P)` or None; `fixed` the fixed
    parameters (display names, units); `wedge_deg` the wedges' angles (per-wedge widths are
    interpolated between them); `layer_um` the specimen's layer (None if unknown); `source`
    and `notes` for the reader.
    """

    kind: str
    rounded: bool
    index_nm: np.ndarray
    index: np.ndarray
    lab: bool
    keys: tuple[tuple[str, int | None], ...]
    names: tuple[str, ...]
    best: np.ndarray
    draws: np.ndarray | None
    covariance: np.ndarray | None
    fixed: dict[str, float]
    wedge_deg: np.ndarray | None
    layer_um: float | None
    source: str
    notes: tuple[str, ...] = ()

    @property
    def uncertainty(self) -> str:
        """How the uncertainty is obtained, in words."""
        if self.draws is not None:
            return f"posterior ({self.draws.shape[0]} draws)"
        if self.covariance is not None:
            return "covariance (delta method)"
        return "none"


class GlossRow(NamedTuple):
    """One surface in one geometry: gloss units at the optimum (`gloss`, its `specular` and
    `body` parts) and, when known, the posterior's median and 16-84% interval or the delta
    method's standard deviation (`sd`), and how (`uncertainty`)."""

    wedge_deg: float
    layer_um: float
    azimuth_deg: float
    layer_lines: str
    angle_deg: float
    gloss: float
    specular: float
    body: float
    median: float | None
    p16: float | None
    p84: float | None
    sd: float | None
    uncertainty: str


# --- the parameters -------------------------------------------------------------------------


def index_at(model: GlossModel, wavelength_nm: ArrayLike) -> np.ndarray:
    """The material's index (without `delta_n`) at `wavelength_nm`: linear between the samples
    of `model`, held at the end values outside them."""
    lam = np.asarray(wavelength_nm, float)
    order = np.argsort(model.index_nm)
    x, n = model.index_nm[order], np.asarray(model.index, complex)[order]
    return np.interp(lam, x, n.real) + 1j * np.interp(lam, x, n.imag)


def given_gloss_model(
    kind: str,
    index_nm: np.ndarray,
    index: np.ndarray,
    width: float,
    edge_radius_um: float = 0.0,
    body_albedo: float = 0.0,
    delta_n: float = 0.0,
) -> GlossModel:
    """Given parameters: the material's index `index` at `index_nm`; `width` is sigma in degrees
    for Gaussian facets, alpha for microfacet ones; `body_albedo` the diffuse body's albedo
    (its weight is `albedo / pi`)."""
    sigma_deg = width if kind == "gaussian" else float(np.degrees(np.arctan(width)))
    fixed = {"sigma_deg": sigma_deg, "delta_n": float(delta_n), "edge_radius_um":
             float(edge_radius_um), "floor": float(body_albedo) / np.pi, "scale": 1.0}  # fmt: skip
    return GlossModel(kind=kind, rounded=edge_radius_um > 0.0,
                      index_nm=np.asarray(index_nm, float), index=np.asarray(index, complex),
                      lab=True,
                      keys=(), names=(), best=np.zeros(0), draws=None, covariance=None,
                      fixed=fixed, wedge_deg=None, layer_um=None,
                      source="given parameters")  # fmt: skip


def _read_json(path: Path) -> JSONObject:
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise UserError(f"{path}: not found; give a `stairfit fit` output folder") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise UserError(
            f"{path}: cannot be read as results.json ({e}); re-run `stairfit fit`"
        ) from None


def _field(results: JSONObject, path: Path, *keys: str) -> JSONValue:
    """`results[k1][k2]...`, or a one-line UserError naming the missing field."""
    node: JSONValue = results
    for k in keys:
        if not isinstance(node, dict) or k not in node:
            raise UserError(
                f"{path}: field {'.'.join(keys)} is missing; the folder was written by another "
                "stairfit version or is incomplete: re-run `stairfit fit`"
            )
        node = node[k]
    return node


def _material_index(results: JSONObject, path: Path) -> tuple[np.ndarray, np.ndarray]:
    """The material's index (without `delta_n`) sampled in wavelength: results.json's
    `specimen.index` (every 10 nm), or from a folder written without it the `spectral`
    record's index at the camera channels' effective wavelengths."""
    index = (results.get("specimen") or {}).get("index")
    if index is not None:
        lam, n, k = (np.asarray(index[f], float) for f in ("wavelength_nm", "n", "k"))
        where = "specimen.index"
    else:
        lam = np.asarray(_field(results, path, "spectral", "effective_wavelength_nm"), float)
        n = np.asarray(_field(results, path, "spectral", "index_n"), float)
        k = np.asarray(_field(results, path, "spectral", "index_k"), float)
        where = "spectral.index_n"
    if lam.size == 0 or lam.shape != n.shape or n.shape != k.shape or not np.all(np.isfinite(n)):
        raise UserError(f"{path}: {where} is empty or malformed; re-run `stairfit fit`")
    return lam, n + 1j * k


def _draws(fit_dir: Path, results: JSONObject, keys: Sequence[tuple[str, int | None]],
           limit: int) -> np.ndarray | None:  # fmt: skip
    """Up to `limit` evenly spaced draws of the thinned chain (chain.npz), columns in the order
    of `keys`, display units (widths in degrees); None without a posterior."""
    from stairfit import fitting
    from stairfit.fitting.posterior import load_chain

    post = results.get("diagnostics", {}).get("posterior")
    if post is None:
        return None
    path = fit_dir / post.get("chain_file", "chain.npz")
    if not path.is_file():
        raise UserError(
            f"{path}: the posterior was sampled but its chain file is missing; restore it or "
            "re-run `stairfit fit`"
        )
    try:
        chain = load_chain(path)
    except (fitting.FitInputError, OSError, ValueError) as e:
        raise UserError(f"{path}: cannot be read ({e}); re-run `stairfit fit`") from None
    params = [str(p) for p in chain.get("parameters", ())]
    wedges = [None if int(w) < 0 else int(w) for w in chain.get("wedges", ())]
    ident = list(zip(params, wedges, strict=True))
    missing = [k for k in keys if k not in ident]
    if missing:
        raise UserError(f"{path}: has no column for {missing[0]}; re-run `stairfit fit`")
    cols = [ident.index(k) for k in keys]
    samples = np.asarray(chain["chain"], float)[int(post["burn_in"]) :: int(post["thin"])]
    flat = samples.reshape(-1, samples.shape[-1])[:, cols]
    if flat.shape[0] == 0:
        return None
    count = min(limit, flat.shape[0])
    pick = np.unique(np.linspace(0, flat.shape[0] - 1, count).round().astype(int))
    factor = np.array([1.0 / DEG if k[0] == "sigma_rad" else 1.0 for k in keys])
    return flat[pick] * factor


def fitted_gloss_model(fit_dir: str | Path, draws: int = GLOSS_DRAWS) -> GlossModel:
    """What the gloss depends on, from a fit folder (see `GlossModel`): the chosen variant's
    parameters (results.json), its facets and model of the directions, the material's index
    over wavelength, and its uncertainty: posterior draws (chain.npz) or the covariance. Any
    problem with the folder is a one-line UserError naming the file and the fix."""
    fit_dir = Path(fit_dir)
    if not fit_dir.is_dir():
        raise UserError(f"--fit {fit_dir}: no such folder; give a `stairfit fit` output folder")
    return gloss_model_from_results(_read_json(fit_dir / "results.json"), fit_dir, draws)


def gloss_model_from_results(
    results: JSONObject, fit_dir: Path, draws: int = GLOSS_DRAWS
) -> GlossModel:
    """`fitted_gloss_model` of results.json's content `results` (the chain file, if any, in
    `fit_dir`)."""
    from .results_file import (
        OlderResultsError,
        check_parameter_records,
        covariance_from_results,
        parameter_key,
    )

    path = fit_dir / "results.json"
    try:
        check_parameter_records(results, fit_dir)
    except OlderResultsError as e:
        raise UserError(str(e)) from None
    records = _field(results, path, "parameters")
    keys = tuple(parameter_key(r) for r in records)
    names = tuple(str(r["name"]) for r in records)
    best = np.array([float(r["least_squares"]["value"]) for r in records])
    directions = _field(results, path, "directions")
    kind = str(directions.get("facets", "gaussian"))
    fixed = {str(k): float(v) for k, v in _field(results, path, "fixed_parameters").items()}
    specimen = results.get("specimen") or {}
    wedge_deg = None
    if specimen.get("wedges"):
        wedge_deg = np.array([float(w["angle_deg"]) for w in specimen["wedges"]])
    per_wedge = [w for p, w in keys if p == "sigma_rad" and w is not None]
    if per_wedge and wedge_deg is None:
        raise UserError(
            f"{path}: the fit has a width per wedge but no specimen.wedges (their angles); "
            "re-run `stairfit fit` with this stairfit version"
        )
    notes = []
    if fixed.get("fillet_radius_um", 0.0) > 0.0 or any(p == "fillet_radius_um" for p, _ in keys):
        notes.append("the fit's concave fillets are not modelled out of the plane of incidence "
                     "(docs/model.md §7.6); the gloss leaves them out")  # fmt: skip
    rounded = any(p == "edge_radius_um" for p, _ in keys) or fixed.get("edge_radius_um", 0.0) > 0
    chain = _draws(fit_dir, results, keys, draws)
    lam, index = _material_index(results, path)
    return GlossModel(
        kind=kind, rounded=rounded, index_nm=lam, index=index,
        lab=directions.get("model") == "lab", keys=keys, names=names, best=best, draws=chain,
        covariance=None if chain is not None else covariance_from_results(results),
        fixed=fixed, wedge_deg=wedge_deg,
        layer_um=None if specimen.get("layer_um") is None else float(specimen["layer_um"]),
        source=f"fit folder {fit_dir}", notes=tuple(notes),
    )  # fmt: skip


# --- the surface of a parameter vector ------------------------------------------------------


def _value(
    model: GlossModel, vector: jax.Array, param: str, display: str, default: float
) -> jax.Array | float:
    """A shared parameter from the vector (free) or `fixed` (display name), else `default`."""
    key = (param, None)
    if key in model.keys:
        return vector[model.keys.index(key)]
    return model.fixed.get(display, default)


def _width_deg(model: GlossModel, vector: jax.Array, wedge_deg: ArrayLike) -> jax.Array | float:
    """The facets' width (deg) for a surface at `wedge_deg`: the shared width, or the per-wedge
    widths interpolated linearly in the wedge angle (held at the outermost wedges' values)."""
    import jax.numpy as jnp

    own = [(w, i) for i, (p, w) in enumerate(model.keys) if p == "sigma_rad" and w is not None]
    if not own:
        return _value(model, vector, "sigma_rad", "sigma_deg", float("nan"))
    assert model.wedge_deg is not None
    own.sort(key=lambda wi: model.wedge_deg[wi[0]])
    xs = jnp.asarray([model.wedge_deg[w] for w, _ in own])
    ys = jnp.stack([vector[i] for _, i in own])
    return jnp.interp(wedge_deg, xs, ys)


SURFACE_PARAMS = frozenset({"sigma_rad", "delta_n", "edge_radius_um", "scale", "floor"})
"""The fitted parameters `surface_of` reads: the delta method differentiates the gloss in these
alone (the model-error term, for one, changes no surface)."""


def surface_of(
    model: GlossModel, vector: jax.Array, wedge_deg: ArrayLike, layer_um: ArrayLike
) -> m.GlossSurface:
    """The `stairfit.model.GlossSurface` of a parameter vector (display units, in the order of
    `model.keys`) for a surface at `wedge_deg` with layers `layer_um`; traceable by JAX.

    The index: at the wavelengths of the glossmeter's luminous response (`luminous_rule`),
    with `delta_n`. The diffuse body's weight is `floor / scale`, the lab model's scale; an
    in-plane fit's
    scale absorbed the out-of-plane density `line_gaussian(0, 0, sigma)` (conventions §11), so
    its body weight is `floor line_gaussian(0, 0, sigma) / scale` (docs/gloss.md §3)."""
    import jax.numpy as jnp

    from stairfit import model as m

    width_rad = _width_deg(model, vector, wedge_deg) * DEG
    lam, weight = m.luminous_rule()
    n = jnp.asarray(index_at(model, lam)) + _value(model, vector, "delta_n", "delta_n", 0.0)
    scale = _value(model, vector, "scale", "scale", 1.0)
    floor = _value(model, vector, "floor", "floor", 0.0)
    if not model.lab:
        scale = scale / m.line_gaussian(0.0, 0.0, width_rad)
    width = width_rad if model.kind == "gaussian" else m.roughness_alpha(width_rad)
    return m.GlossSurface(
        beta2=wedge_deg * DEG, layer_um=layer_um, n=n, width=width,
        edge_radius_um=_value(model, vector, "edge_radius_um", "edge_radius_um", 0.0),
        body=floor / scale, spectral_weight=jnp.asarray(weight),
    )  # fmt: skip


OUT_OF_PLANE_CHECKED_DEG = 45.0
"""How far out of the staircase's profile plane (the plane across the layer lines) the light
of the rough two-bounce path was checked against the 3-D ray tracer (docs/model.md §7.4)."""


def out_of_plane_note(model: GlossModel, azimuth_deg: Sequence[float],
                      angles_deg: Sequence[float]) -> str | None:  # fmt: skip
    """A note when microfacet facets are lit further out of the profile plane than their
    two-bounce path was checked (`asin(sin theta sin azimuth)` above
    `OUT_OF_PLANE_CHECKED_DEG`), else None: along the layer lines at 60 and 85 deg the model read
    up to 3.5 times the ray tracer's gloss (docs/gloss.md §4)."""
    if model.kind == "gaussian":
        return None
    worst = max(
        np.degrees(np.arcsin(abs(np.sin(a * DEG) * np.sin(z * DEG))))
        for a in angles_deg for z in azimuth_deg
    )  # fmt: skip
    if worst <= OUT_OF_PLANE_CHECKED_DEG:
        return None
    return (
        f"the glossmeter's light is up to {worst:.0f} deg out of the plane across the layer "
        f"lines; the rough facets' two-bounce path is checked against the 3-D ray tracer up to "
        f"{OUT_OF_PLANE_CHECKED_DEG:g} deg, and along the layer lines at 60 and 85 deg it reads "
        "up to 3.5 times the tracer's gloss on steep wedges (docs/gloss.md §4)"
    )


# --- the table ------------------------------------------------------------------------------


COMBO_BATCH = 3
"""Surface-and-geometry combinations evaluated at once (`jax.lax.map`'s batch), and parameter
vectors one at a time: a rounded microfacet surface holds hundreds of MB of arrays per
combination, so that a whole table vectorised, times the delta method's forward Jacobian or a
batch of draws, exceeds a small machine's memory (benchmarks/results/lab_fit.md)."""


class _Combos(NamedTuple):
    """The table's (surface angle, azimuth, geometry) combinations, one entry each (deg)."""

    wedge_deg: np.ndarray
    azimuth_deg: np.ndarray
    angle_deg: np.ndarray


def _combos(wedge_deg: Sequence[float], azimuth_deg: Sequence[float],
            angles_deg: Sequence[float]) -> _Combos:  # fmt: skip
    grid = [(w, a, g) for w in wedge_deg for a in azimuth_deg for g in angles_deg]
    return _Combos(*(np.array([c[i] for c in grid], float) for i in range(3)))


def _table_function(model: GlossModel, combos: _Combos, layer_um: float
                    ) -> Callable[[jax.Array], jax.Array]:  # fmt: skip
    """`f(vector) -> (C, 3)`: gloss (total, specular, body) of one parameter vector at every
    combination, a few combinations at a time (`COMBO_BATCH`)."""
    import jax
    import jax.numpy as jnp

    from stairfit import model as m

    geos = [m.iso2813_geometry(a) for a in combos.angle_deg]
    geometry = m.GlossGeometry(*(jnp.stack([getattr(g, f) for g in geos])
                                 for f in m.GlossGeometry._fields))  # fmt: skip
    wedge, azimuth = jnp.asarray(combos.wedge_deg), jnp.asarray(combos.azimuth_deg * DEG)

    def one(vector: jax.Array, w: jax.Array, az: jax.Array, geo: m.GlossGeometry) -> jax.Array:
        s = surface_of(model, vector, w, jnp.asarray(layer_um, float))
        g = m.gloss(s, geo, az, model.kind, rounded=model.rounded)
        return jnp.stack([g.total, g.specular, g.body])

    def table(vector: jax.Array) -> jax.Array:
        return jax.lax.map(lambda c: one(vector, *c), (wedge, azimuth, geometry),
                           batch_size=COMBO_BATCH)  # fmt: skip

    return table


def gloss_table(
    model: GlossModel,
    wedge_deg: Sequence[float],
    layer_um: float,
    azimuth_deg: Sequence[float] = (0.0,),
    angles_deg: Sequence[float] = GLOSS_ANGLES_DEG,
) -> list[GlossRow]:
    """Gloss units of every surface angle x azimuth x ISO 2813 geometry (see `GlossRow`):
    at the optimum, and with the posterior draws' median and 16-84% interval or the delta
    method's standard deviation. One compiled program: for the optimum and the draws, or for
    the optimum and its gradient."""
    import jax
    import jax.numpy as jnp

    combos = _combos(wedge_deg, azimuth_deg, angles_deg)
    f = _table_function(model, combos, layer_um)
    sd = np.full(combos.wedge_deg.size, np.nan)
    if model.draws is None and model.covariance is not None and model.best.size:
        # the delta method: the table and its gradient in one program (the forward-mode
        # Jacobian evaluates the table on the way), in the parameters the surface depends on
        used = np.array([i for i, (p, _) in enumerate(model.keys) if p in SURFACE_PARAMS], int)
        best = jnp.asarray(model.best, float)

        def with_table(u: jax.Array) -> tuple[jax.Array, jax.Array]:
            t = f(best.at[used].set(u))
            return t[:, 0], t

        jac, table = jax.jit(jax.jacfwd(with_table, has_aux=True))(best[used])
        jac, values = np.asarray(jac), np.asarray(table)[None]  # (C, U), (1, C, 3)
        cov = model.covariance[np.ix_(used, used)]
        sd = np.sqrt(np.einsum("cp,pq,cq->c", jac, cov, jac))
    else:
        vectors = model.best[None, :] if model.draws is None else np.vstack([model.best,
                                                                            model.draws])
        values = np.asarray(jax.jit(lambda v: jax.lax.map(f, v))(
            jnp.asarray(vectors, float)))  # (V, C, 3)  # fmt: skip
    best, totals = values[0], values[1:, :, 0]
    rows = []
    for c in range(best.shape[0]):
        median = p16 = p84 = None
        if totals.shape[0] > 0:
            p16, median, p84 = (float(q) for q in np.quantile(totals[:, c], (0.16, 0.5, 0.84)))
            sd[c] = np.std(totals[:, c], ddof=1) if totals.shape[0] > 1 else np.nan
        rows.append(GlossRow(
            float(combos.wedge_deg[c]), float(layer_um), float(combos.azimuth_deg[c]),
            layer_lines(combos.azimuth_deg[c]), float(combos.angle_deg[c]), float(best[c, 0]),
            float(best[c, 1]), float(best[c, 2]), median, p16, p84,
            float(sd[c]) if np.isfinite(sd[c]) else None, model.uncertainty,
        ))  # fmt: skip
    return rows
