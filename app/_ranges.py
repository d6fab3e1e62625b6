"""Parsing of angle and wavelength lists given on the command line (degrees, nanometres)."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from .errors import UserError

MAX_VALUES = 2_000_000
"""The most values one list or range may give (`-90:90:1e-9` would need 1.4 TB)."""

MAX_WORKERS = 32
"""The most worker processes `--workers` may start (each holds a photo: ~0.2 GB at 24 MP)."""


def check_workers(workers: int) -> int:
    """`--workers` in [1, MAX_WORKERS], else a one-line UserError."""
    if not 1 <= workers <= MAX_WORKERS:
        raise UserError(f"--workers: must be >= 1 and <= {MAX_WORKERS}, not {workers}")
    return workers


def _range_count(start: float, stop: float, step: float, text: str, option: str) -> int:
    """How many values `start:stop:step` gives (stop included when on the grid), checked."""
    if not all(math.isfinite(v) for v in (start, stop, step)):
        raise UserError(f"{option}: {text!r} has a value that is not a finite number")
    count = math.floor((stop - start) / step + 1e-9) + 1
    if count > MAX_VALUES:
        raise UserError(
            f"{option}: {text!r} gives {count:.3g} values, more than the {MAX_VALUES:,} allowed; "
            "use a coarser step"
        )
    return count


def parse_values(text: str, option: str) -> NDArray:
    """`"10,20,30"` or `"start:stop:step"` (stop included when on the grid) to a float array."""
    text = text.strip()
    try:
        if ":" in text:
            parts = [float(p) for p in text.split(":")]
            if len(parts) != 3 or not parts[2] > 0 or not parts[1] >= parts[0]:
                raise ValueError
            start, stop, step = parts
            return start + step * np.arange(_range_count(start, stop, step, text, option))
        values = np.array([float(p) for p in text.split(",") if p.strip()], dtype=float)
    except ValueError:
        raise UserError(
            f"{option}: cannot read {text!r}; give a comma list such as '10,20,30' or a range "
            "'start:stop:step' with step > 0 and stop >= start"
        ) from None
    if not np.all(np.isfinite(values)):
        raise UserError(f"{option}: {text!r} has a value that is not a finite number")
    return values


def check_range(values: NDArray, lo: float, hi: float, option: str, unit: str) -> NDArray:
    """Refuse values outside `[lo, hi]` (or an empty list) with a message naming the option."""
    if values.size == 0:
        raise UserError(f"{option}: no values given")
    bad = values[(values < lo) | (values > hi) | ~np.isfinite(values)]
    if bad.size:
        raise UserError(
            f"{option}: {bad[0]:g} {unit} is outside [{lo:g}, {hi:g}] {unit}; fix the value"
        )
    return values
