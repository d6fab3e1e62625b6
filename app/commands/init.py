"""`stairfit init DIR`: draft the scene file of a folder of photos (app/draft.py).

Reads every RAW file of DIR, tells photographs, HDR brackets, flat fields and dark frames
apart, estimates each view's angle from its markers, and writes DIR/scene.toml (or
DIR/scene.draft.toml beside an existing one; nothing is ever replaced) with every estimate's
source as a comment and every value it could not know as a TODO that `fit` and `measure`
refuse until it is filled. docs/first-photo-set.md.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from .. import _ranges
from ..draft import DRAFT_FILE, Draft, draft_scene, write_draft


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register the `init` command."""
    p = sub.add_parser(
        "init",
        help="draft DIR/scene.toml from the photos in DIR (markers, brackets, flats, darks)",
        description=(
            "Draft the scene file of a folder of RAW photos: photographs, HDR brackets, flat "
            "fields and dark frames are told apart, each view's angle is estimated from its "
            "markers, and every value that cannot be known is written as a TODO that 'stairfit "
            f"fit' refuses until it is filled. Writes DIR/scene.toml, or DIR/{DRAFT_FILE} when "
            "scene.toml exists; never replaces a file (docs/first-photo-set.md)."
        ),
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("folder", type=Path, metavar="DIR", help="the folder of RAW photos")
    angles = p.add_mutually_exclusive_group()
    angles.add_argument(
        "--light-deg",
        metavar="DEG[,DEG...]",
        default=None,
        help="the lamp's angle from the base normal (deg, positive on the downhill side): one "
        "value for every photo, or a comma list with one per view in file-name order",
    )
    angles.add_argument(
        "--angles",
        type=Path,
        metavar="FILE.csv",
        default=None,
        help="a CSV with columns file, light_deg and optionally view_deg (which then wins over "
        "the markers' estimate)",
    )
    p.add_argument(
        "--layout",
        type=Path,
        metavar="FILE",
        default=None,
        help="the plate's and setup's tables ([specimen], [markers], [light], [camera] of a "
        "scene file), written once and reused",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """`stairfit init DIR`."""
    light_deg: tuple[float, ...] = ()
    if args.light_deg is not None:
        values = _ranges.parse_values(args.light_deg, "--light-deg")
        light_deg = tuple(
            float(v) for v in _ranges.check_range(values, -90, 90, "--light-deg", "deg")
        )
    draft = draft_scene(
        args.folder,
        layout_path=args.layout,
        light_deg=light_deg,
        angles_path=args.angles,
        progress=not args.quiet,
    )
    path = write_draft(args.folder, draft)
    print_summary(draft, path)
    return 0


def print_summary(draft: Draft, path: Path) -> None:
    """What was written: the views with their angles and sources, the calibration frames and
    the TODOs left."""
    brackets = sum(len(v.files) > 1 for v in draft.views)
    flats, darks = len(draft.flat_field), len(draft.dark_frames)
    print(
        f"stairfit init: wrote {path}: {len(draft.views)} views ({brackets} HDR brackets), "
        f"{flats} flat field{'s' * (flats != 1)}, {darks} dark frame{'s' * (darks != 1)}"
    )
    if draft.focal is not None:
        f = draft.focal.focal_length_px
        what = "affine (no focal length)" if f is None else f"focal length {f:.6g} px"
        print(f"  camera: {what}; from {draft.focal.source}")
    for v in draft.views:
        name = v.files[0] + (f" (+{len(v.files) - 1})" if len(v.files) > 1 else "")
        light = "TODO" if v.light_deg is None else f"{v.light_deg:g} ({v.light_source})"
        if v.view_deg is None:
            view = f"TODO ({v.view_source})"
        elif v.view_source == "markers" and v.estimate is not None:
            view = f"{v.view_deg:.3f} (markers, {v.estimate.model} camera)"
        else:
            view = f"{v.view_deg:g} ({v.view_source})"
        print(f"  {name}: light_deg {light}, view_deg {view}")
    if draft.todos:
        shown = ", ".join(draft.todos[:6]) + (", ..." if len(draft.todos) > 6 else "")
        print(f"  {len(draft.todos)} TODOs to fill in {path.name}: {shown}")
    print(
        f"  next: check the file, then 'stairfit measure {path.parent}' shows the placed faces"
        + (f" (rename {path.name} to scene.toml first)" if path.name == DRAFT_FILE else "")
    )
