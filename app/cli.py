"""The `stairfit` command line. Degrees and nanometres here; radians inside [conventions §1]."""

from __future__ import annotations

import argparse
import sys

from . import __version__, demo, fit, predict, simulate
from .errors import UserError


def build_parser() -> argparse.ArgumentParser:
    """The argument parser with every subcommand registered."""
    parser = argparse.ArgumentParser(
        prog="stairfit",
        description=(
            "Fit a physical model of the FDM staircase (facet reflections + retroreflection) "
            "to RAW photographs of printed wedges. Conventions: docs/conventions.md."
        ),
    )
    parser.add_argument("--version", action="version", version=f"stairfit {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    predict.add_parser(sub)
    simulate.add_parser(sub)
    fit.add_parser(sub)
    demo.add_parser(sub)
    return parser


def _join_negative_values(argv: list[str]) -> list[str]:
    """Let `--theta-o-deg -90:90:1` mean `--theta-o-deg=-90:90:1`.

    argparse takes a value that starts with '-' and is not a plain number for an option; angle
    ranges often do. Only a token that starts with '-' followed by a digit is joined.
    """
    out: list[str] = []
    for tok in argv:
        takes_angle = bool(out) and out[-1].startswith("--") and out[-1].endswith("-deg")
        negative = len(tok) > 1 and tok[0] == "-" and (tok[1].isdigit() or tok[1] == ".")
        if takes_angle and negative and "=" not in out[-1]:
            out[-1] = f"{out[-1]}={tok}"
            continue
        out.append(tok)
    return out


def main(argv: list[str] | None = None) -> int:
    """Entry point: float64 on, one-line errors for user mistakes, non-zero exit on failure."""
    parser = build_parser()
    args = parser.parse_args(_join_negative_values(sys.argv[1:] if argv is None else argv))
    import jax

    jax.config.update("jax_enable_x64", True)  # [conventions §10]
    try:
        return int(args.func(args) or 0)
    except UserError as e:
        print(f"stairfit {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"stairfit {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
