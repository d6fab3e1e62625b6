"""Atomic file writes: a temporary file in the same folder, then `os.replace`.

The temporary file `.NAME.XXXXXXXX.tmp` is created with mode 0666 less the umask, like any file
the user creates (`tempfile.mkstemp` would make it 0600, and the finished file would stay so),
and an `OSError` names the real target, not the hidden temporary file. (`stairfit.imaging`
depends on no other stairfit package, so this mirrors `stairfit.outputs.atomic_bytes`.)
"""

from __future__ import annotations

import os
import secrets
from pathlib import Path

_FILE_MODE = 0o666


def _create_sibling(path: Path) -> tuple[int, Path]:
    """Create and open a new temporary file beside `path` (the umask applies)."""
    for _ in range(100):
        tmp = path.with_name(f".{path.name}.{secrets.token_hex(4)}.tmp")
        try:
            return os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, _FILE_MODE), tmp
        except FileExistsError:
            continue
    raise FileExistsError(f"{path.parent}: cannot find a free name for a temporary file")


def _naming(e: OSError, tmp: Path, path: Path) -> OSError:
    """`e` naming `path` where it named the temporary file `tmp` (or nothing)."""
    if e.filename is not None and str(e.filename) != str(tmp):
        return e
    return OSError(e.errno, e.strerror or str(e), str(path))


def atomic_write_bytes(path: str | Path, data: bytes) -> Path:
    """Write `data` to `path` so that readers see the old file or the new one, never a part."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = _create_sibling(path)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except OSError as e:
        tmp.unlink(missing_ok=True)
        raise _naming(e, tmp, path) from e
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def temporary_sibling(path: str | Path) -> Path:
    """A fresh, empty temporary file next to `path` (for writers that need a name)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = _create_sibling(path)
    os.close(fd)
    return tmp
