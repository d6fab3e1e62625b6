"""`stairfit render FITDIR`: the fitted material in Mitsuba 3, on the photographed specimen from
every photographed view (beside the photos, also in report.html), or with `--mesh OBJ` on a
printed object (docs/render.md). A thin adapter over `stairfit.render.render_specimen` and
`render_mesh`.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..errors import UserError


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register the `render` command."""
    p = sub.add_parser(
        "render",
        help="render the fitted material (Mitsuba 3): the specimen's views, or a printed mesh",
        description=(
            "Render the fitted staircase material with Mitsuba 3 (the render extra): on the "
            "photographed specimen from every photo's camera pose and lamp, beside the photo "
            "(FITDIR/renders, also shown in FITDIR/report.html), or with --mesh on a printed "
            "object whose every point takes the staircase of its angle to --build-axis "
            "(FITDIR/renders-NAME). The material is also written as RGL .bsdf tables "
            "(materials/) for Mitsuba's and pbrt-v4's 'measured' material. docs/render.md."
        ),
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("fit", type=Path, metavar="FITDIR", help="a folder written by stairfit fit")
    p.add_argument("--photos", type=Path, default=None,
                   help="the photo folder the fit read (default: FITDIR without '-fit')")
    p.add_argument("--mesh", type=Path, default=None, help="a printed object (Wavefront OBJ, mm)")
    p.add_argument("--build-axis", default="z",
                   help="the mesh's printing direction: x, y, z, -z ... or 'X Y Z'")
    p.add_argument("--size", type=int, default=512, help="a mesh render's width and height (px)")
    p.add_argument("--step-deg", type=float, default=10.0,
                   help="a mesh's wedge angles are binned this wide, one material table each")
    p.add_argument("--view", action="append", default=[], metavar="PHOTO",
                   help="render only this photo (repeatable; default: every photo)")
    p.add_argument("--downscale", type=int, default=2,
                   help="render at the photos' colour-pixel size divided by this")
    p.add_argument("--spp", type=int, default=16, help="samples per pixel")
    p.add_argument("--quality", default="default", choices=("draft", "default", "fine"),
                   help="the material tables' resolution (docs/render.md, 'Resolution')")
    p.add_argument("--plate-albedo", type=float, default=0.03,
                   help="the plate's albedo (the fit does not measure it)")
    p.add_argument("--threads", type=int, default=None, help="Mitsuba's threads (default: all)")
    p.add_argument("-o", "--output", type=Path, default=None,
                   help="output folder (default: FITDIR/renders, or FITDIR/renders-MESHNAME)")
    p.add_argument("--force", action="store_true", help="replace an earlier render folder")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    p.set_defaults(func=run)  # fmt: skip


def _check(args: argparse.Namespace) -> None:
    for name, value, lo in (("--spp", args.spp, 1), ("--downscale", args.downscale, 1),
                            ("--size", args.size, 8)):  # fmt: skip
        if value < lo:
            raise UserError(f"{name} {value}: give an integer >= {lo}")
    if not 0.0 <= args.plate_albedo <= 1.0:
        raise UserError(f"--plate-albedo {args.plate_albedo}: give a value in [0, 1]")
    if not 0.5 <= args.step_deg <= 90.0:
        raise UserError(f"--step-deg {args.step_deg}: give a value in [0.5, 90]")
    if args.threads is not None and args.threads < 1:
        raise UserError(f"--threads {args.threads}: give an integer >= 1")


def run(args: argparse.Namespace) -> int:
    """`stairfit render FITDIR [--mesh OBJ]`."""
    from stairfit import render

    from ..fileio import made_by
    from ..outputs import staged_folder

    _check(args)
    fit = render.read_fit(args.fit, args.photos)
    options = render.RenderOptions(
        downscale=args.downscale, spp=args.spp, plate_albedo=args.plate_albedo,
        threads=args.threads, views=tuple(args.view), size=args.size, step_deg=args.step_deg,
        resolution=render.QUALITIES[args.quality],
    )  # fmt: skip

    def say(line: str) -> None:
        if not args.quiet:
            print(f"stairfit render: {line}", file=sys.stderr, flush=True)

    if args.mesh is not None:
        axis = render.parse_axis(args.build_axis)
        out = args.output or args.fit / f"renders-{args.mesh.stem}"
    else:
        out = args.output or args.fit / "renders"
    reuse = out / "materials" if made_by(out) == "render" else None
    inputs = fit.scene.input_files() + ((args.mesh,) if args.mesh else ())
    with staged_folder(out, args.force, command="render", inputs=inputs) as tmp:
        if args.mesh is not None:
            record = render.render_mesh(fit.material, args.mesh, axis, tmp, options, say, reuse)
        else:
            record = render.render_specimen(fit, tmp, options, say, reuse)
    if args.mesh is None and args.output is None:
        render.update_report(args.fit)
    print(f"stairfit render: {len(record['views'])} view(s) in {record['seconds']['total']:.0f} "
          f"s -> {out}")  # fmt: skip
    return 0
