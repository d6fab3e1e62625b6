"""`stairfit predict`'s options checked before any work: ranges, contradictions, table size.

Every numeric option must be finite and in range; options that would be silently ignored by the
chosen output (`--sigma-deg` with `--lobes`, ...) or that contradict each other (`--n` with
`--material`, `--lobes` with `--diffuse`) are refused; a table larger than `MAX_ROWS` is refused
up front instead of running for minutes (README "stairfit predict"). Each mistake is one line.
"""

from __future__ import annotations

import argparse
import cmath
import math
from collections.abc import Iterable, Sequence
from typing import Protocol

from ..errors import UserError

MAX_ROWS = 1_000_000
"""The largest CSV table `predict` writes: a million rows of the density take tens of seconds
and most of a gigabyte (benchmarks/bench_limits.py, benchmarks/results/limits.md); split a
larger request into several."""

SIGMA_MAX_DEG = 90.0
"""Broadening beyond this is no longer a lobe: the truncated Gaussian is flat over +-90 deg."""


class RowWriter(Protocol):
    """What `csv.writer` returns, as far as `predict` uses it."""

    def writerow(self, row: Iterable[object], /) -> object: ...


class Given(argparse.Action):
    """Store an option's value and note in `namespace.given` that the user gave it.

    Lets `predict` refuse an option that has no effect on the chosen output, while `--help`
    still shows its default.
    """

    def __call__(
        self,
        parser: argparse.ArgumentParser,
        namespace: argparse.Namespace,
        values: object,
        option_string: str | None = None,
    ) -> None:
        setattr(namespace, self.dest, values)
        namespace.given = frozenset(getattr(namespace, "given", frozenset()) | {self.dest})


def check_combination(args: argparse.Namespace) -> None:
    """Refuse options that contradict each other or have no effect on the chosen output."""
    given = getattr(args, "given", frozenset())
    conflicts = [
        (args.lobes and args.diffuse, "--lobes with --diffuse: choose one of the two tables"),
        (
            args.cosine_weighted and not args.diffuse,
            "--cosine-weighted weights the diffuse integral only; add --diffuse or drop it",
        ),
        (
            args.n is not None and "material" in given,
            "--n with --material: --n replaces the material's index; give only one of them",
        ),
        (
            args.lobes and "sigma_deg" in given and args.sigma_deg != 0,
            "--sigma-deg with --lobes: the lobes are sharp (broadening does not change them); "
            "drop --sigma-deg, or leave out --lobes for the broadened density",
        ),
        (
            args.lobes and "theta_o_deg" in given,
            "--theta-o-deg with --lobes: each lobe has its own direction theta_o; drop "
            "--theta-o-deg, or leave out --lobes for the density at given angles",
        ),
        (
            args.diffuse and "theta_i_deg" in given,
            "--theta-i-deg with --diffuse: the diffuse integral runs over every theta_i; drop "
            "--theta-i-deg",
        ),
    ]
    for bad, message in conflicts:
        if bad:
            raise UserError(message)


def check_number(value: float, option: str, lo: float, hi: float, unit: str = "") -> float:
    """`value` if it is finite and in `[lo, hi]`, else a one-line UserError naming `option`."""
    u = f" {unit}" if unit else ""
    if not math.isfinite(value):
        raise UserError(f"{option}: must be a finite number, not {value}")
    if not lo <= value <= hi:
        raise UserError(f"{option}: {value:g}{u} is outside [{lo:g}, {hi:g}]{u}; fix the value")
    return value


def check_scalars(args: argparse.Namespace) -> None:
    """The single-number options: finite and in range."""
    check_number(args.layer_um, "--layer-um", 1.0, 10_000.0, "um")
    check_number(args.delta_n, "--delta-n", -1.0, 1.0)
    if args.sigma_deg < 0:
        raise UserError(
            f"--sigma-deg: must be >= 0 (0 means the sharp model), not {args.sigma_deg:g}"
        )
    check_number(args.sigma_deg, "--sigma-deg", 0.0, SIGMA_MAX_DEG, "deg")
    if args.n is not None:
        parse_index(args.n)


def parse_index(text: str) -> complex:
    """`--n`: a finite complex index with 1 < Re n <= 10 and 0 <= Im n <= 10 [conventions §6]."""
    try:
        n = complex(text.replace(" ", ""))
    except ValueError:
        raise UserError(f"--n: cannot read {text!r}; give e.g. 1.46 or 1.5+0.01j") from None
    if not cmath.isfinite(n):
        raise UserError(f"--n: {text!r} is not a finite number; give e.g. 1.46 or 1.5+0.01j")
    if not (1.0 < n.real <= 10.0 and 0.0 <= n.imag <= 10.0):
        raise UserError(
            f"--n: {text!r} is outside 1 < Re(n) <= 10, 0 <= Im(n) <= 10 (docs/conventions.md §6)"
        )
    return n


def check_size(counts: Sequence[tuple[str, int]], per_row: int) -> None:
    """Refuse a table of more than `MAX_ROWS` rows; `counts` are (name, values) per axis."""
    rows = per_row
    for _, n in counts:
        rows *= n
    if rows > MAX_ROWS:
        axes = " x ".join(f"{n:,} {name if n != 1 else name.rstrip('s')}" for name, n in counts)
        extra = f" x {per_row} lobes" if per_row > 1 else ""
        raise UserError(
            f"the table would have {rows:,} rows ({axes}{extra}); the limit is {MAX_ROWS:,}: "
            "use coarser steps, or split the request into several runs"
        )
