"""Failed allocations: how `stairfit` recognises them and says them in one line (app/cli.py,
the accuracy check's refit in app/accuracy.py)."""

from __future__ import annotations


def is_out_of_memory(err: BaseException) -> bool:
    """Whether `err` is a failed allocation (Python's `MemoryError`, or XLA's "Out of memory" /
    RESOURCE_EXHAUSTED runtime error)."""
    text = str(err)
    return isinstance(err, MemoryError) or "Out of memory" in text or "RESOURCE_EXHAUSTED" in text


def first_line(err: BaseException) -> str:
    """The first line of an error's message, at most 160 characters."""
    return (str(err).strip().splitlines() or [type(err).__name__])[0][:160]
