"""Identifiability of the tip radius r against the fillet radius r_f (issue 15).

On the standard scene (6 wedges 10-60 deg x 19 views x 3 channels, theta_i = 20 deg, 1%
noise) at a filleted truth (sigma 4 deg, r, r_f, scale 2), the Fisher information of the
`rounded+fillet` variant (free: sigma, r, r_f, scale) from the fit's forward-mode Jacobian of
the model in the physical parameters, through `stairfit.explore.fisher_matrix`: the standard
errors and the correlation of r and r_f. Per wedge and per view, which rows separate them:
`|cos|` of the angle between the whitened sensitivity vectors d model / d r and d model / d r_f
on those rows (1 = the two radii change those rows alike, up to a factor; 0 = independently),
and each subset's share of the information that separates them (the Schur complement of r_f
given r on the subset's rows, over the full scene's; a two-parameter view that ignores sigma
and scale, so the shares do not add up to 1).

    python benchmarks/bench_fillet_identifiability.py [--tip 20] [--fillet 15] [--out f.md]
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import zoo

from stairfit import fitting
from stairfit.explore import fisher_matrix
from stairfit.fitting import _forward, _params, _problem

DEG = np.pi / 180
FREE = ("sigma_rad", "edge_radius_um", "fillet_radius_um", "scale")


def physical_jacobian(tip: float, fillet: float) -> tuple[np.ndarray, np.ndarray, object]:
    """(model Jacobian in the physical values of `FREE`, rows' stderr, observations)."""
    truth = fitting.Params(sigma_rad=4 * DEG, edge_radius_um=tip, fillet_radius_um=fillet,
                           scale=2.0)  # fmt: skip
    scene = zoo.standard(truth, seed=0, noise=0.01)
    problem = _problem.prepare(scene.obs, scene.spec)
    spec = _problem.spec_for(fitting.FILLET_RUNGS[0], problem)
    static, data = problem.static_for(spec), problem.arrays_for(spec)
    lay = problem.layout
    z = np.zeros(lay.size)
    for rec in lay.parameters():
        x = float(np.asarray(getattr(truth, rec.param)).reshape(-1)[0])
        z[rec.slot] = _params.from_physical(x, rec.transform, problem.r_max_um, tip)
    jz = jax.jit(jax.jacfwd(lambda z: _forward.model_values(z, static, data)[0]))(jnp.asarray(z))
    slots = [lay.slot(n) for n in FREE]
    free = np.zeros(lay.size, bool)
    free[slots] = True
    dx = _params.dx_matrix(z, lay.kinds, problem.r_max_um, free, tip)[np.ix_(slots, slots)]
    jx = np.asarray(jz)[:, slots] @ np.linalg.inv(dx)  # d model / d x = d model / d z dz/dx
    return jx, np.asarray(scene.obs.stderr), scene.obs


def separation(jx: np.ndarray, sd: np.ndarray, rows: np.ndarray) -> tuple[float, float]:
    """(|cos| of d/dr against d/dr_f on `rows`, whitened; the Schur information of r_f given r
    on those rows)."""
    a, b = jx[rows, 1] / sd[rows], jx[rows, 2] / sd[rows]
    cos = abs(float(a @ b)) / max(float(np.linalg.norm(a) * np.linalg.norm(b)), 1e-300)
    schur = float(b @ b - (a @ b) ** 2 / max(float(a @ a), 1e-300))
    return cos, schur


def run(tip: float, fillet: float) -> str:
    jax.config.update("jax_enable_x64", True)
    jx, sd, obs = physical_jacobian(tip, fillet)
    info = fisher_matrix(jx, sd)
    cov = np.linalg.inv(info)
    se = np.sqrt(np.diag(cov))
    corr = cov / np.outer(se, se)
    lines = [
        f"Standard scene, truth r = {tip:g} um, r_f = {fillet:g} um, 1% noise; free "
        f"{', '.join(FREE)}. Load average {os.getloadavg()[0]:.1f} (2 cores).",
        "",
        f"- standard errors: r {se[1]:.3g} um, r_f {se[2]:.3g} um; correlation(r, r_f) = "
        f"{corr[1, 2]:+.3f}; correlation(sigma, r_f) = {corr[0, 2]:+.3f}",
        "",
        "| rows | abs cos(d/dr, d/dr_f) | share of the r_f-given-r information |",
        "|---|---|---|",
    ]
    all_rows = np.arange(jx.shape[0])
    total = separation(jx, sd, all_rows)[1]
    lines.append(f"| all | {separation(jx, sd, all_rows)[0]:.3f} | 1 |")
    for w, b2 in enumerate(obs.wedge_beta2_rad):
        rows = np.flatnonzero(obs.wedge_index == w)
        cos, schur = separation(jx, sd, rows)
        lines.append(f"| wedge {b2 / DEG:.0f} deg | {cos:.3f} | {schur / total:.3f} |")
    views = np.unique(np.round(obs.theta_o_rad / DEG, 6))
    for v in views:
        rows = np.flatnonzero(np.isclose(obs.theta_o_rad / DEG, v))
        cos, schur = separation(jx, sd, rows)
        lines.append(f"| view {v:+.0f} deg | {cos:.3f} | {schur / total:.3f} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--tip", type=float, default=20.0)
    ap.add_argument("--fillet", type=float, default=15.0)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    text = run(args.tip, args.fillet)
    print(text)
    if args.out:
        args.out.write_text(text + "\n")


if __name__ == "__main__":
    main()
