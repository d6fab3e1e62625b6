"""Mitsuba's continuous 2-D sample warping (`MarginalContinuous2D0`, mitsuba3
`include/mitsuba/core/distr_2d.h`, `Marginal2D<Float, 0, true>`) for many points at once.

The RGL tables (`_rgl.tabulate`) must hold the model at the light directions Mitsuba's
`measured` plugin will look up, i.e. where its `vndf` warp sends the sample grid's nodes.
Mitsuba's scalar Python binding warps one point per call (1.4 million calls per table); its
vectorised variants need LLVM. This is the same algorithm in float32 numpy, step by step:
the conditional and marginal CDFs of the bilinear density (accumulated in float64, stored in
float32, normalised), the row by binary search in the marginal CDF and the linear segment
inverted (`sample_segment`), then the column likewise in the conditional CDF interpolated
between the row's two rows. tests/app/test_render_rgl.py checks it against Mitsuba's own class.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

F32 = np.float32
EPSILON = F32(2.0**-24)
"""drjit's `Epsilon<float>`; samples are held inside `[EPSILON, 1 - EPSILON]`."""
ONE_MINUS_EPSILON = np.nextafter(F32(1.0), F32(0.0))


def _cdfs(data: NDArray) -> tuple[NDArray, NDArray, NDArray]:
    """The normalised density `(h, w)`, conditional CDFs `(h, w - 1)` and marginal CDF
    `(h - 1,)`, float32, as Mitsuba's constructor builds them (`normalize=True`)."""
    h, w = data.shape
    d = data.astype(np.float64)
    cond = np.cumsum((0.5 / (w - 1)) * (d[:, :-1] + d[:, 1:]), axis=1)
    sums = cond[:, -1]
    marg = np.cumsum((0.5 / (h - 1)) * (sums[:-1] + sums[1:]))
    norm = F32(1.0 / marg[-1])
    return (data.astype(F32) * norm, cond.astype(F32) * norm, marg.astype(F32) * norm)


def _search(cdf: NDArray, x: NDArray, end: int) -> NDArray:
    """drjit's `binary_search(0, end, cdf[idx] < x)` over rows of nondecreasing `cdf`
    `(N, n)` (or one `(n,)`): the first index whose value is not below `x`, at most `end`."""
    below = cdf < x[:, None]
    return np.minimum(np.sum(below, axis=-1), end)


def _segment(sample: NDArray, inv_width: NDArray, v0: NDArray, v1: NDArray) -> NDArray:
    """Mitsuba's `sample_segment`: the position in `[0, 1]` of a linear density from `v0` to
    `v1` over a segment of width `1 / inv_width` at which its integral reaches `sample`."""
    non_const = np.abs(v0 - v1) > F32(1e-4) * (v0 + v1)
    divisor = np.where(non_const, v0 - v1, v0 + v1)
    s = sample * (F32(2.0) * inv_width)
    root = v0 - np.sqrt(np.maximum(v0 * v0 + s * (v1 - v0), F32(0.0)))
    s = np.where(non_const, root, s)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(divisor != 0.0, s / np.where(divisor != 0.0, divisor, F32(1.0)), s)


def _fma(a: NDArray, b: NDArray, c: NDArray) -> NDArray:
    """`a b + c` rounded once to float32, as a fused multiply-add (the float32 product is
    exact in float64)."""
    return (np.asarray(a, np.float64) * b + np.asarray(c, np.float64)).astype(F32)


def _lerp(a: NDArray, b: NDArray, t: NDArray) -> NDArray:
    """drjit's `lerp`: `fmadd(b, t, fnmadd(a, t, a))`."""
    return _fma(b, t, _fma(-a, t, a))


def sample_continuous(data: NDArray, points: NDArray) -> tuple[NDArray, NDArray]:
    """Mitsuba's `MarginalContinuous2D0(data, normalize=True).sample(p)` for every point `p`
    `(N, 2)` of the unit square: the warped points `(N, 2)` and their densities `(N,)`,
    float32. `data` `(h, w)`: the density at the nodes, rows along the second coordinate."""
    pdf, cond, marg = _cdfs(np.asarray(data))
    h, w = pdf.shape
    inv = np.array([w - 1, h - 1], F32)
    p = np.clip(np.asarray(points, F32), EPSILON, ONE_MINUS_EPSILON)
    sx, sy = p[:, 0], p[:, 1]
    row = _search(marg, sy, h - 2)
    sy = sy - np.where(row > 0, marg[np.maximum(row - 1, 0)], F32(0.0))
    r0, r1 = cond[row, -1], cond[row + 1, -1]
    sy = _segment(sy, inv[1], r0, r1)
    sx = sx * _lerp(r0, r1, sy)
    c_row = _lerp(cond[row], cond[row + 1], sy[:, None])
    col = _search(c_row, sx, w - 2)  # Mitsuba's end is w - 1, reached only past the total
    prev = np.take_along_axis(c_row, np.maximum(col - 1, 0)[:, None], axis=1)[:, 0]
    sx = sx - np.where(col > 0, prev, F32(0.0))
    c0 = _lerp(pdf[row, col], pdf[row + 1, col], sy)
    c1 = _lerp(pdf[row, col + 1], pdf[row + 1, col + 1], sy)
    sx = _segment(sx, inv[0], c0, c1)
    patch = F32(1.0) / inv
    warped = np.stack([(col.astype(F32) + sx) * patch[0], (row.astype(F32) + sy) * patch[1]],
                      axis=-1)  # fmt: skip
    return warped.astype(F32), _lerp(c0, c1, sx).astype(F32)
