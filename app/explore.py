"""Exploring a fit output folder, for notebooks: tables, chains, residuals on the photos,
and which further photos would teach the most.

A fit folder (written by `stairfit fit` or `stairfit demo`, see `stairfit.report`) holds
`results.json`, `observations.csv`, `measurements.csv`, `chain.npz` (when the posterior was
sampled), `figures/` and `previews/`. It does not hold the photos: the photo folder (with
`scene.toml`) is found next to it (`DIR-fit` beside `DIR`, or `photos/` beside `fit/` for the
demo) and checked against the scene's SHA-256 in `results.json`.

Angles are in degrees here, as in every file [conventions §1]; `sigma` is shown as `sigma_deg`
like in results.json. Parameter vectors follow the order of `results.json["parameters"]`.
"""

from __future__ import annotations

import csv
import hashlib
import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .results_file import OLDER_RESULTS as OLDER_RESULTS
from .results_file import OlderResultsError as OlderResultsError
from .results_file import check_parameter_records as check_parameter_records
from .results_file import covariance_from_results as covariance_from_results
from .results_file import parameter_key as parameter_key

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.cm import ScalarMappable

    from stairfit import fitting, model

    from ._jsontypes import JSONObject, Record
    from .scene import Scene

DEG = np.pi / 180

OBSERVATION_COLUMNS: dict[str, type] = {
    "photo": str,
    "wedge": str,
    "channel": str,
    "light_deg": float,
    "view_deg": float,
    "theta_i_deg": float,
    "theta_o_deg": float,
    "value": float,
    "stderr": float,
    "used": bool,
    "model": float,
    "uncertainty": float,
    "whitened_residual": float,
}
"""The columns of observations.csv (`stairfit.report.write_observations`) and their types."""

# --- the folder -----------------------------------------------------------------------------


@dataclass(frozen=True)
class FitFolder:
    """A fit output folder read back.

    `results` is results.json as a dict; `observations` holds observations.csv as one array
    per column (`OBSERVATION_COLUMNS`); `photo_folder` is the folder with scene.toml and the
    photos, or None when it was not found (then the photo-based helpers cannot be used).
    """

    path: Path
    results: JSONObject
    observations: dict[str, np.ndarray]
    photo_folder: Path | None

    @property
    def chain_path(self) -> Path | None:
        """chain.npz, or None when the posterior was not sampled."""
        post = self.results["diagnostics"].get("posterior")
        if post is None:
            return None
        path = self.path / post.get("chain_file", "chain.npz")
        return path if path.is_file() else None


def read_observations(path: str | Path) -> dict[str, np.ndarray]:
    """observations.csv as {column: array}, typed as in `OBSERVATION_COLUMNS`."""
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    missing = set(OBSERVATION_COLUMNS) - set(rows[0] if rows else {})
    if not rows or missing:
        raise ValueError(f"{path}: not an observations table (missing {sorted(missing)})")
    out: dict[str, np.ndarray] = {}
    for name, kind in OBSERVATION_COLUMNS.items():
        col = [r[name] for r in rows]
        if kind is bool:
            out[name] = np.array([c.strip() in ("1", "True", "true") for c in col])
        elif kind is float:
            out[name] = np.array([float(c) if c.strip() else np.nan for c in col])
        else:
            out[name] = np.array(col)
    return out


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def find_photo_folder(fit_dir: str | Path, results: JSONObject) -> Path | None:
    """The photo folder of a fit: `<fit>/../photos` (demo) or `DIR` for `DIR-fit`.

    A candidate counts only if its scene file has the SHA-256 recorded in results.json, so a
    folder edited after the fit is not silently used.
    """
    fit_dir = Path(fit_dir).resolve()
    scene = results["inputs"]["scene"]
    candidates = [fit_dir.parent / "photos"]
    if fit_dir.name.endswith("-fit"):
        candidates.append(fit_dir.with_name(fit_dir.name[: -len("-fit")]))
    for folder in candidates:
        path = folder / scene["file"]
        if path.is_file() and _sha256(path) == scene["sha256"]:
            return folder
    return None


def open_fit(fit_dir: str | Path, photo_folder: str | Path | None = None) -> FitFolder:
    """Read a fit output folder (`photo_folder`: where scene.toml is, if not next to it)."""
    fit_dir = Path(fit_dir)
    results_path = fit_dir / "results.json"
    if not results_path.is_file():
        raise FileNotFoundError(f"{fit_dir}: no results.json; is this a `stairfit fit` folder?")
    results = json.loads(results_path.read_text())
    obs = read_observations(fit_dir / results["files"]["observations"])
    check_parameter_records(results, fit_dir)
    photos = Path(photo_folder) if photo_folder is not None else None
    if photos is None:
        photos = find_photo_folder(fit_dir, results)
    return FitFolder(fit_dir, results, obs, photos)


def run_demo(out: str | Path, *extra: str) -> Path:
    """Run `stairfit demo OUT EXTRA...` in this process and return the fit folder `OUT/fit`.

    Raises RuntimeError when the command fails (its one-line error is on stderr).
    """
    from .cli import main

    status = main(["demo", str(out), *extra])
    if status != 0:
        raise RuntimeError(f"stairfit demo {out} {' '.join(extra)} failed with status {status}")
    return Path(out) / "fit"


# --- tables ---------------------------------------------------------------------------------


def parameter_table(results: JSONObject) -> list[Record]:
    """One row per free parameter: least-squares value and standard error, posterior median
    and 68 % / 95 % intervals (None when not sampled), relative uncertainty. Display units."""
    rows = []
    for rec in results["parameters"]:
        ls, po = rec["least_squares"], rec.get("posterior")
        stderr = ls["stderr"]
        row = {
            "name": rec["name"],
            "unit": rec["unit"],
            "value": ls["value"],
            "stderr": stderr,
            "relative": None if stderr is None or ls["value"] == 0 else abs(stderr / ls["value"]),
            "at_bound": ls["at_bound"],
            "median": None,
            "p16": None,
            "p84": None,
            "p2_5": None,
            "p97_5": None,
        }
        if po is not None:
            row.update({k: po[k] for k in ("median", "p16", "p84", "p2_5", "p97_5")})
        rows.append(row)
    return rows


def selection_table(results: JSONObject) -> list[Record]:
    """The model-selection table of results.json, the chosen variant marked."""
    sel = results["model_selection"]
    return [{"chosen": r["variant"] == sel["chosen"], **r} for r in sel["table"]]


def format_table(rows: Sequence[Record], columns: Sequence[str] | None = None) -> str:
    """A plain-text table (numbers to 5 significant digits, None as '-')."""
    if not rows:
        return "(empty)"
    cols = list(columns or rows[0].keys())

    def cell(v: object) -> str:
        if v is None:
            return "-"
        if isinstance(v, bool):
            return "yes" if v else ""
        if isinstance(v, float):
            return f"{v:.5g}"
        if isinstance(v, list | tuple):
            return ",".join(map(str, v))
        return str(v)

    cells = [[cell(r.get(c)) for c in cols] for r in rows]
    widths = [max(len(c), *(len(line[i]) for line in cells)) for i, c in enumerate(cols)]
    lines = ["  ".join(c.ljust(w) for c, w in zip(cols, widths, strict=True))]
    lines += ["  ".join(v.ljust(w) for v, w in zip(line, widths, strict=True)) for line in cells]
    return "\n".join(lines)


def strong_correlations(
    names: Sequence[str], matrix: np.ndarray | Sequence[Sequence[float]], threshold: float = 0.5
) -> list[tuple[str, str, float]]:
    """Pairs of parameters with |correlation| >= threshold, strongest first."""
    m = np.asarray(matrix, dtype=float)
    pairs = [
        (names[i], names[j], float(m[i, j]))
        for i in range(len(names))
        for j in range(i + 1, len(names))
        if abs(m[i, j]) >= threshold
    ]
    return sorted(pairs, key=lambda p: -abs(p[2]))


# --- chains ---------------------------------------------------------------------------------


def autocorrelation(chain: np.ndarray, max_lag: int | None = None) -> np.ndarray:
    """Normalised autocorrelation of a chain (n_steps, n_walkers, p) against lag, averaged
    over walkers (emcee's estimator); shape (max_lag, p), value 1 at lag 0."""
    import emcee

    chain = np.asarray(chain, float)
    n = chain.shape[0]
    max_lag = n if max_lag is None else min(max_lag, n)
    out = np.empty((max_lag, chain.shape[2]))
    for k in range(chain.shape[2]):
        acf = np.mean(
            [emcee.autocorr.function_1d(chain[:, w, k]) for w in range(chain.shape[1])], 0
        )
        out[:, k] = acf[:max_lag]
    return out


def display_chain(fit: FitFolder) -> tuple[list[str], np.ndarray, int, int]:
    """(names, chain in display units (n_steps, n_walkers, p), burn_in, thin) of chain.npz."""
    from stairfit.fitting.posterior import load_chain

    if fit.chain_path is None:
        raise FileNotFoundError(f"{fit.path}: no chain.npz (the fit ran without a posterior)")
    data = load_chain(fit.chain_path)
    records = fit.results["parameters"]  # the chain's columns, in the same order
    if len(records) != data["chain"].shape[-1]:
        raise ValueError(f"{fit.chain_path}: its columns do not match results.json's parameters")
    shown = [str(rec["name"]) for rec in records]
    factors = np.array([1 / DEG if parameter_key(r)[0] == "sigma_rad" else 1.0 for r in records])
    post = fit.results["diagnostics"]["posterior"]
    return shown, np.asarray(data["chain"]) * factors, int(post["burn_in"]), int(post["thin"])


# --- the model of the fit, rebuilt ----------------------------------------------------------


@dataclass(frozen=True)
class FitModel:
    """What is needed to evaluate the fitted model anywhere: the scene, the fit's observations
    (same row order as observations.csv), spectral setup, aperture, best-fit parameters, the
    names of the free parameters (display units) and their `(param, wedge)` keys."""

    scene: Scene
    observations: fitting.Observations
    spectral: fitting.Spectral
    aperture: model.Aperture
    params: fitting.Params
    free: tuple[str, ...]
    resolution: fitting.Resolution  # rounded resolution, fillet rays
    uncertainty: np.ndarray
    keys: tuple[tuple[str, int | None], ...] = ()


def params_from_results(results: JSONObject) -> fitting.Params:
    """The least-squares `fitting.Params` of results.json (sigma back in radians)."""
    from stairfit import fitting

    values: dict[str, float | np.ndarray] = {}
    per_wedge: dict[int, float] = {}
    for name, v in results["fixed_parameters"].items():
        if name == "sigma_deg":
            values["sigma_rad"] = v * DEG
        else:
            values[name] = v
    for rec in results["parameters"]:
        (param, wedge), v = parameter_key(rec), rec["least_squares"]["value"]
        if param == "sigma_rad" and wedge is not None:
            per_wedge[wedge] = v * DEG
        elif param == "sigma_rad":
            values["sigma_rad"] = v * DEG
        else:
            values[param] = v
    if per_wedge:
        values["sigma_rad"] = np.array([per_wedge[k] for k in sorted(per_wedge)])
    return fitting.Params(**values)


def fit_model(fit: FitFolder) -> FitModel:
    """Rebuild the fitted model from the folder and its photo folder (needs scene.toml)."""
    from stairfit import fitting, imaging

    from .pipeline import fit_setup, observations
    from .presets import get_preset
    from .scene import load_scene

    if fit.photo_folder is None:
        raise FileNotFoundError(
            f"{fit.path}: the photo folder (scene.toml) was not found next to the fit folder; "
            "pass photo_folder= to open_fit"
        )
    results = fit.results
    scene = load_scene(fit.photo_folder / results["inputs"]["scene"]["file"])
    table = imaging.MeasurementTable.read_csv(fit.path / results["files"]["measurements"])
    obs = observations(scene, table).data
    preset = get_preset(results["settings"]["preset"]["name"])
    setup = fit_setup(scene, preset)
    free = tuple(p["name"] for p in results["parameters"])
    return FitModel(
        scene,
        obs,
        setup.spectral,
        setup.aperture,
        params_from_results(results),
        free,
        fitting.Resolution(preset.rounded_resolution, preset.fillet_rays),
        np.asarray(fit.observations["uncertainty"], float),
        tuple(parameter_key(p) for p in results["parameters"]),
    )


def predict(
    m: FitModel,
    observations: fitting.Observations | None = None,
    params: fitting.Params | None = None,
) -> np.ndarray:
    """Model radiance of `observations` (default: the fit's) for `params` (default: best fit)."""
    from stairfit import fitting

    return fitting.model_radiance(
        m.params if params is None else params,
        m.observations if observations is None else observations,
        m.spectral,
        aperture=m.aperture,
        resolution=m.resolution,
    )


def jacobian(
    m: FitModel,
    observations: fitting.Observations | None = None,
    names: Sequence[str] | None = None,
) -> tuple[tuple[str, ...], np.ndarray]:
    """d(model)/d(parameter) in display units (per degree for a width); (names, (n_rows, p)).

    Forward-mode autodiff of the fit's own forward model (`stairfit.fitting.model_jacobian`).
    `model_error_frac` changes the uncertainty, not the model, and is left out.
    """
    from stairfit import fitting

    key = dict(zip(m.free, m.keys, strict=True))
    names = tuple(n for n in (names or m.free) if key[n][0] != "model_error_frac")
    J = fitting.model_jacobian(
        m.params,
        m.observations if observations is None else observations,
        m.spectral,
        [key[n] for n in names],
        aperture=m.aperture,
        resolution=m.resolution,
    )
    per_display_unit = np.array([DEG if key[n][0] == "sigma_rad" else 1.0 for n in names])
    return names, J * per_display_unit


def fisher_matrix(
    J: np.ndarray, uncertainty: np.ndarray, use: np.ndarray | None = None
) -> np.ndarray:
    """Fisher information `J^T W J` of Gaussian rows with standard deviations `uncertainty`
    (`stairfit.fitting.fisher_information`)."""
    from stairfit import fitting

    return np.asarray(fitting.fisher_information(J, uncertainty, use))


def candidate_observations(
    m: FitModel, view_deg: float, light_deg: float | None = None
) -> tuple[fitting.Observations | None, list[str]]:
    """Rows one more photo at `view_deg` (base frame, like scene.toml) would add: every wedge
    it can see x every channel. `light_deg` defaults to the light of most existing photos.
    Values are placeholders (1.0); returns (Observations, wedge name per row)."""
    from stairfit import fitting

    from .scene import Photo, visible

    scene = m.scene
    if light_deg is None:
        lights = [p.light_deg for p in scene.photos]
        light_deg = max(set(lights), key=lights.count)
    photo = Photo(file="candidate", light_deg=float(light_deg), view_deg=float(view_deg))
    rows: dict[str, list[float]] = {k: [] for k in ("ti", "to", "b", "k", "c")}
    names = []
    for k, wedge in enumerate(scene.specimen.wedges):
        if not visible(scene, photo, wedge):
            continue
        ti, to = scene.face_angles_deg(photo, wedge)
        for c in range(m.spectral.n_channels):
            for key, v in zip(rows, (ti * DEG, to * DEG, wedge.angle_deg * DEG, k, c), strict=True):
                rows[key].append(v)
            names.append(wedge.name)
    if not names:
        return None, []
    obs = fitting.Observations.from_arrays(
        theta_i_rad=rows["ti"],
        theta_o_rad=rows["to"],
        beta2_rad=rows["b"],
        layer_um=scene.specimen.layer_um,
        wedge_index=np.asarray(rows["k"], int),
        channel_index=np.asarray(rows["c"], int),
        value=1.0,
        stderr=1.0,
    )
    return obs, names


def relative_uncertainty(fit: FitFolder) -> float:
    """Median of uncertainty / model over the fitted rows: the noise assumed for new photos."""
    o = fit.observations
    used = o["used"] & (o["model"] > 0)
    return float(np.median(o["uncertainty"][used] / o["model"][used]))


def _concat(parts: Sequence[fitting.Observations]) -> fitting.Observations:
    """One `fitting.Observations` from several (rows in order)."""
    from stairfit import fitting

    fields = (
        "theta_i_rad",
        "theta_o_rad",
        "beta2_rad",
        "layer_um",
        "wedge_index",
        "channel_index",
        "value",
        "stderr",
        "use",
        "photo_index",
        "saturated",
    )
    cat = {f: np.concatenate([np.asarray(getattr(o, f)) for o in parts]) for f in fields}
    return fitting.Observations.from_arrays(**cat)


def view_gain(
    m: FitModel,
    views_deg: Sequence[float],
    relative_error: float,
    light_deg: float | None = None,
) -> list[Record]:
    """What one more photo at each base-frame view angle would teach (Fisher information).

    New rows get the uncertainty `relative_error x model`. For each view: `n_rows`, the
    information gain `0.5 log det(F + F_new) / det(F)` (nats; D-optimal design), and per free
    parameter the ratio of the new to the current standard error (1 = no improvement).
    The current F comes from the fit's own rows and uncertainties. All rows (the fit's and every
    candidate's) are evaluated in one table, so the model is compiled for one shape only.
    """
    cands = [candidate_observations(m, v, light_deg)[0] for v in views_deg]
    parts = [m.observations, *(c for c in cands if c is not None)]
    table = _concat(parts)
    names, J = jacobian(m, table)
    n_fit = m.observations.n_rows
    F = fisher_matrix(J[:n_fit], m.uncertainty, np.asarray(m.observations.use, bool))
    cov = np.linalg.inv(F)
    _, logdet = np.linalg.slogdet(F)
    pred = predict(m, table)[n_fit:]
    out = []
    start = 0  # into the candidate rows
    for v, obs in zip(views_deg, cands, strict=True):
        row: Record = {"view_deg": float(v), "n_rows": 0, "gain_nats": 0.0}
        ratios = dict.fromkeys(names, 1.0)
        if obs is not None:
            rows = slice(start, start + obs.n_rows)
            start += obs.n_rows
            Jc = J[n_fit:][rows]
            F_new = F + fisher_matrix(Jc, relative_error * np.abs(pred[rows]))
            _, logdet_new = np.linalg.slogdet(F_new)
            cov_new = np.linalg.inv(F_new)
            row.update(n_rows=obs.n_rows, gain_nats=0.5 * (logdet_new - logdet))
            ratios = {n: float(np.sqrt(cov_new[i, i] / cov[i, i])) for i, n in enumerate(names)}
        row.update({f"stderr_ratio[{n}]": r for n, r in ratios.items()})
        out.append(row)
    return out


# --- residuals on the photographs -----------------------------------------------------------


def photo_image(m: FitModel, photo: str) -> tuple[np.ndarray, float, dict[str, np.ndarray]]:
    """(preview RGB image, preview px per raw px, {wedge: ROI polygon in preview px}).

    The image is `imaging.render_preview` of the decoded photo without overlays; polygons are
    the scene's ROIs (pixel polygons, or faces placed through the markers), before erosion.
    """
    from stairfit import imaging

    from .imaging_specs import photo_specs

    spec = next(s for s in photo_specs(m.scene) if s.name == photo)
    frame = imaging.decode_raw(spec.path)
    polygons = {n: np.asarray(p, float) for n, p in spec.rois}
    _detection, _pose, placed = imaging.place_faces(frame, spec)  # as the measurement does
    polygons |= {n: np.asarray(p, float) for n, p in placed.items()}
    img = imaging.render_preview(frame)[..., ::-1]  # BGR -> RGB
    scale = img.shape[1] / frame.width
    return img, scale, {n: (p + 0.5) * scale - 0.5 for n, p in polygons.items()}


def wedge_residuals(fit: FitFolder, photo: str, channel: str | None = None) -> dict[str, float]:
    """Whitened residual per wedge in one photo: one channel, or the mean over channels."""
    o = fit.observations
    sel = (o["photo"] == photo) & o["used"]
    if channel is not None:
        sel &= o["channel"] == channel
    out: dict[str, float] = {}
    for w in dict.fromkeys(o["wedge"][sel]):
        out[str(w)] = float(np.mean(o["whitened_residual"][sel & (o["wedge"] == w)]))
    return out


def draw_residuals(
    ax: Axes,
    image: np.ndarray,
    polygons: dict[str, np.ndarray],
    residuals: dict[str, float],
    limit: float = 3.0,
    title: str = "",
) -> ScalarMappable:
    """Draw `image` with each ROI filled by its whitened residual (blue < 0 < red, clipped at
    +-limit) and labelled; returns the colour mapping for a colour bar."""
    import matplotlib as mpl
    from matplotlib.patches import Polygon as MplPolygon

    cmap = mpl.colormaps["coolwarm"]
    norm = mpl.colors.Normalize(-limit, limit)
    ax.imshow(image)
    for name, poly in polygons.items():
        if name not in residuals:
            ax.add_patch(MplPolygon(poly, closed=True, fill=False, ec="0.6", ls="--"))
            continue
        r = residuals[name]
        ax.add_patch(MplPolygon(poly, closed=True, fc=cmap(norm(r)), ec="k", alpha=0.75))
        cx, cy = poly.mean(axis=0)
        ax.text(cx, cy, f"{name}\n{r:+.1f}", ha="center", va="center", fontsize="x-small")
    ax.set(title=title, xticks=[], yticks=[])
    return mpl.cm.ScalarMappable(norm=norm, cmap=cmap)


# --- speed and accuracy ---------------------------------------------------------------------


def read_table(path: str | Path) -> list[dict[str, float | str | None]]:
    """A CSV file as a list of dicts; numeric cells become floats, empty cells None."""

    def parse(text: str) -> float | str | None:
        if text.strip() == "":
            return None
        try:
            return float(text)
        except ValueError:
            return text

    with open(path, newline="") as fh:
        return [{k: parse(v) for k, v in row.items()} for row in csv.DictReader(fh)]


def pareto_front(time_s: Sequence[float], error: Sequence[float]) -> np.ndarray:
    """Indices of the points no other point beats in both time and error, fastest first.

    A point is dominated if another is at most as slow and at most as wrong, and strictly
    better in one of them; points with a non-finite coordinate are ignored.
    """
    t, e = np.asarray(time_s, float), np.asarray(error, float)
    ok = np.flatnonzero(np.isfinite(t) & np.isfinite(e))
    front = []
    best = np.inf
    for i in sorted(ok, key=lambda i: (t[i], e[i])):
        if e[i] < best:
            front.append(i)
            best = e[i]
    return np.asarray(front, dtype=int)


def preset_table() -> list[Record]:
    """Every preset of `stairfit.presets.PRESETS` as a row (README: Speed and accuracy)."""
    from .presets import PRESETS

    return [p.as_dict() for p in PRESETS.values()]
