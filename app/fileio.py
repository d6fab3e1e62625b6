"""Reading and writing files safely: the one home of atomic writes and of result replacement.

Every package of stairfit writes through this module (the command line's `stairfit.outputs`,
`stairfit.imaging`'s caches and previews, `stairfit.fitting`'s chain, netCDF and exported
programs). It imports nothing but the standard library, so any package may use it.

* Reads: `read_bytes(path, max_bytes)` opens without blocking and reads a regular file only; a
  named pipe, a device (a link to /dev/zero), a folder or a loop of symbolic links is refused
  with `FileTypeError`, a file over `max_bytes` with `FileTooLargeError`, both `OSError`s
  whose message says what the path is (`describe(path)`).
* Writes: `atomic_bytes`, `atomic_text` and `atomic_path` write a temporary sibling
  `.NAME.XXXXXXXX.tmp` (mode 0666 less the umask, as any file the user makes) and rename it
  into place only when complete; an `OSError` names the real file (`named_error`), never the
  temporary one.
* Replacing a result folder (`replace_folder`, `recover`): a complete result is marked by the
  file `MARKER` inside it (`mark_complete`), written last. The replacement renames the old
  result to `.NAME.old-PID`, the new one into place, then deletes the old one, with signals
  held back in between; a process killed in between (SIGKILL, power loss) leaves both
  findable, and `recover` (called by the next run before anything else) moves the newer
  complete one back into place. No run deletes a complete result before its own is in place.
"""

from __future__ import annotations

import errno
import json
import os
import re
import secrets
import shutil
import signal
import stat
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import TextIO

FILE_MODE = 0o666
"""Mode of new files before the umask, as for any file the user creates (`tempfile.mkstemp`
would make it 0600, and the finished file would stay so)."""
MARKER = ".stairfit-output"
"""The file inside every output folder stairfit makes: which command made it, written last (a
folder holding it is complete), and the proof that `--force` may replace the folder."""
_TOKEN_HEX = 4  # bytes of randomness in temporary names: 8 hex digits
_TEXT = {"newline": "", "encoding": "utf-8", "errors": "surrogateescape"}
"""How text files are written: UTF-8, and a file or folder name that is not UTF-8 (its bytes
held as surrogates by Python) written back as the bytes it has on disk."""
_READ_CHUNK = 1 << 20


# --- what a path is ---------------------------------------------------------------------------


class FileTypeError(OSError):
    """A path that is not a regular file where one is read (a pipe, a device, a folder, a loop
    of links, a missing file); `strerror` says what it is."""


class FileTooLargeError(OSError):
    """A file larger than the reader allows (`read_bytes(..., max_bytes)`)."""


_KINDS = (
    (stat.S_ISDIR, "a folder"),
    (stat.S_ISFIFO, "a named pipe (FIFO)"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISSOCK, "a socket"),
)


def kind(mode: int) -> str:
    """What a file of this `st_mode` is, in words ("a regular file", "a named pipe (FIFO)")."""
    if stat.S_ISREG(mode):
        return "a regular file"
    return next((name for test, name in _KINDS if test(mode)), "not a regular file")


def describe(path: str | Path) -> str | None:
    """Why `path` is not a regular file one can read, in words ("is a named pipe (FIFO)", "is a
    loop of symbolic links", "is a link to /dev/zero, a character device"), or None."""
    path = Path(path)
    try:
        mode = os.stat(path).st_mode
    except OSError as e:
        if e.errno == errno.ELOOP:
            return "is a loop of symbolic links"
        if e.errno == errno.ENOENT and path.is_symlink():
            return f"is a link to {os.readlink(path)}, which does not exist"
        if e.errno == errno.ENOENT:
            return "does not exist"
        return f"cannot be read ({e.strerror or e})"
    if stat.S_ISREG(mode):
        return None
    if path.is_symlink():
        return f"is a link to {os.path.realpath(path)}, {kind(mode)}"
    return f"is {kind(mode)}"


def resolved(path: str | Path) -> Path:
    """The absolute path with every link resolved; a loop of links is left unresolved, not an
    exception (`Path.resolve` raises RuntimeError on one before Python 3.13)."""
    return Path(os.path.realpath(os.path.abspath(os.fspath(path))))


def open_regular(path: Path) -> int:
    """A read descriptor of `path` if it is a regular file, else `FileTypeError`.

    Opened without blocking (a named pipe with no writer would block `open` forever) and
    checked on the descriptor, so the file checked is the file read."""
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_NOCTTY", 0)
    try:
        fd = os.open(path, flags | getattr(os, "O_CLOEXEC", 0))
    except OSError as e:
        if e.errno == errno.ELOOP:
            raise FileTypeError(e.errno, "is a loop of symbolic links", str(path)) from None
        raise
    mode = os.fstat(fd).st_mode
    if not stat.S_ISREG(mode):
        os.close(fd)
        what = describe(path) or f"is {kind(mode)}"
        raise FileTypeError(errno.EINVAL, f"{what}, not a regular file", str(path))
    return fd


def check_size(fd: int, path: Path, max_bytes: int | None) -> int:
    """The size of the open file `fd`; `FileTooLargeError` when it exceeds `max_bytes`."""
    size = os.fstat(fd).st_size
    if max_bytes is not None and size > max_bytes:
        raise FileTooLargeError(
            errno.EFBIG,
            f"is {size / 2**30:.3g} GiB, more than the {max_bytes / 2**30:.3g} GiB allowed",
            str(path),
        )
    return size


def read_bytes(path: str | Path, max_bytes: int | None = None) -> bytes:
    """The bytes of a regular file; `FileTypeError` for anything else, `FileTooLargeError` for
    a file of more than `max_bytes` (checked before reading: a sparse file of terabytes is
    refused, not read)."""
    path = Path(path)
    fd = open_regular(path)
    with os.fdopen(fd, "rb") as fh:
        size = check_size(fd, path, max_bytes)
        limit = size + 1 if max_bytes is None else min(size, max_bytes) + 1
        data = fh.read(limit)  # a file that grows while read is cut, then refused below
    if max_bytes is not None and len(data) > max_bytes:
        raise FileTooLargeError(errno.EFBIG, "grew while it was read", str(path))
    return data


def read_text(path: str | Path, max_bytes: int | None = None) -> str:
    """`read_bytes` decoded as UTF-8 (`UnicodeDecodeError` when it is not)."""
    return read_bytes(path, max_bytes).decode("utf-8")


# --- atomic writes ----------------------------------------------------------------------------


def _create_sibling(path: Path) -> tuple[int, Path]:
    """Create and open a new temporary file `.NAME.XXXXXXXX.tmp` beside `path` (umask applies)."""
    for _ in range(100):
        tmp = path.with_name(f".{path.name}.{secrets.token_hex(_TOKEN_HEX)}.tmp")
        try:
            return os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, FILE_MODE), tmp
        except FileExistsError:
            continue
    raise FileExistsError(f"{path.parent}: cannot find a free name for a temporary file")


def named_error(e: OSError, tmp: Path, shown: Path) -> OSError:
    """`e` naming `shown` where it named the temporary `tmp` (or a file inside it) or nothing."""
    name = None if e.filename is None else os.fsdecode(e.filename)
    if name is None:
        new = str(shown)
    elif name == str(tmp) or name.startswith(str(tmp) + os.sep):
        new = str(shown) + name[len(str(tmp)) :]
    else:
        return e
    code = e.errno or errno.EIO
    return type(e)(code, e.strerror or os.strerror(code), new)


def _make_parent(path: Path, shown: Path) -> None:
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise NotADirectoryError(
            errno.ENOTDIR, "is a file, not a folder", str(file_in_the_way(shown.parent))
        ) from None
    except OSError as e:
        raise named_error(e, path.parent, shown.parent) from None


def file_in_the_way(folder: Path) -> Path:
    """The first of `folder` and its ancestors, from the root, that exists and is not a folder
    (what makes `-o afile/out` impossible); `folder` itself when there is none."""
    for p in (*reversed(folder.parents), folder):
        if p.exists() and not p.is_dir():
            return p
    return folder


@contextmanager
def atomic_path(path: str | Path, *, shown: str | Path | None = None) -> Iterator[Path]:
    """A temporary file beside `path` for a writer that needs a name; renamed to `path` when
    the block ends without an exception, removed otherwise. An `OSError` names `shown`
    (default `path`)."""
    path = Path(path)
    shown = Path(shown) if shown is not None else path
    _make_parent(path, shown)
    fd, tmp = _create_sibling(path)
    os.close(fd)
    try:
        yield tmp
        os.replace(tmp, path)
    except OSError as e:
        tmp.unlink(missing_ok=True)
        raise named_error(e, tmp, shown) from e
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


@contextmanager
def atomic_text(path: str | Path, *, shown: str | Path | None = None) -> Iterator[TextIO]:
    """A text file (UTF-8, `_TEXT`) written via a temporary sibling, renamed into place on
    success."""
    with atomic_path(path, shown=shown) as tmp, open(tmp, "w", **_TEXT) as fh:
        yield fh


def atomic_bytes(path: str | Path, data: bytes, *, shown: str | Path | None = None) -> Path:
    """Write `data` to `path` so that readers see the old file or the new one, never a part."""
    with atomic_path(path, shown=shown) as tmp, open(tmp, "wb") as fh:
        fh.write(data)
    return Path(path)


def create_text(path: str | Path, text: str) -> Path:
    """Write `text` (UTF-8, `_TEXT`) to `path`, which must not exist: a finished temporary
    sibling is hard-linked to `path`, which fails with `FileExistsError` if the name appeared
    meanwhile (never over a file the user made), and the temporary is removed either way."""
    path = Path(path)
    fd, tmp = _create_sibling(path)
    try:
        with os.fdopen(fd, "w", **_TEXT) as fh:
            fh.write(text)
        os.link(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


@contextmanager
def writing(path: str | Path) -> Iterator[TextIO]:
    """A text file (UTF-8) opened for writing where no temporary is needed (inside a staging
    folder); an `OSError` (a full disk) names the file."""
    path = Path(path)
    try:
        with open(path, "w", **_TEXT) as fh:
            yield fh
    except OSError as e:
        raise named_error(e, path, path) from e


def write_file(path: str | Path, data: str | bytes) -> Path:
    """Write a whole file inside a staging folder (as `writing`; bytes or UTF-8 text)."""
    path = Path(path)
    if isinstance(data, str):
        with writing(path) as fh:
            fh.write(data)
        return path
    try:
        with open(path, "wb") as fh:
            fh.write(data)
    except OSError as e:
        raise named_error(e, path, path) from e
    return path


def temporary_sibling(path: str | Path) -> Path:
    """A fresh, empty temporary file next to `path` (for writers that need a name; the caller
    renames or removes it)."""
    path = Path(path)
    _make_parent(path, path)
    fd, tmp = _create_sibling(path)
    os.close(fd)
    return tmp


# --- replacing a result folder ----------------------------------------------------------------


@contextmanager
def deferred() -> Iterator[None]:
    """Within the block, SIGINT, SIGTERM and SIGHUP wait until it ends (POSIX; else no-op)."""
    if not hasattr(signal, "pthread_sigmask"):  # pragma: no cover - Windows
        yield
        return
    held = {getattr(signal, n) for n in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, n)}
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, held)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


def partial_pattern(name: str | None = None) -> re.Pattern[str]:
    """Staging folders `.NAME.XXXXXXXX.partial` (of output `name`, or of any output)."""
    n = re.escape(name) if name is not None else "(?P<name>.+)"
    return re.compile(rf"^\.{n}\.[0-9a-f]{{8}}\.partial$")


def backup_pattern(name: str) -> re.Pattern[str]:
    """Old results set aside during a replacement: `.NAME.old-PID`."""
    return re.compile(rf"^\.{re.escape(name)}\.old-\d+$")


def tmp_pattern(name: str) -> re.Pattern[str]:
    """Temporary files of atomic writes: `.NAME.XXXXXXXX.tmp`."""
    return re.compile(rf"^\.{re.escape(name)}\.[A-Za-z0-9_]{{8}}\.tmp$")


def fresh_staging_folder(out: Path) -> Path:
    """A new, empty hidden folder `.NAME.XXXXXXXX.partial` next to `out` (made with `mkdir`,
    so it gets the user's umask; `tempfile.mkdtemp` would make it 0700)."""
    for _ in range(100):
        tmp = out.with_name(f".{out.name}.{secrets.token_hex(_TOKEN_HEX)}.partial")
        try:
            tmp.mkdir()
        except FileExistsError:
            continue
        return tmp
    raise FileExistsError(f"{out.parent}: cannot find a free name for a temporary folder")


def mark_complete(folder: Path, command: str, version: str) -> None:
    """Write `MARKER` into `folder`: made by `stairfit COMMAND`, complete (written last)."""
    record = {"made_by": "stairfit", "command": command, "version": version}
    atomic_bytes(folder / MARKER, (json.dumps(record) + "\n").encode())


def made_by(folder: Path) -> str | None:
    """The command whose complete result `folder` is (its `MARKER`), or None when it has none
    (or `folder` is a link, or not a folder)."""
    if folder.is_symlink() or not folder.is_dir():
        return None
    try:
        record = json.loads(read_bytes(folder / MARKER, max_bytes=1 << 16))
    except (OSError, ValueError):
        return None
    if not isinstance(record, dict) or record.get("made_by") != "stairfit":
        return None
    command = record.get("command")
    return command if isinstance(command, str) else None


def remove_tree(path: Path) -> None:
    """Remove a file, a link or a folder tree (never following links)."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        with suppress(FileNotFoundError):
            path.unlink()


def replace_folder(new: Path, out: Path) -> None:
    """Move the complete folder `new` to `out`; an existing `out` is set aside as
    `.NAME.old-PID` first and removed only once `new` is in place (module docstring)."""
    if not (out.exists() or out.is_symlink()):
        new.rename(out)
        return
    backup = out.with_name(f".{out.name}.old-{os.getpid()}")
    remove_tree(backup)
    with deferred():  # no signal between the two renames
        out.rename(backup)
        try:
            new.rename(out)
        except BaseException:
            backup.rename(out)  # put the old result back
            raise
    remove_tree(backup)


def _siblings(out: Path, pattern: re.Pattern[str]) -> list[Path]:
    try:
        entries = list(out.parent.iterdir())
    except OSError:
        return []
    return [p for p in entries if pattern.match(p.name)]


def _newest_first(paths: list[Path]) -> list[Path]:
    def mtime(p: Path) -> float:
        try:
            return p.lstat().st_mtime
        except OSError:
            return 0.0

    return sorted(paths, key=mtime, reverse=True)


def complete_partials(out: Path) -> list[Path]:
    """Staging folders of `out` that hold a complete result (their `MARKER`), newest first."""
    found = [p for p in _siblings(out, partial_pattern(out.name)) if made_by(p) is not None]
    return _newest_first(found)


def recover(out: Path) -> Path | None:
    """Where `out` is missing, move back the result a killed replacement left beside it: a
    complete staging folder (the newer result) before an old copy `.NAME.old-PID`. Returns
    the folder moved to `out`, or None. Call it holding `out`'s lock."""
    if out.exists() or out.is_symlink():
        return None
    backups = _newest_first(_siblings(out, backup_pattern(out.name)))
    for candidate in (*complete_partials(out), *backups):
        try:
            candidate.rename(out)
        except OSError:
            continue
        return candidate
    return None


def leftovers(out: Path, *, complete_too: bool = False) -> list[Path]:
    """What killed runs left beside `out` that is safe to delete now (`out` is in place, or
    nothing complete is lost): temporary files, incomplete staging folders, old copies of a
    result that `out` (a stairfit result) has replaced, and with `complete_too` (once this
    run's own result is in place) complete staging folders too."""
    found = _siblings(out, tmp_pattern(out.name))
    for p in _siblings(out, partial_pattern(out.name)):
        if complete_too or made_by(p) is None:
            found.append(p)
    if made_by(out) is not None:
        found += _siblings(out, backup_pattern(out.name))
    return found
