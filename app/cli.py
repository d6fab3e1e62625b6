"""The `stairfit` command line. Degrees and nanometres here; radians inside [conventions §1]."""

from __future__ import annotations

import argparse
import gc
import importlib
import sys
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from typing import TextIO

from . import __version__
from ._jaxcache import start_jax
from ._memory import first_line, is_out_of_memory
from ._signals import Terminated, terminate_by_exception
from .errors import StairfitWarning, UserError

COMMANDS = ("predict", "simulate", "fit", "measure", "demo", "study")
"""The subcommands, each the module `stairfit.commands.<name>` with `add_parser(sub)` and
`run(args)`."""


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The argument parser with every subcommand registered, or just `only` (then only that
    command's module is imported: `stairfit predict` does not import fit's; issue 14)."""
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
    for name in COMMANDS if only is None else (only,):
        importlib.import_module(f"{__package__}.commands.{name}").add_parser(sub)
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


EXIT_USER_ERROR = 2
"""Exit status for a mistake in the input (scene file, photos, options), as argparse uses."""
EXIT_OS_ERROR = 1
"""Exit status for a file the system would not read or write (permissions, a full disk)."""


MAX_WORD = 200
"""A longer run of characters without a space in a message (a value echoed back, e.g. a 5 MB
illuminant name) is shortened to its start and end."""
MAX_MESSAGE = 2000
"""A longer message keeps its start (file, field) and end (the fix), with the middle cut."""


def _short_word(word: str) -> str:
    if len(word) <= MAX_WORD:
        return word
    return f"{word[:120]}...{word[-40:]} ({len(word)} characters)"


def one_line(message: str) -> str:
    """A message on one line: line breaks and runs of spaces become single spaces; echoed
    values longer than `MAX_WORD` and messages longer than `MAX_MESSAGE` are shortened."""
    text = " ".join(_short_word(w) for w in str(message).split())
    if len(text) <= MAX_MESSAGE:
        return text
    cut = len(text) - MAX_MESSAGE
    return f"{text[:1200]} [... {cut} characters left out ...] {text[-(MAX_MESSAGE - 1200):]}"


def _is_imaging_error(e: BaseException) -> bool:
    """Whether `e` is a `stairfit.imaging.ImagingError` (without importing imaging for it)."""
    imaging = sys.modules.get("stairfit.imaging")
    return imaging is not None and isinstance(e, imaging.ImagingError)


def _is_ours(category: type[Warning]) -> bool:
    """Whether a warning category is stairfit's own (shown as one line)."""
    imaging = sys.modules.get("stairfit.imaging")
    ours = (StairfitWarning,) + ((imaging.ImagingWarning,) if imaging is not None else ())
    return issubclass(category, ours)


@contextmanager
def one_line_warnings(command: str) -> Iterator[None]:
    """Within the block, stairfit's warnings print as `stairfit COMMAND: warning: ...`."""
    with warnings.catch_warnings():
        warnings.simplefilter("always", StairfitWarning)
        original = warnings.showwarning

        def show(
            message: Warning | str,
            category: type[Warning],
            filename: str,
            lineno: int,
            file: TextIO | None = None,
            line: str | None = None,
        ) -> None:
            if _is_ours(category):
                print(f"stairfit {command}: warning: {one_line(str(message))}", file=sys.stderr)
            else:
                original(message, category, filename, lineno, file, line)

        warnings.showwarning = show
        yield


def main(argv: list[str] | None = None, freeze_imports: bool = False) -> int:
    """Entry point: float64 on, one-line errors for user mistakes, non-zero exit on failure.

    A `UserError` (or an `ImagingError` that reached this far) is printed as one line,
    `stairfit COMMAND: error: FILE: FIELD: what is wrong; the fix`, with exit status 2; an
    `OSError` (a folder that cannot be written, a full disk) as one line with status 1. SIGINT
    exits with 130, SIGTERM and SIGHUP with 128 + the signal number (143, 129) after the same
    cleanup (app/_signals.py). A failed allocation (`MemoryError`, XLA's "Out of memory") is
    one line with what to do, status 1. Warnings are one line each. Anything else is a bug and
    keeps its traceback.

    `freeze_imports` (the console script, `entry`): once jax and the command's modules are
    imported, and after each of a fit's late imports (`_prefetch.prefetch`), `gc.freeze()`
    takes them out of the collector's way (they live until the process ends); not for a
    process that goes on, where what is frozen is never collected.
    """
    argv = sys.argv[1:] if argv is None else argv
    parser = build_parser(argv[0] if argv and argv[0] in COMMANDS else None)
    if not argv:  # no command: say what the commands are, not only that one is required
        parser.print_help(sys.stderr)
        return EXIT_USER_ERROR
    args = parser.parse_args(_join_negative_values(argv))
    # float64 [conventions §10], the persistent compilation cache, and under --quiet no XLA
    # log banners (set before jax is first imported: app/_jaxcache.py)
    start_jax(quiet=bool(getattr(args, "quiet", False)))
    args.freeze_imports = freeze_imports
    if freeze_imports:
        gc.freeze()
    try:
        with terminate_by_exception(), one_line_warnings(args.command):
            return int(args.func(args) or 0)
    except Terminated as t:
        print(f"stairfit {args.command}: terminated by {t.name}", file=sys.stderr)
        return 128 + t.signum
    except UserError as e:
        print(f"stairfit {args.command}: error: {one_line(str(e))}", file=sys.stderr)
        return EXIT_USER_ERROR
    except KeyboardInterrupt:
        print(f"stairfit {args.command}: interrupted", file=sys.stderr)
        return 130
    except OSError as e:
        where = f"{e.filename}: " if e.filename else ""
        what = e.strerror or str(e)
        print(f"stairfit {args.command}: error: {one_line(where + what)}", file=sys.stderr)
        return EXIT_OS_ERROR
    except Exception as e:
        if is_out_of_memory(e):
            print(f"stairfit {args.command}: error: {one_line(_out_of_memory(e))}", file=sys.stderr)
            return EXIT_OS_ERROR
        if not _is_imaging_error(e):
            raise
        print(f"stairfit {args.command}: error: {one_line(str(e))}", file=sys.stderr)
        return EXIT_USER_ERROR


def _out_of_memory(e: BaseException) -> str:
    """The one-line message for a run that ran out of memory, with what to do."""
    return (
        f"ran out of memory ({first_line(e)}); the accurate preset's filleted rungs hold the most "
        "(5 nm sampling x 4096 rays, docs/fitting.md §3): use --preset balanced, fewer photos, "
        "or a machine with more memory"
    )


def entry() -> None:
    """The `stairfit` console script: `main()`, then exit with its status.

    Before the interpreter shuts down, `gc.freeze()` moves every object into the collector's
    permanent generation, so the shutdown's last garbage collection does not walk the whole
    heap of JAX, XLA and matplotlib objects only to free memory the operating system frees
    anyway: that walk took 0.5 s of a 9 s warm `stairfit fit` (issue 14; median of 5 runs).
    Files are closed and atexit handlers still run. Not done in `main()`, which tests and
    notebooks call in a process that goes on; for the same reason only this entry asks `main`
    to freeze the imports as they are made (`freeze_imports`)."""
    code = main(freeze_imports=True)
    gc.freeze()
    sys.exit(code)


if __name__ == "__main__":
    entry()
