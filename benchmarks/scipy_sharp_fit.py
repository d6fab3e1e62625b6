"""The NumPy + SciPy baseline of one sharp-model fit, run as its own process (issue 14).

Reads what `stairfit fit` measured (the scene's `scene.toml` and the fit folder's
`observations.csv`: face-frame angles, values, the uncertainties stairfit fitted with, each
ROI's channel correlations and each row's viewing spread) and fits the same model with
`scipy.optimize.least_squares` (trf, 2-point finite-difference Jacobian) on the plain NumPy
staircase of `numpy_staircase.py`:

* the sharp lobes broadened by sigma, averaged over the same Gauss-Legendre aperture nodes as
  `stairfit.model.Aperture`, the viewing offsets scaled by each row's `view_spread` and
  foreshortened by `cos(theta_o)`, each viewing node's density weighted by
  `cos(theta_o) / cos(node)` (its own radiance conversion, `stairfit.model.view_conversion`);
* `scale * cos(theta_i) * rho / cos(theta_o) + floor * cos(theta_i)` [conventions §9], one
  effective wavelength per channel (the balanced preset's sampling);
* residuals whitened per ROI with the 3 x 3 correlation of its R, G, B errors
  (docs/fitting.md §Correlated channels).

The stairfit fit it is compared with runs with `--no-model-error` (a variance parameter has no
least-squares form here). The starts are stairfit's sigma starts, with scale (and floor) from
a linear least-squares solve at each. It imports neither jax nor stairfit, so timing this
process from outside (`bench_cold.py`) is the baseline's whole cost, imports included.

    python benchmarks/scipy_sharp_fit.py PHOTOS_DIR FIT_DIR [--variant sharp+floor]

Prints one JSON line: the fitted values, chi^2, and the time spent importing and fitting.
"""

from __future__ import annotations

import time

T_START = time.perf_counter()

import argparse  # noqa: E402  (after the clock starts: the imports are part of the baseline)
import csv  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import tomllib  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from scipy.optimize import least_squares  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import numpy_staircase as nps  # noqa: E402

T_IMPORTED = time.perf_counter()

DEG = np.pi / 180
COS_FLOOR = np.cos(89.9 * DEG)
CONSTANT_INDEX = {"pla": 1.46, "pla-constant": 1.46}
"""The named materials the baseline knows: the paper's constant PLA (stairfit's default)."""


def read_rows(photos: Path, fit: Path) -> dict[str, np.ndarray]:
    """The fitted rows (used = 1) as arrays, with each row's wedge angle from scene.toml."""
    scene = tomllib.loads((photos / "scene.toml").read_text())
    beta2 = {w["name"]: w["angle_deg"] for w in scene["specimen"]["wedges"]}
    with open(fit / "observations.csv", newline="") as fh:
        rows = [r for r in csv.DictReader(fh) if r["used"] == "1"]
    return {
        "theta_i": np.array([float(r["theta_i_deg"]) for r in rows]) * DEG,
        "theta_o": np.array([float(r["theta_o_deg"]) for r in rows]) * DEG,
        "beta2": np.array([beta2[r["wedge"]] for r in rows]) * DEG,
        "value": np.array([float(r["value"]) for r in rows]),
        "sigma_y": np.array([float(r["uncertainty"]) for r in rows]),
        "spread": np.array([float(r["view_spread"]) for r in rows]),
        "groups": roi_groups(rows),
        "scene": scene,
    }


EIGEN_FLOOR = 1e-3
"""As stairfit's: a correlation matrix's eigenvalues are clipped at this, then its diagonal
rescaled to 1 (docs/fitting.md §Correlated channels)."""


def _clipped(r: np.ndarray) -> np.ndarray:
    w, v = np.linalg.eigh(r)
    if w.min() >= EIGEN_FLOOR:
        return r
    c = (v * np.maximum(w, EIGEN_FLOOR)) @ v.T
    d = np.sqrt(np.diag(c))
    return c / np.outer(d, d)


def roi_groups(rows: list[dict[str, str]]) -> list[tuple[np.ndarray, np.ndarray]]:
    """(row positions in channel order, correlation matrix) of every ROI group of the used
    rows; a row with roi_index -1 is a group of its own."""
    channel = {"R": 0, "G": 1, "B": 2}
    keys: dict[str, list[int]] = {}
    for i, r in enumerate(rows):
        keys.setdefault(r["roi_index"] if r["roi_index"] != "-1" else f"single{i}", []).append(i)
    out = []
    for members in keys.values():
        members.sort(key=lambda i: channel.get(rows[i]["channel"], 0))
        r = rows[members[0]]
        c01, c02, c12 = (float(r[k]) for k in ("corr_01", "corr_02", "corr_12"))
        full = np.array([[1.0, c01, c02], [c01, 1.0, c12], [c02, c12, 1.0]])
        ch = [channel.get(rows[i]["channel"], 0) for i in members]
        out.append((np.array(members), _clipped(full[np.ix_(ch, ch)])))
    return out


def whitener(d: dict[str, np.ndarray]) -> list[tuple[np.ndarray, np.ndarray]]:
    """(rows, inverse Cholesky factor of S R S) per group: `L^-1 r` are the residuals whose
    squares sum to chi^2."""
    out = []
    for members, corr in d["groups"]:
        s = d["sigma_y"][members]
        out.append((members, np.linalg.inv(np.linalg.cholesky(s[:, None] * corr * s[None, :]))))
    return out


def whiten(r: np.ndarray, w: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """`r` (rows, or rows x columns) whitened group by group."""
    return np.concatenate([inv @ r[members] for members, inv in w])


def aperture_nodes(half_i: float, half_o: float, n_nodes: int) -> tuple[np.ndarray, ...]:
    """Offsets in theta_i and theta_o and weights (sum 1), as `stairfit.model.Aperture`."""
    if n_nodes == 1:
        return np.zeros(1), np.zeros(1), np.ones(1)
    x, w = np.polynomial.legendre.leggauss(n_nodes)
    xi, xo = np.meshgrid(x, x, indexing="ij")
    return (xi * half_i).ravel(), (xo * half_o).ravel(), (np.outer(w, w) / 4.0).ravel()


def density(d: dict[str, np.ndarray], n: float, sigma: float, nodes: tuple) -> np.ndarray:
    """Aperture-averaged broadened density (1/rad) of every row."""
    di, do, dw = nodes
    ti = np.clip(d["theta_i"][:, None] + di, -np.pi / 2, np.pi / 2)
    # the face-on spread, narrowed by the ROI's share and foreshortened by cos(theta_o)
    half_o = d["spread"] * np.cos(d["theta_o"])
    to = np.clip(d["theta_o"][:, None] + do * half_o[:, None], -np.pi / 2, np.pi / 2)
    # each viewing node converts to radiance at its own angle [conventions §9]: its density
    # weighted by cos(theta_o) / cos(node), both floored
    conv = np.maximum(np.cos(d["theta_o"]), COS_FLOOR)[:, None] / np.maximum(np.cos(to), COS_FLOOR)
    return (nps.brdf(ti, to, d["beta2"][:, None], n, sigma) * conv) @ dw


def fit(d: dict[str, np.ndarray], variant: str, starts_deg: list[float], n_nodes: int) -> dict:
    """Best of the starts (chi^2) of trf + 2-point FD Jacobian."""
    scene = d["scene"]
    n = CONSTANT_INDEX[scene["specimen"].get("material", "pla")]
    if scene["light"].get("shape", "uniform") != "uniform":
        raise SystemExit('the baseline knows only [light] shape = "uniform" (stairfit\'s own)')
    half_i = 0.5 * scene["light"].get("angular_diameter_deg", 0.0) * DEG
    half_o = 0.5 * scene["camera"].get("angular_extent_deg", 0.0) * DEG
    nodes = aperture_nodes(half_i, half_o, n_nodes if half_i > 0 or half_o > 0 else 1)
    cos_i = np.cos(d["theta_i"])
    geo = cos_i / np.maximum(np.cos(d["theta_o"]), COS_FLOOR)
    with_floor = variant == "sharp+floor"
    w = whitener(d)
    white_value = whiten(d["value"], w)

    def resid(p: np.ndarray) -> np.ndarray:
        model = np.exp(p[1]) * geo * density(d, n, np.exp(p[0]), nodes)
        if with_floor:
            model = model + p[2] * cos_i
        return white_value - whiten(model, w)

    best = None
    for s_deg in starts_deg:
        cols = [geo * density(d, n, s_deg * DEG, nodes), cos_i][: 2 if with_floor else 1]
        a = whiten(np.stack(cols, axis=1), w)
        lin = np.linalg.lstsq(a, white_value, rcond=None)[0]
        p0 = [np.log(s_deg * DEG), np.log(max(lin[0], 1e-12))]
        lo, hi = [-np.inf, -np.inf], [np.inf, np.inf]
        if with_floor:
            p0, lo, hi = [*p0, max(lin[1], 0.0)], [*lo, 0.0], [*hi, np.inf]
        sol = least_squares(resid, np.array(p0), method="trf", jac="2-point", bounds=(lo, hi))
        if best is None or 2 * sol.cost < 2 * best.cost:
            best = sol
    out = {
        "sigma_deg": float(np.exp(best.x[0]) / DEG),
        "scale": float(np.exp(best.x[1])),
        "chi2": float(2 * best.cost),
        "n_rows": int(d["value"].size),
        "nfev": int(best.nfev),
    }
    if with_floor:
        out["floor"] = float(best.x[2])
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("photos", type=Path, help="the photo folder (scene.toml)")
    p.add_argument("fit", type=Path, help="a stairfit fit folder (observations.csv)")
    p.add_argument("--variant", choices=("sharp", "sharp+floor"), default="sharp+floor")
    p.add_argument("--starts-deg", default="1,4,12", help="sigma starts (the balanced preset's)")
    p.add_argument("--aperture-nodes", type=int, default=2, help="as the balanced preset")
    args = p.parse_args()
    t0 = time.perf_counter()
    d = read_rows(args.photos, args.fit)
    starts = [float(s) for s in args.starts_deg.split(",")]
    result = fit(d, args.variant, starts, args.aperture_nodes)
    t1 = time.perf_counter()
    result.update(import_s=T_IMPORTED - T_START, fit_s=t1 - t0)
    print(json.dumps(result))


if __name__ == "__main__":
    main()
