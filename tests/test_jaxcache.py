"""The CLI's JAX set-up (app/_jaxcache.py): where it keeps its persistent compilation cache,
and no XLA log banners under --quiet."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from stairfit._jaxcache import cache_dir, quiet_xla_logs


def test_default_is_under_the_user_cache_folder() -> None:
    home = Path.home()
    assert cache_dir({}) == home / ".cache" / "stairfit" / "jax"
    assert cache_dir({"XDG_CACHE_HOME": "/x/c"}) == Path("/x/c/stairfit/jax")


def test_environment_variable_sets_or_disables_it() -> None:
    assert cache_dir({"STAIRFIT_JAX_CACHE": "/y/jc"}) == Path("/y/jc")
    for off in ("off", "OFF", "0", "none", "false"):
        assert cache_dir({"STAIRFIT_JAX_CACHE": off}) is None


def test_quiet_xla_logs_sets_the_level_unless_the_user_chose_one() -> None:
    env: dict[str, str] = {}
    quiet_xla_logs(env)
    assert env == {"TF_CPP_MIN_LOG_LEVEL": "3"}  # level 2 would still print ERROR banners
    mine = {"TF_CPP_MIN_LOG_LEVEL": "0"}
    quiet_xla_logs(mine)
    assert mine == {"TF_CPP_MIN_LOG_LEVEL": "0"}


def _cli_in_fresh_process(args: list[str]) -> list[str]:
    """Run `stairfit.cli.main(args)` in a new interpreter; report the exit status, the XLA log
    level it left in the environment, and whether jax was already loaded before main."""
    code = (
        "import os, sys\n"
        "from stairfit import cli\n"
        "before = 'jax' in sys.modules\n"
        f"rc = cli.main({args!r})\n"
        "print(rc, os.environ.get('TF_CPP_MIN_LOG_LEVEL'), before)\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "TF_CPP_MIN_LOG_LEVEL"}
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, env=env
    )
    return out.stdout.split()


def test_quiet_commands_silence_xla_before_jax_is_imported(tmp_path: Path) -> None:
    missing = str(tmp_path / "no-such-folder")  # fails as a user error after the set-up
    assert _cli_in_fresh_process(["fit", missing, "--quiet"]) == ["2", "3", "False"]
    rc, level, _ = _cli_in_fresh_process(["fit", missing])
    assert rc == "2" and level != "3"  # jax's own default (it sets 1 when unset)


# A program whose compilation makes XLA print its slow-constant-folding banner: sorting a
# constant array is folded by XLA's (slow) evaluator, > 1 s for 20000 values on the 2-core machine.
_SLOW_FOLD = """
import sys
from stairfit._jaxcache import quiet_xla_logs
if sys.argv[1] == "quiet":
    quiet_xla_logs()
import jax, jax.numpy as jnp, numpy as np
values = np.random.default_rng(0).random(20000).astype(np.float32)
print(jax.jit(lambda x: jnp.sort(jnp.asarray(values))[:2] + x)(1.0))
"""


@pytest.mark.slow
def test_quiet_xla_logs_hides_the_slow_compile_banner() -> None:
    env = {k: v for k, v in os.environ.items() if k != "TF_CPP_MIN_LOG_LEVEL"}
    runs = {
        mode: subprocess.run(
            [sys.executable, "-c", _SLOW_FOLD, mode], capture_output=True, text=True, env=env
        )
        for mode in ("loud", "quiet")
    }
    assert all(r.returncode == 0 for r in runs.values()), runs
    assert "Constant folding an instruction is taking" in runs["loud"].stderr  # the control
    assert "Constant folding" not in runs["quiet"].stderr, runs["quiet"].stderr
