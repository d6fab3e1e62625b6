"""`stairfit study`: folders per minute with 1 and 2 workers, peak memory per worker, and what
the shared JAX compilation cache saves (issue 16).

Simulates N photo folders of the same layout (different seeds, so different photos), then runs
each case as a fresh `stairfit study` process on a LocalCluster:

* `1 worker, cold`: empty JAX cache;
* `2 workers, cold`: another empty JAX cache;
* `2 workers, warm`: `--force` again on the cache the previous case filled (new worker
  processes, so nothing is compiled in memory: what a second study, or a worker joining a
  running one, sees).

Per case: wall time of the study process (cluster start-up included), folders per minute, the
`fit_s` of each worker's first folder and of its later ones (from study.csv: compilation shows
up in the first), and the peak resident memory of each worker process (`peak_rss_mb`).

    python benchmarks/bench_study.py --quick   # 3 tiny folders, sharp, no posterior (~3 min)
    python benchmarks/bench_study.py           # 6 folders of 2 MP x 9 views, the full fit

Writes benchmarks/results/study.md unless --no-write. Label any figure with the machine's load.
"""

from __future__ import annotations

import argparse
import csv
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"


def simulate(root: Path, n: int, megapixels: float, views: int) -> list[Path]:
    """N photo folders of one layout, seeds 0..N-1."""
    folders = []
    for k in range(n):
        folder = root / f"specimen{k}"
        cmd = ["stairfit", "simulate", str(folder), "--megapixels", str(megapixels)]
        cmd += ["--views", str(views), "--seed", str(k), "--quiet"]
        subprocess.run(cmd, check=True, capture_output=True)
        with open(folder / "scene.toml", "a") as fh:
            fh.write(f"\n[specimen.metadata]\nseed = {k}\n")
        folders.append(folder)
    return folders


def run_case(root: Path, out: Path, workers: int, cache: Path, fit_args: list[str]) -> dict:
    """One `stairfit study` process; its wall time and the rows of its study.csv."""
    cmd = ["stairfit", "study", str(root), "-o", str(out), "--local-workers", str(workers)]
    cmd += ["--jax-cache", str(cache), "--quiet", "--force", *fit_args]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    with open(out / "study.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    return {"wall_s": wall, "rows": rows}


def first_and_later(rows: list[dict]) -> tuple[list[float], list[float]]:
    """fit_s of each worker process's first folder, and of all its later folders."""
    by_pid: dict[str, list[dict]] = {}
    for row in rows:
        by_pid.setdefault(row["pid"], []).append(row)
    first, later = [], []
    for runs in by_pid.values():
        runs.sort(key=lambda r: r["started_utc"])
        first.append(float(runs[0]["fit_s"]) + float(runs[0]["posterior_s"] or 0))
        later += [float(r["fit_s"]) + float(r["posterior_s"] or 0) for r in runs[1:]]
    return first, later


def summarise(name: str, workers: int, case: dict) -> dict:
    rows = case["rows"]
    assert all(r["status"] == "fitted" for r in rows), [r["error"] for r in rows]
    first, later = first_and_later(rows)
    peaks: dict[str, float] = {}
    for r in rows:
        peaks[r["pid"]] = max(peaks.get(r["pid"], 0.0), float(r["peak_rss_mb"]))
    return {
        "case": name,
        "workers": workers,
        "folders": len(rows),
        "wall_s": case["wall_s"],
        "per_min": 60 * len(rows) / case["wall_s"],
        "first_fit_s": statistics.mean(first),
        "later_fit_s": statistics.mean(later) if later else float("nan"),
        "peak_mb": max(peaks.values()),
    }


def table(results: list[dict], header: str) -> str:
    lines = [
        header,
        "",
        "| case | folders | wall (s) | folders / min | fit + posterior, each worker's first "
        "folder (s) | later folders (s) | peak memory per worker (MB) |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in results:
        lines.append(
            f"| {r['case']} | {r['folders']} | {r['wall_s']:.1f} | {r['per_min']:.2f} | "
            f"{r['first_fit_s']:.2f} | {r['later_fit_s']:.2f} | {r['peak_mb']:.0f} |"
        )
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="3 tiny folders, sharp, no posterior")
    ap.add_argument("--folders", type=int, default=None)
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args()
    n = args.folders or (3 if args.quick else 6)
    mp, views = (0.3, 3) if args.quick else (2.0, 9)
    fit_args = ["--model", "sharp", "--no-posterior"] if args.quick else []
    with tempfile.TemporaryDirectory(prefix="bench-study-") as tmp:
        tmp = Path(tmp)
        simulate(tmp / "root", n, mp, views)
        results = []
        for name, workers, cache in (
            ("1 worker, cold", 1, tmp / "cache1"),
            ("2 workers, cold", 2, tmp / "cache2"),
            ("2 workers, warm", 2, tmp / "cache2"),
        ):
            case = run_case(tmp / "root", tmp / f"out-{workers}", workers, cache, fit_args)
            results.append(summarise(name, workers, case))
            print(table(results[-1:], f"{name}:"), flush=True)
    load = os.getloadavg()
    header = (
        f"`python benchmarks/bench_study.py{' --quick' if args.quick else ''}`: {n} folders of "
        f"{mp:g} MP x {views} views{', --model sharp --no-posterior' if args.quick else ''}; "
        f"{os.cpu_count()} cores, load average {load[0]:.1f} at the end"
    )
    text = table(results, header)
    print(text)
    if not args.no_write:
        RESULTS.mkdir(exist_ok=True)
        (RESULTS / "study.md").write_text(text)


if __name__ == "__main__":
    sys.exit(main())
