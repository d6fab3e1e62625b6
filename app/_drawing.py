"""The report's figures drawn and written in a second process (issue 14: a warm `stairfit fit`).

A warm default fit holds the interpreter lock most of its time: the imports of the scientific
stack, JAX's lowering, emcee's Python, and matplotlib. Drawing the report's figures (rendering
on the Agg canvas and encoding the PNGs, about 1.9 s of the 2.6 s the figures took) ran in a
thread beside the posterior sampling and slowed it by as much: without the figures, a warm fit
of the 2 MP x 9-view demo took 7.3-7.5 s against 8.4-9.2 s (4 interleaved runs each).

So the figures are still *built* where the data are (a `matplotlib.figure.Figure` is cheap to
make: artists and numbers), then pickled and *drawn* by a spawned process (JAX does not
survive fork) that imports matplotlib and Pillow only, on the second core, while this process
samples the posterior and writes the other outputs (`fit --no-posterior` has nothing to draw
beside, and draws here; so do a study's workers, already one per core). `Drawer.__call__`
has the signature of `figures.save`; `drawing()` starts the process and, when its block ends,
waits until every figure is written, so nothing writes into the output folder afterwards. Any
failure of the process (it cannot start, it died, a figure does not pickle) falls back to
drawing that figure here with `figures.save`: the same bytes either way (tests/test_drawing.py).
A warm default fit: 7.8 s (7.7-8.3) against 9.7 s before the evening's three changes (this,
the exported programs' keys remembered, the console script's frozen imports;
benchmarks/results/cold.md).

The process ignores SIGINT (Ctrl-C reaches the whole process group): this process decides
when it stops, and waits for the figure being written.
"""

from __future__ import annotations

import pickle
from collections.abc import Iterator
from concurrent.futures import Future, ProcessPoolExecutor
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

if TYPE_CHECKING:
    from matplotlib.figure import Figure


def _start_worker() -> None:
    """In the drawing process: leave Ctrl-C to the parent; import what drawing needs."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    import matplotlib.backends.backend_agg  # noqa: F401
    import PIL.Image  # noqa: F401

    from . import figures  # noqa: F401


def _ready() -> bool:
    return True


def _draw(blob: bytes, path: str, dpi: int) -> str:
    """In the drawing process: unpickle a figure, draw it and write its PNG (`figures.save`)."""
    from .figures import save

    save(pickle.loads(blob), Path(path), dpi)
    return path


class _Pending(NamedTuple):
    future: Future[str]
    fig: Figure
    path: Path
    dpi: int


class Drawer:
    """`figures.save`, sending each figure to the drawing process (`pool`), or drawing it here
    where there is none. `finish()` waits for every figure sent."""

    def __init__(self, pool: ProcessPoolExecutor | None) -> None:
        self._pool = pool
        self._pending: list[_Pending] = []

    @property
    def in_process(self) -> bool:
        """Whether figures go to a drawing process."""
        return self._pool is not None

    def __call__(self, fig: Figure, path: Path, dpi: int = 120) -> Path:
        from .figures import save

        if self._pool is not None:
            try:
                blob = pickle.dumps(fig)
                future = self._pool.submit(_draw, blob, str(path), dpi)
            except Exception:  # an artist that does not pickle, or a pool that broke: draw here
                return save(fig, path, dpi)
            self._pending.append(_Pending(future, fig, path, dpi))
            return path
        return save(fig, path, dpi)

    def finish(self) -> None:
        """Wait for every figure sent; draw here any the process failed to write."""
        from .figures import save

        pending, self._pending = self._pending, []
        for p in pending:
            try:
                p.future.result()
            except Exception:  # the process died or the figure failed there: the same, here
                save(p.fig, p.path, p.dpi)


def _pool() -> ProcessPoolExecutor | None:
    """The drawing process, started (and its imports begun) now; None where it cannot start."""
    import multiprocessing

    try:
        pool = ProcessPoolExecutor(
            max_workers=1,
            mp_context=multiprocessing.get_context("spawn"),
            initializer=_start_worker,
        )
    except Exception:  # no processes here (a sandbox, a missing semaphore): draw in-process
        return None
    try:
        pool.submit(_ready)  # spawn it now: its imports overlap the fit
    except Exception:  # it could not start: draw in-process
        pool.shutdown(wait=False, cancel_futures=True)
        return None
    return pool


@contextmanager
def drawing(in_process: bool = True) -> Iterator[Drawer]:
    """A `Drawer` for the block: with `in_process`, figures are drawn by a second process that
    starts now; every figure is written when the block ends (also when it ends by an error:
    the process is then stopped after the figure it is writing)."""
    pool = _pool() if in_process else None
    drawer = Drawer(pool)
    try:
        yield drawer
        drawer.finish()
    finally:
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)
