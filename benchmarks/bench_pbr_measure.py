"""The measurement of a physically based photo set against its truth (issue 45's bounds).

The set is one of benchmarks/make_pbr_set.py's folders (tests/pbr_photos.py, Mitsuba 3). Every
photo is measured as `stairfit measure` measures it (the scene's specs and [extraction], the
flat field), in this process so that each ROI's pixels are known, and every row of a face the
renderer calls visible is compared with two truths:

* **truth.json**: the renderer's face radiance (`photos[].faces[wedge].radiance`), the mean of
  the noise-free render over the pixels `truth_erode_px` inside the face's outline. It is not
  the region the ROI covers (the scene's `erode_px`, adapted), and on these faces the region
  matters: the layer stripes' incomplete periods at its edges, the near lamp's curvature, and
  the render's Monte Carlo noise (a few bright samples per pixel: `mc_stderr`, up to 0.4% of a
  face's mean) differ between the two regions.
* **the ROI's own render** (with `--renders DIR`, a folder holding `renders/DSC_*.npz` of the
  same photos: `make_pbr_set.py --keep-renders`; the DNGs must be the same bytes, which is
  checked; photos without a kept render are compared with truth.json only): `T` the render's
  mean over the pixels the ROI used, compared with the ROI's mean radiance as measured,
  `value x (1 + stripe_offset)` (docs/imaging.md §Layer stripes: `value` is the layer-period
  average, `stripe_offset` how far the ROI's own mean lies from it). The
  pull's denominator adds the Monte Carlo variance of `T` minus that of the channel's own sites
  (their render noise is in the photo, so in `stderr`, and cancels in the difference), both
  exact from the render's per-pixel variance.

For both: rows used (unflagged rows over the rows of visible faces), |measured / truth - 1|
(median and worst), pulls (sd, how many beyond 4); a grey face's channel split `R / B - 1`
(the truth is grey) with its pull against the combined error of R and B; marker placement
(the reprojection error per photo, px).

    python benchmarks/bench_pbr_measure.py FOLDER [--renders DIR] [--worst N]

Results: benchmarks/results/pbr_set.md.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

TESTS = Path(__file__).resolve().parents[1] / "tests"


def measure(folder: Path) -> list[tuple[Any, Any]]:
    """Per photo (in the scene's order): its `FrameMeasurement` (rows and ROIs)."""
    from stairfit import imaging
    from stairfit.imaging import _pipeline
    from stairfit.imaging_specs import extraction_settings, photo_specs
    from stairfit.scene import load_scene

    scene = load_scene(folder)
    settings = extraction_settings(scene)
    specs = photo_specs(scene)
    calibrations: dict[Any, Any] = {}
    out = []
    for spec in specs:
        calibration = None
        if spec.calibration is not None:
            if spec.calibration not in calibrations:
                calibrations[spec.calibration] = imaging.build_calibration(
                    spec.calibration, settings.saturation_level
                )
            calibration = calibrations[spec.calibration]
        frames = imaging.decode_view(spec)
        radiometry = _pipeline.view_radiometry(frames, spec, settings, calibration)
        out.append((spec, imaging.measure_frame(frames[0], spec, settings, radiometry)))
    return out


def _roi_truth(render: Any, k_cam: float, roi: Any, colour: np.ndarray, c: int) -> tuple:
    """(T, MC variance of T minus the channel's sites' mean, MC variance of that sites' mean)."""
    h, w = colour.shape
    m = np.zeros((h, w), bool)
    m[roi.y0 : roi.y0 + roi.mask.shape[0], roi.x0 : roi.x0 + roi.mask.shape[1]] = roi.mask
    sites = m & (colour == c)
    n, n_c = int(m.sum()), int(sites.sum())
    var = k_cam**2 * np.nan_to_num(render.mc_variance[..., c])
    t = k_cam * float(render.radiance[m, c].mean())
    var_diff = float(
        np.sum(var[sites]) * (1 / n_c - 1 / n) ** 2 + np.sum(var[m & ~sites]) / n**2
    )
    return t, var_diff, float(np.sum(var[sites]) / n_c**2)


def compare(
    measured: list[tuple[Any, Any]], truth: dict[str, Any], renders: Path | None
) -> dict[str, Any]:
    """The rows beside both truths (module docstring): per row a dict of what was compared."""
    sys.path.insert(0, str(TESTS))
    import pbr_photos as pb

    setup = pb.setup_from_truth(truth)
    colour = np.tile(np.array([[0, 1], [1, 2]]), (setup.height // 2, setup.width // 2))
    rows = []
    index = {p["file"]: i for i, p in enumerate(truth["photos"])}  # a blind photo is left out
    # a kept render is named by the photo's place in the setup (a folder may hold a subset)
    render_index = {pb.photo_name(j): j for j in range(len(setup.photos))}
    for spec, fm in measured:
        i = index[spec.name]
        photo = truth["photos"][i]
        render = (
            pb.load_render(renders, render_index[spec.name])
            if renders is not None and (renders / "renders" / f"{spec.name}.npz").exists()
            else None
        )
        for r in fm.rows:
            face = photo["faces"].get(r.wedge)
            if face is None:
                continue
            c = "RGB".index(r.channel)
            row = {"row": r, "truth": face["radiance"][c], "mc": face["mc_stderr"][c]}
            if render is not None and not r.flag:
                row["T"], row["var_diff"], row["var_sites"] = _roi_truth(
                    render, setup.k_cam, fm.rois[r.wedge], colour, c
                )
            rows.append(row)
    return {"rows": rows, "stats": stats(rows)}


def _offset(r: Any) -> float:
    return r.stripe_offset if r.stripe_offset is not None else 0.0


def stats(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """The issue's numbers against truth.json and, where computed, against the ROI's render."""
    used = [d for d in rows if not d["row"].flag]
    out: dict[str, Any] = {"rows_visible": len(rows), "rows_used": len(used)}
    out["used_fraction"] = len(used) / max(1, len(rows))
    value = np.array([d["row"].value for d in used])
    se = np.array([d["row"].stderr for d in used])
    t = np.array([d["truth"] for d in used])
    out["truth_json"] = _numbers(value / t - 1, (value - t) / se)
    rendered = [i for i, d in enumerate(used) if "T" in d]  # photos with a kept render
    if rendered:
        sub = [used[i] for i in rendered]
        mean = value[rendered] * np.array([1 + _offset(d["row"]) for d in sub])
        big_t = np.array([d["T"] for d in sub])
        extra = np.array([d["var_diff"] - d["var_sites"] for d in sub])
        pull = (mean - big_t) / np.sqrt(se[rendered] ** 2 + extra)
        out["roi_render"] = {"rows": len(sub), **_numbers(mean / big_t - 1, pull)}
    out["grey_split"] = _split(used)
    rms = {d["row"].photo: d["row"].reprojection_error_px for d in rows}
    finite = [e for e in rms.values() if e is not None and math.isfinite(e)]
    out["marker_rms_px"] = [min(finite), max(finite)] if finite else None
    return out


def _numbers(rel: np.ndarray, pull: np.ndarray) -> dict[str, float]:
    return {
        "rel_median": float(np.median(rel)),
        "abs_rel_median": float(np.median(np.abs(rel))),
        "abs_rel_max": float(np.abs(rel).max()),
        "pull_sd": float(np.std(pull, ddof=1)),
        "pull_mean": float(np.mean(pull)),
        "pulls_beyond_4": int(np.sum(np.abs(pull) > 4)),
        "pull_max": float(np.abs(pull).max()),
    }


def _split(used: list[dict[str, Any]]) -> dict[str, float]:
    """R / B - 1 of the faces whose three rows are used, and its pull (corr_rb included)."""
    faces: dict[tuple[str, str], dict[str, Any]] = {}
    for d in used:
        r = d["row"]
        faces.setdefault((r.photo, r.wedge), {})[r.channel] = r
    split, pull = [], []
    for rgb in faces.values():
        if set(rgb) != {"R", "G", "B"}:
            continue
        r, b = rgb["R"], rgb["B"]
        sr, sb = r.stderr / r.value, b.stderr / b.value
        rho = r.corr_rb if math.isfinite(r.corr_rb) else 0.0
        var = sr**2 + sb**2 - 2 * rho * sr * sb
        split.append(r.value / b.value - 1)
        pull.append(math.log(r.value / b.value) / math.sqrt(var) if var > 0 else math.inf)
    s, p = np.abs(split), np.array(pull)
    return {
        "faces": len(split),
        "median": float(np.median(s)),
        "max": float(s.max()),
        "median_stderr": float(np.median(np.abs(np.log(1 + np.array(split))) / np.abs(p))),
        "pull_sd": float(np.std(p, ddof=1)),
        "pull_max": float(np.abs(p).max()),
    }


def worst(rows: list[dict[str, Any]], n: int) -> list[str]:
    """The n used rows of largest |pull| against the ROI's render (else truth.json)."""

    def pull(d: dict[str, Any]) -> float:
        r = d["row"]
        if "T" in d:
            var = r.stderr**2 + d["var_diff"] - d["var_sites"]
            return (r.value * (1 + _offset(r)) - d["T"]) / math.sqrt(var)
        return (r.value - d["truth"]) / r.stderr

    used = sorted((d for d in rows if not d["row"].flag), key=lambda d: -abs(pull(d)))
    out = []
    for d in used[:n]:
        r = d["row"]
        period = "-" if r.stripe_period_px is None else f"{r.stripe_period_px:.2f}"
        out.append(
            f"{r.photo} {r.wedge} {r.channel}: pull {pull(d):+.2f}, value / truth.json "
            f"{r.value / d['truth'] - 1:+.4f}, stderr {r.stderr / r.value:.4f}, period {period}, "
            f"thickness {r.thickness_px:.0f} px, view {r.face_view_deg:.1f} deg"
        )
    return out


def _same_photos(folder: Path, renders: Path, truth: dict[str, Any]) -> None:
    from stairfit.imaging import file_sha256

    for p in truth["photos"]:
        if not (renders / "renders" / f"{p['file']}.npz").exists():
            continue  # compared with truth.json only
        a, b = folder / p["file"], renders / p["file"]
        if file_sha256(a) != file_sha256(b):
            raise SystemExit(f"{b} is not {a}: render the same set (seed) with --keep-renders")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("folder", type=Path)
    parser.add_argument("--renders", type=Path, help="the same set rendered with --keep-renders")
    parser.add_argument("--worst", type=int, default=0, help="list the N rows of largest |pull|")
    args = parser.parse_args(argv)
    truth = json.loads((args.folder / "truth.json").read_text())
    if args.renders is not None:
        _same_photos(args.folder, args.renders, truth)
    result = compare(measure(args.folder), truth, args.renders)
    print(json.dumps(result["stats"], indent=1))
    for line in worst(result["rows"], args.worst):
        print(line)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
