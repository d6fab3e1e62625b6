"""JAX set-up of the command line: float64, the persistent compilation cache (issue 7:
compilation is part of the user's wait) and, under `--quiet`, no XLA log banners (issue 12).

A fit compiles its least-squares and posterior functions once per model variant (shapes are
kept static across photos and wedges, so one scene compiles once); the persistent cache keeps
those compilations on disk so that the next `stairfit fit` or `demo` on this machine skips
them. Location: `$STAIRFIT_JAX_CACHE` if set (`off` disables the cache), otherwise
`$XDG_CACHE_HOME/stairfit/jax` (default `~/.cache/stairfit/jax`). Only the CLI enables it;
library users choose for themselves (`jax.config.update("jax_compilation_cache_dir", ...)`).
"""

from __future__ import annotations

import os
import sys
from collections.abc import MutableMapping
from pathlib import Path

ENV_VAR = "STAIRFIT_JAX_CACHE"
XLA_LOG_LEVEL_VAR = "TF_CPP_MIN_LOG_LEVEL"
XLA_QUIET_LEVEL = "3"
"""XLA's C++ logging keeps only FATAL messages at level 3. Its "slow compile" banners
("Constant folding an instruction is taking > 1s", "Very slow compile?") are ERROR lines, so
level 2 would still print them; real failures still reach Python as exceptions."""
MIN_COMPILE_TIME_S = 0.0
"""Compilations faster than this are not written to disk (JAX's default is 1 s). Every one is
kept: a warm `stairfit fit` of the demo scene otherwise recompiled about 35 small programs
(0.06 s each, 2.3 s in all), while reading one back takes about 0.01 s."""


def cache_dir(environ: dict[str, str] | None = None) -> Path | None:
    """Where the CLI keeps compiled programs (None when `STAIRFIT_JAX_CACHE=off`)."""
    env = os.environ if environ is None else environ
    value = env.get(ENV_VAR, "").strip()
    if value.lower() in ("off", "0", "none", "false"):
        return None
    if value:
        return Path(value).expanduser()
    base = env.get("XDG_CACHE_HOME", "").strip()
    root = Path(base).expanduser() if base else Path.home() / ".cache"
    return root / "stairfit" / "jax"


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
    banners (first, before jax loads), float64 [conventions §10] and the persistent compilation
    cache; returns the cache folder (None if disabled)."""
    if quiet:
        quiet_xla_logs(environ)
    import jax

    jax.config.update("jax_enable_x64", True)
    return enable_persistent_cache(None if environ is None else dict(environ))
