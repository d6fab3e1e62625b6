"""The demo scene end to end: wall time cold and with a warm JAX cache, and peak memory.

Issue 6 asks for: the demo scene (19 photos of about 12 megapixels, 6 wedges) fitted end to
end, cold and with a warm persistent JAX compilation cache, and the peak memory; aims under
60 s cold, under 20 s warm, under 2 GB. Every run is a fresh `stairfit` process (so nothing is
cached in memory) with its own `STAIRFIT_JAX_CACHE` folder:

* `simulate`: rendering the photo folder (not part of the fit; reported apart);
* `fit cold`: `stairfit fit` with an empty JAX cache and an empty measurement cache (which it
  fills);
* `fit warm`: again, JAX cache filled by the cold run, measurements decoded again
  (`--no-cache`), so only compilation is saved;
* `fit warm + measurement cache`: the user's second run on the same folder.

Peak memory is the maximum resident set size of each `stairfit` process (`getrusage` of a
wrapper process that runs only that command). The stages (measure, fits, posterior) are the
`timings_s` each fit writes to its results.json; the rest of a fit's wall time is process
start-up and imports, and writing the outputs.
Repeats give the median and the range. Run:

    python benchmarks/bench_demo.py               # the demo scene, 3 repeats
    python benchmarks/bench_demo.py --megapixels 2 --views 7 --repeats 1   # quick look

Writes benchmarks/results/demo.md (a table) unless --no-write.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"


def peak_of(cmd: list[str], env: dict[str, str]) -> tuple[float, float]:
    """Wall time and this child's own peak RSS (MB), via a wrapper Python process."""
    wrapper = (
        "import resource, subprocess, sys, time\n"
        "t0 = time.perf_counter()\n"
        "r = subprocess.run(sys.argv[1:], capture_output=True, text=True)\n"
        "wall = time.perf_counter() - t0\n"
        "sys.stderr.write(r.stderr[-2000:] if r.returncode else '')\n"
        "print(wall, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0)\n"
        "sys.exit(r.returncode)\n"
    )
    proc = subprocess.run(
        [sys.executable, "-c", wrapper, *cmd], env=env, capture_output=True, text=True
    )
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({proc.returncode}):\n{proc.stderr}")
    wall, mb = (float(x) for x in proc.stdout.split())
    return wall, mb


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--megapixels", type=float, default=12.0)
    p.add_argument("--views", type=int, default=19)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--preset", default="balanced")
    p.add_argument("--no-write", action="store_true")
    args = p.parse_args(argv)
    exe = shutil.which("stairfit") or "stairfit"
    rows: dict[str, list[tuple[float, float]]] = {}
    stages: dict[str, list[dict[str, float]]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        tmp_path = Path(tmp)
        for k in range(args.repeats):
            env = {**os.environ, "STAIRFIT_JAX_CACHE": str(tmp_path / f"jax{k}")}
            photos = tmp_path / f"photos{k}"
            sim = [exe, "simulate", str(photos), "--megapixels", str(args.megapixels),
                   "--views", str(args.views), "--quiet"]  # fmt: skip
            rows.setdefault("simulate (not part of the fit)", []).append(peak_of(sim, env))
            base = [exe, "fit", str(photos), "--preset", args.preset, "--quiet"]
            cases = [  # the cold run fills the measurement cache that the last one reads
                ("fit, cold (empty JAX cache, photos decoded)", []),
                ("fit, warm JAX cache (photos decoded again)", ["--no-cache"]),
                ("fit, warm JAX cache + measurement cache", []),
            ]
            for j, (label, extra) in enumerate(cases):
                out = tmp_path / f"fit{k}_{j}"
                rows.setdefault(label, []).append(peak_of([*base, *extra, "-o", str(out)], env))
                result = json.loads((out / "results.json").read_text())
                stages.setdefault(label, []).append(result["diagnostics"]["timings_s"])
            print(f"repeat {k + 1}/{args.repeats} done", file=sys.stderr)
    lines = [
        f"Demo scene: {args.views} photos of {args.megapixels:g} MP, 6 wedges, preset "
        f"{args.preset}; {platform.processor() or platform.machine()}, {os.cpu_count()} cores; "
        f"median of {args.repeats} (range).",
        "",
        "| stage | wall time (s) | peak memory (MB) | measure / fits / posterior (s) |",
        "|---|---|---|---|",
    ]
    for label, vals in rows.items():
        walls = [w for w, _ in vals]
        mbs = [m for _, m in vals]
        parts = stages.get(label)
        split = (
            " / ".join(
                f"{statistics.median(t.get(k, 0.0) for t in parts):.1f}"
                for k in ("measure_s", "fit_s", "posterior_s")
            )
            if parts
            else ""
        )
        lines.append(
            f"| {label} | {statistics.median(walls):.1f} ({min(walls):.1f}-{max(walls):.1f}) "
            f"| {max(mbs):.0f} | {split} |"
        )
    text = "\n".join(lines) + "\n"
    print(text)
    if not args.no_write:
        RESULTS.mkdir(exist_ok=True)
        (RESULTS / "demo.md").write_text(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
