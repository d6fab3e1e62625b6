"""JAX set-up of the command line: float64, the persistent compilation cache (issue 7:
compilation is part of the user's wait), XLA:CPU's faster-compiling fusion emitters (issue 14)
and, under `--quiet`, no XLA log banners (issue 12).

A fit compiles its least-squares and posterior functions once per model variant (shapes are
kept static across photos and wedges, so one scene compiles once); the persistent cache keeps
those compilations on disk so that the next `stairfit fit` or `demo` on this machine skips
them. Location: `$STAIRFIT_JAX_CACHE` if set (`off` disables the cache), otherwise
`$XDG_CACHE_HOME/stairfit/jax` (default `~/.cache/stairfit/jax`; none when HOME is empty or
"/"). Only the CLI enables it; library users choose for themselves
(`jax.config.update("jax_compilation_cache_dir", ...)`).
"""

from __future__ import annotations

import os
import re
import sys
from collections.abc import Mapping, MutableMapping
from importlib import metadata
from pathlib import Path

ENV_VAR = "STAIRFIT_JAX_CACHE"
XLA_LOG_LEVEL_VAR = "TF_CPP_MIN_LOG_LEVEL"
XLA_QUIET_LEVEL = "3"
"""XLA's C++ logging keeps only FATAL messages at level 3. Its "slow compile" banners
("Constant folding an instruction is taking > 1s", "Very slow compile?") are ERROR lines, so
level 2 would still print them; real failures still reach Python as exceptions."""
MIN_COMPILE_TIME_S = 0.0
"""Compilations faster than this are not written to disk (JAX's default is 1 s). Every one is
kept: otherwise a warm `stairfit fit` recompiles dozens of small programs, each of which is
read back from disk several times faster than it compiles."""


XLA_FLAGS_VAR = "XLA_FLAGS"
FAST_COMPILE_OPTION = "xla_cpu_use_fusion_emitters"
FAST_COMPILE_FLAG = f"--{FAST_COMPILE_OPTION}=false"
"""XLA:CPU compiles fusions with its earlier (LLVM IR) emitters instead of the MLIR ones: a third
less compilation for stairfit's programs at the same run time (docs/fitting.md §7;
benchmarks/results/cold.md); results equal to about 1e-13 relative,
the differences of a different order of floating-point operations."""
FAST_COMPILE_JAXLIB = ((0, 6), (0, 10))
"""The jaxlib releases (major, minor), first and last, whose XLA knows the option: it appeared
in 0.6 (0.5.0 lacks it), and 0.10 is the newest release checked. XLA stops the process on an option
it does not know, so a release outside this range compiles with its defaults (widen the range
once a newer release is checked: tests/app/test_jaxcache.py)."""


def jaxlib_release() -> tuple[int, int] | None:
    """(major, minor) of the installed jaxlib, from its metadata (jaxlib is not imported);
    None if it cannot be read."""
    try:
        found = re.match(r"(\d+)\.(\d+)", metadata.version("jaxlib"))
    except metadata.PackageNotFoundError:
        return None
    return None if found is None else (int(found[1]), int(found[2]))


def _backend_started() -> bool:
    """Whether JAX has started a backend in this process (so XLA has read `XLA_FLAGS`)."""
    bridge = sys.modules.get("jax._src.xla_bridge")
    started = getattr(bridge, "backends_are_initialized", None)
    return bool(started()) if callable(started) else False


def fast_compile(
    environ: MutableMapping[str, str] | None = None, release: tuple[int, int] | None = None
) -> bool:
    """Add `FAST_COMPILE_FLAG` to `XLA_FLAGS` (returns whether the process now compiles with it).

    Left alone: a user's own choice of the option in `XLA_FLAGS` (kept as it is), a jaxlib
    outside `FAST_COMPILE_JAXLIB` (`release`: the installed one unless given), and this
    process's environment once JAX has started its backend: XLA has read the variable by then,
    and JAX's cache keys, which include it, would describe programs compiled without it. Child
    processes (a study's workers, notebook kernels) inherit the variable.
    """
    env = os.environ if environ is None else environ
    flags = env.get(XLA_FLAGS_VAR, "")
    if FAST_COMPILE_OPTION in flags:
        return FAST_COMPILE_FLAG in flags.split()
    if environ is None and _backend_started():
        return False
    release = jaxlib_release() if release is None else release
    first, last = FAST_COMPILE_JAXLIB
    if release is None or not first <= release <= last:
        return False
    env[XLA_FLAGS_VAR] = f"{flags} {FAST_COMPILE_FLAG}".strip()
    return True


def user_cache_dir(environ: Mapping[str, str] | None = None) -> Path | None:
    """stairfit's folder in the user's cache: `$XDG_CACHE_HOME/stairfit`, else
    `$HOME/.cache/stairfit` (HOME unset: the account's home); None when neither names a folder
    (HOME empty, "/" or relative): never a cache at the root of the filesystem or in the
    current folder."""
    env = os.environ if environ is None else environ
    base = env.get("XDG_CACHE_HOME", "").strip()
    if base and Path(base).is_absolute():
        return Path(base) / "stairfit"
    home = env["HOME"].strip() if "HOME" in env else os.path.expanduser("~")  # unset: passwd
    if not home or not Path(home).is_absolute() or Path(home) == Path(home).parent:
        return None
    return Path(home) / ".cache" / "stairfit"


def cache_dir(environ: Mapping[str, str] | None = None) -> Path | None:
    """Where the CLI keeps compiled programs (None when `STAIRFIT_JAX_CACHE=off`, or when there
    is no user cache folder: `user_cache_dir`)."""
    env = os.environ if environ is None else environ
    value = env.get(ENV_VAR, "").strip()
    if value.lower() in ("off", "0", "none", "false"):
        return None
    if value:
        return Path(value).expanduser()
    folder = user_cache_dir(env)
    return None if folder is None else folder / "jax"


def enable_persistent_cache(environ: dict[str, str] | None = None) -> Path | None:
    """Point JAX at the persistent compilation cache; returns the folder (None if disabled).

    A folder that cannot be created disables the cache silently: it only saves time.
    """
    import jax

    folder = cache_dir(environ)
    if folder is None:
        return None
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None
    jax.config.update("jax_compilation_cache_dir", str(folder))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_TIME_S)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return folder


def quiet_xla_logs(environ: MutableMapping[str, str] | None = None) -> bool:
    """Keep XLA's C++ log lines off the terminal (`TF_CPP_MIN_LOG_LEVEL=3`, unless the user set
    a level). jaxlib reads the variable when it is loaded, so this only works before the first
    `import jax` of the process; returns whether it was in time."""
    env = os.environ if environ is None else environ
    env.setdefault(XLA_LOG_LEVEL_VAR, XLA_QUIET_LEVEL)
    return "jax" not in sys.modules


def start_jax(quiet: bool = False, environ: MutableMapping[str, str] | None = None) -> Path | None:
    """The CLI's JAX set-up, once per process before any computation: under `quiet` no XLA log
    banners (first, before jax loads), the faster-compiling emitters (`fast_compile`), float64
    [conventions §10] and the persistent compilation cache; returns the cache folder (None if
    disabled)."""
    if quiet:
        quiet_xla_logs(environ)
    fast_compile(environ)
    import jax

    jax.config.update("jax_enable_x64", True)
    return enable_persistent_cache(None if environ is None else dict(environ))
