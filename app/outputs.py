"""Output files and folders: the one home of output safety (README "Commands", "Outputs").

Every command that writes a result goes through this module:

* `check_output(out, inputs=..., reserved=...)` refuses an output that is, or contains, a file
  or folder the run reads (the photo folder, the scene file, every photo: `Scene.input_files()`),
  the current folder, the home folder or a filesystem root, with or without `--force`;
* `output_lock(out)` lets one run at a time write an output: `fcntl.flock` on a hidden lock file
  `.NAME.lock` beside it, released by the operating system when the process dies, so a killed
  run never blocks a later one; a second run into the same output is refused with one line;
* `remove_stale_leftovers(out)` removes what killed runs left beside the output: the staging
  folders `.NAME.XXXXXXXX.partial`, `.NAME.old-PID` and temporary files `.NAME.XXXXXXXX.tmp`
  of the same output (under its lock, so none of them belongs to a live run), and staging
  folders of other outputs in the same parent older than `STALE_AGE_S` whose lock is free;
* `staged_folder(out, force, ...)` and `staged_file(path, force, ...)` build a result under a
  temporary name and move it into place only when complete; an existing output is replaced only
  with `force`, and leaves nothing behind (a file, a folder or a link);
* `atomic_text(path)` / `atomic_bytes(path, data)` write one file via a temporary sibling that
  gets the user's umask (not the 0600 of `tempfile.mkstemp`);
* an `OSError` raised while writing names the real target (`results/report.html`), never the
  hidden temporary (`.results.1a2b3c4d.partial/report.html`).

Commands call these rather than writing their own.
"""

from __future__ import annotations

import errno
import os
import re
import secrets
import shutil
import stat
import time
import warnings
from collections.abc import Iterable, Iterator
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import TextIO

from ._signals import deferred
from .errors import StairfitWarning, UserError

try:  # POSIX; on other systems runs are not locked (documented in the README)
    import fcntl
except ImportError:  # pragma: no cover - Windows
    fcntl = None  # type: ignore[assignment]

STALE_AGE_S = 3600.0
"""A staging folder of *another* output older than this (and whose lock is free) is removed."""

_FILE_MODE = 0o666  # the umask takes its share, as for any file the user creates
_NO_LOCKS = {errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS}
_TOKEN_HEX = 4  # bytes of randomness in temporary names: 8 hex digits


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
    resolved = Path(os.path.abspath(out)).resolve()
    for path in inputs:
        p = Path(path).resolve()
        if _contains(resolved, p):
            what = "is" if p == resolved else "contains"
            raise UserError(
                f"{out}: {option} {what} {p}, which this run reads; replacing it would delete "
                f"the input, so choose an output outside it (with or without --force)"
            )
    for path in reserved:
        p = Path(path).resolve()
        if _contains(resolved, p) or _contains(p, resolved):
            raise UserError(f"{out}: {option} overlaps {p}, which stairfit keeps; choose another")
    for name, p in (("the current folder", Path.cwd()), ("your home folder", Path.home())):
        if _contains(resolved, p.resolve()):
            what = "is" if p.resolve() == resolved else "contains"
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
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, _FILE_MODE)
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

_PARTIAL = re.compile(r"^\.(?P<name>.+)\.[0-9a-f]{8}\.partial$")


def in_staging(path: Path) -> bool:
    """Whether `path` lies inside a staging folder (removed when its run fails)."""
    return any(_PARTIAL.match(p.name) for p in Path(path).parents)


def _own_leftover(name: str) -> re.Pattern[str]:
    """Names that runs writing output `name` create beside it (staging, old copy, temp file)."""
    n = re.escape(name)
    return re.compile(rf"^\.{n}\.(?:[0-9a-f]{{8}}\.partial|old-\d+|[A-Za-z0-9_]{{8}}\.tmp)$")


def _remove(path: Path) -> None:
    """Remove a file, a link or a folder tree (not following links)."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        with suppress(FileNotFoundError):
            path.unlink()


def _is_stale_partial(path: Path, now: float) -> bool:
    """Another output's staging folder, old, and no run holds that output's lock."""
    m = _PARTIAL.match(path.name)
    if m is None or not path.is_dir() or path.is_symlink():
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


def remove_stale_leftovers(out: Path) -> list[Path]:
    """Remove what earlier, killed runs left beside output `out`; call it holding its lock.

    Only entries of `out`'s parent folder whose names stairfit makes are considered: this
    output's `.NAME.XXXXXXXX.partial`, `.NAME.old-PID` and `.NAME.XXXXXXXX.tmp` (any age: the
    lock proves that no live run owns them), and other outputs' `.OTHER.XXXXXXXX.partial`
    folders older than `STALE_AGE_S` whose lock is free. Returns what was removed.
    """
    own = _own_leftover(out.name)
    now = time.time()
    removed = []
    try:
        entries = list(out.parent.iterdir())
    except OSError:
        return []
    for path in entries:
        try:
            stale = own.match(path.name) is not None or _is_stale_partial(path, now)
            if stale:
                _remove(path)
                removed.append(path)
        except OSError:  # not ours to clean after all (permissions): leave it
            continue
    return removed


# --- staged folders and files ---------------------------------------------------------------


def _fresh_partial_folder(out: Path) -> Path:
    """A new, empty hidden folder `.NAME.XXXXXXXX.partial` next to `out`.

    Made with `mkdir`, so it gets the user's umask like any folder they create (tempfile.mkdtemp
    would make it private, 0700, and the finished results would stay that way).
    """
    for _ in range(100):
        tmp = out.with_name(f".{out.name}.{secrets.token_hex(_TOKEN_HEX)}.partial")
        try:
            tmp.mkdir()
        except FileExistsError:
            continue
        return tmp
    raise FileExistsError(f"{out.parent}: cannot find a free name for a temporary folder")


def _replace(new: Path, out: Path) -> None:
    """Move `new` to `out`; an existing `out` (file, link or folder) is set aside, then removed."""
    if not (out.exists() or out.is_symlink()):
        new.rename(out)
        return
    trash = out.with_name(f".{out.name}.old-{os.getpid()}")
    _remove(trash)
    with deferred():  # no signal between the two renames
        out.rename(trash)
        try:
            new.rename(out)
        except BaseException:
            trash.rename(out)  # put the old result back
            raise
    _remove(trash)


def _real_target(e: OSError, tmp: Path, out: Path) -> OSError:
    """`e` with its file name mapped from the temporary `tmp` (or none) to the real `out`."""
    name = str(e.filename) if e.filename is not None else None
    if name is None:
        new = str(out)
    elif name == str(tmp) or name.startswith(str(tmp) + os.sep):
        new = str(out) + name[len(str(tmp)) :]
    else:
        return e
    return type(e)(e.errno, e.strerror or os.strerror(e.errno or errno.EIO), new)


def _refuse_special(shown: Path) -> None:
    """A device, pipe or socket (`-o /dev/null`) is never replaced by an output."""
    try:
        mode = os.stat(shown).st_mode
    except OSError:
        return
    if not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):
        raise UserError(
            f"{shown}: is a device, pipe or socket, not a file or folder stairfit can replace; "
            "give a file name (predict writes to stdout without -o)"
        )


def _refuse_existing(out: Path, shown: Path, force: bool) -> None:
    """An existing output is only replaced with `force`."""
    if (out.exists() or out.is_symlink()) and not force:
        raise UserError(
            f"{shown}: already exists; choose another output or add --force to replace it"
        )


@contextmanager
def staged_folder(
    out: Path,
    force: bool,
    *,
    inputs: Iterable[Path] = (),
    reserved: Iterable[Path] = (),
    option: str = "--output",
) -> Iterator[Path]:
    """Build a folder under a temporary name next to `out` and move it into place on success.

    The whole output-folder safety in one place: `check_output` (never an output that holds an
    input), the lock of `out`, the refusal of an existing `out` without `force`, the removal of
    stale leftovers, then the staging folder `.NAME.XXXXXXXX.partial` that is renamed to `out`
    when the block ends without an exception and removed otherwise (SIGINT and SIGTERM included,
    see `stairfit.cli`). A crash leaves no folder named `out`; an `OSError` names `out`.
    """
    shown = Path(out)
    out = check_output(shown, inputs, reserved, option)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise _real_target(e, out.parent, shown.parent) from None
    with output_lock(out):
        _refuse_existing(out, shown, force)
        remove_stale_leftovers(out)
        tmp = _fresh_partial_folder(out)
        try:
            yield tmp
            _replace(tmp, out)
        except OSError as e:
            shutil.rmtree(tmp, ignore_errors=True)
            raise _real_target(e, tmp, shown) from e
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise


@contextmanager
def staged_file(
    path: Path, force: bool, *, inputs: Iterable[Path] = (), option: str = "--output"
) -> Iterator[TextIO]:
    """A text file written under a temporary name and moved to `path` on success.

    As `staged_folder` for one file: refused when it is an input, a folder, or exists without
    `force`; locked; stale temporary files of earlier runs removed; the temporary file removed
    on any failure (SIGINT and SIGTERM included).
    """
    shown = Path(path)
    target = check_output(shown, inputs, (), option)
    if target.is_dir():
        raise UserError(f"{shown}: {option} is a folder; give a file name, e.g. {shown}/out.csv")
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise _real_target(e, target.parent, shown.parent) from None
    with output_lock(target):
        _refuse_existing(target, shown, force)
        remove_stale_leftovers(target)
        with atomic_text(target, shown=shown) as fh:
            yield fh


def _create_sibling(path: Path) -> tuple[int, Path]:
    """Create and open a new temporary file `.NAME.XXXXXXXX.tmp` beside `path` (umask applies)."""
    for _ in range(100):
        tmp = path.with_name(f".{path.name}.{secrets.token_hex(_TOKEN_HEX)}.tmp")
        try:
            return os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, _FILE_MODE), tmp
        except FileExistsError:
            continue
    raise FileExistsError(f"{path.parent}: cannot find a free name for a temporary file")


@contextmanager
def atomic_text(path: Path, *, shown: Path | None = None) -> Iterator[TextIO]:
    """Write a text file via a temporary sibling that is renamed into place only on success.

    The file gets the user's umask; an `OSError` names `shown` (default `path`), not the
    temporary file.
    """
    path = Path(path)
    shown = shown or path
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = _create_sibling(path)
    try:
        with os.fdopen(fd, "w", newline="", encoding="utf-8") as fh:
            yield fh
        os.replace(tmp, path)
    except OSError as e:
        tmp.unlink(missing_ok=True)
        raise _real_target(e, tmp, shown) from e
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def atomic_bytes(path: Path, data: bytes) -> Path:
    """Write `data` to `path` atomically (as `atomic_text`); returns `path`."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = _create_sibling(path)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        os.replace(tmp, path)
    except OSError as e:
        tmp.unlink(missing_ok=True)
        raise _real_target(e, tmp, path) from e
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path
