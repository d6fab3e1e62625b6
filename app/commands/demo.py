"""`stairfit demo`: simulate a photo folder from known parameters, fit it, compare.

The README's first command. Everything goes into one output folder: `photos/` (the synthetic
DNGs, scene.toml, truth.json) and `fit/` (what `stairfit fit` writes).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from ..errors import UserError
from ..outcome import FitOutcome
from ..outputs import staged_folder
from ..pipeline import fit_scene
from ..scene import load_scene
from . import simulate
from ._fit_options import add_fit_options, options_from_args

DEG = np.pi / 180


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
    simulate.add_truth_options(p, seed_and_workers=False)
    add_fit_options(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Simulate, fit, compare."""
    if args.output is not None:
        raise UserError("--output: demo writes to OUT/fit; give OUT instead")
    out: Path = args.out
    if out.exists() and not args.force:
        raise UserError(f"{out}: already exists; choose another folder or add --force")
    settings = simulate.settings_from_args(args)
    options = options_from_args(args)
    t0 = time.perf_counter()
    with staged_folder(out, args.force, command="demo", option="OUT") as tmp:
        photos = tmp / "photos"
        photos.mkdir()
        print(
            f"stairfit demo: rendering {len(settings.views_deg)} photos of "
            f"{settings.megapixels:g} MP into {out / 'photos'}"
        )
        simulate.simulate(photos, settings, progress=options.progress)
        t_sim = time.perf_counter() - t0
        scene = load_scene(photos)
        outcome = fit_scene(scene, tmp / "fit", options)
    from ..report import print_summary

    print_summary(outcome, out / "fit", source=out / "photos")
    truth = json.loads((out / "photos" / simulate.TRUTH_FILE).read_text())["parameters"]
    print()
    print(compare_table(outcome, truth))
    print(
        f"\n  simulate {t_sim:.1f} s; measure {outcome.timings['measure_s']:.1f} s, fit "
        f"{outcome.timings['fit_s']:.1f} s, posterior {outcome.timings.get('posterior_s', 0):.1f}"
        f" s, outputs {outcome.timings['outputs_s']:.1f} s (compilation "
        f"{outcome.timings.get('compile_s', 0):.1f} s of fit and posterior)"
    )
    return 0


def compare_table(outcome: FitOutcome, truth: dict[str, float]) -> str:
    """Recovered against true values, the 95% interval, and the deviation in standard deviations.

    A truth outside its 95% interval happens for about 1 parameter in 20 by chance; the last
    column says how far off it is (|pull| > 3 would point to a bias, not to chance).
    """
    from ..report import display_param, parameter_records

    lines = [
        f"  {'parameter':<16} {'true':>12} {'recovered':>12} {'95% interval':>26}  "
        f"{'inside?':>7}  {'(rec - true) / sd':>17}"
    ]
    records = parameter_records(outcome)
    for rec in records:  # matched by identity: each wedge's own width against the one truth
        name, key = rec["name"], display_param(rec["parameter"])
        if key not in truth:
            continue
        true = truth[key]
        po, ls = rec.get("posterior"), rec["least_squares"]
        if po is not None:
            val, lo, hi = po["median"], po["p2_5"], po["p97_5"]
        elif ls["stderr"] is not None:
            val, lo, hi = (
                ls["value"],
                ls["value"] - 2 * ls["stderr"],
                ls["value"] + 2 * ls["stderr"],
            )
        else:
            val, lo, hi = ls["value"], np.nan, np.nan
        inside = "yes" if lo <= true <= hi else "NO"
        sd = 0.25 * (hi - lo)  # the interval spans about +-2 standard deviations
        pull = f"{(val - true) / sd:+.2f}" if sd > 0 else "-"
        interval = f"[{lo:.6g}, {hi:.6g}]"
        lines.append(
            f"  {name:<16} {true:>12.6g} {val:>12.6g} {interval:>26}  {inside:>7}  {pull:>17}"
        )
    fitted = {display_param(r["parameter"]) for r in records}
    fixed = [k for k in truth if k not in fitted]
    for k in fixed:
        lines.append(f"  {k:<16} {truth[k]:>12.5g} {'(not fitted: the chosen model fixes it)':>40}")
    return "\n".join(lines)
