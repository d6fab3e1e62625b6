"""Output files and folders: the one home of output safety (README "Commands", "Outputs").

Every command that writes a result goes through this module (and it, for the files themselves,
through `stairfit.fileio`):

* `check_output(out, inputs=..., reserved=...)` refuses an output that is, or contains, a file
  or folder the run reads (the photo folder, the scene file, every photo: `Scene.input_files()`),
  the current folder, the home folder or a filesystem root, with or without `--force`;
* `output_lock(out)` lets one run at a time write an output: `fcntl.flock` on a hidden lock file
  `.NAME.lock` beside it, released by the operating system when the process dies, so a killed
  run never blocks a later one; a second run into the same output is refused with one line;
* `remove_stale_leftovers(out)` first puts back a result a killed replacement left aside
  (`fileio.recover`), then removes what killed runs left that holds no complete result: this
  output's temporary files, incomplete staging folders and superseded old copies (under its
  lock, so none of them belongs to a live run), and incomplete staging folders of other
  outputs in the same parent older than `STALE_AGE_S` whose lock is free;
* `staged_folder(out, force, command=...)` and `staged_file(path, force, signature=...)` build
  a result under a temporary name and move it into place only when complete. With `force` an
  existing output is replaced only when stairfit made it: a folder whose `fileio.MARKER` names
  the same command, a file that starts with the command's `signature`; anything else (a photo
  folder, a file of the user's, a link) is refused;
* `atomic_text(path)` / `atomic_bytes(path, data)` write one file via a temporary sibling
  (`stairfit.fileio`);
* an `OSError` raised while writing names the real target (`results/report.html`), never the
  hidden temporary (`.results.1a2b3c4d.partial/report.html`).

Commands call these rather than writing their own.
"""

from __future__ import annotations

import errno
import os
import stat
import time
import warnings
from collections.abc import Iterable, Iterator
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import TextIO

from . import __version__, fileio
from .errors import StairfitWarning, UserError
from .fileio import atomic_bytes as atomic_bytes
from .fileio import atomic_text as atomic_text

try:  # POSIX; on other systems runs are not locked (documented in the README)
    import fcntl
except ImportError:  # pragma: no cover - Windows
    fcntl = None  # type: ignore[assignment]

STALE_AGE_S = 3600.0
"""A staging folder of *another* output older than this (and whose lock is free) is removed."""

_NO_LOCKS = {errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS}


# --- refusing outputs that would destroy inputs --------------------------------------------


def _contains(folder: Path, path: Path) -> bool:
    """Whether `path` is `folder` or lies inside it (both resolved)."""
    return path == folder or folder in path.parents


def check_output(
    out: Path,
    inputs: Iterable[Path] = (),
    reserved: Iterable[Path] = (),
    option: str = "--output",
) -> Path:
    """The resolved output path, or a one-line `UserError` if replacing it could lose data.

    Refused, with or without `--force`: an output that is or contains one of `inputs` (files
    and folders the run reads), that is, contains or lies inside one of `reserved` (e.g. the
    measurement cache), or that is or contains the current folder, the home folder or a
    filesystem root, or that is a device, pipe or socket. `option` names the command-line
    option in the message.
    """
    _refuse_special(Path(out))
    resolved = fileio.resolved(out)
    for path in inputs:
        p = fileio.resolved(path)
        if _contains(resolved, p):
            what = "is" if p == resolved else "contains"
            raise UserError(
                f"{out}: {option} {what} {p}, which this run reads; replacing it would delete "
                f"the input, so choose an output outside it (with or without --force)"
            )
    for path in reserved:
        p = fileio.resolved(path)
        if _contains(resolved, p) or _contains(p, resolved):
            raise UserError(f"{out}: {option} overlaps {p}, which stairfit keeps; choose another")
    for name, p in (("the current folder", Path.cwd()), ("your home folder", Path.home())):
        if _contains(resolved, fileio.resolved(p)):
            what = "is" if fileio.resolved(p) == resolved else "contains"
            example = f"{option} results" if option.startswith("-") else "results"
            raise UserError(
                f"{out}: {option} {what} {name} ({p}); an output is replaced as a whole, so give "
                f"a new folder, e.g. {example}"
            )
    if resolved.parent == resolved or os.path.ismount(resolved):
        raise UserError(f"{out}: {option} is a filesystem root or mount point; give a new folder")
    return resolved


# --- one run per output ---------------------------------------------------------------------


def lock_path(out: Path) -> Path:
    """The lock file of an output: `.NAME.lock` beside it."""
    return out.with_name(f".{out.name}.lock")


def _try_lock(lock: Path) -> int | None:
    """A locked descriptor of `lock` (made if needed); None if held, -1 where flock fails.

    The lock is taken on the file that is at `lock` *after* locking: a run that unlinked it in
    the meantime makes us retry, so two runs never both hold "the" lock of one output.
    """
    while True:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, fileio.FILE_MODE)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            return None
        except OSError as e:
            os.close(fd)
            if e.errno in _NO_LOCKS:
                return -1  # a filesystem without flock (some network shares): not locked
            raise
        except BaseException:
            os.close(fd)
            raise
        try:
            same = os.stat(lock).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            same = False
        if same:
            return fd
        os.close(fd)


def _release(lock: Path, fd: int) -> None:
    """Remove the lock file while still holding it, then release it."""
    with suppress(FileNotFoundError):
        lock.unlink()
    if fd >= 0:
        os.close(fd)


@contextmanager
def output_lock(out: Path) -> Iterator[None]:
    """Hold the lock of output `out` (resolved) for the duration; refuse if another run holds it.

    The lock is `fcntl.flock` on `.NAME.lock` beside `out`, so the operating system releases it
    when the process ends in any way (SIGKILL included); the file is removed on release.
    """
    if fcntl is None:  # pragma: no cover - no flock on this system
        yield
        return
    lock = lock_path(out)
    fd = _try_lock(lock)
    if fd == -1:
        warnings.warn(
            f"{out.parent}: this filesystem does not support file locks; two runs into {out} at "
            "once would not be stopped",
            StairfitWarning,
            stacklevel=3,
        )
    if fd is None:
        raise UserError(
            f"{out}: another stairfit run is writing this output now (it holds {lock}); wait "
            "for it to finish, or choose another output"
        )
    try:
        yield
    finally:
        _release(lock, fd)


# --- leftovers of killed runs ---------------------------------------------------------------


def in_staging(path: Path) -> bool:
    """Whether `path` lies inside a staging folder (removed when its run fails)."""
    partial = fileio.partial_pattern()
    return any(partial.match(p.name) for p in Path(path).parents)


def _is_stale_partial(path: Path, now: float) -> bool:
    """Another output's incomplete staging folder, old, and no run holds that output's lock."""
    m = fileio.partial_pattern().match(path.name)
    if m is None or not path.is_dir() or path.is_symlink() or fileio.made_by(path) is not None:
        return False
    try:
        old = now - path.lstat().st_mtime > STALE_AGE_S
    except FileNotFoundError:
        return False
    if not old or fcntl is None:
        return old
    lock = path.with_name(f".{m.group('name')}.lock")
    if not lock.exists():
        return True
    fd = _try_lock(lock)
    if fd is None:
        return False
    _release(lock, fd)
    return True


def remove_stale_leftovers(out: Path, *, complete_too: bool = False) -> list[Path]:
    """Recover, then clean what earlier, killed runs left beside output `out`; call it holding
    its lock. Returns what was removed.

    A result a killed replacement left aside is moved back first (`fileio.recover`); then
    removed are this output's temporary files, incomplete staging folders, old copies that a
    stairfit result in place has replaced (`fileio.leftovers`; with `complete_too`, once this
    run's own result is in place, complete staging folders too), and other outputs' incomplete
    staging folders older than `STALE_AGE_S` whose lock is free. A complete result is never
    removed before one is in place.
    """
    fileio.recover(out)
    now = time.time()
    removed = []
    candidates = fileio.leftovers(out, complete_too=complete_too)
    try:
        others = [p for p in out.parent.iterdir() if p not in candidates]
    except OSError:
        others = []
    for path in candidates + [p for p in others if _is_stale_partial(p, now)]:
        try:
            fileio.remove_tree(path)
        except OSError:  # not ours to clean after all (permissions): leave it
            continue
        removed.append(path)
    return removed


# --- staged folders and files ---------------------------------------------------------------


def _refuse_special(shown: Path) -> None:
    """A device, pipe or socket (`-o /dev/null`) or a loop of links is never an output."""
    try:
        mode = os.stat(shown).st_mode
    except OSError as e:
        if e.errno == errno.ELOOP:
            raise UserError(
                f"{_short(shown)}: is a loop of symbolic links; give a real file or folder name"
            ) from None
        if e.errno == errno.ENOTDIR:
            parent = fileio.file_in_the_way(Path(shown).parent)
            raise UserError(
                f"{_short(shown)}: {_short(parent)} is a file, not a folder; give an output "
                "whose parent folders are folders"
            ) from None
        return
    if not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):
        raise UserError(
            f"{_short(shown)}: is {fileio.kind(mode)}, not a file or folder stairfit can "
            "replace; give a file name (predict writes to stdout without -o)"
        )


def _short(value: object, limit: int = 200) -> str:
    """`value` as text, shortened in the middle to about `limit` characters for a message."""
    text = str(value)
    if len(text) <= limit:
        return text
    return f"{text[: limit // 2]}...{text[-limit // 2 :]} ({len(text)} characters)"


def _refuse_existing_folder(out: Path, shown: Path, force: bool, command: str) -> None:
    """An existing output folder is replaced only with `force`, and only when `command` made
    it (its `fileio.MARKER`)."""
    if not (out.exists() or out.is_symlink()):
        return
    if not force:
        raise UserError(
            f"{shown}: already exists; choose another output or add --force to replace it"
        )
    made = fileio.made_by(out)
    if made == command:
        return
    if out.is_symlink():
        what = f"is a link to {os.path.realpath(out)}"
    elif made is not None:
        what = f"was made by 'stairfit {made}', not by 'stairfit {command}'"
    elif out.is_dir():
        what = f"is a folder that 'stairfit {command}' did not make (no {fileio.MARKER} in it)"
    else:
        what = "is a file, not a folder stairfit made"
    raise UserError(
        f"{shown}: {what}; --force replaces only a result 'stairfit {command}' made itself, so "
        "choose another output (or move it away yourself)"
    )


@contextmanager
def staged_folder(
    out: Path,
    force: bool,
    *,
    command: str,
    inputs: Iterable[Path] = (),
    reserved: Iterable[Path] = (),
    option: str = "--output",
) -> Iterator[Path]:
    """Build a folder under a temporary name next to `out` and move it into place on success.

    The whole output-folder safety in one place: `check_output` (never an output that holds an
    input), the lock of `out`, the recovery of a result a killed run left aside, the refusal of
    an existing `out` without `force` or that `stairfit COMMAND` did not make, then the staging
    folder `.NAME.XXXXXXXX.partial`, marked complete (`fileio.mark_complete`) and moved to `out`
    when the block ends without an exception, removed otherwise (SIGINT and SIGTERM included,
    see `stairfit.cli`). A crash leaves no folder named `out` that is not complete; an
    `OSError` names `out`.
    """
    shown = Path(out)
    out = check_output(shown, inputs, reserved, option)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise fileio.named_error(e, out.parent, shown.parent) from None
    with output_lock(out):
        remove_stale_leftovers(out)
        _refuse_existing_folder(out, shown, force, command)
        tmp = fileio.fresh_staging_folder(out)
        try:
            yield tmp
            fileio.mark_complete(tmp, command, __version__)
            fileio.replace_folder(tmp, out)
        except OSError as e:
            fileio.remove_tree(tmp)
            raise fileio.named_error(e, tmp, shown) from e
        except BaseException:
            fileio.remove_tree(tmp)
            raise
        with suppress(OSError):
            remove_stale_leftovers(out, complete_too=True)


def _starts_with(path: Path, signature: bytes) -> bool:
    """Whether the regular file `path` begins with `signature`."""
    try:
        fd = fileio.open_regular(path)
    except OSError:
        return False
    with os.fdopen(fd, "rb") as fh:
        return fh.read(len(signature)) == signature


@contextmanager
def staged_file(
    path: Path,
    force: bool,
    *,
    signature: bytes,
    command: str,
    inputs: Iterable[Path] = (),
    option: str = "--output",
) -> Iterator[TextIO]:
    """A text file written under a temporary name and moved to `path` on success.

    As `staged_folder` for one file: refused when it is an input, a folder, or exists without
    `force`; with `force` an existing file is replaced only when it begins with `signature`
    (the first bytes `stairfit COMMAND` writes, e.g. its CSV header); locked; stale temporary
    files of earlier runs removed; the temporary file removed on any failure (SIGINT and
    SIGTERM included).
    """
    shown = Path(path)
    target = check_output(shown, inputs, (), option)
    if target.is_dir():
        raise UserError(f"{shown}: {option} is a folder; give a file name, e.g. {shown}/out.csv")
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise fileio.named_error(e, target.parent, shown.parent) from None
    with output_lock(target):
        if target.exists() or target.is_symlink():
            if not force:
                raise UserError(
                    f"{shown}: already exists; choose another output or add --force to replace it"
                )
            if target.is_symlink() or not _starts_with(target, signature):
                raise UserError(
                    f"{shown}: was not written by 'stairfit {command}' (it does not start with "
                    f"its header); --force replaces only stairfit's own output, so choose "
                    "another file name (or move it away yourself)"
                )
        remove_stale_leftovers(target)
        with atomic_text(target, shown=shown) as fh:
            yield fh
