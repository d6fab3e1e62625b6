"""Benchmark: RAW decoding and ROI extraction against a full demosaic, on a synthetic DNG (issue 3).

Writes a synthetic photo (default 24 megapixels, RGGB, 14 bits, six wedge faces and four ArUco
markers) to a temporary folder, then times, as medians of --repeats runs in the same process:

* rawpy/LibRaw decoding alone (`imaging.decode_raw`: read, SHA-256, unpack, EXIF),
* decoding + measuring the 6 ROIs given as pixel polygons (the per-photo cost of the fit),
* the same with the ROIs placed from the ArUco markers (detection + homography),
* the baseline: `rawpy.postprocess` (full AHD demosaic to 8-bit sRGB) of the same file,
* writing a preview PNG,

then the throughput of `measure_photos` over --photos copies with 1 and with --workers worker
processes (process start-up included), and the peak memory (ru_maxrss of a fresh process that
decodes and measures one photo; tracemalloc peak of the Python/NumPy allocations in it).

    python benchmarks/bench_imaging.py [--repeats 5] [--megapixels 24] [--out results.md]
"""

from __future__ import annotations

import argparse
import json
import math
import multiprocessing
import resource
import shutil
import statistics
import sys
import tempfile
import time
import tracemalloc
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import rawpy

from stairfit import imaging
from stairfit.imaging import synthetic

EXPOSURE = imaging.Exposure(exposure_time_s=1 / 125, f_number=8.0, iso=200)


def median_seconds(fn: Callable[[], Any], repeats: int) -> float:
    """Median wall time of `repeats` calls (after one warm-up call)."""
    fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def scene(megapixels: float) -> dict[str, Any]:
    """Image size, a base-plane layout of 4 markers and 6 faces, and its homography to pixels."""
    width = round(math.sqrt(megapixels * 1e6 * 1.5) / 2) * 2
    height = round(width / 1.5 / 2) * 2
    layout = imaging.MarkerLayout(
        {
            0: [(0, 0), (15, 0), (15, 15), (0, 15)],
            1: [(165, 0), (180, 0), (180, 15), (165, 15)],
            2: [(0, 105), (15, 105), (15, 120), (0, 120)],
            3: [(165, 105), (180, 105), (180, 120), (165, 120)],
        }
    )
    faces_mm = {}
    for k in range(6):
        x0, y0 = 22 + 52 * (k % 3), 20 + 45 * (k // 3)
        faces_mm[f"w{k}"] = [(x0, y0), (x0 + 40, y0), (x0 + 40, y0 + 35), (x0, y0 + 35)]
    corners_px = np.float32(
        [[0.05 * width, 0.06 * height], [0.95 * width, 0.08 * height],
         [0.94 * width, 0.95 * height], [0.06 * width, 0.93 * height]]
    )  # fmt: skip
    hom = cv2.getPerspectiveTransform(
        np.float32([[0, 0], [180, 0], [180, 120], [0, 120]]), corners_px
    )
    return {"size": (width, height), "layout": layout, "faces_mm": faces_mm, "hom": hom}


def faces_px(sc: dict[str, Any]) -> dict[str, list]:
    """The faces in pixels (through the true homography)."""
    out = {}
    for name, poly in sc["faces_mm"].items():
        pts = cv2.perspectiveTransform(np.asarray(poly, float).reshape(-1, 1, 2), sc["hom"])
        out[name] = [tuple(p) for p in pts.reshape(-1, 2)]
    return out


def _peak_memory_child(path: str, rois: dict, queue: Any) -> None:
    """In a fresh process: decode + measure once; report ru_maxrss and the tracemalloc peak."""
    tracemalloc.start()
    frame = imaging.decode_raw(path)
    imaging.measure_frame(frame, imaging.PhotoSpec(path, rois=rois), imaging.ExtractionSettings())
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    queue.put((_peak_rss_bytes(), peak))


def _peak_rss_bytes() -> int:
    """This process's peak resident memory. Linux: VmHWM, which (unlike ru_maxrss) is not
    inherited from the parent that forked the process before it exec'd the interpreter."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def peak_memory(path: Path, rois: dict) -> tuple[int, int]:
    ctx = multiprocessing.get_context("spawn")
    queue = ctx.Queue()
    proc = ctx.Process(target=_peak_memory_child, args=(str(path), rois, queue))
    proc.start()
    result = queue.get()
    proc.join()
    return result


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--repeats", type=int, default=5, help="timed runs per case (median)")
    ap.add_argument("--megapixels", type=float, default=24.0, help="synthetic photo size")
    ap.add_argument("--photos", type=int, default=6, help="photos for the throughput test")
    ap.add_argument("--workers", type=int, default=2, help="worker processes for throughput")
    ap.add_argument("--out", type=Path, help="write the results (.json, otherwise markdown)")
    args = ap.parse_args(argv)

    sc = scene(args.megapixels)
    rois = faces_px(sc)
    radiance = {n: np.array([1500.0, 3000.0, 2200.0]) * (1 + 0.3 * k) * EXPOSURE.scale
                for k, n in enumerate(rois)}  # fmt: skip
    tmp = Path(tempfile.mkdtemp(prefix="bench_imaging_"))
    results: dict[str, Any] = {
        "megapixels": sc["size"][0] * sc["size"][1] / 1e6,
        "size": f"{sc['size'][0]} x {sc['size'][1]}",
        "repeats": args.repeats,
    }
    try:
        t0 = time.perf_counter()
        photo = synthetic.render_photo(
            sc["size"], rois, radiance, EXPOSURE,
            background=np.full(3, 2500.0) * EXPOSURE.scale,
            markers=sc["layout"], plane_to_image=sc["hom"], seed=1,
        )  # fmt: skip
        results["render_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        path = photo.write_dng(tmp / "bench.dng")
        results["write_dng_s"] = time.perf_counter() - t0
        results["file_mb"] = path.stat().st_size / 1e6
        del photo

        settings = imaging.ExtractionSettings()
        spec_px = imaging.PhotoSpec(path, rois=rois)
        spec_mk = imaging.PhotoSpec(path, faces_mm=sc["faces_mm"], markers=sc["layout"])
        frame = imaging.decode_raw(path)
        check = imaging.measure_frame(frame, spec_mk, settings)
        results["marker_rms_px"] = check.placement.rms_error_px if check.placement else None

        def postprocess() -> None:
            with rawpy.imread(str(path)) as raw:
                raw.postprocess()

        cases = {
            "decode": lambda: imaging.decode_raw(path),
            "decode + 6 ROIs (polygons)": lambda: imaging.measure_frame(
                imaging.decode_raw(path), spec_px, settings
            ),
            "decode + 6 ROIs (markers)": lambda: imaging.measure_frame(
                imaging.decode_raw(path), spec_mk, settings
            ),
            "6 ROIs only (decoded frame)": lambda: imaging.measure_frame(frame, spec_px, settings),
            "rawpy.postprocess (demosaic)": postprocess,
            "preview PNG": lambda: imaging.write_preview(
                frame, check.rois, check.detection, tmp / "preview.png"
            ),
        }
        timings = {}
        for name, fn in cases.items():
            timings[name] = median_seconds(fn, args.repeats)
            print(f"{name:32s} {timings[name] * 1e3:9.1f} ms", flush=True)
        results["timings_s"] = timings

        copies = []
        for k in range(args.photos):
            dst = tmp / f"copy{k}.dng"
            shutil.copyfile(path, dst)
            copies.append(imaging.PhotoSpec(dst, rois=rois))
        throughput = {}
        for workers in sorted({1, args.workers}):
            t0 = time.perf_counter()
            imaging.measure_photos(copies, settings, max_workers=workers)
            dt = time.perf_counter() - t0
            throughput[workers] = {"seconds": dt, "photos_per_s": args.photos / dt}
            print(f"measure_photos, {workers} worker(s): {dt:.2f} s for {args.photos} photos "
                  f"({args.photos / dt:.2f} photos/s)", flush=True)  # fmt: skip
        results["throughput"] = throughput
        rss, traced = peak_memory(path, rois)
        results["peak_rss_mb"] = rss / 1e6
        results["tracemalloc_peak_mb"] = traced / 1e6
        print(f"peak RSS of one decode + measure: {rss / 1e6:.0f} MB "
              f"(NumPy/Python allocations: {traced / 1e6:.0f} MB)")  # fmt: skip
    finally:
        shutil.rmtree(tmp, ignore_errors=True)

    lines = [
        f"Synthetic DNG: {results['size']} px ({results['megapixels']:.1f} MP, "
        f"{results['file_mb']:.0f} MB); median of {args.repeats} runs.",
        "",
        "| case | median |",
        "|---|---|",
    ]
    lines += [f"| {k} | {v * 1e3:.0f} ms |" for k, v in results["timings_s"].items()]
    lines += [
        "",
        "| measure_photos | photos | wall time | photos/s |",
        "|---|---|---|---|",
    ]
    lines += [
        f"| {w} worker(s) | {args.photos} | {t['seconds']:.2f} s | {t['photos_per_s']:.2f} |"
        for w, t in results["throughput"].items()
    ]
    lines += [
        "",
        f"Rendering the photo: {results['render_s']:.2f} s; writing the DNG: "
        f"{results['write_dng_s']:.2f} s. Marker placement RMS error: "
        f"{results['marker_rms_px']:.2f} px. Peak RSS of a process that decodes and measures "
        f"one photo: {results['peak_rss_mb']:.0f} MB (NumPy/Python allocations: "
        f"{results['tracemalloc_peak_mb']:.0f} MB).",
    ]
    report = "\n".join(lines)
    print()
    print(report)
    if args.out:
        if args.out.suffix == ".json":
            args.out.write_text(json.dumps(results, indent=2))
        else:
            args.out.write_text(report + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
