"""The fit's late imports, loaded in a background thread while the model is compiled and
fitted (issue 14: imports are part of the user's wait).

A default `stairfit fit` needs, after the least-squares fit, emcee (which imports
scipy.stats), ArviZ with xarray (which imports dask.array the first time it checks whether an
array is a dask array) and h5netcdf for the chain, and matplotlib for the report: about 3 s of
imports on the 2-core machine, spent while the second core idled. The compilation and the
least-squares fit run in XLA, single-threaded and without the interpreter lock, so the same
imports done in a thread started once the photos are measured cost the user little of that
(`benchmarks/bench_cold.py --compare-exe`: a warm default fit 10.8 -> 8.8 s with `cli.entry`
and the threaded starts). Not earlier: decoding the photos keeps both cores busy, and imports
started before it only slowed it.

Nothing but imports (and a 2 x 2 ArviZ dataset, which is how xarray's lazy imports are
reached) happens in the thread, and it never raises: a module that fails to import there is
imported again where it is used, in the main thread, which reports the error as before.
Python's per-module import locks make a main-thread import of a module the thread is still
loading wait for it, not load it twice.
"""

from __future__ import annotations

import gc
import importlib
import threading

REPORT_MODULES = ("stairfit.report",)
"""What `fit --no-posterior` imports after the least-squares fit (the report: matplotlib)."""
FIT_MODULES = (
    "stairfit.fitting._posterior",
    "stairfit.fitting._diagnostics",
    "arviz",
    "h5netcdf",
    *REPORT_MODULES,
)
"""What a default `fit` imports after the least-squares fit, in the order it needs them."""


def _load(modules: tuple[str, ...], freeze: bool) -> None:
    for name in modules:
        try:
            importlib.import_module(name)
        except Exception:  # imported (and reported) again where it is used
            continue
        if freeze:
            gc.freeze()
    if "arviz" not in modules:
        return
    try:
        import arviz
        import numpy as np

        arviz.convert_to_dataset({"x": np.zeros((2, 2))})  # xarray's lazy dask import
    except Exception:  # as above
        pass
    if freeze:
        gc.freeze()


def prefetch(modules: tuple[str, ...] = FIT_MODULES, freeze: bool = False) -> threading.Thread:
    """Start importing `modules` in a daemon thread; returns the thread (already started).

    `freeze` (the console script, `cli.entry`): after each module, `gc.freeze()` moves what
    the imports made into the collector's permanent generation. Modules live until the process
    ends, and every full collection walked them again: 8 full collections of up to 0.2 s each,
    0.63-0.69 s of a warm default fit, collecting at most a hundred objects; with the start-up's
    imports frozen too (`cli.main`) 0.12-0.16 s (2 runs each, gc.callbacks). Not in processes
    that go on (tests, notebooks): what is frozen is never collected."""
    thread = threading.Thread(
        target=_load, args=(modules, freeze), name="stairfit-imports", daemon=True
    )
    thread.start()
    return thread
