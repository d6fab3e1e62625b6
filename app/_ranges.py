"""Parsing of angle and wavelength lists given on the command line (degrees, nanometres)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from .errors import UserError


def parse_values(text: str, option: str) -> NDArray:
    """`"10,20,30"` or `"start:stop:step"` (stop included when on the grid) to a float array."""
    text = text.strip()
    try:
        if ":" in text:
            parts = [float(p) for p in text.split(":")]
            if len(parts) != 3 or parts[2] <= 0 or parts[1] < parts[0]:
                raise ValueError
            start, stop, step = parts
            count = int(np.floor((stop - start) / step + 1e-9)) + 1
            return start + step * np.arange(count)
        return np.array([float(p) for p in text.split(",") if p.strip()], dtype=float)
    except ValueError:
        raise UserError(
            f"{option}: cannot read {text!r}; give a comma list such as '10,20,30' or a range "
            "'start:stop:step' with step > 0 and stop >= start"
        ) from None


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
