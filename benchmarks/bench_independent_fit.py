"""Issue 12's "Done when", timed: `stairfit fit` of the independent renderer's paper setup.

Renders the photo set of tests/independent_photos.py (16 views of 1600 x 1200, 15% vignetting
with a flat-field photo, one fixed exposure; the exposure tags in IFD0 when this stairfit reads
them there, else as scene-file overrides) and runs the default `stairfit fit` on it in a fresh
process with an empty JAX cache, then reports the wall and CPU time, the peak memory, and the
issue's criteria: sigma inside its 95% interval, floor and scale within 3 standard errors, the
model-error term, the chosen variant. The aim: under 5 minutes on the 2-core machine.

    python benchmarks/bench_independent_fit.py            # the issue's set
    python benchmarks/bench_independent_fit.py --quick    # 0.5 MP, 8 views: a look in minutes
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

TESTS = Path(__file__).resolve().parents[1] / "tests"

_WRAPPER = (
    "import resource, subprocess, sys, time\n"
    "t0 = time.perf_counter()\n"
    "r = subprocess.run(sys.argv[1:], capture_output=True, text=True)\n"
    "wall = time.perf_counter() - t0\n"
    "u = resource.getrusage(resource.RUSAGE_CHILDREN)\n"
    "sys.stderr.write(r.stderr[-3000:] if r.returncode else '')\n"
    "print(wall, u.ru_utime + u.ru_stime, u.ru_maxrss / 1024.0)\n"
    "sys.exit(r.returncode)\n"
)


def render(folder: Path, quick: bool) -> dict[str, Any]:
    sys.path.insert(0, str(TESTS))
    import jax

    jax.config.update("jax_enable_x64", True)
    import independent_photos as ip
    from test_independent_photos import setup_for_this_stairfit

    setup = setup_for_this_stairfit(folder.parent)
    kwargs: dict[str, Any] = {}
    if quick:
        kwargs = {"megapixels": 0.5, "views": (-70.0, -50.0, -30.0, -10.0, 10.0, 30.0, 50.0, 70.0)}
    truth = ip.render_folder(folder, seed=7, setup=setup, **kwargs)
    truth["exposure_tags"] = setup.exposure_tags
    return truth


def criteria(results: dict[str, Any], truth: dict[str, float]) -> dict[str, Any]:
    est = {p["name"]: p for p in results["parameters"]}
    out: dict[str, Any] = {"chosen": results["model_selection"]["chosen"]}
    sigma = est["sigma_deg"]
    po = sigma.get("posterior") or {}
    out["sigma_deg"] = sigma["least_squares"]["value"]
    out["sigma_in_95"] = bool(po) and po["p2_5"] <= truth["sigma_deg"] <= po["p97_5"]
    for name in ("scale", "floor"):
        ls = est[name]["least_squares"]
        out[f"{name}_pull"] = (ls["value"] - truth[name]) / ls["stderr"]
    mef = est.get("model_error_frac")
    out["model_error_frac"] = mef["least_squares"]["value"] if mef else 0.0
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="0.5 MP, 8 views")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="bench_independent_fit_") as name:
        tmp = Path(name)
        truth = render(tmp / "photos", args.quick)
        env = dict(os.environ, STAIRFIT_JAX_CACHE=str(tmp / "jax-cache"))
        cmd = [sys.executable, "-c", _WRAPPER, "stairfit", "fit", str(tmp / "photos"),
               "-o", str(tmp / "fit"), "--quiet"]  # fmt: skip
        proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
        if proc.returncode:
            print(proc.stderr, file=sys.stderr)
            return proc.returncode
        wall, cpu, peak_mb = map(float, proc.stdout.split()[-3:])
        results = json.loads((tmp / "fit" / "results.json").read_text())
    report = {
        "set": "quick (0.5 MP, 8 views)" if args.quick else "16 views of 1600 x 1200",
        "exposure tags": truth["exposure_tags"],
        "wall_s": round(wall, 1),
        "cpu_s": round(cpu, 1),
        "peak_mb": round(peak_mb),
        "load_average": os.getloadavg(),
        **criteria(results, truth["parameters"]),
        "timings_s": results.get("diagnostics", {}).get("timings_s"),
    }
    print(json.dumps(report, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
