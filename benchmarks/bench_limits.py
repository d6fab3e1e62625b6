"""Benchmark: the sizes behind the documented input limits (issue 18, item 7).

* `stairfit predict`: wall time and peak memory of a density table of --rows rows (a fresh
  `stairfit predict` process each run, writing to a temporary file), and, side by side in one
  process, writing the rows from the model's JAX array element by element (the code before
  issue 18) against a NumPy copy of it, on a smaller table; this is what `MAX_ROWS`
  (app/commands/_predict_checks.py) rests on;
* ROI erosion (`imaging.roi_mask`) of a square ROI of --roi-px pixels at several radii, the
  basis of `MAX_ERODE_PX` (imaging/_roi.py).

    python benchmarks/bench_limits.py [--quick] [--repeats 3]

Reports medians; the figures depend on the machine's load (say so when quoting them).
"""

from __future__ import annotations

import argparse
import csv
import io
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from _timing import median_seconds


def _predict_seconds(step: float, out: Path) -> tuple[float, float]:
    """(wall seconds, peak MB) of one fresh `stairfit predict` process writing `out`."""
    code = (
        "import resource, sys; from stairfit.cli import main; "
        f"rc = main(['predict', '--theta-o-deg', '-90:90:{step!r}', '-o', {str(out)!r}, "
        "'--force']); "
        "print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, file=sys.stderr); "
        "sys.exit(rc)"
    )
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    seconds = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(proc.stderr)
    return seconds, int(proc.stderr.strip().splitlines()[-1]) / 1024


def predict_process(rows_wanted: int, repeats: int) -> dict[str, float]:
    """`stairfit predict` of a density table of about `rows_wanted` rows against one of 6 rows.

    Fresh processes, interleaved (the persistent JAX cache as a user has it); the difference
    of the medians is the cost of the rows themselves (start-up, imports, compilation apart).
    """
    step = 180.0 / (rows_wanted // 6 - 1)  # 6 wedges x (180 / step + 1) angles <= rows_wanted
    big, small, peak = [], [], []
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "p.csv"
        for _ in range(repeats):
            seconds, mb = _predict_seconds(step, out)
            big.append(seconds)
            peak.append(mb)
            small.append(_predict_seconds(180.0, Path(tmp) / "small.csv")[0])
        rows = sum(1 for _ in out.open()) - 1
    return {
        "rows": rows,
        "seconds": statistics.median(big),
        "baseline_seconds": statistics.median(small),
        "peak_mb": statistics.median(peak),
    }


def row_writing(n_angles: int, repeats: int) -> dict[str, float]:
    """Seconds per row writing density rows from the JAX array itself and from a NumPy copy."""
    import jax
    import jax.numpy as jnp

    from stairfit import model

    jax.config.update("jax_enable_x64", True)
    theta_o = np.deg2rad(np.linspace(-90, 90, n_angles))
    B, N, T, Th_o = np.meshgrid(np.deg2rad([30.0]), [1.46], [0.0], theta_o, indexing="ij")
    R = model.brdf(jnp.asarray(T), jnp.asarray(Th_o), jnp.asarray(B), jnp.asarray(N), 0.1)

    def write(values: object) -> None:
        w = csv.writer(io.StringIO())
        for idx in np.ndindex(B.shape):
            w.writerow([f"{float(np.rad2deg(Th_o[idx])):.10g}", f"{float(values[idx]):.10g}"])

    out = {}
    for name, values in (("jax array", R), ("numpy copy", np.asarray(R))):
        out[name] = median_seconds(lambda v=values: write(v), repeats) / B.size
    return out


def erosion(roi_px: int, radii: list[int], repeats: int) -> dict[int, float]:
    """Median seconds of `roi_mask` of a roi_px x roi_px square at each erosion radius."""
    from stairfit import imaging

    a, b = 300.0, 300.0 + roi_px
    square = ((a, a), (b, a), (b, b), (a, b))
    shape = (roi_px + 600, roi_px + 600)
    return {
        r: median_seconds(
            lambda r=r: imaging.roi_mask(square, shape, r, photo="p", wedge="w"), repeats
        )
        for r in radii
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small sizes, one repeat (a smoke test)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--rows", type=int, default=1_000_000, help="predict table size")
    ap.add_argument("--roi-px", type=int, default=1500)
    args = ap.parse_args()
    repeats = 1 if args.quick else args.repeats
    rows_wanted = 20_000 if args.quick else args.rows
    load = os.getloadavg()[0]
    print(f"load average at start: {load:.1f} (figures are for this load)")
    p = predict_process(rows_wanted, repeats)
    print(
        f"stairfit predict, density, {p['rows']:,} rows: {p['seconds']:.1f} s (a 6-row table: "
        f"{p['baseline_seconds']:.1f} s), peak {p['peak_mb']:.0f} MB"
    )
    per_row = row_writing(2_000 if args.quick else 20_000, repeats)
    for name, s in per_row.items():
        print(f"  writing rows from the {name}: {s * 1e6:.1f} us per row")
    radii = [8, 32] if args.quick else [8, 32, 64, 128]
    roi = 400 if args.quick else args.roi_px
    for r, s in erosion(roi, radii, repeats).items():
        print(f"roi_mask {roi} x {roi} px, erode_px {r}: {s:.3f} s")
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"peak memory of this process: {peak_mb:.0f} MB")


if __name__ == "__main__":
    main()
