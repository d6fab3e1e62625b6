"""`stairfit fit DIR`: decode -> extract -> fit -> select model -> posterior -> results.

A thin adapter over `stairfit.pipeline.fit_scene` (the stages are there): parse the options,
stage the output folder, run, print the summary. Every stage shows a progress bar; the results
are written into a temporary folder that is moved into place only when complete.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from .. import pipeline
from ..imaging_specs import CACHE_DIR
from ..scene import load_scene
from ._fit_options import add_fit_options, options_from_args


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register the `fit` command."""
    p = sub.add_parser(
        "fit",
        help="fit the staircase model to a folder of RAW photos",
        description=(
            "Decode the RAW photos listed in DIR/scene.toml, measure every wedge face, fit the "
            "model ladder by least squares, choose the simplest model the data support, sample "
            "its posterior, and write results.json, the measurement table, figures and "
            "report.html to the output folder."
        ),
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("folder", type=Path, metavar="DIR", help="photo folder with scene.toml")
    add_fit_options(p)
    p.set_defaults(func=run)


def default_output(folder: Path) -> Path:
    """`DIR-fit` next to the photo folder."""
    from ..fileio import resolved

    folder = resolved(folder)
    return folder.with_name(f"{folder.name}-fit")


def run(args: argparse.Namespace) -> int:
    """`stairfit fit DIR`."""
    from ..outputs import staged_folder

    options = options_from_args(args)
    scene = load_scene(args.folder)
    out = args.output or default_output(args.folder)
    inputs = (scene.folder, *scene.input_files())
    reserved = (scene.folder / CACHE_DIR,)
    with staged_folder(out, args.force, command="fit", inputs=inputs, reserved=reserved) as tmp:
        pipeline.check_photos(scene)
        outcome = pipeline.fit_scene(scene, tmp, options)
    from ..report import print_summary

    print_summary(outcome, out)
    return 0
