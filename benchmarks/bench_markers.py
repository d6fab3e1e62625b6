"""Benchmark: the smallest usable ArUco marker, old detector against new (issue 12).

Renders small synthetic photos (`imaging.synthetic.marker_test_photo`: four DICT_4X4_50
markers around a bright face, exposed for the face as a session exposed for the wedges would)
over a grid of

* marker cell size (full-resolution px of the cell's foreshortened side),
* view angle (0: square cells; 70 deg: cells 2.9 times longer across the view),
* marker paper against the face's peak (0.5: a dark view; 0.02: a bright specular view),
* quiet zone (a one-cell white margin, or none: the border on the dark base plate),

and for each detector (`imaging.LEGACY_DETECTOR`, the single gamma tone map before issue 12,
and `imaging.DetectorSettings()`) reports the fraction of markers found, the RMS corner error
against the rendered truth and the time per photo. Measured under whatever load the machine
has; the detection rates do not depend on it.

    python benchmarks/bench_markers.py [--quick] [--seeds 3] [--out benchmarks/results/markers.md]
"""

from __future__ import annotations

import argparse
import itertools
import math
import tempfile
import time
from pathlib import Path

import numpy as np

from stairfit import imaging
from stairfit.imaging import synthetic

DETECTORS = {"legacy": imaging.LEGACY_DETECTOR, "new": imaging.DetectorSettings()}
CELLS = (1.0, 1.25, 1.5, 2.0, 2.5, 3.0, 4.0, 6.0, 10.0, 16.0)
QUICK_CELLS = (1.5, 2.5, 4.0)


def run_case(cell: float, view: float, paper: float, quiet: float, seed: int, folder: Path):
    """{detector: (markers found of 4, squared corner errors, seconds)} for one photo."""
    photo, layout = synthetic.marker_test_photo(
        cell, view_deg=view, paper_to_peak=paper, quiet_zone_cells=quiet, seed=seed
    )
    frame = imaging.decode_raw(photo.write_dng(folder / "m.dng"))
    out = {}
    for name, settings in DETECTORS.items():
        t0 = time.perf_counter()
        det = imaging.detect_markers(frame, layout.dictionary, settings, expected_ids=range(4))
        dt = time.perf_counter() - t0
        sq = [
            np.sum((c - photo.marker_corners_px[i]) ** 2, axis=1)
            for i, c in zip(det.ids, det.corners_px, strict=True)
            if i in photo.marker_corners_px
        ]
        out[name] = (len(sq), np.concatenate(sq) if sq else np.zeros(0), dt)
    return out


def sweep(cells: tuple[float, ...], seeds: int) -> list[dict]:
    """One record per (quiet zone, paper, view, cell, detector)."""
    records = []
    with tempfile.TemporaryDirectory() as tmp:
        grid = itertools.product((1.0, 0.0), (0.5, 0.02), (0.0, 70.0), cells)
        for quiet, paper, view, cell in grid:
            found = {n: 0 for n in DETECTORS}
            errs: dict[str, list] = {n: [] for n in DETECTORS}
            secs = {n: 0.0 for n in DETECTORS}
            for seed in range(seeds):
                case = run_case(cell, view, paper, quiet, seed, Path(tmp))
                for name, (n, sq, dt) in case.items():
                    found[name] += n
                    errs[name].append(sq)
                    secs[name] += dt
            for name in DETECTORS:
                e = np.concatenate(errs[name])
                records.append(
                    {
                        "quiet": quiet, "paper": paper, "view": view, "cell": cell,
                        "detector": name, "found": found[name] / (4 * seeds),
                        "rms": math.sqrt(float(e.mean())) if e.size else math.nan,
                        "ms": 1000 * secs[name] / seeds,
                    }
                )  # fmt: skip
            print(f"quiet {quiet:g} paper {paper:g} view {view:2.0f} cell {cell:4.1f}: "
                  + "  ".join(f"{r['detector']} {r['found']:.2f} ({r['rms']:.2f} px)"
                              for r in records[-len(DETECTORS):]), flush=True)  # fmt: skip
    return records


def smallest(records: list[dict], rate: float = 0.95) -> dict[tuple, float]:
    """Per (detector, quiet, paper, view): the smallest cell from which on every larger cell
    has at least `rate` of the markers found."""
    out = {}
    keys = {(r["detector"], r["quiet"], r["paper"], r["view"]) for r in records}
    for key in sorted(keys):
        rows = sorted(
            (r for r in records if (r["detector"], r["quiet"], r["paper"], r["view"]) == key),
            key=lambda r: -r["cell"],
        )
        best = math.nan
        for r in rows:
            if r["found"] < rate:
                break
            best = r["cell"]
        out[key] = best
    return out


def report(records: list[dict], seeds: int) -> str:
    lines = [
        "# Smallest usable ArUco marker (benchmarks/bench_markers.py)",
        "",
        f"{seeds} photos per case, 4 markers each; found = fraction of markers detected; rms = "
        "corner error against the rendered truth (full-resolution px). Cell = the cell's "
        "foreshortened side in full-resolution px; view 70 deg makes the other side 2.9 times "
        "longer. Paper = marker paper radiance / the bright face's (exposed for the face).",
        "",
        "| quiet zone | paper | view | cell px | legacy found | legacy rms | new found | new rms"
        " | legacy ms | new ms |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    by = {}
    for r in records:
        by.setdefault((r["quiet"], r["paper"], r["view"], r["cell"]), {})[r["detector"]] = r
    for (q, p, v, c), d in by.items():
        lg, nw = d["legacy"], d["new"]
        lines.append(
            f"| {'1 cell' if q else 'none'} | {p:g} | {v:g} | {c:g} | {lg['found']:.2f} | "
            f"{lg['rms']:.2f} | {nw['found']:.2f} | {nw['rms']:.2f} | {lg['ms']:.0f} | "
            f"{nw['ms']:.0f} |"
        )
    lines += ["", "Smallest cell (px) with >= 95% found from there up:", ""]
    lines += ["| detector | quiet zone | paper | view | smallest cell px |"]
    lines += ["|---|---|---|---|---|"]
    for (det, q, p, v), c in smallest(records).items():
        lines.append(f"| {det} | {'1 cell' if q else 'none'} | {p:g} | {v:g} | {c:g} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="3 cell sizes, 1 seed (about a minute)")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--out", type=Path, default=None, help="write the markdown tables here")
    args = ap.parse_args()
    cells, seeds = (QUICK_CELLS, 1) if args.quick else (CELLS, args.seeds)
    text = report(sweep(cells, seeds), seeds)
    print(text)
    if args.out is not None:
        args.out.write_text(text)


if __name__ == "__main__":
    main()
