"""The options of `stairfit fit`, shared by `demo` and `study`: the parser's arguments and the
validated `FitOptions` they give."""

from __future__ import annotations

import argparse
from pathlib import Path

from .. import _ranges
from ..errors import UserError
from ..imaging_specs import CACHE_DIR
from ..outcome import FitOptions
from ..pipeline import check_kernel_name, check_model_name
from ..presets import PRESETS, get_preset


def add_fit_options(p: argparse.ArgumentParser) -> None:
    """Options shared by `fit` and `demo`."""
    p.add_argument(
        "-o",
        "--output",
        type=Path,
        default=None,
        help="results folder (default: DIR-fit next to DIR)",
    )
    p.add_argument(
        "--preset",
        default="balanced",
        choices=sorted(PRESETS),
        help="speed/accuracy preset (README: Speed and accuracy)",
    )
    p.add_argument("--no-posterior", action="store_true", help="skip the emcee posterior")
    p.add_argument(
        "--model",
        default=None,
        help="force one model variant (e.g. 'sharp+delta_n') instead of selecting",
    )
    p.add_argument(
        "--kernel",
        default=None,
        help="the facets' kernel of the lab model (gaussian, ggx or beckmann) instead of "
        "fitting each and choosing (docs/fitting.md)",
    )
    p.add_argument(
        "--no-model-error", action="store_true", help="do not fit a fractional model-error term"
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the posterior sampler")
    p.add_argument(
        "--workers", type=int, default=1, help="processes decoding photos (1 is fastest on 2 cores)"
    )
    p.add_argument(
        "--no-cache", action="store_true", help=f"decode every photo again (ignore DIR/{CACHE_DIR})"
    )
    p.add_argument("--force", action="store_true", help="replace an existing results folder")
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def options_from_args(args: argparse.Namespace) -> FitOptions:
    """Validated options (user mistakes raise UserError)."""
    _ranges.check_workers(args.workers)
    if args.seed < 0:
        raise UserError(f"--seed: {args.seed} is negative; give an integer >= 0")
    if args.model is not None:
        check_model_name(args.model)
    if args.kernel is not None:
        check_kernel_name(args.kernel)
    return FitOptions(
        preset=get_preset(args.preset),
        posterior=not args.no_posterior,
        model=args.model,
        model_error=not args.no_model_error,
        freeze_imports=bool(getattr(args, "freeze_imports", False)),
        seed=args.seed,
        workers=args.workers,
        cache=not args.no_cache,
        progress=not args.quiet,
        kernel=args.kernel,
    )
