"""Where the CLI keeps its persistent JAX compilation cache (app/_jaxcache.py)."""

from __future__ import annotations

from pathlib import Path

from stairfit._jaxcache import cache_dir


def test_default_is_under_the_user_cache_folder() -> None:
    home = Path.home()
    assert cache_dir({}) == home / ".cache" / "stairfit" / "jax"
    assert cache_dir({"XDG_CACHE_HOME": "/x/c"}) == Path("/x/c/stairfit/jax")


def test_environment_variable_sets_or_disables_it() -> None:
    assert cache_dir({"STAIRFIT_JAX_CACHE": "/y/jc"}) == Path("/y/jc")
    for off in ("off", "OFF", "0", "none", "false"):
        assert cache_dir({"STAIRFIT_JAX_CACHE": off}) is None
