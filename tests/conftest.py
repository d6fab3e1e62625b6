"""Test configuration: float64 and no implicit rank promotion for every test [conventions §10],
shared-data locations."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from stairfit._jaxcache import fast_compile

# the programs the tests check are compiled as the command line compiles them (XLA:CPU's
# faster-compiling emitters, app/_jaxcache.py); set before JAX starts its backend, inherited by
# the CLI subprocesses, notebook kernels and Dask workers the tests start
fast_compile()

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
# As in optimistix's tests: an implicit rank promotion (broadcasting arrays of different ranks)
# raises, so that no accidental broadcast of mismatched axes goes unnoticed.
jax.config.update("jax_numpy_rank_promotion", "raise")
# CLI tests call stairfit.cli.main() in-process; it would point the whole test session at the
# user's persistent JAX cache (app/_jaxcache.py). Tests run without it unless asked to.
os.environ.setdefault("STAIRFIT_JAX_CACHE", "off")

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


@pytest.fixture
def shared_data() -> Path:
    """`../shared/data`, or skip: a user's clone has no ../shared (only the developers' does)."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"{SHARED_DATA} is absent (only the developers' checkout has ../shared/data)")
    return SHARED_DATA
