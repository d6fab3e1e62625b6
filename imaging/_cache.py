"""The measurement cache on disk: the table, a checksum written with it, and best-effort writes.

A cache is `NAME.csv` (the `MeasurementTable`) and `NAME.checksum.json` beside it:
`{"table_version": TABLE_VERSION, "sha256": ...}`, the SHA-256 of the version line and the
table's bytes. `read_cache` trusts the table only when the checksum matches: an edited, damaged,
half-written or older cache is ignored with one `ImagingWarning` saying so, and every photo is
measured again. Each row carries the SHA-256 of its photo and its `settings_key` (ROIs, marker
layout, exposure overrides, extraction settings, `TABLE_VERSION`), which tie it to the photo's
bytes and to what the scene says about measuring it; `measure_photos` checks both. A cache that
cannot be read or written (a folder in its place, a read-only photo folder) never stops a run:
it is skipped with a warning. docs/imaging.md §The cache.
"""

from __future__ import annotations

import hashlib
import json
import warnings
from pathlib import Path

from stairfit.fileio import atomic_bytes

from ._errors import ImagingError, ImagingWarning
from ._table import MeasurementTable


def checksum_path(cache: Path) -> Path:
    """The checksum file of a cache: `measurements.csv` -> `measurements.checksum.json`."""
    return cache.with_name(f"{cache.stem}.checksum.json")


def table_digest(csv_bytes: bytes, table_version: int) -> str:
    """SHA-256 (hex) of the table version and the table's CSV bytes."""
    h = hashlib.sha256(f"stairfit measurement table v{table_version}\n".encode())
    h.update(csv_bytes)
    return h.hexdigest()


def _warn(message: str) -> None:
    warnings.warn(message, ImagingWarning, stacklevel=3)


def _read_checksum(cache: Path) -> dict | None:
    try:
        data = json.loads(checksum_path(cache).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def read_cache(cache: Path | None, table_version: int) -> MeasurementTable | None:
    """The cached table if present and verified, else None (with a one-line warning why).

    No warning when there is simply no cache yet.
    """
    if cache is None or not (cache.exists() or cache.is_symlink()):
        return None
    again = "measuring every photo again"
    try:
        blob = cache.read_bytes()
    except OSError as e:
        _warn(f"measurement cache {cache}: cannot read it ({e.strerror or e}); {again}")
        return None
    check = _read_checksum(cache)
    if check is None or "sha256" not in check:
        _warn(
            f"measurement cache {cache}: no checksum beside it (written by an older stairfit, "
            f"or damaged); {again}"
        )
        return None
    if check.get("table_version") != table_version:
        _warn(
            f"measurement cache {cache}: written for measurement table version "
            f"{check.get('table_version')}, this stairfit writes version {table_version}; {again}"
        )
        return None
    if check["sha256"] != table_digest(blob, table_version):
        _warn(
            f"measurement cache {cache}: does not match its checksum (edited or damaged); " + again
        )
        return None
    try:
        return MeasurementTable.read_csv(cache)
    except ImagingError as e:
        _warn(f"{e}; {again}")
        return None


def write_cache(cache: Path, table: MeasurementTable, table_version: int) -> bool:
    """Write the table and its checksum; on a system error warn and return False.

    The table is written first, then its checksum: a run killed in between leaves a cache that
    fails its check, never one that passes it with the wrong content.
    """
    blob = table.to_csv().encode()
    check = {"table_version": table_version, "sha256": table_digest(blob, table_version)}
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
    """Delete the cached previews in `folder` not named in `keep` (best effort)."""
    if not folder.is_dir():
        return
    for path in folder.glob("*.png"):
        if path.name not in keep:
            try:
                path.unlink(missing_ok=True)
            except OSError:
                return  # a read-only cache: stale previews are never read, only kept
