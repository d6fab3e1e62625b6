"""Benchmark: what flat fields, dark frames and HDR brackets cost per photo (issue 12), and how
long the independent photo renderer (tests/independent_photos.py) takes for one folder.

Renders a synthetic photo (default 12 MP, six faces, 15% vignetting, a sensor 6 DN above its
black-level tag), --flats flat-field photos, --darks dark frames and a bracket of --bracket
exposures, then times as medians of --repeats runs in one process:

* building the master calibration frames (`imaging.build_calibration`: decode, average, fit),
* measuring one photo (decode + 6 ROIs) plain, with dark + flat, and as a bracket of N files,

and one `render_folder` of the independent renderer (16 views of 1600 x 1200; --quick: 4 views
of 0.5 MP, smaller photos, one repeat).

    python benchmarks/bench_radiometry.py [--megapixels 12] [--repeats 3] [--quick]
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from stairfit import imaging
from stairfit.imaging import _pipeline, synthetic

EXPOSURE = imaging.Exposure(exposure_time_s=1 / 125, f_number=8.0, iso=200)
SENSOR = synthetic.SensorModel(bias_dn=6.0, fixed_pattern_dn=2.0)


def median_seconds(fn: Callable[[], Any], repeats: int) -> float:
    """Median wall time of `repeats` calls after one warm-up call."""
    fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def _size(megapixels: float) -> tuple[int, int]:
    h = round(math.sqrt(megapixels * 1e6 * 3 / 4) / 2) * 2
    return round(h * 4 / 3 / 2) * 2, h


def _faces(size: tuple[int, int]) -> dict[str, list]:
    w, h = size
    out = {}
    for k in range(6):
        x0, y0 = w * (0.05 + 0.31 * (k % 3)), h * (0.1 + 0.45 * (k // 3))
        out[f"w{k}"] = [(x0, y0), (x0 + 0.25 * w, y0), (x0 + 0.25 * w, y0 + 0.35 * h),
                        (x0, y0 + 0.35 * h)]  # fmt: skip
    return out


def write_inputs(tmp: Path, size: tuple[int, int], args: argparse.Namespace) -> dict[str, Any]:
    """The photo, its bracket, the flats and the darks; their paths and the calibration spec."""
    faces = _faces(size)
    radiance = {n: np.full(3, 300.0 * 3**k) * EXPOSURE.scale for k, n in enumerate(faces)}
    members = []
    for k in range(args.bracket):
        e = imaging.Exposure(EXPOSURE.exposure_time_s * 4**k, EXPOSURE.f_number, EXPOSURE.iso)
        photo = synthetic.render_photo(
            size, faces, radiance, e, background=np.full(3, 20.0 * EXPOSURE.scale),
            sensor=SENSOR, vignetting=0.15, seed=10 + k, texture_seed=10,
        )  # fmt: skip
        members.append(photo.write_dng(tmp / f"photo_{k}.dng"))
    flats, darks = [], []
    for k in range(args.flats):
        photo = synthetic.render_photo(
            size, {}, {}, EXPOSURE, background=np.full(3, 6000 * EXPOSURE.scale), sensor=SENSOR,
            texture_amplitude=0.002, vignetting=0.15, seed=100 + k,
        )  # fmt: skip
        flats.append((f"calibration.flat_field[{k}]", photo.write_dng(tmp / f"flat_{k}.dng")))
    for k in range(args.darks):
        photo = synthetic.render_photo(
            size, {}, {}, EXPOSURE, background=np.zeros(3), sensor=SENSOR,
            texture_amplitude=0.0, vignetting=0.0, seed=200 + k,
        )  # fmt: skip
        darks.append((f"calibration.dark_frames[{k}]", photo.write_dng(tmp / f"dark_{k}.dng")))
    spec = imaging.calibration_spec(flat_field=flats, dark_frames=darks)
    return {"faces": faces, "members": members, "calibration": spec}


def _measure(spec: imaging.PhotoSpec, cal: imaging.Calibration | None) -> None:
    settings = imaging.ExtractionSettings()
    frames = imaging.decode_view(spec)
    radiometry = _pipeline.view_radiometry(frames, spec, settings, cal)
    imaging.measure_frame(frames[0], spec, settings, radiometry)


def time_imaging(inputs: dict[str, Any], repeats: int) -> dict[str, float]:
    faces, members, spec = inputs["faces"], inputs["members"], inputs["calibration"]
    cal = imaging.build_calibration(spec)
    plain = imaging.PhotoSpec(members[0], rois=faces)
    calibrated = imaging.PhotoSpec(members[0], rois=faces, calibration=spec)
    bracket = imaging.PhotoSpec(
        members[0], rois=faces, bracket=tuple(members[1:]), calibration=spec
    )
    return {
        "build_calibration (flats + darks)": median_seconds(
            lambda: imaging.build_calibration(spec), repeats
        ),
        "decode + 6 ROIs, plain": median_seconds(lambda: _measure(plain, None), repeats),
        "decode + 6 ROIs, dark + flat": median_seconds(lambda: _measure(calibrated, cal), repeats),
        f"decode + 6 ROIs, bracket of {len(members)} + dark + flat": median_seconds(
            lambda: _measure(bracket, cal), repeats
        ),
    }


def time_renderer(tmp: Path, quick: bool, repeats: int) -> tuple[str, float]:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    import jax

    jax.config.update("jax_enable_x64", True)
    import independent_photos as ip

    kwargs: dict[str, Any] = (
        {"megapixels": 0.5, "views": (-60.0, -20.0, 20.0, 60.0)} if quick else {}
    )
    label = "render_folder, " + ("4 views of 0.5 MP" if quick else "16 views of 1600 x 1200")
    counter = iter(range(1000))

    def run() -> None:
        ip.render_folder(tmp / f"folder{next(counter)}", seed=1, **kwargs)

    return label, median_seconds(run, repeats)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--megapixels", type=float, default=12.0)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--flats", type=int, default=2)
    ap.add_argument("--darks", type=int, default=4)
    ap.add_argument("--bracket", type=int, default=3)
    ap.add_argument("--quick", action="store_true", help="2 MP, one repeat, a small folder")
    args = ap.parse_args(argv)
    if args.quick:
        args.megapixels, args.repeats = 2.0, 1
    size = _size(args.megapixels)
    with tempfile.TemporaryDirectory(prefix="bench_radiometry_") as name:
        tmp = Path(name)
        inputs = write_inputs(tmp, size, args)
        timings = time_imaging(inputs, args.repeats)
        label, seconds = time_renderer(tmp, args.quick, args.repeats)
        timings[label] = seconds
    print(f"\n{size[0]} x {size[1]} px, {args.flats} flats, {args.darks} darks, medians of "
          f"{args.repeats} (after a warm-up run)\n")  # fmt: skip
    print("| case | median |\n|---|---|")
    for k, v in timings.items():
        print(f"| {k} | {v:.2f} s |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
