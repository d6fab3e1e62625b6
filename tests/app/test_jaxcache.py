"""The CLI's JAX set-up (app/_jaxcache.py): where it keeps its persistent compilation cache,
XLA:CPU's faster-compiling emitters, and no XLA log banners under --quiet."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from stairfit._jaxcache import (
    FAST_COMPILE_FLAG,
    FAST_COMPILE_JAXLIB,
    cache_dir,
    fast_compile,
    jaxlib_release,
    quiet_xla_logs,
)


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


def _fresh_process(code: str, unset: str) -> list[str]:
    """Run `code` in a new interpreter without the environment variable `unset`; its printed
    words."""
    env = {k: v for k, v in os.environ.items() if k != unset}
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, env=env
    )
    return out.stdout.split()


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
    return _fresh_process(code, unset="TF_CPP_MIN_LOG_LEVEL")


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


def test_fast_compile_adds_the_flag_and_keeps_the_user_s_own_choice() -> None:
    inside = FAST_COMPILE_JAXLIB[1]
    env: dict[str, str] = {}
    assert fast_compile(env, release=inside) and env == {"XLA_FLAGS": FAST_COMPILE_FLAG}
    assert fast_compile(env, release=inside) and env == {"XLA_FLAGS": FAST_COMPILE_FLAG}  # once
    other = {"XLA_FLAGS": "--xla_force_host_platform_device_count=2"}
    assert fast_compile(other, release=inside)
    assert other["XLA_FLAGS"].split() == ["--xla_force_host_platform_device_count=2",
                                          FAST_COMPILE_FLAG]  # fmt: skip
    mine = {"XLA_FLAGS": "--xla_cpu_use_fusion_emitters=true"}
    assert not fast_compile(mine, release=inside)
    assert mine == {"XLA_FLAGS": "--xla_cpu_use_fusion_emitters=true"}


@pytest.mark.parametrize("release", [(0, 5), (FAST_COMPILE_JAXLIB[1][0], 99), (1, 0)])
def test_fast_compile_leaves_a_release_it_was_not_checked_on_alone(
    release: tuple[int, int],
) -> None:
    # XLA stops the process on an option it does not know (0.5.0 lacks this one)
    env: dict[str, str] = {}
    assert fast_compile(env, release=release) is False
    assert env == {}


def test_fast_compile_without_a_readable_jaxlib_version_does_nothing(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from importlib import metadata

    def missing(name: str) -> str:
        raise metadata.PackageNotFoundError(name)

    monkeypatch.setattr(metadata, "version", missing)
    assert jaxlib_release() is None
    env: dict[str, str] = {}
    assert fast_compile(env) is False and env == {}


def test_the_installed_jaxlib_release_is_read() -> None:
    import jaxlib

    assert jaxlib_release() == tuple(int(x) for x in jaxlib.__version__.split(".")[:2])


_VALUES = """
import sys
import jax, jax.numpy as jnp, numpy as np
jax.config.update("jax_enable_x64", True)
from stairfit import model
ti = jnp.linspace(-1.4, 1.4, 7)[:, None]
to = jnp.linspace(-1.5, 1.5, 41)[None, :]
f = jax.jit(lambda p: model.brdf(ti, to, p[0], p[1], p[2]))
p = jnp.array([0.5, 1.46, 0.08])
w_i = jnp.array([[0.3, 0.1, 0.95], [-0.5, 0.2, 0.84]])
w_o = jnp.array([[-0.2, -0.1, 0.97], [0.6, 0.05, 0.8]])[:, None, :]
g = jax.jit(lambda q: model.lab_density_rounded(w_i, w_o, 0.6, q[0], q[1], 150.0, q[2], "ggx"))
q = jnp.array([1.46, 0.06, 25.0])
np.save(sys.argv[1], np.concatenate([f(p).ravel(), jax.jacfwd(f)(p).ravel(),
                                     g(q).ravel(), jax.jacfwd(g)(q).ravel()]))
"""


def test_the_installed_xla_knows_the_flag_and_gives_the_same_numbers(tmp_path: Path) -> None:
    release = jaxlib_release()
    first, last = FAST_COMPILE_JAXLIB
    if release is None or not first <= release <= last:
        pytest.skip(f"jaxlib {release} is outside {FAST_COMPILE_JAXLIB}: check the option on it "
                    "(this test) and widen FAST_COMPILE_JAXLIB")  # fmt: skip
    runs = {}
    for flags in (FAST_COMPILE_FLAG, "--xla_cpu_use_fusion_emitters=true"):
        env = {**os.environ, "XLA_FLAGS": flags}
        out = tmp_path / f"{len(runs)}.npy"
        done = subprocess.run(
            [sys.executable, "-c", _VALUES, str(out)], capture_output=True, text=True, env=env
        )
        assert done.returncode == 0, done.stderr[-2000:]  # an unknown flag aborts XLA
        runs[flags] = np.load(out)
    fast, default = runs.values()
    assert np.all(np.isfinite(fast)) and np.any(fast != 0)
    # the same models (in-plane, rough rounded lab) to rounding: the emitters order some
    # floating-point operations apart
    np.testing.assert_allclose(fast, default, rtol=1e-12, atol=1e-15 * np.max(np.abs(default)))


def test_fast_compile_leaves_a_started_backend_alone() -> None:
    # XLA read XLA_FLAGS when the backend started: adding the option then would only make JAX's
    # cache keys (which include the variable) describe programs compiled without it
    code = (
        "import os\n"
        "import jax.numpy as jnp\n"
        "from stairfit._jaxcache import fast_compile\n"
        "jnp.zeros(1).block_until_ready()\n"
        "print(fast_compile(), repr(os.environ.get('XLA_FLAGS')))\n"
    )
    out = _fresh_process(code, unset="XLA_FLAGS")
    assert out == ["False", "None"], out


def test_the_command_line_compiles_with_the_flag(tmp_path: Path) -> None:
    code = (
        "import os\n"
        "from stairfit import cli\n"
        f"rc = cli.main(['fit', {str(tmp_path / 'none')!r}, '--quiet'])\n"
        "print(rc, os.environ.get('XLA_FLAGS', ''))\n"
    )
    out = _fresh_process(code, unset="XLA_FLAGS")
    release = jaxlib_release()
    first, last = FAST_COMPILE_JAXLIB
    expected = release is not None and first <= release <= last
    assert out[0] == "2" and (FAST_COMPILE_FLAG in out[1:]) == expected, out
