"""Calibration study of the ROI standard errors (issue 13): pulls of ROI means against the truth.

Every cell of the grid (texture none / multiplicative / additive, correlation length 0-8 px,
ROI area 20-2000 blocks of 8 x 8 px, uniform or graded illumination; shot + read noise always)
renders `--rois` independent ROIs with the independent NumPy generator tests/roi_fields.py
(never `stairfit.imaging.synthetic`), measures each with `imaging.roi_channel_stats` (a
RawFrame built in memory) and computes, per channel,

* the **total pull** `(mean - untextured) / stderr`: the error of the ROI value as an estimate of
  the untextured radiance at the ROI's centroid (what a model of the surface predicts; the value
  is each channel's fitted plane there, docs/imaging.md §Channel sites, and the truths of
  tests/roi_fields.py are taken at the same point). Every ROI has its own texture,
  drawn afresh, so the pulls sample texture and noise together, as a model fitted to many faces
  would see them;
* the **noise pull** `(mean - exact) / stderr_noise`: against the noise-free mean of *this*
  textured surface, i.e. the error that changes from photo to photo of the same face.

Rows flagged by imaging (`few_blocks`: too few effective blocks) are counted and left out. The
Monte Carlo uncertainty of each pull sd is the standard deviation of 200 bootstrap resamples of
the ROIs (each ROI's three channels together: they share one texture).

    python benchmarks/bench_roi_errors.py                 # the full grid, 1000 ROIs per cell
    python benchmarks/bench_roi_errors.py --quick         # a few cells, 60 ROIs: does it run?
    python benchmarks/bench_roi_errors.py --workers 2 --out benchmarks/results/roi_errors.md
    python benchmarks/bench_roi_errors.py --rois 600 --large-rois 250   # ~40 min, 2 workers
"""

from __future__ import annotations

import argparse
import math
import multiprocessing
import sys
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import roi_fields as rf

from stairfit import imaging
from stairfit.imaging._pipeline import _flags

ELLS_PX = (0.0, 1.0, 2.0, 4.0, 8.0)
SIZES_BLOCKS = (20, 60, 200, 2000)
PASS_RANGE = (0.9, 1.1)
BOOTSTRAP = 200
MIN_EVALUATED = 30
"""A cell with fewer unflagged ROIs is reported as flagged: its pull sd is not measured."""


def grid(sizes: tuple[int, ...] = SIZES_BLOCKS, ells: tuple[float, ...] = ELLS_PX) -> list:
    """The cells: no texture, then multiplicative and additive texture at every ell."""
    textures = [("none", 0.0)] + [(t, e) for t in ("mult", "add") for e in ells]
    return [
        rf.Cell(t, e, n, graded) for t, e in textures for n in sizes for graded in (False, True)
    ]


def measure_cell(cell: rf.Cell, n_rois: int, seed: int) -> dict:
    """Per ROI and channel: pulls, dof, block size, flags (arrays of shape (n_rois, 3))."""
    rng = np.random.default_rng(seed)
    settings = imaging.ExtractionSettings(erode_px=0)
    per_image = max(1, min(64, int(3e6 / rf.tile_px(cell) ** 2)))
    keys = ("total", "noise", "dof", "block_px", "n_blocks", "flagged", "corr")
    out: dict[str, list] = {k: [] for k in keys}
    t0 = time.perf_counter()
    while len(out["total"]) < n_rois:
        mosaic, truths = rf.render(cell, min(per_image, n_rois - len(out["total"])), rng)
        frame = rf.frame(mosaic)
        for t in truths:
            st = imaging.roi_channel_stats(frame, t.roi, settings)
            u, e = t.untextured, t.exact
            out["total"].append([(s.mean_dn - u[c]) / s.stderr_dn for c, s in enumerate(st)])
            out["noise"].append([(s.mean_dn - e[c]) / s.stderr_noise_dn for c, s in enumerate(st)])
            out["dof"].append([s.dof for s in st])
            out["block_px"].append([s.block_px for s in st])
            out["n_blocks"].append([s.n_blocks for s in st])
            out["flagged"].append([bool(_flags(s, settings)) for s in st])
            out["corr"].append(list(st[0].channel_corrs))
    res = {k: np.array(v, dtype=float) for k, v in out.items()}
    res["seconds"] = time.perf_counter() - t0
    return res


def _sd_and_error(pulls: np.ndarray, rng: np.random.Generator) -> tuple[float, float, float]:
    """Pooled pull sd over the channels, its bootstrap error (ROIs resampled), and the mean."""
    ok = np.isfinite(pulls)
    if ok.sum() < 10:
        return math.nan, math.nan, math.nan
    sd = float(np.std(pulls[ok], ddof=1))
    boot = []
    for _ in range(BOOTSTRAP):
        p = pulls[rng.integers(0, len(pulls), len(pulls))]
        boot.append(np.std(p[np.isfinite(p)], ddof=1))
    return sd, float(np.std(boot)), float(np.mean(pulls[ok]))


def summarise(cell: rf.Cell, res: dict) -> dict:
    """One row of the table."""
    rng = np.random.default_rng(1)
    flagged = res["flagged"].astype(bool)
    total = np.where(flagged, np.nan, res["total"])
    noise = np.where(flagged, np.nan, res["noise"])
    sd, sd_err, mean = _sd_and_error(total, rng)
    nsd, nsd_err, _ = _sd_and_error(noise, rng)
    ok_dof = res["dof"][~flagged]
    both = np.isfinite(total[:, 0]) & np.isfinite(total[:, 1])
    emp_corr = (
        float(np.corrcoef(total[both, 0], total[both, 1])[0, 1]) if both.sum() > 10 else math.nan
    )
    return {
        "cell": cell,
        "rois": len(res["total"]),
        "evaluated": int(np.all(~flagged, axis=1).sum()),
        "flagged": float(flagged.mean()),
        "emp_corr": emp_corr,
        "sd": sd,
        "sd_err": sd_err,
        "mean": mean,
        "noise_sd": nsd,
        "noise_sd_err": nsd_err,
        "dof": float(np.median(ok_dof)) if ok_dof.size else math.nan,
        "block_px": float(np.median(res["block_px"])),
        "corr": float(np.nanmedian(res["corr"])) if np.isfinite(res["corr"]).any() else math.nan,
        "seconds": res["seconds"],
    }


def verdict(row: dict) -> str:
    """pass / FAIL on the total pull sd; "flagged" when fewer than MIN_EVALUATED ROIs are left."""
    if row["evaluated"] < MIN_EVALUATED:
        return "flagged"
    return "pass" if PASS_RANGE[0] <= row["sd"] <= PASS_RANGE[1] else "FAIL"


def table(rows: list[dict]) -> str:
    head = (
        "| texture | ell (px) | blocks | light | ROIs | flagged | pull sd (total) | mean "
        "| pull sd (noise) | median dof | block (px) | corr R-G: reported / pulls | result |\n"
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|"
    )
    lines = [head]
    for r in rows:
        c = r["cell"]
        lines.append(
            f"| {c.texture} | {c.ell_px:g} | {c.roi_blocks} | "
            f"{'graded' if c.graded else 'uniform'} | {r['rois']} | {100 * r['flagged']:.0f}% | "
            f"{r['sd']:.3f} +- {r['sd_err']:.3f} | {r['mean']:+.3f} | "
            f"{r['noise_sd']:.3f} +- {r['noise_sd_err']:.3f} | {r['dof']:.0f} | "
            f"{r['block_px']:.0f} | {r['corr']:.2f} / {r['emp_corr']:.2f} | {verdict(r)} |"
        )
    return "\n".join(lines)


def _job(args: tuple[int, dict, int]) -> tuple[int, dict]:
    k, cell_dict, n_rois = args
    cell = rf.Cell(**cell_dict)
    return k, measure_cell(cell, n_rois, seed=1000 + k)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--rois", type=int, default=1000, help="ROIs per cell")
    ap.add_argument(
        "--large-rois", type=int, help="ROIs per cell of the largest ROI size (default --rois)"
    )
    ap.add_argument("--quick", action="store_true", help="6 cells, 60 ROIs each")
    ap.add_argument("--workers", type=int, default=1, help="processes (spawn)")
    ap.add_argument("--out", type=Path, help="write the markdown table here")
    ap.add_argument("--raw", type=Path, help="write the per-ROI arrays here (.npz)")
    args = ap.parse_args(argv)
    cells = grid()
    n_rois = args.rois
    if args.quick:
        cells = [c for c in grid((20, 200), (0.0, 4.0)) if c.texture != "add" and not c.graded]
        n_rois = 60
    n_large = args.large_rois or n_rois
    largest = max(c.roi_blocks for c in cells)
    jobs = [
        (k, asdict(c), n_large if c.roi_blocks == largest else n_rois) for k, c in enumerate(cells)
    ]
    jobs.sort(key=lambda j: -j[1]["roi_blocks"] * j[2])  # the longest first: no idle tail
    results: dict[int, dict] = {}
    t0 = time.perf_counter()
    if args.workers > 1:
        ctx = multiprocessing.get_context("spawn")
        with ctx.Pool(args.workers) as pool:
            for k, res in pool.imap_unordered(_job, jobs):
                results[k] = res
                _progress(cells[k], res, len(results), len(cells), t0)
    else:
        for job in jobs:
            k, res = _job(job)
            results[k] = res
            _progress(cells[k], res, len(results), len(cells), t0)
    rows = [summarise(cells[k], results[k]) for k in range(len(cells))]
    counts = f"{n_rois}" if n_large == n_rois else f"{n_rois} ({n_large} at {largest} blocks)"
    report = _report(rows, counts, time.perf_counter() - t0, args.workers)
    print(report)
    if args.out:
        args.out.write_text(report + "\n")
    if args.raw:
        arrays = {f"{key}_{k}": v for k, r in results.items() for key, v in r.items()}
        np.savez_compressed(args.raw, cells=np.array([c.label() for c in cells]), **arrays)
    return 0 if all(verdict(r) != "FAIL" for r in rows) else 1


def _progress(cell: rf.Cell, res: dict, done: int, total: int, t0: float) -> None:
    row = summarise(cell, res)
    print(
        f"[{done}/{total} {time.perf_counter() - t0:6.0f} s] {cell.label():40s} "
        f"sd {row['sd']:.3f} +- {row['sd_err']:.3f}  noise {row['noise_sd']:.3f}  "
        f"flagged {100 * row['flagged']:.0f}%  ({res['seconds']:.0f} s)",
        file=sys.stderr,
        flush=True,
    )


def _report(rows: list[dict], n_rois: str, seconds: float, workers: int) -> str:
    n_fail = sum(verdict(r) == "FAIL" for r in rows)
    n_all = sum(verdict(r) == "flagged" for r in rows)
    settings = imaging.ExtractionSettings()
    return "\n".join(
        [
            "# ROI standard errors: calibration study (benchmarks/bench_roi_errors.py)",
            "",
            f"{len(rows)} cells x {n_rois} ROIs; generator tests/roi_fields.py (texture "
            f"amplitude {rows[0]['cell'].amplitude:g}, graded = +-{rows[0]['cell'].gradient:g} "
            f"ramp, gain {rf.GAIN_E_PER_DN:g} e/DN, read noise {rf.READ_NOISE_DN:g} DN, levels "
            f"R/G/B {'/'.join(f'{x:g}' for x in rf.LEVELS_DN)} DN x U(0.4, 1.6)); extraction "
            f"defaults (block_px {settings.block_px}, min_blocks {settings.min_blocks}), no "
            "erosion. Pull sd pooled over R, G, B, flagged rows left out; +- is the bootstrap "
            f"Monte Carlo error. Pass: total pull sd in [{PASS_RANGE[0]}, {PASS_RANGE[1]}].",
            "",
            table(rows),
            "",
            f"{len(rows) - n_fail - n_all} cells pass, {n_fail} fail, {n_all} have fewer than "
            f"{MIN_EVALUATED} unflagged ROIs. {seconds:.0f} s with {workers} worker(s).",
        ]
    )


if __name__ == "__main__":
    sys.exit(main())
