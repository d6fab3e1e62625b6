"""Benchmark: the rounded-edge model at each resolution, side by side with the sharp model.

The case is the sharp benchmark's (benchmarks/bench_model.py): 6 wedges (10-60 deg) x 181
viewing angles x 31 wavelengths (400-700 nm, Bodurov PLA dispersion), theta_i = 20 deg, the
radiance model of conventions §9, sigma = 5 deg; here with an edge radius r = 30 um on 150 um
layers. Jacobians by forward mode (`jax.jacfwd`): with respect to (sigma, delta_n, scale) for the
sharp model, (sigma, delta_n, r, scale) for the rounded one. Every row is its own geometry (as in
a fit, where each observation has its own theta_i).

Errors are against a converged reference (resolution 32): max |error| / max |value| of the
radiance, and of each Jacobian column (worst column), at sigma = 5 deg and at sigma = 1 deg.
With `--tracer`, also the unbroadened structure against the brute-force ray tracer
(tests/raytrace.py): power in 2-degree bins (max error / total) and total reflectance, for
beta2 in {10, 30, 45, 60}, r / l1 in {0.05, 0.2, 0.4}, 25 angles of incidence, 100 000 rays.
Timings are medians of `--repeats` calls after compilation; compilation is reported apart.

With `--fillet` (issue 15, docs/rounded.md §11), instead: the filleted model (fillet radius
15 um) against the rounded one in the same run, both with the geometry once per wedge (the
six distinct geometries on their own axis, as a fit evaluates them), on (1) the case above,
Jacobian by `jax.jacfwd` in (sigma, delta_n, r[, r_f], scale); (2) the fit-side grid density of
the standard scene (6 wedges x 19 views x 3 channels, `fitting._forward.rounded_grid_density`
against `filleted_grid_density`), value and value + Jacobian in (widths, delta_n, r[, r_f]), at
every fillet ray count of the presets (app/presets.py), each with its error against
`FILLET_REFERENCE_RAYS`. Medians of `--repeats` (at least 3) interleaved rounds; state the
machine's load. With `--fillet-accuracy`, the fit grid's error per ray count over angles of
incidence, radii and widths (`run_fillet_accuracy`; docs/rounded.md §11).

    python benchmarks/bench_rounded.py [--repeats 20] [--tracer] [--out results.md]
    python benchmarks/bench_rounded.py --fillet [--repeats 5] [--grid-only] [--out results.md]
    python benchmarks/bench_rounded.py --fillet-accuracy 256,512,1024,2048 [--out results.md]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _timing import first_call_seconds, fmt_ms, interleaved_medians, median_seconds

from stairfit import model

DEG = np.pi / 180
LAYER_UM = 150.0
RADIUS_UM = 30.0
RESOLUTIONS = (1, 2, 3, 4, 6, 8, 12)
REFERENCE = 32


def make_case() -> dict[str, np.ndarray]:
    """Flattened observation arrays: rows (wedge, theta_o), columns wavelengths."""
    wedges = np.array([10, 20, 30, 40, 45, 60]) * DEG
    theta_o = np.linspace(-90, 90, 181) * DEG
    lam = np.linspace(400, 700, 31)
    b, to = np.meshgrid(wedges, theta_o, indexing="ij")
    n_base = np.asarray(model.materials.PLA_BODUROV_2016(lam))
    n_obs = b.size
    return {
        "theta_i": np.full((n_obs, 1), 20 * DEG),
        "theta_o": to.reshape(n_obs, 1),
        "beta2": b.reshape(n_obs, 1),
        "n_base": np.broadcast_to(n_base, (n_obs, lam.size)).copy(),
        "weight": np.full((n_obs, lam.size), 1.0 / lam.size),
    }


def sharp_value(p: jax.Array, c: dict[str, jax.Array]) -> jax.Array:
    """Radiance of the sharp model for p = (sigma, delta_n, scale)."""
    rho = model.brdf(c["theta_i"], c["theta_o"], c["beta2"], c["n_base"] + p[1], p[0])
    dens = jnp.sum(rho * c["weight"], axis=-1)
    return model.radiance(dens, c["theta_i"][:, 0], c["theta_o"][:, 0], p[2])


def rounded_value(p: jax.Array, c: dict[str, jax.Array], resolution: int) -> jax.Array:
    """Radiance of the rounded model for p = (sigma, delta_n, r, scale)."""
    rho = model.brdf_rounded(
        c["theta_i"],
        c["theta_o"],
        c["beta2"],
        c["n_base"] + p[1],
        p[0],
        LAYER_UM,
        p[2],
        resolution=resolution,
    )
    dens = jnp.sum(rho * c["weight"], axis=-1)
    return model.radiance(dens, c["theta_i"][:, 0], c["theta_o"][:, 0], p[3])


def _rel_err(a: np.ndarray, ref: np.ndarray) -> float:
    return float(np.max(np.abs(a - ref)) / np.max(np.abs(ref)))


def _jac_err(a: np.ndarray, ref: np.ndarray) -> float:
    scale = np.max(np.abs(ref), axis=0)
    return float(np.max(np.max(np.abs(a - ref), axis=0) / np.where(scale > 0, scale, 1.0)))


def run(repeats: int) -> list[tuple[str, ...]]:
    """Time and measure everything; returns table rows."""
    jax.config.update("jax_enable_x64", True)
    case = {k: jnp.asarray(v) for k, v in make_case().items()}
    rows = []

    ps = jnp.array([5 * DEG, 0.01, 2.0])
    value = jax.jit(sharp_value)
    both = jax.jit(lambda q, c: (sharp_value(q, c), jax.jacfwd(sharp_value)(q, c)))
    c_v = first_call_seconds(lambda: value(ps, case))
    c_b = first_call_seconds(lambda: both(ps, case))
    t_v = median_seconds(lambda: value(ps, case), repeats)
    t_b = median_seconds(lambda: both(ps, case), repeats)
    rows.append(("sharp", fmt_ms(c_v), fmt_ms(c_b), fmt_ms(t_v), fmt_ms(t_b), "exact", "", ""))

    def make(resolution: int):
        v = jax.jit(lambda q, c: rounded_value(q, c, resolution))
        b = jax.jit(
            lambda q, c: (
                rounded_value(q, c, resolution),
                jax.jacfwd(lambda x: rounded_value(x, c, resolution))(q),
            )
        )
        return v, b

    p5 = jnp.array([5 * DEG, 0.01, RADIUS_UM, 2.0])
    p1 = p5.at[0].set(1 * DEG)
    _ref_v, ref_b = make(REFERENCE)
    ref5 = [np.asarray(a) for a in ref_b(p5, case)]
    ref1 = [np.asarray(a) for a in ref_b(p1, case)]
    for res in RESOLUTIONS:
        v, b = make(res)
        c_v = first_call_seconds(lambda v=v: v(p5, case))
        c_b = first_call_seconds(lambda b=b: b(p5, case))
        t_v = median_seconds(lambda v=v: v(p5, case), repeats)
        t_b = median_seconds(lambda b=b: b(p5, case), max(3, repeats // 4))
        out5 = [np.asarray(a) for a in b(p5, case)]
        out1 = [np.asarray(a) for a in b(p1, case)]
        rows.append(
            (
                f"rounded, resolution {res}",
                fmt_ms(c_v),
                fmt_ms(c_b),
                fmt_ms(t_v),
                fmt_ms(t_b),
                f"{_rel_err(out5[0], ref5[0]):.1e}",
                f"{_jac_err(out5[1], ref5[1]):.1e}",
                f"{_rel_err(out1[0], ref1[0]):.1e}",
            )
        )
    return rows


def run_tracer(resolutions: tuple[int, ...]) -> list[tuple[str, str, str]]:
    """Unbroadened structure against the brute-force tracer, per resolution."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from raytrace import Staircase, histogram, total_reflectance, trace

    jax.config.update("jax_enable_x64", True)
    edges = np.arange(-90.7, 91.4, 2.0)
    tis = np.array([-89, -85, -70, -60, -45, -40, -30, -20, -10, -5, 0, 5, 10, 20, 25, 30, 40])
    tis = np.concatenate([tis, [45, 50, 55, 60, 70, 80, 85, 89]]).astype(float)
    refs = {}
    for b2 in (10, 30, 45, 60):
        for frac in (0.05, 0.2, 0.4):
            for ti in tis:
                res = trace(Staircase(b2, LAYER_UM, frac * LAYER_UM), ti, 1.46, n_rays=100_000)
                refs[b2, frac, ti] = (histogram(res, edges), total_reflectance(res))
    rows = []
    for resolution in resolutions:
        fn = jax.jit(
            lambda t, b, r, resolution=resolution: (
                model.rounded_binned(
                    t, jnp.asarray(edges * DEG), b, 1.46, LAYER_UM, r, resolution=resolution
                ),
                model.rounded_total(t, b, 1.46, LAYER_UM, r, resolution=resolution),
            )
        )
        worst_bin = worst_total = 0.0
        for b2 in (10, 30, 45, 60):
            for frac in (0.05, 0.2, 0.4):
                binned, total = (
                    np.asarray(a) for a in fn(jnp.asarray(tis * DEG), b2 * DEG, frac * LAYER_UM)
                )
                for i, ti in enumerate(tis):
                    h_ref, t_ref = refs[b2, frac, ti]
                    worst_bin = max(worst_bin, float(np.max(np.abs(binned[i] - h_ref)) / t_ref))
                    worst_total = max(worst_total, abs(float(total[i]) / t_ref - 1.0))
        rows.append((str(resolution), f"{worst_bin:.1e}", f"{worst_total:.1e}"))
    return rows


FILLET_UM = 15.0
FILLET_REFERENCE_RAYS = 16384
"""The converged reference of the fit grid's error columns (docs/rounded.md §11)."""


def _wedge_case() -> dict[str, jax.Array]:
    """The case of `make_case` with the wedge on its own axis: (6, 1, 1) geometry, (181, 1)
    viewing angles, (31,) indices."""
    lam = np.linspace(400, 700, 31)
    return {
        "beta2": jnp.asarray(np.array([10, 20, 30, 40, 45, 60])[:, None, None] * DEG),
        "theta_o": jnp.asarray(np.linspace(-90, 90, 181)[:, None] * DEG),
        "n_base": jnp.asarray(np.asarray(model.materials.PLA_BODUROV_2016(lam))),
    }


def _wedge_value(p: jax.Array, c: dict[str, jax.Array], filleted: bool) -> jax.Array:
    """Radiance (6, 181) for p = (sigma, delta_n, r, r_f, scale); r_f unused when rounded."""
    ti = 20 * DEG
    args = (ti, c["theta_o"], c["beta2"], c["n_base"] + p[1], p[0], LAYER_UM, p[2])
    rho = model.brdf_filleted(*args, p[3]) if filleted else model.brdf_rounded(*args)
    return model.radiance(jnp.mean(rho, axis=-1), ti, c["theta_o"][:, 0], p[4])


def _standard_grid():
    """(grid, widths per key, delta_n, aperture) of the standard scene's fit-side evaluation."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    import zoo

    from stairfit import fitting
    from stairfit.fitting import _forward, _problem

    truth = fitting.Params(sigma_rad=4 * DEG, edge_radius_um=RADIUS_UM, scale=2.0)
    scene = zoo.standard(truth, seed=0, noise=0.01)
    data = _problem.prepare(scene.obs, scene.spec).data
    grid = _forward._grid(data)
    sigma_k = jnp.full(data.r_ti.shape, 4 * DEG)
    return grid, sigma_k, data.r_ti.shape[0], _forward


def _preset_fillet_rays() -> dict[int, list[str]]:
    """The fillet ray counts of the presets (app/presets.py), each with the presets using it."""
    from stairfit.presets import PRESETS

    out: dict[int, list[str]] = {}
    for name, p in PRESETS.items():
        out.setdefault(p.fillet_rays, []).append(name)
    return dict(sorted(out.items()))


def run_fillet(repeats: int, grid_only: bool = False) -> list[tuple[str, ...]]:
    """Rounded against filleted, same run: compile, value, value + Jacobian, and ratios; on the
    fit grid at every ray count a preset uses, with the error of the value and of the
    Jacobian's `r`, `r_f` columns against `FILLET_REFERENCE_RAYS`."""
    jax.config.update("jax_enable_x64", True)
    repeats = max(3, repeats)
    rows = [] if grid_only else _fillet_model_rows(repeats)
    grid, sigma_k, n_keys, fwd = _standard_grid()
    cfg = (model.Aperture(), None)
    counts = _preset_fillet_rays()

    def rounded(x: jax.Array) -> jax.Array:
        return fwd.rounded_grid_density(sigma_k * jnp.exp(x[0]), x[1], x[2], cfg, grid)

    def filleted(rays: int):
        cfg_f = (*cfg, rays, model.FILLET_BOUNCES)
        return lambda x: fwd.filleted_grid_density(
            sigma_k * jnp.exp(x[0]), x[1], x[2], x[3], cfg_f, grid
        )

    x_r, x_f = jnp.array([0.0, 0.0, RADIUS_UM]), jnp.array([0.0, 0.0, RADIUS_UM, FILLET_UM])
    grid_fns = {}
    cases = [("rounded", rounded, x_r)]
    cases += [(f"filleted, {k} rays", filleted(k), x_f) for k in counts]
    for name, fn, x in cases:
        v = jax.jit(fn)
        b = jax.jit(lambda x, fn=fn: (fn(x), jax.jacfwd(fn)(x)))
        grid_fns[name] = (v, b, x, first_call_seconds(lambda v=v, x=x: v(x)),
                          first_call_seconds(lambda b=b, x=x: b(x)))  # fmt: skip
    t = interleaved_medians(
        {f"{k} {w}": (lambda f=f, i=i: f[i](f[2])) for k, f in grid_fns.items()
         for i, w in ((0, "value"), (1, "both"))},
        repeats,
    )  # fmt: skip
    ref_fn = filleted(FILLET_REFERENCE_RAYS)
    ref_v, ref_j = (
        np.asarray(a) for a in jax.jit(lambda x: (ref_fn(x), jax.jacfwd(ref_fn)(x)))(x_f)
    )
    label = f"fit grid, standard scene ({n_keys} keys x 19 views x 3 channels)"
    for k, f in grid_fns.items():
        err = ""
        if k != "rounded":
            v, j = (np.asarray(a) for a in f[1](f[2]))
            err = (f"{_rel_err(v, ref_v):.1e}", f"{_col_err(j, ref_j, 2):.2f}",
                   f"{_col_err(j, ref_j, 3):.2f}")  # fmt: skip
        rows.append((f"{label}: {k}", fmt_ms(f[3]), fmt_ms(f[4]), fmt_ms(t[f"{k} value"]),
                     fmt_ms(t[f"{k} both"]), *(err or ("", "", ""))))  # fmt: skip
    for k in counts:
        name = f"filleted, {k} rays"
        rows.append((f"  ratio {name} ({', '.join(counts[k])}) / rounded (aim: value + Jacobian "
                     "<= 3)", "", "", f"{t[f'{name} value'] / t['rounded value']:.2f}",
                     f"{t[f'{name} both'] / t['rounded both']:.2f}", "", "", ""))  # fmt: skip
    return rows


def _col_err(j: np.ndarray, ref: np.ndarray, c: int) -> float:
    """|J - ref| / |ref| of the Jacobian's column `c` (norms over every grid element)."""
    return float(np.linalg.norm(j[..., c] - ref[..., c]) / np.linalg.norm(ref[..., c]))


def _fillet_model_rows(repeats: int) -> list[tuple[str, ...]]:
    """The model half of `run_fillet`: `brdf_filleted` against `brdf_rounded` on the wedge case
    at the model's default ray count."""
    rows = []
    c = _wedge_case()
    p = jnp.array([5 * DEG, 0.01, RADIUS_UM, FILLET_UM, 2.0])
    fns = {}
    for name, fil in (("rounded", False), ("filleted", True)):
        v = jax.jit(lambda q, c, fil=fil: _wedge_value(q, c, fil))
        jac = jax.jit(lambda q, c, fil=fil: jax.jacfwd(lambda x: _wedge_value(x, c, fil))(q))
        b = jax.jit(lambda q, c, v=v, jac=jac: (v(q, c), jac(q, c)))
        fns[name] = (v, b, first_call_seconds(lambda v=v: v(p, c)),
                     first_call_seconds(lambda b=b: b(p, c)))  # fmt: skip
    t = interleaved_medians(
        {f"{k} {w}": (lambda f=f[i]: f(p, c)) for k, f in fns.items()
         for i, w in ((0, "value"), (1, "both"))},
        repeats,
    )  # fmt: skip
    for k, f in fns.items():
        rows.append((f"model, 6 wedges x 181 views x 31 indices: {k}", fmt_ms(f[2]), fmt_ms(f[3]),
                     fmt_ms(t[f"{k} value"]), fmt_ms(t[f"{k} both"]), "", "", ""))  # fmt: skip
    rows.append(("  ratio filleted / rounded", "", "",
                 f"{t['filleted value'] / t['rounded value']:.2f}",
                 f"{t['filleted both'] / t['rounded both']:.2f}", "", "", ""))  # fmt: skip
    return rows


ACCURACY_THETA_I_DEG = (20.0, 0.0, -40.0, 60.0, 80.0, -75.0)
ACCURACY_RADII_UM = ((30.0, 15.0), (5.0, 40.0), (10.0, 60.0), (30.0, 3.0), (0.0, 20.0))
ACCURACY_SIGMA_DEG = (2.0, 4.0)


def run_fillet_accuracy(counts: tuple[int, ...]) -> list[tuple[str, ...]]:
    """The fit grid's filleted density and its Jacobian in (sigma, r, r_f) at each ray count
    against `FILLET_REFERENCE_RAYS`: the standard design at each theta_i of
    `ACCURACY_THETA_I_DEG` (six wedges 10-60 deg, 19 views, 3 channels), radii
    `ACCURACY_RADII_UM`, widths `ACCURACY_SIGMA_DEG`. Per theta_i, the worst over the radii of
    the rms of `error / stderr` with the zoo's noise model at 1% (`stderr = sqrt((0.01 v)^2 +
    (1e-3 peak)^2)`), at each width; and the worst relative error (norm over the grid) of the
    Jacobian's r and r_f columns at 4 deg."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    import zoo

    from stairfit import fitting
    from stairfit.fitting import _forward, _problem

    jax.config.update("jax_enable_x64", True)
    grids = {}
    for ti in ACCURACY_THETA_I_DEG:
        truth = fitting.Params(sigma_rad=4 * DEG, edge_radius_um=RADIUS_UM, scale=2.0)
        s = zoo.scene(truth, fitting.standard_design(theta_i_deg=ti), zoo.effective(), 0.01, 0)
        grids[ti] = _forward._grid(_problem.prepare(s.obs, s.spec).data)

    def values(rays: int) -> dict[tuple, tuple[np.ndarray, np.ndarray]]:
        cfg = (model.Aperture(), None, rays, model.FILLET_BOUNCES)

        def f(x: jax.Array, g: object) -> jax.Array:
            sig = jnp.full(g.r_ti.shape, x[0])
            return _forward.filleted_grid_density(sig, 0.0, x[1], x[2], cfg, g)

        fn = jax.jit(lambda x, g: (f(x, g), jax.jacfwd(f)(x, g)))
        return {
            (ti, r, rf, sg): tuple(np.asarray(a) for a in fn(jnp.array([sg * DEG, r, rf]), g))
            for ti, g in grids.items()
            for r, rf in ACCURACY_RADII_UM
            for sg in ACCURACY_SIGMA_DEG
        }

    ref = values(FILLET_REFERENCE_RAYS)
    rows = []
    for rays in counts:
        out = values(rays)
        worst: dict[tuple, float] = {}
        for key, (v, j) in out.items():
            vr, jr = ref[key]
            peak = np.max(np.abs(vr))
            sd = np.sqrt((0.01 * vr) ** 2 + (1e-3 * peak) ** 2)
            cell = (key[0], key[3])
            worst[cell] = max(worst.get(cell, 0.0), float(np.sqrt(np.mean(((v - vr) / sd) ** 2))))
            if key[3] == 4.0:
                jac = max(_col_err(j, jr, c) for c in (1, 2) if np.linalg.norm(jr[..., c]) > 0)
                worst["jac"] = max(worst.get("jac", 0.0), jac)
        cells = [
            f"{worst[ti, ACCURACY_SIGMA_DEG[0]]:.2f} / {worst[ti, ACCURACY_SIGMA_DEG[1]]:.2f}"
            for ti in ACCURACY_THETA_I_DEG
        ]
        rows.append((str(rays), *cells, f"{worst['jac']:.2f}"))
    return rows


def main() -> None:
    """Command line entry."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--tracer", action="store_true", help="also compare with the ray tracer")
    ap.add_argument("--out", type=Path, default=None, help="also write the tables here (markdown)")
    ap.add_argument("--fillet", action="store_true", help="the filleted model against the rounded")
    ap.add_argument("--grid-only", action="store_true", help="with --fillet: the fit grid only")
    ap.add_argument(
        "--fillet-accuracy", default=None, help="ray counts (e.g. 256,512,1024,2048): the fit "
        "grid's error against the reference over theta_i, radii and widths"
    )  # fmt: skip
    args = ap.parse_args()
    if args.fillet_accuracy:
        rows = run_fillet_accuracy(tuple(int(a) for a in args.fillet_accuracy.split(",")))
        table = (
            f"rms error / stderr (1% noise) against {FILLET_REFERENCE_RAYS} rays, worst over "
            "the radii, sigma 2 / 4 deg\n\n| rays | "
            + " | ".join(f"theta_i {t:g} deg" for t in ACCURACY_THETA_I_DEG)
            + " | Jacobian r, r_f (4 deg) |\n|---|"
            + "---|" * (len(ACCURACY_THETA_I_DEG) + 1)
            + "\n"
            + "\n".join("| " + " | ".join(r) + " |" for r in rows)
        )
        print(table)
        if args.out:
            args.out.write_text(table + "\n")
        return
    if args.fillet:
        import os

        load = os.getloadavg()[0]
        table = (
            f"Load average at the start: {load:.1f} (2 cores)\n\n"
            "| case | compile: value | compile: value + Jacobian | value | value + Jacobian "
            f"| value error vs {FILLET_REFERENCE_RAYS} rays (max / peak) | Jacobian r | "
            "Jacobian r_f |\n|---|---|---|---|---|---|---|---|\n"
        ) + "\n".join("| " + " | ".join(r) + " |" for r in run_fillet(args.repeats, args.grid_only))
        table += f"\n\nLoad average at the end: {os.getloadavg()[0]:.1f}"
        print(table)
        if args.out:
            args.out.write_text(table + "\n")
        return
    rows = run(args.repeats)
    head = (
        "| model | compile: value | compile: value + Jacobian | value | value + Jacobian "
        "| error (sigma 5 deg) | Jacobian error (sigma 5 deg) | error (sigma 1 deg) |\n"
        "|---|---|---|---|---|---|---|---|\n"
    )
    table = head + "\n".join("| " + " | ".join(r) + " |" for r in rows)
    if args.tracer:
        t_rows = run_tracer((1, 2, 3, 4, 8))
        table += (
            "\n\n| resolution | bins: max error / total | total: max relative error |\n"
            "|---|---|---|\n" + "\n".join("| " + " | ".join(r) + " |" for r in t_rows)
        )
    print(table)
    if args.out:
        args.out.write_text(table + "\n")


if __name__ == "__main__":
    main()
