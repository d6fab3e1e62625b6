"""Checks the model tests share.

In NumPy on purpose: a check written with `jax.numpy` on a computed array dispatches small
programs of its own (compiled once per shape and dtype), which in a loop over hundreds of
cases cost more than the compiled model call they check (issue 14).
"""

from __future__ import annotations

from typing import Any

import jax
import numpy as np


def all_finite(tree: Any) -> bool:
    """Every leaf of `tree` (arrays or scalars, real or complex) is finite."""
    return all(bool(np.all(np.isfinite(np.asarray(x)))) for x in jax.tree_util.tree_leaves(tree))
