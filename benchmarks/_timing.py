"""Timing helpers shared by the benchmark scripts: medians of repeats, compile time apart, a
command timed from outside as a fresh process."""

from __future__ import annotations

import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from typing import Any


def block(x: Any) -> Any:
    """Wait for JAX arrays (anything with block_until_ready) inside a result."""
    import jax

    return jax.tree_util.tree_map(
        lambda a: a.block_until_ready() if hasattr(a, "block_until_ready") else a, x
    )


def first_call_seconds(fn: Callable[[], Any]) -> float:
    """Wall time of the first call: tracing + compilation + one run, for JAX functions."""
    t0 = time.perf_counter()
    block(fn())
    return time.perf_counter() - t0


def median_seconds(fn: Callable[[], Any], repeats: int, min_time: float = 0.0) -> float:
    """Median wall time of `repeats` calls (after any warm-up the caller did)."""
    times = []
    t_start = time.perf_counter()
    while len(times) < repeats or (time.perf_counter() - t_start) < min_time:
        t0 = time.perf_counter()
        block(fn())
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def interleaved_medians(fns: dict[str, Callable[[], Any]], repeats: int) -> dict[str, float]:
    """Median wall time of each function, timed in interleaved rounds.

    Every round calls each function once (the order rotates from round to round), so a
    slow phase of the machine affects all of them alike and their ratios stay meaningful.
    """
    names = list(fns)
    times: dict[str, list[float]] = {k: [] for k in names}
    for r in range(repeats):
        for k in names[r % len(names) :] + names[: r % len(names)]:
            t0 = time.perf_counter()
            block(fns[k]())
            times[k].append(time.perf_counter() - t0)
    return {k: statistics.median(v) for k, v in times.items()}


def fmt_ms(seconds: float) -> str:
    """Milliseconds with three significant figures."""
    return f"{seconds * 1e3:.3g} ms"


_WRAPPER = (
    "import resource, subprocess, sys, time\n"
    "t0 = time.perf_counter()\n"
    "r = subprocess.run(sys.argv[1:], capture_output=True, text=True)\n"
    "wall = time.perf_counter() - t0\n"
    "sys.stderr.write(r.stderr[-3000:] if r.returncode else '')\n"
    "sys.stdout.write(r.stdout)\n"
    "u = resource.getrusage(resource.RUSAGE_CHILDREN)\n"
    "print(wall, u.ru_maxrss / 1024.0, u.ru_utime + u.ru_stime)\n"
    "sys.exit(r.returncode)\n"
)
"""Runs one command and reports its wall time, its own peak RSS (MB) and CPU time (user +
system, all threads: less distorted by other jobs than the wall time), as bench_demo.py does,
and passes its standard output on."""


def timed(cmd: list[str], env: dict[str, str]) -> tuple[float, float, float, str]:
    """Wall time, peak memory (MB), CPU time and standard output of `cmd`, a fresh process."""
    proc = subprocess.run(
        [sys.executable, "-c", _WRAPPER, *cmd], env=env, capture_output=True, text=True
    )
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({proc.returncode}):\n{proc.stderr}")
    *out, last = proc.stdout.rstrip("\n").split("\n")
    wall, mb, cpu = (float(x) for x in last.split())
    return wall, mb, cpu, "\n".join(out)
