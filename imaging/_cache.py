"""The measurement cache on disk: the table, a checksum written with it, and best-effort writes.

A cache is `NAME.csv` (the `MeasurementTable`) and `NAME.checksum.json` beside it:
`{"table_version": TABLE_VERSION, "scheme": ..., "digest": ..., "previews": {file: SHA-256}}`.
The digest covers the version, the table's bytes and the list of cached previews with their
SHA-256. With a `secret` (the command line passes a key kept in the user's own cache folder) it
is an HMAC-SHA256, so an edited table whose checksum was recomputed, or a preview swapped for
another, does not pass: only a process holding the key writes a cache it will trust. Without a
secret it is a plain SHA-256, which catches damage but not deliberate edits.

`read_cache` trusts the table only when the digest matches: an edited, damaged, half-written,
older or foreign cache is ignored with one `ImagingWarning` saying so, and every photo is
measured again. Each row carries the SHA-256 of its photo and its `settings_key` (ROIs, marker
layout, exposure overrides, extraction settings, `TABLE_VERSION`), which tie it to the photo's
bytes and to what the scene says about measuring it; `measure_photos` checks both. A cached
preview is used only when its bytes have the SHA-256 the verified checksum lists. A cache that
cannot be read or written (a folder or a named pipe in its place, a read-only photo folder)
never stops a run: it is skipped with a warning. docs/imaging.md §The cache.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import warnings
from collections.abc import Iterable
from pathlib import Path

from stairfit.fileio import atomic_bytes, read_bytes

from ._errors import ImagingError, ImagingWarning
from ._table import MeasurementTable

MAX_CACHE_BYTES = 1 << 30
"""The largest cache file read (a table of a million rows is about 500 MB)."""
MAX_PREVIEW_BYTES = 64 << 20
"""The largest cached preview read."""


def checksum_path(cache: Path) -> Path:
    """The checksum file of a cache: `measurements.csv` -> `measurements.checksum.json`."""
    return cache.with_name(f"{cache.stem}.checksum.json")


def _scheme(secret: bytes | None) -> str:
    return "sha256" if secret is None else "hmac-sha256"


def table_digest(
    csv_bytes: bytes,
    table_version: int,
    secret: bytes | None = None,
    previews: dict[str, str] | None = None,
) -> str:
    """The digest (hex) of the table version, the table's CSV bytes and the cached previews'
    names and SHA-256: HMAC-SHA256 keyed by `secret`, or SHA-256 without one."""
    h = hashlib.sha256() if secret is None else hmac.new(secret, digestmod=hashlib.sha256)
    h.update(f"stairfit measurement table v{table_version}\n".encode())
    h.update(csv_bytes)
    if previews:
        h.update(b"\0previews\0" + json.dumps(previews, sort_keys=True).encode())
    return h.hexdigest()


def _warn(message: str) -> None:
    warnings.warn(message, ImagingWarning, stacklevel=3)


def _read_checksum(cache: Path) -> dict | None:
    try:
        data = json.loads(read_bytes(checksum_path(cache), max_bytes=MAX_CACHE_BYTES))
    except (OSError, ValueError, RecursionError):
        return None
    return data if isinstance(data, dict) else None


class VerifiedCache:
    """A cache that passed its check: the table and the SHA-256 of each cached preview."""

    def __init__(self, table: MeasurementTable, previews: dict[str, str]) -> None:
        self.table = table
        self.previews = previews

    def preview(self, folder: Path, name: str) -> bytes | None:
        """The cached preview `name` in `folder` if its bytes are those the checksum lists."""
        expected = self.previews.get(name)
        if expected is None:
            return None
        try:
            png = read_bytes(folder / name, max_bytes=MAX_PREVIEW_BYTES)
        except OSError:
            return None
        return png if hashlib.sha256(png).hexdigest() == expected else None


def _check_problem(
    blob: bytes, check: dict | None, table_version: int, secret: bytes | None
) -> str | None:
    """Why the checksum does not vouch for the table `blob`, or None."""
    if check is None:
        return "no checksum beside it (written by an older stairfit, or damaged)"
    if check.get("table_version") != table_version:
        return (
            f"written for measurement table version {check.get('table_version')}, this "
            f"stairfit writes version {table_version}"
        )
    if "digest" not in check:
        return "its checksum is of an older stairfit"
    previews = check.get("previews", {})
    if not isinstance(previews, dict) or not all(
        isinstance(k, str) and isinstance(v, str) for k, v in previews.items()
    ):
        return "its checksum file is damaged"
    if check.get("scheme") != _scheme(secret):
        return "written without this user's cache key (by another user, machine or program)"
    expected = table_digest(blob, table_version, secret, previews)
    if not hmac.compare_digest(str(check["digest"]), expected):
        return "does not match its checksum (edited, damaged, or written with another key)"
    return None


def read_cache(
    cache: Path | None, table_version: int, secret: bytes | None = None
) -> VerifiedCache | None:
    """The cached table and previews if present and verified, else None (with a one-line
    warning why). No warning when there is simply no cache yet."""
    if cache is None or not (cache.exists() or cache.is_symlink()):
        return None
    again = "measuring every photo again"
    try:
        blob = read_bytes(cache, max_bytes=MAX_CACHE_BYTES)
    except OSError as e:
        _warn(f"measurement cache {cache}: cannot read it ({e.strerror or e}); {again}")
        return None
    check = _read_checksum(cache)
    problem = _check_problem(blob, check, table_version, secret)
    if problem is not None:
        _warn(f"measurement cache {cache}: {problem}; {again}")
        return None
    try:
        table = MeasurementTable.from_csv_text(blob.decode("utf-8"), cache)
    except (ImagingError, UnicodeDecodeError) as e:
        _warn(f"{e}; {again}")
        return None
    return VerifiedCache(table, dict(check["previews"]))  # type: ignore[index]


def preview_digests(folder: Path, names: Iterable[str]) -> dict[str, str]:
    """SHA-256 of each cached preview in `folder` that can be read (for the checksum)."""
    out = {}
    for name in sorted(set(names)):
        try:
            out[name] = hashlib.sha256(read_bytes(folder / name, MAX_PREVIEW_BYTES)).hexdigest()
        except OSError:
            continue
    return out


def write_cache(
    cache: Path,
    table: MeasurementTable,
    table_version: int,
    secret: bytes | None = None,
    previews: dict[str, str] | None = None,
) -> bool:
    """Write the table and its checksum (covering `previews`: name -> SHA-256); on a system
    error warn and return False.

    The table is written first, then its checksum: a run killed in between leaves a cache that
    fails its check, never one that passes it with the wrong content.
    """
    blob = table.to_csv().encode()
    previews = dict(previews or {})
    check = {
        "table_version": table_version,
        "scheme": _scheme(secret),
        "digest": table_digest(blob, table_version, secret, previews),
        "previews": previews,
    }
    try:
        checksum_path(cache).unlink(missing_ok=True)
        atomic_bytes(cache, blob)
        atomic_bytes(checksum_path(cache), json.dumps(check, indent=1).encode())
    except OSError as e:
        _warn(
            f"measurement cache {cache}: cannot write it ({e.strerror or e}); the results are "
            "not affected, but the next run decodes every photo again"
        )
        return False
    return True


def prune_previews(folder: Path, keep: set[str]) -> None:
    """Delete the cached previews in `folder` not named in `keep`, and temporary files that
    killed runs left there (best effort)."""
    if not folder.is_dir():
        return
    for path in [*folder.glob("*.png"), *folder.glob(".*.tmp")]:
        if path.name not in keep:
            try:
                path.unlink(missing_ok=True)
            except OSError:
                return  # a read-only cache: stale previews are never read, only kept
