"""Traced programs kept on disk (issue 14: a warm fit re-traced its solver every run).

JAX's persistent compilation cache keeps compiled XLA programs, but every new process still
traces and lowers each jitted function before it can look one up: for the least-squares solver
(optimistix around the whole model) that was seconds of every warm `stairfit fit`. `jax.export`
serialises a traced and lowered program (StableHLO); a later process deserialises it and calls
it without tracing the Python again.

`call(name, fn, static_key, args, unflatten)` does that for one program: where JAX's persistent
compilation cache is configured (`jax.config.jax_compilation_cache_dir`, which the CLI sets,
app/_jaxcache.py) the exported program is kept in its subfolder `EXPORT_SUBDIR`, keyed by

* the program's name and `static_key` (the caller's deterministic description of everything
  static: layout, flags, solver, step limit);
* the arguments' tree structure, shapes and dtypes;
* `code_fingerprint()`: the source of the stairfit package and the versions of jax, jaxlib,
  optimistix, equinox and lineax, so an edited or upgraded checkout never reuses a stale
  program;

and written atomically, with its key and its SHA-256 in the file: a file copied or swapped
under another program's name, damaged or foreign is not used (and neither is one whose program
takes other arguments), only traced again. Where no cache folder is configured (library use,
the tests), or with `STAIRFIT_EXPORTED=off`, `fn` is called as it is. A program that cannot
be exported or a file that cannot be read falls back to `fn`; the result is the same either
way (tested).
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import os
import re
from collections.abc import Callable, Sequence
from importlib import metadata
from pathlib import Path
from typing import Any

import jax
import numpy as np

from stairfit.fileio import atomic_bytes, read_bytes

EXPORT_SUBDIR = "stairfit-exported"
"""Subfolder of JAX's persistent compilation cache that holds the exported programs."""

_PACKAGE_ROOT = Path(__file__).resolve().parents[1]
_SOURCE_DIRS = ("model", "fitting")
_VERSIONED = ("jax", "jaxlib", "optimistix", "equinox", "lineax")


@functools.cache
def code_fingerprint() -> str:
    """Hash of the source that traced programs are made of (`model/`, `fitting/` and their
    package data) and of the versions of the libraries that trace them."""
    h = hashlib.sha256()
    for sub in _SOURCE_DIRS:
        for path in sorted((_PACKAGE_ROOT / sub).rglob("*")):
            if path.is_file() and path.suffix in (".py", ".json"):
                h.update(str(path.relative_to(_PACKAGE_ROOT)).encode())
                h.update(path.read_bytes())
    for name in _VERSIONED:
        try:
            h.update(f"{name}={metadata.version(name)}".encode())
        except metadata.PackageNotFoundError:
            h.update(f"{name}=absent".encode())
    h.update(f"x64={jax.config.jax_enable_x64}".encode())
    return h.hexdigest()


OFF_VAR = "STAIRFIT_EXPORTED"
"""Environment variable: `off` keeps no exported programs (every process traces again)."""


def export_folder() -> Path | None:
    """Where exported programs are kept: beside JAX's persistent compilation cache; None
    without one, or with `STAIRFIT_EXPORTED=off`."""
    if os.environ.get(OFF_VAR, "").strip().lower() in ("off", "0", "no", "false"):
        return None
    base = jax.config.jax_compilation_cache_dir
    return Path(base) / EXPORT_SUBDIR if base else None


def _spec(leaf: Any) -> jax.ShapeDtypeStruct:
    a = np.asarray(leaf) if not hasattr(leaf, "dtype") else leaf
    return jax.ShapeDtypeStruct(np.shape(a), a.dtype)


def program_key(name: str, static_key: str, treedef: Any, leaves: Sequence[Any]) -> str:
    """The file name of a program (module doc)."""
    h = hashlib.sha256()
    for part in (name, static_key, str(treedef), code_fingerprint()):
        h.update(part.encode())
        h.update(b"\0")
    for leaf in leaves:
        s = _spec(leaf)
        h.update(f"{s.shape}:{s.dtype};".encode())
    return f"{re.sub(r'[^A-Za-z0-9_]', '_', name)}-{h.hexdigest()[:32]}"


def _shape_dtype(leaf: Any) -> tuple[tuple[int, ...], np.dtype]:
    s = _spec(leaf)
    return tuple(s.shape), np.dtype(s.dtype)


@functools.lru_cache(maxsize=64)
def _program_path(
    folder: Path, name: str, static_key: str, treedef: Any, shapes: tuple[Any, ...]
) -> Path:
    """The file of a program (`program_key`), remembered: the posterior calls its program
    hundreds of times, and hashing the tree's description on every call would add up to a
    visible part of a warm fit."""
    specs = [jax.ShapeDtypeStruct(shape, dtype) for shape, dtype in shapes]
    return folder / f"{program_key(name, static_key, treedef, specs)}.bin"


_PROGRAMS: dict[Path, Callable[..., Any]] = {}
"""The programs this process has loaded or exported, by file, as jitted callers (a memo: the
posterior calls its program hundreds of times)."""


def _named(fn: Callable[..., Any], name: str) -> Callable[..., Any]:
    """`fn` under the name `name` (what JAX's compilation log and the CLI's compile line show)."""

    def named(*args: Any) -> Any:
        return fn(*args)

    named.__name__ = named.__qualname__ = name
    return named


def _caller(exported: jax.export.Exported, name: str) -> Callable[..., Any]:
    return jax.jit(_named(exported.call, name))


_MAGIC = b"stairfit exported program 1\n"
MAX_PROGRAM_BYTES = 1 << 30
"""The largest program file read."""


def _pack(key: str, payload: bytes) -> bytes:
    """A program file: `_MAGIC`, the program's key, the payload's SHA-256, the payload."""
    digest = hashlib.sha256(payload).hexdigest()
    return _MAGIC + f"{key}\n{digest}\n".encode() + payload


def _unpack(blob: bytes, key: str) -> bytes | None:
    """The payload of a program file written for `key`, or None: a file written for another
    key (swapped or copied under another name), damaged or foreign."""
    if not blob.startswith(_MAGIC):
        return None
    header, _, payload = blob[len(_MAGIC) :].partition(b"\n")
    digest, _, payload = payload.partition(b"\n")
    if header.decode(errors="replace") != key:
        return None
    intact = hashlib.sha256(payload).hexdigest() == digest.decode("ascii", "replace")
    return payload if intact else None


def _fits(exported: jax.export.Exported, name: str, shapes: tuple[Any, ...]) -> bool:
    """Whether a deserialised program is `name` and takes arguments of `shapes`."""
    avals = [(tuple(a.shape), np.dtype(a.dtype)) for a in exported.in_avals]
    return exported.fun_name == name and avals == [(tuple(s), np.dtype(d)) for s, d in shapes]


def _load(path: Path, name: str, shapes: tuple[Any, ...] = ()) -> Callable[..., Any] | None:
    """The caller of the exported program in `path` (None if absent, unreadable, damaged, or
    written for another program: a missed saving, never an error or a wrong result)."""
    if path in _PROGRAMS:
        return _PROGRAMS[path]
    try:
        payload = _unpack(read_bytes(path, MAX_PROGRAM_BYTES), path.stem)
        exported = None if payload is None else jax.export.deserialize(bytearray(payload))
    except Exception:  # a missing, damaged or foreign file is a missed saving, not an error
        return None
    if exported is None or (shapes and not _fits(exported, name, shapes)):
        return None
    _PROGRAMS[path] = caller = _caller(exported, name)
    return caller


_CUSTOM_CALL = re.compile(r"stablehlo\.custom_call @([A-Za-z0-9_.]+)")
_LAPACK = tuple(
    f"lapack_{t}{op}_ffi"
    for t in "sdcz"
    for op in ("geqrf", "orgqr", "ungqr", "ormqr", "unmqr", "potrf", "trsm", "getrf", "syevd",
               "heevd", "gesdd", "gesvd", "geqp3")
)  # fmt: skip
"""The CPU LAPACK custom calls linear solves and decompositions lower to (JAX does not promise
their stability across versions; `code_fingerprint` holds the jaxlib version)."""


def _export(flat: Callable[..., Any], specs: list[jax.ShapeDtypeStruct]) -> jax.export.Exported:
    """Trace and lower `flat` once, allowing the LAPACK custom calls; a program with another
    custom call is lowered once more to find them (the file is only read back by this
    installation: `code_fingerprint` holds the jaxlib version)."""
    jitted = jax.jit(flat)
    checks = [jax.export.DisabledSafetyCheck.custom_call(t) for t in _LAPACK]
    try:
        return jax.export.export(jitted, disabled_checks=checks)(*specs)
    except ValueError:
        text = jitted.trace(*specs).lower().as_text()
    targets = sorted(set(_CUSTOM_CALL.findall(text)))
    checks = [jax.export.DisabledSafetyCheck.custom_call(t) for t in targets]
    return jax.export.export(jitted, disabled_checks=checks)(*specs)


def _save(exported: jax.export.Exported, path: Path) -> None:
    """Write atomically (`stairfit.fileio.atomic_bytes`) under the program's key (`_pack`); a
    file that cannot be written is only a missed saving."""
    with contextlib.suppress(OSError):
        atomic_bytes(path, _pack(path.stem, bytes(exported.serialize())))


def call(
    name: str,
    fn: Callable[..., Any],
    static_key: str,
    args: tuple[Any, ...],
    unflatten: Callable[[list[Any]], Any],
) -> Any:
    """`fn(*args)`, through an exported program kept on disk where a cache folder is set.

    `fn` takes the dynamic arguments only (static configuration closed over and described by
    `static_key`); `unflatten` rebuilds its output from the flat list of output arrays (the
    order of `jax.tree.leaves(fn(*args))`)."""
    folder = export_folder()
    if folder is None:
        return fn(*args)
    leaves, treedef = jax.tree.flatten(args)
    shapes = tuple(map(_shape_dtype, leaves))
    path = _program_path(folder, name, static_key, treedef, shapes)
    caller = _load(path, name, shapes)
    if caller is None:

        def flat(*lv: Any) -> tuple[Any, ...]:
            return tuple(jax.tree.leaves(fn(*jax.tree.unflatten(treedef, lv))))

        try:
            exported = _export(_named(flat, name), [_spec(leaf) for leaf in leaves])
        except (ValueError, TypeError, ImportError):  # not exportable: trace as usual
            return fn(*args)
        _save(exported, path)
        _PROGRAMS[path] = caller = _caller(exported, name)
    return unflatten(list(caller(*leaves)))
