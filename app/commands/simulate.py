"""`stairfit simulate OUT`: a synthetic photo folder (real DNGs, scene file, truth) from known
physical parameters.

A thin adapter over `stairfit.simulation` (which says how the photos are made): the options
(`_simulate_options`, shared with `demo`), the output folder staged, a line printed.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ..outputs import staged_folder
from ..scene import SCENE_FILE
from ..simulation import TRUTH_FILE, simulate
from ._simulate_options import add_truth_options, settings_from_args


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register the `simulate` command."""
    p = sub.add_parser(
        "simulate",
        help="write a synthetic photo folder (DNGs + scene.toml + truth.json)",
        description=(
            "Render a synthetic photo folder from known parameters: real DNG files of six wedges "
            "on a marked base seen from several angles, the scene file that describes them, and "
            "the truth in truth.json (kept apart from the photos)."
        ),
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("out", type=Path, help="the folder to create")
    add_truth_options(p)
    p.add_argument("--force", action="store_true", help="replace an existing folder")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """`stairfit simulate OUT`."""
    settings = settings_from_args(args)
    with staged_folder(args.out, args.force, command="simulate", option="OUT") as tmp:
        simulate(tmp, settings, progress=not args.quiet)
    print(f"wrote {len(settings.views_deg)} photos, {SCENE_FILE} and {TRUTH_FILE} to {args.out}")
    return 0
