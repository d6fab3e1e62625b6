"""Issue 12's "Done when", timed: `stairfit fit` of the independent renderer's paper setup.

Renders the photo set of tests/independent_photos.py (16 views of 1600 x 1200, 15% vignetting
with a flat-field photo, one fixed exposure; the exposure tags in IFD0 when this stairfit reads
them there, else as scene-file overrides) and runs the default `stairfit fit` on it in a fresh
process with an empty JAX cache, then reports the wall and CPU time, the peak memory, and the
issue's criteria: sigma inside its 95% interval, floor and scale within 3 standard errors, the
model-error term, the chosen variant. The aim: under 5 minutes on the 2-core machine.

With `--layout standing` the wedges stand on the plate (faces rising by their angle, lit at
-10 deg, 8 views from -50 to 20 deg) and every photo's roi_px is dropped where at least four
markers are found: the ROIs are placed in 3-D from the markers and `[camera] focal_length_px`
(the paper's flush faces cannot be described by `face_mm`, whose convention is a wedge standing
on the base; tests/validation/test_independent_fit.py).

    python benchmarks/bench_independent_fit.py            # the issue's set
    python benchmarks/bench_independent_fit.py --quick    # 0.5 MP, 8 views: a look in minutes
    python benchmarks/bench_independent_fit.py --layout standing   # ROIs from the markers
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


def render(folder: Path, quick: bool, layout: str) -> dict[str, Any]:
    sys.path.insert(0, str(TESTS))  # the renderer
    sys.path.insert(0, str(TESTS / "validation"))  # the tests' layouts and placement
    import jax

    jax.config.update("jax_enable_x64", True)
    import independent_photos as ip
    from test_independent_fit import rois_from_markers
    from test_independent_photos import setup_for_this_stairfit

    setup = setup_for_this_stairfit(folder.parent)
    if layout == "standing":
        setup = ip.standing_setup(exposure_tags=setup.exposure_tags, write_intrinsics=True)
    kwargs: dict[str, Any] = {}
    if quick:
        views = setup.views_deg if layout == "standing" else tuple(range(-70, 71, 20))
        kwargs = {"megapixels": 0.5, "views": tuple(float(v) for v in views)}
    truth = ip.render_folder(folder, seed=7, setup=setup, **kwargs)
    truth["exposure_tags"] = setup.exposure_tags
    drawn = rois_from_markers(folder, 4) if layout == "standing" else list(truth["photos"])
    truth["hand_drawn_rois"] = drawn
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
    # issue 13's "Done when": reduced chi^2 in [0.8, 1.25], every true parameter inside its
    # posterior 95% interval, R-hat and ESS reported
    ls = results["diagnostics"]["least_squares"]
    out["reduced_chi2"] = ls["reduced_chi2"]
    inside, rhat, ess = {}, [], []
    for name, p in est.items():
        po = p.get("posterior") or {}
        if po:
            rhat.append(po["rhat"])
            ess.append(min(po["ess_bulk"], po["ess_tail"]))
        if name in truth and po:
            inside[name] = bool(po["p2_5"] <= truth[name] <= po["p97_5"])
    out["truth_in_posterior_95"] = inside
    out["rhat_max"] = max(rhat) if rhat else None
    out["ess_min"] = min(ess) if ess else None
    out["issue13_done_when"] = bool(
        0.8 <= ls["reduced_chi2"] <= 1.25 and inside and all(inside.values()) and rhat
    )
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="0.5 MP, 8 views")
    ap.add_argument(
        "--layout", choices=("paper", "standing"), default="paper",
        help="paper: flush faces, roi_px in every photo; standing: ROIs from the markers",
    )  # fmt: skip
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="bench_independent_fit_") as name:
        tmp = Path(name)
        truth = render(tmp / "photos", args.quick, args.layout)
        env = dict(os.environ, STAIRFIT_JAX_CACHE=str(tmp / "jax-cache"))
        cmd = [sys.executable, "-c", _WRAPPER, "stairfit", "fit", str(tmp / "photos"),
               "-o", str(tmp / "fit"), "--quiet"]  # fmt: skip
        proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
        if proc.returncode:
            print(proc.stderr, file=sys.stderr)
            return proc.returncode
        wall, cpu, peak_mb = map(float, proc.stdout.split()[-3:])
        results = json.loads((tmp / "fit" / "results.json").read_text())
        from stairfit import imaging

        rows = list(imaging.MeasurementTable.read_csv(tmp / "fit" / "measurements.csv"))
        by_markers = sum(r.roi_source == "markers" for r in rows)
    report = {
        "set": "quick (0.5 MP, 8 views)" if args.quick else "1600 x 1200",
        "layout": args.layout,
        "views": len(truth["photos"]),
        "exposure tags": truth["exposure_tags"],
        "hand-drawn ROIs (photos)": truth["hand_drawn_rois"],
        "rows placed by markers": f"{by_markers} of {len(rows)}",
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
