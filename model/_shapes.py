"""Explicit broadcasting: the model's functions broadcast their arguments like numpy, but say so.

Every public function of `stairfit.model` accepts arguments of different shapes and broadcasts
them [conventions §1]. numpy does that by *rank promotion* (prepending unit axes); here that
step is explicit, once per public function, so that no operation inside relies on it (the test
suite runs with `jax_numpy_rank_promotion = "raise"`, as optimistix's does: an accidental
broadcast of mismatched axes fails loudly instead of silently producing a larger array).
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike


def with_rank(x: ArrayLike, ndim: int) -> Array:
    """`x` with unit axes prepended until it has `ndim` axes (numpy's rank promotion)."""
    a = jnp.asarray(x)
    if a.ndim > ndim:
        raise ValueError(f"cannot lower the rank of an array of shape {a.shape} to {ndim}")
    return a.reshape((1,) * (ndim - a.ndim) + a.shape)


def same_rank(*arrays: ArrayLike) -> tuple[Array, ...]:
    """The arrays with unit axes prepended so that all have as many axes as the largest."""
    xs = [jnp.asarray(a) for a in arrays]
    ndim = max((x.ndim for x in xs), default=0)
    return tuple(with_rank(x, ndim) for x in xs)
