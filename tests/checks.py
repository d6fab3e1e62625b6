"""Checks the model tests share.

In NumPy on purpose: a check written with `jax.numpy` on a computed array dispatches small
programs of its own (compiled once per shape and dtype), which in a loop over hundreds of
cases cost more than the compiled model call they check (issue 14).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import numpy as np


def all_finite(tree: Any) -> bool:
    """Every leaf of `tree` (arrays or scalars, real or complex) is finite."""
    return all(bool(np.all(np.isfinite(np.asarray(x)))) for x in jax.tree_util.tree_leaves(tree))


def generic_direction(n: int) -> np.ndarray:
    """A tangent of `n` components, every one non-zero and no two in a rational ratio
    (`1 / sqrt(k)`, k = 1..n): a check of finite derivatives needs the one derivative along it,
    not the whole Jacobian.

    A non-finite Jacobian comes from an operation whose derivative is not finite at the point;
    along this direction every input's tangent is non-zero, so the tangent reaching that
    operation is non-zero (it could cancel only for components in a rational ratio) and the
    derivative is non-finite too. (`jax.jacfwd`'s columns whose tangent reaches it as an exact
    0 are NaN there as well, 0 x inf: tests/validation/test_checks.py.)
    """
    return 1.0 / np.sqrt(np.arange(1.0, n + 1.0))


def jacobian_by_columns(tangent: Callable[[np.ndarray], Any], n: int) -> Any:
    """The Jacobian of a function of `n` inputs, one column at a time: `tangent(e_k)` is its
    derivative along the k-th unit vector, from one compiled program that takes the tangent as
    an argument (`jax.jvp` inside `jax.jit`). `jax.jacfwd` compiles a program `n` tangents wide,
    which for the rounded and filleted models took 1.8x longer to trace, lower and compile
    (issue 14; benchmarks/bench_jvp_programs.py); its
    one call runs faster than the `n`, so the gain is largest where a test needs one direction
    (one column, or `generic_direction`) at many points. Each leaf of the result has the
    columns on a last axis, as `jax.jacfwd` gives them."""
    columns = [tangent(np.eye(n)[k]) for k in range(n)]
    return jax.tree_util.tree_map(
        lambda *c: np.stack([np.asarray(x) for x in c], axis=-1), *columns
    )
