"""The persistent JAX compilation cache of the command line (issue 7: compilation is part of
the user's wait).

A fit compiles its least-squares and posterior functions once per model variant (shapes are
kept static across photos and wedges, so one scene compiles once); the persistent cache keeps
those compilations on disk so that the next `stairfit fit` or `demo` on this machine skips
them. Location: `$STAIRFIT_JAX_CACHE` if set (`off` disables the cache), otherwise
`$XDG_CACHE_HOME/stairfit/jax` (default `~/.cache/stairfit/jax`). Only the CLI enables it;
library users choose for themselves (`jax.config.update("jax_compilation_cache_dir", ...)`).
"""

from __future__ import annotations

import os
from pathlib import Path

ENV_VAR = "STAIRFIT_JAX_CACHE"
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
