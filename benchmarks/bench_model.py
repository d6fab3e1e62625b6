"""Benchmark: the broadened sharp model and its Jacobian, JAX against plain NumPy (issue 2).

The case: 6 wedges (10-60 deg) x 181 viewing angles x 31 wavelengths (400-700 nm, the Bodurov
PLA dispersion), theta_i = 20 deg; the radiance model of conventions §9; the Jacobian with
respect to (sigma, delta_n, scale). JAX uses forward-mode AD three ways: `jax.jacfwd` of the
whole function, one `jax.jvp` per parameter, and one jvp per factor of the density
(`model.band_ratio`, `model.band_kernel`), combined by the product rule (defined here: the fit
differentiates its own evaluation grid, fitting/_forward.py); NumPy uses forward finite differences
(one extra evaluation per parameter). Both are timed in the same run; the
table reports medians of interleaved rounds (each round times every variant once), and JAX
compilation separately.

    python benchmarks/bench_model.py [--repeats 50] [--out results.md]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import numpy_staircase as nps
from _timing import first_call_seconds, fmt_ms, interleaved_medians

from stairfit import model

DEG = np.pi / 180


def make_case() -> dict[str, np.ndarray]:
    """Flattened observation arrays for the benchmark case."""
    wedges = np.array([10, 20, 30, 40, 45, 60]) * DEG
    theta_o = np.linspace(-90, 90, 181) * DEG
    lam = np.linspace(400, 700, 31)
    b, to = np.meshgrid(wedges, theta_o, indexing="ij")
    n_base = np.asarray(model.materials.PLA_BODUROV_2016(lam))
    n_obs = b.size
    return {
        "theta_i": np.full(n_obs, 20 * DEG),
        "theta_o": to.ravel(),
        "beta2": b.ravel(),
        "n_base": np.broadcast_to(n_base, (n_obs, lam.size)).copy(),
        "weight": np.full((n_obs, lam.size), 1.0 / lam.size),
    }


def jax_value(p: jax.Array, c: dict[str, jax.Array]) -> jax.Array:
    """Radiance for parameters p = (sigma_rad, delta_n, scale)."""
    dens = model.band_density(
        c["theta_i"], c["theta_o"], c["beta2"], c["n_base"] + p[1], c["weight"], p[0]
    )
    return model.radiance(dens, c["theta_i"], c["theta_o"], p[2])


def jax_value_and_jacobian_by_jvp(p: jax.Array, c: dict[str, jax.Array]) -> tuple:
    """Value and Jacobian from one jvp per parameter with the others held constant.

    A closed-over constant has a symbolic-zero tangent, so each jvp only traverses the paths
    its parameter touches: sigma only the broadening, delta_n only the Fresnel factors, and the
    scale column is value / scale.
    """
    s, dn, sc = p[0], p[1], p[2]
    v, d_sigma = jax.jvp(lambda x: jax_value(jnp.stack([x, dn, sc]), c), (s,), (jnp.ones_like(s),))
    _, d_dn = jax.jvp(lambda x: jax_value(jnp.stack([s, x, sc]), c), (dn,), (jnp.ones_like(dn),))
    return v, jnp.stack([d_sigma, d_dn, v / sc], axis=-1)


def jax_value_and_jacobian_by_factors(p: jax.Array, c: dict[str, jax.Array]) -> tuple:
    """Value and Jacobian from one jvp per factor of the band density.

    The density is `sum(ratio * kernel)` over lobes (one aperture node here), where only
    `model.band_ratio` depends on the index and only `model.band_kernel` on sigma: the Fresnel
    factors are evaluated once with their derivative, the broadening kernel once with its
    derivative, and the product rule combines them. The radiance conversion is linear in the
    density.
    """
    n = c["n_base"] + p[1]
    ratio, d_ratio = jax.jvp(
        lambda nn: model.band_ratio(c["theta_i"], c["beta2"], nn, c["weight"]),
        (n,),
        (jnp.ones_like(n),),
    )
    kernel, d_kernel = jax.jvp(
        lambda s: model.band_kernel(c["theta_i"], c["theta_o"], c["beta2"], s),
        (p[0],),
        (jnp.ones_like(p[0]),),
    )
    d = [jnp.sum(a * b, axis=(-2, -1)) for a, b in
         ((ratio, kernel), (ratio, d_kernel), (d_ratio, kernel))]  # fmt: skip
    rad = [model.radiance(x, c["theta_i"], c["theta_o"], p[2]) for x in d]
    return rad[0], jnp.stack([rad[1], rad[2], rad[0] / p[2]], axis=-1)


def numpy_value(p: np.ndarray, c: dict[str, np.ndarray]) -> np.ndarray:
    """The same radiance with plain NumPy."""
    return nps.band_radiance(
        c["theta_i"], c["theta_o"], c["beta2"], c["n_base"] + p[1], c["weight"], p[0], p[2]
    )


def numpy_jacobian(p: np.ndarray, c: dict[str, np.ndarray]) -> np.ndarray:
    """Forward finite differences: one extra evaluation per parameter."""
    f0 = numpy_value(p, c)
    cols = []
    for k in range(p.size):
        h = 1e-7 * max(1.0, abs(p[k]))
        q = p.copy()
        q[k] += h
        cols.append((numpy_value(q, c) - f0) / h)
    return np.stack(cols, axis=-1)


def run(repeats: int) -> list[tuple[str, str, str]]:
    """Time everything; returns table rows (what, time, note)."""
    jax.config.update("jax_enable_x64", True)
    case = make_case()
    jcase = {k: jnp.asarray(v) for k, v in case.items()}
    p = np.array([5 * DEG, 0.01, 2.0])
    jp = jnp.asarray(p)
    value = jax.jit(jax_value)
    both = jax.jit(lambda q, c: (jax_value(q, c), jax.jacfwd(jax_value)(q, c)))
    by_jvp = jax.jit(jax_value_and_jacobian_by_jvp)
    by_factors = jax.jit(jax_value_and_jacobian_by_factors)

    compile_value = first_call_seconds(lambda: value(jp, jcase))
    compile_both = first_call_seconds(lambda: both(jp, jcase))
    compile_jvp = first_call_seconds(lambda: by_jvp(jp, jcase))
    compile_factors = first_call_seconds(lambda: by_factors(jp, jcase))
    t = interleaved_medians(
        {
            "value": lambda: value(jp, jcase),
            "both": lambda: both(jp, jcase),
            "jvp": lambda: by_jvp(jp, jcase),
            "factors": lambda: by_factors(jp, jcase),
            "np_value": lambda: numpy_value(p, case),
            "np_both": lambda: numpy_jacobian(p, case),
        },
        repeats,
    )
    t_value, t_both, t_jvp, t_factors = t["value"], t["both"], t["jvp"], t["factors"]
    t_np_value, t_np_both = t["np_value"], t["np_both"]

    # the two implementations agree (values and derivatives) before any time is compared
    v_j, jac_j = (np.asarray(a) for a in both(jp, jcase))
    np.testing.assert_allclose(v_j, numpy_value(p, case), rtol=1e-10, atol=1e-14)
    jac_np = numpy_jacobian(p, case)
    scale = np.abs(jac_j).max(axis=0)
    assert np.all(np.abs(jac_np - jac_j) <= 1e-4 * scale), "FD and AD Jacobians disagree"
    np.testing.assert_allclose(np.asarray(by_jvp(jp, jcase)[1]), jac_j, rtol=1e-10, atol=1e-12)
    v_f, jac_f = (np.asarray(a) for a in by_factors(jp, jcase))
    np.testing.assert_allclose(v_f, v_j, rtol=1e-12, atol=1e-14)
    assert np.all(np.abs(jac_f - jac_j) <= 1e-10 * scale), "the jvp per factor disagrees"

    n_obs = case["theta_o"].size * case["n_base"].shape[1]
    return [
        ("evaluations per call", f"{n_obs:,}", "6 wedges x 181 theta_o x 31 wavelengths"),
        ("JAX compile: value", fmt_ms(compile_value), "first call, once per shape"),
        ("JAX compile: value + Jacobian (jacfwd)", fmt_ms(compile_both), "first call"),
        ("JAX compile: value + Jacobian (jvp per parameter)", fmt_ms(compile_jvp), "first call"),
        ("JAX compile: value + Jacobian (jvp per factor)", fmt_ms(compile_factors), "first call"),
        ("JAX value", fmt_ms(t_value), "median"),
        ("NumPy value", fmt_ms(t_np_value), f"median; JAX is {t_np_value / t_value:.1f}x faster"),
        ("JAX value + Jacobian (jacfwd)", fmt_ms(t_both), f"median; {t_np_both / t_both:.1f}x"),
        (
            "JAX value + Jacobian (jvp per parameter)",
            fmt_ms(t_jvp),
            f"median; {t_np_both / t_jvp:.1f}x faster than NumPy + FD",
        ),
        (
            "JAX value + Jacobian (jvp per factor)",
            fmt_ms(t_factors),
            f"median; {t_np_both / t_factors:.1f}x faster than NumPy + FD",
        ),
        ("NumPy value + Jacobian (forward FD)", fmt_ms(t_np_both), "median; the baseline"),
    ]


def main() -> None:
    """Command line entry."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--repeats", type=int, default=50)
    ap.add_argument("--out", type=Path, default=None, help="also write the table here (markdown)")
    args = ap.parse_args()
    rows = run(args.repeats)
    table = "| what | time | note |\n|---|---|---|\n" + "\n".join(
        f"| {a} | {b} | {c} |" for a, b, c in rows
    )
    print(table)
    if args.out:
        args.out.write_text(table + "\n")


if __name__ == "__main__":
    main()
