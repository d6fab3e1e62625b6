"""Derivatives of the rounded and filleted models: `jax.jacfwd` against a tangent given as an
argument (issue 14; the model tests' programs, tests/checks.py).

`jax.jacfwd` compiles a program as wide as the parameters. A program that takes the tangent as
an argument (`jax.jvp` inside `jax.jit`) serves every direction: a whole Jacobian is taken
column by column through it, a check of finite derivatives needs one call along a generic
direction. This script measures both forms of two programs, each case in a fresh process (so
nothing is compiled already), the cases of one round one after another and the rounds
repeated, so a slow phase of the machine hits every case alike:

* `filleted`: the filleted model (512 rays) and the rounded model at 37 viewing angles, values
  and derivatives in (sigma, n, r, r_f, theta_i, l1), as tests/model/test_fillet.py (which also
  has the fillet correction alone in its program);
* `rounded`: the rounded model at 73 viewing angles, values and derivatives in
  (sigma, n, r, theta_i) and theta_o, as tests/model/test_rounded.py.

Reported per case (medians): tracing and lowering, XLA compilation, one call, and the whole
Jacobian (one call of the `jacfwd` program; n calls of the tangent program). Compiled as the
command line and the test suite compile (`stairfit._jaxcache.fast_compile`), float64.

    python benchmarks/bench_jvp_programs.py              # 3 rounds
    python benchmarks/bench_jvp_programs.py --repeats 5

Writes benchmarks/results/jvp_programs.md unless --no-write (or --out FILE).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

RESULTS = Path(__file__).resolve().parent / "results" / "jvp_programs.md"
CASES = ("filleted/jacfwd", "filleted/tangent", "rounded/jacfwd", "rounded/tangent")
CALLS = 20


def _programs(program: str, form: str) -> tuple[Any, tuple[Any, ...], int, Any]:
    """(jitted function, its arguments, number of parameters, one call with a tangent)."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from stairfit import model

    deg = np.pi / 180
    if program == "filleted":
        to = jnp.linspace(-np.pi / 2, np.pi / 2, 37)

        def f(p: Any, b2: Any) -> Any:
            sg, n, r, rf, ti, l1 = p
            return (
                model.brdf_filleted(ti, to, b2, n, sg, l1, r, rf, rays=512),
                model.brdf_rounded(ti, to, b2, n, sg, l1, r),
            )

        p = jnp.array([0.05, 1.46, 30.0, 15.0, -20 * deg, 150.0])
        b2 = 30 * deg
        if form == "jacfwd":
            fn = jax.jit(lambda p, b2: (f(p, b2), jax.jacfwd(f)(p, b2)))
            return fn, (p, b2), 6, None
        fn = jax.jit(lambda p, b2, dp: jax.jvp(lambda q: f(q, b2), (p,), (dp,)))
        return fn, (p, b2, jnp.zeros(6)), 6, lambda k: fn(p, b2, jnp.eye(6)[k])

    to = jnp.linspace(-89.0, 89.0, 73) * deg

    def rho(p: Any, t: Any, b2: Any) -> Any:
        return model.brdf_rounded(p[3], t, b2, p[1], p[0], 150.0, p[2])

    p = jnp.array([3 * deg, 1.46, 30.0, 0.3])
    b2 = 30 * deg
    if form == "jacfwd":

        def whole(p: Any, t: Any, b2: Any) -> Any:
            d_to = jax.jvp(lambda u: rho(p, u, b2), (t,), (jnp.ones_like(t),))[1]
            return rho(p, t, b2), jax.jacfwd(rho)(p, t, b2), d_to

        fn = jax.jit(whole)
        return fn, (p, to, b2), 4, None
    fn = jax.jit(lambda p, t, b2, dp, dt: jax.jvp(lambda q, u: rho(q, u, b2), (p, t), (dp, dt)))
    zero = jnp.zeros_like(to)
    return fn, (p, to, b2, jnp.zeros(4), zero), 4, lambda k: fn(p, to, b2, jnp.eye(4)[k], zero)


def run_one(case: str) -> dict[str, float]:
    """In a fresh process: trace + lower, compile, one call, the whole Jacobian (seconds)."""
    from stairfit._jaxcache import fast_compile

    fast_compile()
    import jax

    jax.config.update("jax_enable_x64", True)
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from _timing import block, median_seconds

    program, form = case.split("/")
    fn, args, n, column = _programs(program, form)
    t0 = time.perf_counter()
    lowered = fn.lower(*args)
    t1 = time.perf_counter()
    compiled = lowered.compile()
    t2 = time.perf_counter()
    block(compiled(*args))
    call = median_seconds(lambda: compiled(*args), CALLS)
    if column is None:
        jacobian = call
    else:
        jacobian = median_seconds(lambda: [block(column(k)) for k in range(n)], 5)
    return {"lower": t1 - t0, "compile": t2 - t1, "call": call, "jacobian": jacobian}


def measure(repeats: int) -> tuple[dict[str, dict[str, float]], list[float]]:
    """Medians over `repeats` rounds of every case, each in a fresh process; load averages."""
    runs: dict[str, list[dict[str, float]]] = {c: [] for c in CASES}
    loads = [os.getloadavg()[0]]
    for r in range(repeats):
        for case in CASES:
            out = subprocess.run(
                [sys.executable, __file__, "--one", case],
                capture_output=True,
                text=True,
                check=True,
            )
            runs[case].append(json.loads(out.stdout.strip().splitlines()[-1]))
            print(f"round {r + 1}/{repeats} {case}: {runs[case][-1]}", file=sys.stderr)
    loads.append(os.getloadavg()[0])
    med = {c: {k: statistics.median(x[k] for x in rs) for k in rs[0]} for c, rs in runs.items()}
    return med, loads


def report(med: dict[str, dict[str, float]], loads: list[float], repeats: int) -> str:
    rows = [
        f"| {c} | {m['lower']:.2f} s | {m['compile']:.2f} s | {1e3 * m['call']:.1f} ms "
        f"| {1e3 * m['jacobian']:.1f} ms |"
        for c, m in med.items()
    ]
    ratios = []
    for program in ("filleted", "rounded"):
        a, b = med[f"{program}/jacfwd"], med[f"{program}/tangent"]
        ratios.append(
            f"- {program}: trace, lower and compile {a['lower'] + a['compile']:.2f} -> "
            f"{b['lower'] + b['compile']:.2f} s "
            f"({(b['lower'] + b['compile']) / (a['lower'] + a['compile']):.0%})"
        )
    return "\n".join(
        [
            "# Derivatives: `jax.jacfwd` against a tangent given as an argument "
            "(`benchmarks/bench_jvp_programs.py`)",
            "",
            f"- date: {datetime.datetime.now().strftime('%Y-%m-%dT%H:%M')}",
            f"- machine: {platform.platform()}, {os.cpu_count()} cores, Python "
            f"{platform.python_version()}",
            f"- rounds: {repeats}, each case in a fresh process; medians",
            f"- load average (1 min) at start / end: {loads[0]:.2f} / {loads[1]:.2f}",
            "",
            "| case | trace + lower | XLA compile | one call | whole Jacobian |",
            "|---|---|---|---|---|",
            *rows,
            "",
            *ratios,
            "",
            "The whole Jacobian of the tangent program is one call per parameter (6 for "
            "`filleted`, 4 for `rounded`); a test that needs one direction (one column, or a "
            "check of finite derivatives along a generic direction) makes one call.",
            "",
        ]
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument("--no-write", action="store_true")
    parser.add_argument("--one", choices=CASES, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.one:
        print(json.dumps(run_one(args.one)))
        return 0
    med, loads = measure(args.repeats)
    text = report(med, loads, args.repeats)
    print(text)
    if not args.no_write:
        args.out.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
