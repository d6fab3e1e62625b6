"""Render the physically based photo set of issue 40 (tests/pbr_photos.py, Mitsuba 3) to disk.

Two sets: `default`, the issue's lab (six wedges of 10-60 deg, 150 um layers, 25 um edges, GGX
facets of alpha 0.06 and index 1.46, a 6 mm lamp 500 mm away at 0 and 20 deg, a 135 mm lens
900 mm away, 28 photos of 1800 x 1200 px), and `variant`, the same lab with other parameters
(`pbr_photos.variant_setup`: other wedges, layers, edges, Beckmann roughness, index, lamp and
camera; 24 photos), for a held-back-style check; `dev`, the default lab rendered unpolarised
(`scalar_rgb`) at 1200 x 800 px and 48 samples per pixel on the faces (about a minute a photo),
the development set of benchmarks/bench_lab_fit.py. Each folder holds the DNGs, the flat fields,
scene.toml (what `stairfit measure` / `stairfit fit` read) and truth.json (what they never read).

The folder is outside the repository (default `~/.cache/stairfit/pbr/<set>`). The run is
resumable: a photo already written (its DNG and its truth part) is skipped, and every file is
written atomically, so an interrupted run is continued by running it again. One progress line
per photo. Mitsuba renders on `--threads` threads (default 1, to share the machine); `--nice`
lowers this process's priority.

    nice -n 15 python benchmarks/make_pbr_set.py                     # the issue's set
    python benchmarks/make_pbr_set.py --set variant --out /data/pbr/variant --threads 2
    python benchmarks/make_pbr_set.py --quick --out QUICK_DIR      # 3 photos, few samples

Render times: benchmarks/results/pbr_set.md.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

TESTS = Path(__file__).resolve().parents[1] / "tests"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--set", choices=("default", "variant", "dev"), default="default")
    parser.add_argument("--out", type=Path, help="folder (default ~/.cache/stairfit/pbr/<set>)")
    parser.add_argument("--threads", type=int, default=1, help="Mitsuba's threads (default 1)")
    parser.add_argument("--nice", type=int, default=0, help="add this to the process's niceness")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--keep-renders",
        action="store_true",
        help="keep each photo's noise-free render (renders/*.npz, ~40 MB each)",
    )
    parser.add_argument(
        "--quick", action="store_true", help="a look: the first 3 photos at 1/16 of the samples"
    )
    args = parser.parse_args(argv)
    if args.nice:
        os.nice(args.nice)
    sys.path.insert(0, str(TESTS))
    import pbr_photos as pb

    setup = pb.variant_setup() if args.set == "variant" else pb.PbrSetup()
    if args.set == "dev":
        setup = replace(
            setup, variant="scalar_rgb", width=1200, height=800, pixel_pitch_um=30.0, spp=48,
            spp_markers=16, spp_background=4, max_depth=4, flat_photos=1,
        )  # fmt: skip
    if args.quick:
        setup = replace(
            setup,
            photos=setup.photos[:3],
            spp=setup.spp // 16,
            spp_markers=setup.spp_markers // 4,
            spp_background=2,
        )
    out = args.out or Path.home() / ".cache" / "stairfit" / "pbr" / args.set
    print(
        f"{args.set} set: {len(setup.photos)} photos of {setup.width} x {setup.height} px, "
        f"{setup.variant}, {setup.spp} / {setup.spp_markers} / {setup.spp_background} spp "
        f"(faces / markers / rest), {args.threads} thread(s) -> {out}",
        flush=True,
    )
    t0 = time.perf_counter()
    truth = pb.render_folder(
        out,
        setup,
        args.seed,
        threads=args.threads,
        keep_render=args.keep_renders,
        progress=lambda line: print(line, flush=True),
    )
    seconds = [p["render_seconds"] for p in truth["photos"]]
    print(
        json.dumps(
            {
                "photos": len(seconds),
                "render_s_total": round(sum(seconds), 1),
                "render_s_per_photo_min_median_max": [
                    round(min(seconds), 1),
                    round(sorted(seconds)[len(seconds) // 2], 1),
                    round(max(seconds), 1),
                ],
                "wall_s_this_run": round(time.perf_counter() - t0, 1),
            }
        ),
        flush=True,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
