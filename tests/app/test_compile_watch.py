"""Compilation shown and measured as a stage (issue 14, app/_compile_watch.py)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import pytest

from stairfit import _compile_watch as cw


def test_program_names_are_told_in_words():
    assert cw.program_name("jit(_solve_one)") == "the least-squares fit (_solve_one)"
    assert cw.program_name("jit(brdf)") == "brdf"


def test_a_compilation_inside_the_block_is_counted_and_the_listener_removed():
    def f(x: jax.Array) -> jax.Array:
        return jnp.sin(x) * jnp.arange(7.0)  # a fresh function: nothing cached in-process

    with cw.watching_compilation(show=False) as stats:
        jax.jit(f)(jnp.float32(1.0)).block_until_ready()
    assert stats.programs >= 1
    assert stats.compile_s > 0.0
    counted = stats.programs
    assert stats.as_timings() == {"compile_s": stats.compile_s}
    jax.jit(lambda x: f(x) + 1)(jnp.float32(2.0)).block_until_ready()  # after the block
    assert stats.programs == counted  # the listener is gone


def test_a_long_compilation_opens_a_line_that_stays_with_its_time(capsys):
    stats = cw.CompileStats()
    stats.record(cw.LOWERED_EVENT, 0.01, fun_name="jit(_solve_one)")
    stats._running = (stats._running[0], stats._running[1] - 2 * cw.SHOW_AFTER_S)  # started 2 s ago
    stats.tick(enabled=True)
    stats.record(cw.COMPILED_EVENT, 2.5, fun_name="jit(_solve_one)")
    err = capsys.readouterr().err
    assert "compiling the least-squares fit (_solve_one): 2 s" in err
    assert "compiled the least-squares fit (_solve_one) in 2.5 s" in err
    assert (stats.programs, stats.longest_s) == (1, pytest.approx(2.5))


def test_a_short_compilation_shows_nothing(capsys):
    stats = cw.CompileStats()
    stats.record(cw.LOWERED_EVENT, 0.01, fun_name="jit(f)")
    stats.tick(enabled=True)  # just started: below SHOW_AFTER_S
    stats.record(cw.COMPILED_EVENT, 0.05, fun_name="jit(f)")
    assert capsys.readouterr().err == ""
