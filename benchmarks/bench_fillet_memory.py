"""The filleted fit grid's memory and where its time goes (issue 15; docs/rounded.md §11,
docs/fitting.md §3).

On the standard scene (6 wedges x 19 views x 3 channels, `fitting._forward.filleted_grid_density`,
a 1-degree light and view spread, dispersive PLA, r = 20, r_f = 15 um):

* per preset (`balanced`, `accurate`: their spectral sampling, aperture nodes, rounded
  resolution and fillet rays), the XLA temporary memory of the compiled value + Jacobian
  program (`compiled.memory_analysis()`), with the correction summed in one pass and with the
  default chunking over the rays (`FILLET_CHUNK_BYTES`);
* at the `balanced` knobs, with the 1-degree spreads and with a point light and view, the
  median time of tracing the Jacobian's four ray pairs against the
  contraction of the rays with the index and the kernels (value, two derivative directions,
  three difference points), each as its own compiled program, and the rounded model's value +
  Jacobian of the same grid beside it (the issue's 3x aim at that spread).

    python benchmarks/bench_fillet_memory.py    # about 3 minutes on the 2-core machine
"""

from __future__ import annotations

import os
import statistics
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import zoo  # noqa: E402

from stairfit import fitting, model  # noqa: E402
from stairfit.fitting import _forward, _problem  # noqa: E402
from stairfit.pipeline import fit_setup  # noqa: E402
from stairfit.presets import PRESETS  # noqa: E402

DEG = np.pi / 180
TRUTH = fitting.Params(sigma_rad=4 * DEG, edge_radius_um=20.0, fillet_radius_um=15.0, scale=2.0)


def scene(spread_deg: float) -> SimpleNamespace:
    """What fit_setup reads of a scene: dispersive PLA, a light and a view `spread_deg` wide
    (0: points, one aperture node, as `bench_rounded.py --fillet`'s grid)."""
    return SimpleNamespace(
        specimen=SimpleNamespace(index=SimpleNamespace(build=lambda: "pla-bodurov2016")),
        camera=SimpleNamespace(sensitivity="ideal", angular_extent_deg=spread_deg),
        light=SimpleNamespace(illuminant="D65", angular_diameter_deg=spread_deg, shape="uniform"),
    )


def setup(preset: str, spread_deg: float = 1.0) -> tuple:
    """(grid, widths per key, cfg) of the standard scene at a preset's knobs."""
    spectral, aperture = fit_setup(scene(spread_deg), PRESETS[preset])[1:3]
    s = zoo.standard(TRUTH, seed=0, noise=0.01)
    data = _problem.prepare(s.obs, spectral, aperture=aperture).data
    p = PRESETS[preset]
    cfg = (aperture, p.rounded_resolution, p.fillet_rays, model.FILLET_BOUNCES)
    return _forward._grid(data), jnp.full(data.r_ti.shape, 4 * DEG), cfg


def value_and_jacobian(g: object, sigma_k: jax.Array, cfg: tuple):
    def f(x: jax.Array) -> jax.Array:
        return _forward.filleted_grid_density(sigma_k * jnp.exp(x[0]), x[1], x[2], x[3], cfg, g)

    return jax.jit(lambda x: (f(x), jax.jacfwd(f)(x)))


X = jnp.array([0.0, 0.0, TRUTH.edge_radius_um, TRUTH.fillet_radius_um])


def temp_gb(preset: str, one_pass: bool) -> float:
    """XLA temporary memory (GB) of the value + Jacobian program."""
    saved = _forward.FILLET_CHUNK_BYTES
    _forward.FILLET_CHUNK_BYTES = 2**62 if one_pass else saved
    jax.clear_caches()  # the chunk size is chosen when the program is traced
    try:
        g, sigma_k, cfg = setup(preset)
        compiled = value_and_jacobian(g, sigma_k, cfg).lower(X).compile()
        return compiled.memory_analysis().temp_size_in_bytes / 1e9
    finally:
        _forward.FILLET_CHUNK_BYTES = saved
        jax.clear_caches()


def median_ms(f, *args, repeats: int = 15) -> float:
    jax.block_until_ready(f(*args))
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(f(*args))
        times.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(times)


def time_split(spread_deg: float) -> tuple[float, float, float, float]:
    """(tracing the four ray pairs, the contraction, the whole value + Jacobian, the rounded
    model's value + Jacobian) in ms."""
    g, sigma_k, cfg = setup("balanced", spread_deg)
    r, rf = X[2], X[3]

    def trace(r: jax.Array, rf: jax.Array) -> model.FilletRays:  # as _filleted_grid_jvp
        r_, rf_ = jnp.broadcast_arrays(r, rf, g.g_ti)[:2]
        pts = model.fillet_difference_points(g.g_ti, g.g_b2, g.g_layer, r_, rf_)
        (r_lo, r_hi), (f_lo, f_hi) = pts[3], pts[4]
        r_at, rf_at = jnp.stack([r_, r_hi, r_lo, r_]), jnp.stack([rf_, rf_, rf_, f_hi])
        zero = jnp.zeros_like(rf_)
        st = lambda a: jnp.broadcast_to(a, r_at.shape)  # noqa: E731
        return model.fillet_rays(st(g.g_ti), st(g.g_b2), st(g.g_layer), r_at, rf_at,
                                 rays=cfg[2], bounces=cfg[3],
                                 other_fillet_um=jnp.stack([zero, zero, zero, f_lo]))  # fmt: skip

    traced = jax.jit(trace)
    rays_all = traced(r, rf)

    def contract(rays_all: model.FilletRays) -> tuple:
        first = jax.tree_util.tree_map(lambda a: a[0], rays_all)
        f = lambda e: _forward._fillet_impl(sigma_k + e[0], e[1], first, cfg, g)  # noqa: E731
        value, jac = _forward._value_and_jac_forward(f, jnp.zeros(2))
        moved = jax.tree_util.tree_map(lambda a: a[1:], rays_all)
        at = jax.vmap(lambda rr: _forward._fillet_impl(sigma_k, 0.0, rr, cfg, g))(moved)
        return value, jac, at

    whole = value_and_jacobian(g, sigma_k, cfg)

    def rounded(x: jax.Array) -> jax.Array:
        return _forward.rounded_grid_density(sigma_k * jnp.exp(x[0]), x[1], x[2], cfg[:2], g)

    rounded_both = jax.jit(lambda x: (rounded(x), jax.jacfwd(rounded)(x)))
    return (median_ms(traced, r, rf), median_ms(jax.jit(contract), rays_all),
            median_ms(whole, X), median_ms(rounded_both, X[:3]))  # fmt: skip


def main() -> None:
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"load average (1 min) at the start: {load:.2f}\n")
    print("| preset | temp memory, one pass | temp memory, chunked (default) |")
    print("|---|---|---|")
    for preset in ("balanced", "accurate"):
        print(f"| {preset} | {temp_gb(preset, True):.3g} GB | {temp_gb(preset, False):.3g} GB |")
    for spread in (1.0, 0.0):
        trace, contract, whole, rounded = time_split(spread)
        print(f"\nbalanced, {spread:g}-deg light and view: value + Jacobian {whole:.1f} ms; "
              f"tracing the four ray pairs {trace:.1f} ms, the contraction {contract:.1f} ms "
              f"(each its own program, medians of 15); the rounded model's value + Jacobian "
              f"{rounded:.1f} ms (filleted / rounded {whole / rounded:.2f})")  # fmt: skip


if __name__ == "__main__":
    main()
