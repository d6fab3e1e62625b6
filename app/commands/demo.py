"""`stairfit demo`: simulate a photo folder from known parameters, fit it, compare.

The README's first command. Everything goes into one output folder: `photos/` (the synthetic
DNGs, scene.toml, truth.json) and `fit/` (what `stairfit fit` writes).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from ..errors import UserError
from ..outputs import staged_folder
from ..pipeline import check_kernel_geometry, fit_scene
from ..scene import load_scene
from ..simulation import TRUTH_FILE, simulate
from ._fit_options import add_fit_options, options_from_args
from ._simulate_options import add_truth_options, settings_from_args


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register the `demo` command."""
    p = sub.add_parser(
        "demo",
        help="simulate photos from known parameters, fit them, compare",
        description=(
            "Render a synthetic photo folder of six wedges (real DNGs) from known physical "
            "parameters, run the full fit on it, and print the recovered parameters against "
            "the truth. OUT/photos holds the photos and truth, OUT/fit the results."
        ),
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("out", type=Path, nargs="?", default=Path("stairfit-demo"), help="output folder")
    add_truth_options(p, seed_and_workers=False)
    add_fit_options(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Simulate, fit, compare."""
    if args.output is not None:
        raise UserError("--output: demo writes to OUT/fit; give OUT instead")
    out: Path = args.out
    if out.exists() and not args.force:
        raise UserError(f"{out}: already exists; choose another folder or add --force")
    settings = settings_from_args(args)
    options = options_from_args(args)
    check_kernel_geometry(options.kernel, False, "the demo's simulated scene (a distant lamp)",
                          "leave --kernel out or give gaussian")  # fmt: skip
    t0 = time.perf_counter()
    with staged_folder(out, args.force, command="demo", option="OUT") as tmp:
        photos = tmp / "photos"
        photos.mkdir()
        print(
            f"stairfit demo: rendering {len(settings.views_deg)} photos of "
            f"{settings.megapixels:g} MP into {out / 'photos'}"
        )
        simulate(photos, settings, progress=options.progress)
        t_sim = time.perf_counter() - t0
        scene = load_scene(photos)
        outcome = fit_scene(scene, tmp / "fit", options)
    from ..report import compare_table, print_summary

    print_summary(outcome, out / "fit", source=out / "photos")
    truth = json.loads((out / "photos" / TRUTH_FILE).read_text())["parameters"]
    print()
    print(compare_table(outcome, truth))
    print(
        f"\n  simulate {t_sim:.1f} s; measure {outcome.timings['measure_s']:.1f} s, fit "
        f"{outcome.timings['fit_s']:.1f} s, posterior {outcome.timings.get('posterior_s', 0):.1f}"
        f" s, outputs {outcome.timings['outputs_s']:.1f} s (compilation "
        f"{outcome.timings.get('compile_s', 0):.1f} s of fit and posterior)"
    )
    return 0
