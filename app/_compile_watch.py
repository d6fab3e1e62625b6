"""Compilation as a visible, measured stage (issue 14).

A new scene's first fit waits seconds to minutes while XLA compiles its programs; without a
word on the screen that wait looks like a hang. `watching_compilation` listens to JAX's own
monitoring events (`jax.monitoring`): when a program has been lowered to MLIR, its backend
compilation starts; when that takes longer than `SHOW_AFTER_S`, a progress line of its own
("compiling _solve_one: 12 s") appears and stays, with the time it took, once it is done. A
program found in the persistent cache (app/_jaxcache.py) loads in milliseconds and shows no
line. The totals (compile seconds, programs compiled) go into results.json's timings.

The listener is registered only inside the `with` block and removed after it: no state
outlives the call.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from tqdm import tqdm

LOWERED_EVENT = "/jax/core/compile/jaxpr_to_mlir_module_duration"
"""JAX records this when a top-level program has been lowered: its compilation starts."""
COMPILED_EVENT = "/jax/core/compile/backend_compile_duration"
"""JAX records this when XLA has compiled a program (or loaded it from the persistent cache)."""
SHOW_AFTER_S = 1.0
"""A compilation shorter than this shows no line (small programs, cache hits)."""
TICK_S = 0.5
"""How often the line's clock is redrawn."""
KNOWN_PROGRAMS = {
    "_solve_one": "the least-squares fit",
    "solve_one": "the least-squares fit",
    "evaluate": "the fit's evaluation at its optimum",
    "log_probability": "the posterior's log probability",
    "batched_log_probability": "the posterior's log probability",
    "_batched_physical": "the posterior's parameter transform",
}
"""What the user is told is compiling, for the programs that take long."""


def program_name(fun_name: str) -> str:
    """`jit(_solve_one)` -> `the least-squares fit (_solve_one)`; other names as they are."""
    inner = fun_name[4:-1] if fun_name.startswith("jit(") and fun_name.endswith(")") else fun_name
    known = KNOWN_PROGRAMS.get(inner)
    return f"{known} ({inner})" if known else inner


@dataclass
class CompileStats:
    """What compilation cost during one watched block: `compile_s` (backend compilation, cache
    loads included), `programs` compiled or loaded, `longest_s` and its program's name."""

    compile_s: float = 0.0
    programs: int = 0
    longest_s: float = 0.0
    longest: str = ""
    _running: tuple[str, float] | None = None
    _bar: tqdm | None = None
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def record(self, event: str, duration: float, **kwargs: object) -> None:
        """The `jax.monitoring` duration listener."""
        name = program_name(str(kwargs.get("fun_name", "a program")))
        with self._lock:
            if event == LOWERED_EVENT:
                self._running = (name, time.monotonic())
            elif event == COMPILED_EVENT:
                self.compile_s += duration
                self.programs += 1
                if duration > self.longest_s:
                    self.longest_s, self.longest = duration, name
                self._running = None
                self._close(f"compiled {name} in {duration:.1f} s")

    def tick(self, enabled: bool) -> None:
        """Open or redraw the line of a compilation running for longer than `SHOW_AFTER_S`."""
        with self._lock:
            if self._running is None or not enabled:
                return
            name, start = self._running
            elapsed = time.monotonic() - start
            if elapsed < SHOW_AFTER_S:
                return
            if self._bar is None:
                from tqdm import tqdm

                self._bar = tqdm(total=None, bar_format="{desc}", leave=True)
            self._bar.set_description_str(
                f"compiling {name}: {elapsed:.0f} s (once per scene shape; kept in the JAX "
                "cache for later runs)"
            )

    def _close(self, final: str) -> None:
        if self._bar is not None:
            self._bar.set_description_str(final)
            self._bar.close()
            self._bar = None

    def as_timings(self) -> dict[str, float]:
        """The figures for results.json (`diagnostics.timings_s`)."""
        return {"compile_s": self.compile_s}


@contextmanager
def watching_compilation(show: bool) -> Iterator[CompileStats]:
    """Measure (and, with `show`, display) every compilation inside the block."""
    import jax.monitoring

    stats = CompileStats()
    stop = threading.Event()

    def ticker() -> None:
        while not stop.wait(TICK_S):
            stats.tick(show)

    thread = threading.Thread(target=ticker, name="stairfit-compile-watch", daemon=True)
    jax.monitoring.register_event_duration_secs_listener(stats.record)
    thread.start()
    try:
        yield stats
    finally:
        stop.set()
        thread.join()
        jax.monitoring.unregister_event_duration_listener(stats.record)
        with stats._lock:
            stats._close("")
