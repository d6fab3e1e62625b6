"""The default `stairfit fit` of a physically based photo set (issue 40), cold and warm.

Runs, each a fresh process timed from outside: `stairfit fit FOLDER --no-posterior` with an
empty JAX cache (`STAIRFIT_JAX_CACHE` a new folder) and no measurement cache (`--no-cache`),
then again with both caches filled (the user's second run), and (`--with-posterior`) the
default fit with its posterior, warm. It then compares the fitted parameters with the
renderer's truth.json (tests/pbr_photos.py: `edge_radius_um`, the GGX/Beckmann alpha against
`tan(sigma)`, the floor against `k_cam x body / pi`, the scale against `k_cam`) and prints the
model-error term and the facet kernel chosen. The set comes from benchmarks/make_pbr_set.py
(`--set dev` renders the development set in about half an hour on one thread).

    python benchmarks/make_pbr_set.py --set dev --out /data/pbr/dev
    python benchmarks/bench_lab_fit.py /data/pbr/dev

Results: benchmarks/results/lab_fit.md (newest run first; say whether the machine was loaded).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def _run(args: list[str], env: dict[str, str]) -> float:
    """Wall seconds of one fresh `stairfit` process (its output is discarded, failures raise)."""
    t0 = time.perf_counter()
    subprocess.run(args, env=env, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    return time.perf_counter() - t0


def _compare(results: Path, truth_file: Path) -> dict[str, object]:
    """The fitted parameters beside the renderer's truth (relative differences)."""
    res = json.loads(results.read_text())
    truth = json.loads(truth_file.read_text())
    setup, k_cam = truth["setup"], float(truth["k_cam"])
    par = {p["name"]: p for p in res["parameters"]} if isinstance(res["parameters"], list) else (
        res["parameters"]
    )  # fmt: skip

    def value(name: str) -> float | None:
        p = par.get(name)
        if p is None:
            return None
        p = p.get("least_squares", p) if isinstance(p, dict) else p
        return float(p["value"]) if isinstance(p, dict) else float(p)

    sigma_deg = value("sigma_deg")
    out: dict[str, object] = {
        "chosen": res["model_selection"].get("chosen"),
        "facets": res.get("directions", {}).get("facets"),
        "model_error_frac": value("model_error_frac"),
        "edge_radius_um": [value("edge_radius_um"), setup["edge_radius_um"]],
        "alpha": [math.tan(math.radians(sigma_deg)) if sigma_deg else None, setup["alpha"]],
        "floor": [value("floor"), k_cam * setup["body_diffuse"] / math.pi],
        "scale": [value("scale"), k_cam],
    }
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("folder", type=Path, help="a set from benchmarks/make_pbr_set.py")
    parser.add_argument("--with-posterior", action="store_true")
    args = parser.parse_args(argv)
    exe = str(Path(sys.executable).with_name("stairfit"))
    work = Path(tempfile.mkdtemp(prefix="bench_lab_fit_"))
    env = dict(os.environ, STAIRFIT_JAX_CACHE=str(work / "jax"))
    load = os.getloadavg()[0]
    timings = {}
    try:
        out = work / "cold"
        timings["cold_no_posterior_s"] = _run(
            [exe, "fit", str(args.folder), "-o", str(out), "--no-posterior", "--no-cache",
             "--quiet"], env)  # fmt: skip
        timings["warm_no_posterior_s"] = _run(
            [exe, "fit", str(args.folder), "-o", str(work / "warm"), "--no-posterior",
             "--quiet"], env)  # fmt: skip
        if args.with_posterior:
            timings["warm_posterior_s"] = _run(
                [exe, "fit", str(args.folder), "-o", str(work / "post"), "--quiet"], env
            )
        report = {
            "folder": str(args.folder),
            "load_average_start_end": [round(load, 2), round(os.getloadavg()[0], 2)],
            **{k: round(v, 1) for k, v in timings.items()},
            **_compare(out / "results.json", args.folder / "truth.json"),
        }
        print(json.dumps(report, indent=1))
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
