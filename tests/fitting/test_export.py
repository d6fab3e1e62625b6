"""Traced programs kept on disk (`stairfit.fitting._export`, issue 14): a warm process calls the
exported least-squares solver and log posterior instead of tracing them again, with the same
results; stale, damaged or switched-off caches fall back to tracing."""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import zoo

from stairfit import fitting
from stairfit.fitting import _export, posterior

DEG = np.pi / 180
TRUTH = fitting.Params(sigma_rad=8 * DEG, delta_n=0.02, scale=1.0, floor=0.003)
VARIANT = fitting.variant("dn_floor", "delta_n", "floor")


@pytest.fixture
def cache_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """JAX's persistent compilation cache in a fresh folder (where the exported programs go)
    for this test only; the process memo of loaded programs emptied before and after."""
    before = jax.config.jax_compilation_cache_dir
    monkeypatch.delenv(_export.OFF_VAR, raising=False)
    jax.config.update("jax_compilation_cache_dir", str(tmp_path))
    _export._PROGRAMS.clear()
    yield tmp_path / _export.EXPORT_SUBDIR
    jax.config.update("jax_compilation_cache_dir", before)
    _export._PROGRAMS.clear()


def _fit() -> fitting.FitResult:
    s = zoo.small(TRUTH, 21)
    return fitting.fit_least_squares(s.obs, s.spec, VARIANT, emit_warnings=False)


def test_exported_fit_and_posterior_equal_the_traced_ones(cache_dir: Path) -> None:
    """With a cache folder the solver and the log posterior run as exported programs (files
    appear), from memory and, after the memo is emptied (a new process), from disk; every
    result equals the plain traced run's to the last bit of the fit and 1e-12 of the log
    posterior (XLA may fuse the exported module a little differently)."""
    jax.config.update("jax_compilation_cache_dir", None)
    plain = _fit()
    post_plain = posterior.sample_posterior(
        plain, seed=3, max_steps=200, chunk_steps=100, emit_warnings=False
    )
    jax.config.update("jax_compilation_cache_dir", str(cache_dir.parent))
    first = _fit()
    files = sorted(p.name for p in cache_dir.glob("*.bin"))
    assert any(f.startswith("solve_one-") for f in files), files
    _export._PROGRAMS.clear()  # as a new process: read back from disk
    second = _fit()
    for f in (first, second):
        np.testing.assert_allclose(f.z, plain.z, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(f.chi2, plain.chi2, rtol=1e-10)
        np.testing.assert_allclose(f.stderrs, plain.stderrs, rtol=1e-8)
    post = posterior.sample_posterior(
        second, seed=3, max_steps=200, chunk_steps=100, emit_warnings=False
    )
    assert any(p.name.startswith("log_probability-") for p in cache_dir.glob("*.bin"))
    np.testing.assert_allclose(post.log_prob, post_plain.log_prob, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(post.samples, post_plain.samples, rtol=1e-9, atol=1e-12)


def test_a_damaged_program_file_is_traced_again_and_replaced(cache_dir: Path) -> None:
    """A file that does not deserialise costs a trace, not an error, and is written anew."""
    f = jax.jit(lambda x, y: (x * y, jnp.sin(x)))
    args = (jnp.arange(3.0), jnp.ones(3))
    out = _export.call("toy", lambda x, y: f(x, y), "k", args, tuple)
    (path,) = cache_dir.glob("toy-*.bin")
    path.write_bytes(b"not a program")
    _export._PROGRAMS.clear()
    again = _export.call("toy", lambda x, y: f(x, y), "k", args, tuple)
    for a, b in zip(out, again, strict=True):
        np.testing.assert_array_equal(a, b)
    assert path.read_bytes() != b"not a program"
    assert not list(cache_dir.glob(".*.tmp"))  # written atomically


def test_the_key_follows_the_static_description_shapes_and_code(cache_dir: Path) -> None:
    """Another static description or another argument shape is another program; so is other
    code (`code_fingerprint` hashes the source of model/ and fitting/)."""
    leaves = [np.zeros(3), np.ones((2, 2))]
    tree = jax.tree.structure((0, 0))
    k = _export.program_key("p", "a", tree, leaves)
    assert k == _export.program_key("p", "a", tree, leaves)
    assert k != _export.program_key("p", "b", tree, leaves)
    assert k != _export.program_key("p", "a", tree, [np.zeros(4), np.ones((2, 2))])
    assert k != _export.program_key("p", "a", tree, [np.zeros(3, np.float32), np.ones((2, 2))])
    assert len(_export.code_fingerprint()) == 64


def test_the_remembered_file_of_a_program_is_its_key(tmp_path: Path) -> None:
    """`call` remembers each program's file (the posterior calls its program hundreds of
    times): the same name as `program_key`, for NumPy, JAX and Python-scalar leaves."""
    leaves = [np.zeros(3), jnp.ones((2, 2), jnp.float32), 1.5]
    tree = jax.tree.structure(leaves)
    shapes = tuple(map(_export._shape_dtype, leaves))
    want = tmp_path / f"{_export.program_key('p', 'a', tree, leaves)}.bin"
    assert _export._program_path(tmp_path, "p", "a", tree, shapes) == want
    other = tuple(map(_export._shape_dtype, [np.zeros(3), jnp.ones((2, 2)), 1.5]))
    assert _export._program_path(tmp_path, "p", "a", tree, other) != want  # float64 there


def test_switched_off_or_without_a_cache_folder_nothing_is_written(
    cache_dir: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv(_export.OFF_VAR, "off")
    assert _export.export_folder() is None
    out = _export.call("toy", lambda x: x + 1.0, "k", (jnp.arange(2.0),), lambda v: v[0])
    np.testing.assert_array_equal(out, [1.0, 2.0])
    assert not cache_dir.exists()


def test_a_program_file_swapped_for_another_is_traced_again(cache_dir: Path) -> None:
    # issue 42 case 10: a foreign or swapped file failed the call ("Shape mismatch"), though a
    # foreign file is promised to be only a missed saving
    f = jax.jit(lambda x, y: (x * y, jnp.sin(x)))
    g = jax.jit(lambda x: (x + 1.0,))
    args = (jnp.arange(3.0), jnp.ones(3))
    out = _export.call("toy", lambda x, y: f(x, y), "k", args, tuple)
    _export.call("other", g, "k", (jnp.arange(4.0),), tuple)
    (mine,) = cache_dir.glob("toy-*.bin")
    (theirs,) = cache_dir.glob("other-*.bin")
    mine.write_bytes(theirs.read_bytes())  # the other program under this one's name
    _export._PROGRAMS.clear()
    again = _export.call("toy", lambda x, y: f(x, y), "k", args, tuple)
    for a, b in zip(out, again, strict=True):
        np.testing.assert_array_equal(a, b)
    assert mine.read_bytes() != theirs.read_bytes()  # written anew


def test_a_swapped_jax_cache_entry_costs_a_compilation_not_the_run(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    # JAX loads its persistent cache's files without a check: two entries swapped made
    # `predict` fail with "safe_zip() argument 1 has length 0"; the command line repeats the
    # run without the cache and says so in one line
    import subprocess
    import sys

    cache = tmp_path / "jax"
    env = {**__import__("os").environ, "STAIRFIT_JAX_CACHE": str(cache)}
    argv = [sys.executable, "-c", "from stairfit.cli import entry; entry()", "predict",
            "--theta-o-deg", "0"]  # fmt: skip
    first = subprocess.run([*argv, "-o", str(tmp_path / "a.csv")], env=env, timeout=600,
                           capture_output=True, text=True)  # fmt: skip
    assert first.returncode == 0, first.stderr
    entries = sorted(p for p in cache.glob("jit_*-cache"))
    assert len(entries) >= 2
    a, b = entries[0].read_bytes(), entries[1].read_bytes()
    entries[0].write_bytes(b), entries[1].write_bytes(a)
    done = subprocess.run([*argv, "-o", str(tmp_path / "b.csv")], env=env, timeout=600,
                          capture_output=True, text=True)  # fmt: skip
    assert done.returncode == 0, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "did not fit this run" in lines[0], done.stderr
    assert (tmp_path / "a.csv").read_text() == (tmp_path / "b.csv").read_text()
