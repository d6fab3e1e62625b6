"""The `stairfit` command line. Degrees and nanometres here; radians inside [conventions §1]."""

from __future__ import annotations

import argparse
import gc
import importlib
import os
import sys
import warnings
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from typing import TextIO

from . import __version__
from ._jaxcache import start_jax
from ._memory import first_line, is_out_of_memory
from ._signals import Terminated, terminate_by_exception
from .errors import StairfitWarning, UserError, one_line

COMMANDS = ("predict", "simulate", "init", "fit", "measure", "demo", "study", "render")
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


def main(
    argv: list[str] | None = None, freeze_imports: bool = False, stdout_closed: bool = False
) -> int:
    """Entry point: float64 on, one-line errors for user mistakes, non-zero exit on failure.

    A `UserError` (or an `ImagingError` that reached this far) is printed as one line,
    `stairfit COMMAND: error: FILE: FIELD: what is wrong; the fix`, with exit status 2; an
    `OSError` (a folder that cannot be written, a full disk) as one line naming the file, with
    status 1. SIGINT exits with 130, SIGTERM and SIGHUP with 128 + the signal number (143, 129)
    after the same cleanup (app/_signals.py), at any stage, the imports included. A reader that
    closes the pipe early (`stairfit predict | head -1`) ends the run quietly with status 0. A
    failed allocation (`MemoryError`, XLA's "Out of memory") is one line with what to do,
    status 1. Warnings are one line each. Anything else is a bug and keeps its traceback.

    `freeze_imports` (the console script, `entry`): once jax and the command's modules are
    imported, and after a fit's late imports (the posterior's, the report's), `gc.freeze()`
    takes them out of the collector's way (they live until the process ends); not for a
    process that goes on, where what is frozen is never collected. `stdout_closed`: the
    process was started without a standard output (`>&-`; `entry` put /dev/null there).
    """
    argv = sys.argv[1:] if argv is None else argv
    name = argv[0] if argv and argv[0] in COMMANDS else ""
    for stream in (sys.stdout, sys.stderr):  # a file name that is not UTF-8 is still printed
        with suppress(AttributeError, ValueError):
            stream.reconfigure(errors="backslashreplace")
    with terminate_by_exception():  # before the imports: a SIGTERM there is one line too
        try:
            return _run(argv, freeze_imports, stdout_closed)
        except Terminated as t:
            _say(name, f"terminated by {t.name}")
            return 128 + t.signum
        except KeyboardInterrupt:
            _say(name, "interrupted")
            return 130


def _say(command: str, message: str) -> None:
    """`stairfit COMMAND: message` on stderr."""
    print(f"stairfit {command}: {message}" if command else f"stairfit: {message}", file=sys.stderr)


def _run(argv: list[str], freeze_imports: bool, stdout_closed: bool) -> int:
    """`main` once the signals are handled: parse, set up JAX, run the command, report."""
    parser = build_parser(argv[0] if argv and argv[0] in COMMANDS else None)
    if not argv:  # no command: say what the commands are, not only that one is required
        parser.print_help(sys.stderr)
        return EXIT_USER_ERROR
    args = parser.parse_args(_join_negative_values(argv))
    # float64 [conventions §10], the persistent compilation cache, and under --quiet no XLA
    # log banners (set before jax is first imported: app/_jaxcache.py)
    start_jax(quiet=bool(getattr(args, "quiet", False)))
    args.freeze_imports = freeze_imports
    args.stdout_closed = stdout_closed
    if freeze_imports:
        gc.freeze()
    try:
        with one_line_warnings(args.command):
            return _call(args)
    except UserError as e:
        _say(args.command, f"error: {one_line(str(e))}")
        return EXIT_USER_ERROR
    except BrokenPipeError:  # the reader has all it wanted (`| head`): end quietly
        _silence_stdout()
        return 0
    except OSError as e:
        where = f"{os.fsdecode(e.filename)}: " if e.filename else ""
        what = e.strerror or str(e)
        _say(args.command, f"error: {one_line(where + what)}")
        return EXIT_OS_ERROR
    except Exception as e:
        if is_out_of_memory(e):
            _say(args.command, f"error: {one_line(_out_of_memory(e, args.command))}")
            return EXIT_OS_ERROR
        if not _is_imaging_error(e):
            raise
        _say(args.command, f"error: {one_line(str(e))}")
        return EXIT_USER_ERROR


def _call(args: argparse.Namespace) -> int:
    """Run the command; if JAX failed while its persistent compilation cache is on, run it once
    more without the cache (a foreign, swapped or damaged file there is loaded without any
    check, and makes the program it stands for fail), with a one-line warning; `predict`
    writing to standard output, which may have printed rows already, says so instead."""
    try:
        return int(args.func(args) or 0)
    except Exception as e:
        folder = _jax_cache_folder()
        ours = isinstance(e, UserError | OSError) or _is_imaging_error(e) or is_out_of_memory(e)
        if folder is None or ours or not _raised_in_jax(e):
            raise
        what = (
            f"a compiled program in the JAX cache {folder} did not fit this run (a file from "
            "another machine or version, or damaged)"
        )
        if args.command == "predict" and getattr(args, "output", None) is None:
            raise UserError(f"{what}; delete the folder and run again") from None
    _turn_off_jax_cache()
    warnings.warn(
        f"{what}; the run was repeated without the cache: delete the folder to rebuild it",
        StairfitWarning,
        stacklevel=1,
    )
    return int(args.func(args) or 0)


def _jax_cache_folder() -> str | None:
    """JAX's persistent compilation cache folder when it is on (None if JAX is not loaded)."""
    jax = sys.modules.get("jax")
    if jax is None or not jax.config.jax_enable_compilation_cache:
        return None
    return jax.config.jax_compilation_cache_dir or None


def _turn_off_jax_cache() -> None:
    """No persistent compilation cache for the rest of this process, and nothing compiled so
    far kept in memory (it may have come from the cache)."""
    import jax

    jax.config.update("jax_enable_compilation_cache", False)
    jax.clear_caches()


def _raised_in_jax(e: BaseException) -> bool:
    """Whether the exception passed through JAX's own code (JAX removes its frames from the
    traceback it raises and says so in a note, or keeps them on the exception's cause)."""
    seen: BaseException | None = e
    for _ in range(10):
        if seen is None:
            return False
        if any("JAX has removed its internal frames" in n for n in getattr(seen, "__notes__", ())):
            return True
        tb = seen.__traceback__
        while tb is not None:
            if f"{os.sep}jax{os.sep}_src{os.sep}" in tb.tb_frame.f_code.co_filename:
                return True
            tb = tb.tb_next
        seen = seen.__cause__ or seen.__context__
    return False


def _silence_stdout() -> None:
    """Point standard output at /dev/null, so that what is still buffered for a reader that
    has gone is dropped instead of failing again when the interpreter exits."""
    with suppress(OSError, ValueError):
        null = os.open(os.devnull, os.O_WRONLY)
        os.dup2(null, sys.stdout.fileno())
        os.close(null)


def _reopen_closed_stdio() -> bool:
    """Put /dev/null where standard output or error was closed (`>&-`, `2>&-`), so that
    progress bars and messages cannot fail the run; returns whether standard output was."""
    closed_out = False
    for fd, stream in ((1, "stdout"), (2, "stderr")):
        try:
            os.fstat(fd)
            usable = getattr(sys, stream) is not None
        except OSError:
            usable = False
        if usable:
            continue
        null = os.open(os.devnull, os.O_WRONLY)
        if null != fd:
            os.dup2(null, fd)
            os.close(null)
        setattr(sys, stream, open(fd, "w", closefd=False))  # noqa: SIM115 - lives as sys.std*
        closed_out |= fd == 1
    return closed_out


def _out_of_memory(e: BaseException, command: str) -> str:
    """The one-line message for a run that ran out of memory, with what to do."""
    if command in ("measure", "simulate", "predict"):
        return (
            f"ran out of memory ({first_line(e)}); give fewer or smaller photos (a photo is "
            "held whole while it is decoded), fewer --workers, or a machine with more memory"
        )
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
    anyway: that walk is a visible part of a warm `stairfit fit` (issue 14;
    benchmarks/results/cold.md).
    Files are closed and atexit handlers still run. Not done in `main()`, which tests and
    notebooks call in a process that goes on; for the same reason only this entry asks `main`
    to freeze the imports as they are made (`freeze_imports`). A closed standard output or
    error is replaced by /dev/null first (`_reopen_closed_stdio`), and a reader that left the
    pipe before the last flush ends the run quietly."""
    stdout_closed = _reopen_closed_stdio()
    code = main(freeze_imports=True, stdout_closed=stdout_closed)
    try:
        sys.stdout.flush()
    except BrokenPipeError:  # the reader has gone (`| head`): drop the rest quietly
        _silence_stdout()
    gc.freeze()
    sys.exit(code)


if __name__ == "__main__":
    entry()
