"""The default `stairfit fit` of a physically based photo set (issue 40), cold and warm.

Runs, each a fresh process timed from outside: `stairfit fit FOLDER --no-posterior` with an
empty JAX cache (`STAIRFIT_JAX_CACHE` a new folder) and no measurement cache (`--no-cache`),
then again with both caches filled (the user's second run; an untimed `stairfit measure`
first fills the measurement cache, which the cold runs do not write), and
(`--with-posterior`) the default fit with its posterior, warm. It then compares the fitted
parameters with the renderer's truth.json (tests/pbr_photos.py: `edge_radius_um`, the
GGX/Beckmann alpha against `tan(sigma)`, the floor against `k_cam x body / pi`, the scale
against `k_cam`) and prints the model-error term and the facet kernel chosen. The set comes
from benchmarks/make_pbr_set.py
(`--set dev` renders the development set in about half an hour on one thread).

    python benchmarks/make_pbr_set.py --set dev --out /data/pbr/dev
    python benchmarks/bench_lab_fit.py /data/pbr/dev
    python benchmarks/bench_lab_fit.py SET --compare-exe OTHER/.venv/bin/stairfit --repeats 2
    python benchmarks/bench_lab_fit.py SET --model rounded+floor --compare-xla-flags \
        "--xla_backend_optimization_level=1 --xla_llvm_disable_expensive_passes=true"
    python benchmarks/bench_lab_fit.py SET --model rounded+floor --compare-kernel ggx

`--compare-exe` times another installation's `stairfit` (e.g. the commit before a change, in
its own checkout and virtual environment) beside this one, `--compare-xla-flags FLAGS` this
installation again with `XLA_FLAGS=FLAGS` (other XLA options; the command line adds its own
unless FLAGS sets it), `--compare-kernel KERNEL` this installation again with `--kernel KERNEL`
(no kernel probes); `--model VARIANT` forces one variant
in every fit (the kernel probes still run), for shorter runs: in each repeat both run cold and
then warm, one after another, each with its own empty JAX cache, so that a slow phase of the
machine hits them alike; the medians and each run's `fit_s`, `compile_s` and `measure_s`
(results.json) are printed, with both fits' chosen model and parameters.

Results: benchmarks/results/lab_fit.md (newest run first; say whether the machine was loaded).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any


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


def _stages(results: Path) -> dict[str, float]:
    """The stage times a fit recorded in its results.json (s)."""
    t = json.loads(results.read_text())["diagnostics"]["timings_s"]
    return {k: round(float(v), 1) for k, v in t.items()}


def _fit_cmd(exe: str, folder: Path, out: Path, *options: str) -> list[str]:
    """`stairfit fit FOLDER -o OUT --quiet OPTIONS...`."""
    return [exe, "fit", str(folder), "-o", str(out), "--quiet", *options]


def _fill_measurement_cache(exe: str, folder: Path, work: Path, env: dict[str, str]) -> None:
    """Measure the set once, untimed, so that every warm run finds the measurement cache: the
    cold runs (`--no-cache`) write none, so without this the first warm run would measure."""
    _run([exe, "measure", str(folder), "-o", str(work / "measure"), "--quiet"], env)


def _pair(
    exes: dict[str, tuple[str, dict[str, str], list[str]]],
    folder: Path,
    work: Path,
    repeats: int,
    fit_args: list[str],
) -> dict[str, object]:
    """Cold then warm `stairfit fit --no-posterior` of every (exe, extra environment, extra
    options), `repeats` times interleaved."""
    runs: dict[str, list[dict[str, Any]]] = {name: [] for name in exes}
    first = next(iter(exes.values()))[0]
    _fill_measurement_cache(
        first, folder, work, dict(os.environ, STAIRFIT_JAX_CACHE=str(work / "m"))
    )
    for r in range(repeats):
        for name, (exe, extra, more) in exes.items():
            base = work / f"{name}{r}"
            env = dict(os.environ, STAIRFIT_JAX_CACHE=str(base / "jax"), **extra)
            options = ["--no-posterior", *fit_args, *more]
            cold = _run(_fit_cmd(exe, folder, base / "cold", "--no-cache", *options), env)
            warm = _run(_fit_cmd(exe, folder, base / "warm", *options), env)
            runs[name].append({"cold_s": round(cold, 1), "warm_s": round(warm, 1),
                               "cold_stages": _stages(base / "cold" / "results.json"),
                               "warm_stages": _stages(base / "warm" / "results.json")})  # fmt: skip
            print(name, r, json.dumps(runs[name][-1]), file=sys.stderr, flush=True)
    out: dict[str, object] = {}
    for name in exes:
        out[name] = {
            "cold_median_s": round(statistics.median(x["cold_s"] for x in runs[name]), 1),
            "warm_median_s": round(statistics.median(x["warm_s"] for x in runs[name]), 1),
            "runs": runs[name],
            **_compare(work / f"{name}0" / "cold" / "results.json", folder / "truth.json"),
        }
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("folder", type=Path, help="a set from benchmarks/make_pbr_set.py")
    parser.add_argument("--with-posterior", action="store_true")
    parser.add_argument("--compare-exe", help="another installation's stairfit, timed beside")
    parser.add_argument(
        "--compare-xla-flags",
        metavar="FLAGS",
        help="this installation again with XLA_FLAGS=FLAGS, timed beside",
    )
    parser.add_argument(
        "--compare-kernel",
        metavar="KERNEL",
        help="this installation again with --kernel KERNEL (no kernel probes), timed beside",
    )
    parser.add_argument("--repeats", type=int, default=1, help="with --compare-*")
    parser.add_argument("--model", help="force this variant in every fit (shorter runs)")
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error(f"--repeats {args.repeats}: give at least 1")
    exe = str(Path(sys.executable).with_name("stairfit"))
    work = Path(tempfile.mkdtemp(prefix="bench_lab_fit_"))
    fit_args = ["--model", args.model] if args.model else []
    if args.compare_exe or args.compare_xla_flags is not None or args.compare_kernel:
        other: tuple[str, dict[str, str], list[str]] = (
            (args.compare_exe, {}, []) if args.compare_exe
            else (exe, {}, ["--kernel", args.compare_kernel]) if args.compare_kernel
            else (exe, {"XLA_FLAGS": args.compare_xla_flags}, [])
        )  # fmt: skip
        load = os.getloadavg()[0]
        try:
            pair = _pair({"this": (exe, {}, []), "other": other}, args.folder, work, args.repeats,
                         fit_args)  # fmt: skip
        finally:
            shutil.rmtree(work, ignore_errors=True)
        print(json.dumps({"folder": str(args.folder), "other": list(other),
                          "fit_args": fit_args,
                          "load_average_start_end": [round(load, 2),
                                                     round(os.getloadavg()[0], 2)],
                          **pair}, indent=1))  # fmt: skip
        return 0
    env = dict(os.environ, STAIRFIT_JAX_CACHE=str(work / "jax"))
    load = os.getloadavg()[0]
    timings = {}
    try:
        _fill_measurement_cache(
            exe, args.folder, work, dict(env, STAIRFIT_JAX_CACHE=str(work / "m"))
        )
        out = work / "cold"
        options = ["--no-posterior", *fit_args]
        timings["cold_no_posterior_s"] = _run(
            _fit_cmd(exe, args.folder, out, "--no-cache", *options), env
        )
        timings["warm_no_posterior_s"] = _run(_fit_cmd(exe, args.folder, work / "warm", *options),
                                              env)  # fmt: skip
        if args.with_posterior:
            timings["warm_posterior_s"] = _run(_fit_cmd(exe, args.folder, work / "post"), env)
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
