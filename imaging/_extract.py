"""Per-ROI, per-channel statistics straight from the raw mosaic: mean, block standard error.

Each colour's pixels inside the eroded ROI are averaged after subtracting their black level;
saturated pixels are left out: `mean = sum_b S_b / N`, with S_b and n_b the sum and count of the
channel's unsaturated pixels in block b (square blocks of `block_px` raw pixels aligned to the
image origin) and N = sum_b n_b.

The standard error comes from the scatter of the K block means m_b = S_b / n_b, not of single
pixels, so that texture and noise correlated within a block count fully:

1. a plane a + b x + c y is fitted to the block means (weights n_b, centroids of each block's
   pixels); its intercept is the mean itself. Smooth, deterministic variation across the ROI
   (vignetting, the change of the BRDF across a face) adds no error to the mean, so it is
   removed rather than counted as scatter;
2. with block residuals e_b = n_b (m_b - plane_b), the variance of the mean is the spatial
   Bartlett-kernel (HAC) estimate over the block grid,
   `var = K / (K - 3) * sum_b sum_b' w(b - b') e_b e_b' / N^2`, with w = 1 for the block
   itself, 1/2 for its 4 edge neighbours and 1/4 for its 4 corner neighbours. The neighbour
   terms take in correlation that reaches across block borders; the weights make the estimate
   never negative.

It covers pixel noise and texture correlated over less than about a block; see
docs/imaging.md §Standard errors for the checks and for what it does not cover.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from ._decode import RawFrame
from ._errors import ImagingError
from ._roi import MAX_ERODE_PX, RoiMask


@dataclass(frozen=True)
class ExtractionSettings:
    """How pixels become measurements (the scene file's [extraction] table).

    Attributes:
        erode_px: ROI erosion radius in pixels (>= 0).
        block_px: side of the square blocks (raw pixels) whose means give the standard error;
            rounded up to a multiple of the CFA tile (2 for Bayer) so that every block holds
            whole tiles. Choose it at least 4 times the correlation length of the texture.
        saturation_level: a raw value at or above black + saturation_level * (white - black)
            counts as saturated and is left out (per pixel, with that pixel's black level).
        max_saturated_fraction: an ROI channel with a larger saturated fraction is flagged
            "saturated".
        min_blocks: an ROI channel with fewer non-empty blocks is flagged "few_blocks" (its
            standard error rests on too few independent values to be trusted).
    """

    erode_px: int = 8
    block_px: int = 8
    saturation_level: float = 0.98
    max_saturated_fraction: float = 0.5
    min_blocks: int = 10

    def __post_init__(self) -> None:
        checks = [
            (
                isinstance(self.erode_px, int) and 0 <= self.erode_px <= MAX_ERODE_PX,
                f"erode_px must be an integer in [0, {MAX_ERODE_PX}]",
            ),
            (
                isinstance(self.block_px, int) and self.block_px >= 2,
                "block_px must be an integer >= 2",
            ),
            (0.5 <= self.saturation_level <= 1.0, "saturation_level must be in [0.5, 1]"),
            (0.0 <= self.max_saturated_fraction <= 1.0, "max_saturated_fraction must be in [0, 1]"),
            (isinstance(self.min_blocks, int) and self.min_blocks >= 2, "min_blocks must be >= 2"),
        ]
        for ok, msg in checks:
            if not ok:
                raise ImagingError(f"extraction settings: {msg}")


@dataclass(frozen=True)
class ChannelStats:
    """Statistics of one colour channel inside one ROI, in DN above black (not yet exposure-scaled).

    Attributes:
        mean_dn: mean of (raw - black) over the unsaturated pixels (NaN if there are none).
        stderr_dn: its standard error from the block scatter (NaN with fewer than 2 blocks).
        n_pixels: unsaturated pixels used.
        n_blocks: non-empty blocks.
        n_in_roi: the channel's pixels inside the ROI, saturated or not.
        saturated_fraction: saturated / n_in_roi (NaN if n_in_roi is 0).
        channel_corr: mean correlation of the R, G, B errors of the mean in this ROI
            (`channel_correlation`; the same for the three channels; NaN if undefined).
    """

    mean_dn: float
    stderr_dn: float
    n_pixels: int
    n_blocks: int
    n_in_roi: int
    saturated_fraction: float
    channel_corr: float = math.nan


def block_size(frame: RawFrame, block_px: int) -> int:
    """The block side actually used: `block_px` rounded up to a multiple of the CFA tile."""
    if frame.cfa is None:
        return block_px
    tile = math.lcm(*frame.cfa.shape)
    return -(-block_px // tile) * tile


def roi_channel_stats(
    frame: RawFrame, roi: RoiMask, settings: ExtractionSettings
) -> tuple[ChannelStats, ChannelStats, ChannelStats]:
    """R, G, B statistics of the frame's pixels inside `roi` (both greens together).

    Blocks are `block_size(frame, settings.block_px)` raw pixels square, aligned to the image
    origin, so that every block holds whole CFA tiles.
    """
    b = block_size(frame, settings.block_px)
    h, w = roi.mask.shape
    by0, bx0 = roi.y0 // b, roi.x0 // b
    grid = (-(-(roi.y0 + h) // b) - by0, -(-(roi.x0 + w) // b) - bx0)
    y0, x0 = by0 * b, bx0 * b  # the block-aligned box, which may reach past the image
    hb, wb = grid[0] * b, grid[1] * b
    mask = np.zeros((hb, wb), dtype=bool)
    mask[roi.y0 - y0 : roi.y0 - y0 + h, roi.x0 - x0 : roi.x0 - x0 + w] = roi.mask
    data = frame.data[y0 : y0 + hb, x0 : x0 + wb]
    if data.shape[:2] != (hb, wb):  # past the bottom or right edge: pad (outside the mask)
        pad = [(0, hb - data.shape[0]), (0, wb - data.shape[1])] + [(0, 0)] * (data.ndim - 2)
        data = np.pad(data, pad)
    acc = [_Accumulator(grid) for _ in range(3)]
    level, white = settings.saturation_level, frame.white_level
    if frame.cfa is None:
        for c in range(3):
            acc[c].add(data[..., c], mask, float(frame.black[c]), level, white, b, 1, 0, 0)
    else:
        ph, pw = frame.cfa.shape
        for dy in range(ph):
            for dx in range(pw):
                # y0 and x0 are multiples of the tile, so tile position (dy, dx) is (y0 + dy, ...)
                c = int(frame.cfa[dy, dx])
                sub = (slice(dy, None, ph), slice(dx, None, pw))
                acc[c].add(
                    data[sub], mask[sub], float(frame.black[dy, dx]), level, white, b, ph, dy, dx
                )
    out = [a.stats() for a in acc]
    corr = channel_correlation([a.residuals() for a in acc])
    return tuple(dataclasses.replace(o, channel_corr=corr) for o in out)  # type: ignore[return-value]


class _Accumulator:
    """Per-block sums of one channel, gathered from one or more CFA sub-planes."""

    def __init__(self, grid: tuple[int, int]) -> None:
        self.grid = grid
        self.counts = np.zeros(grid)
        self.sums = np.zeros(grid)
        self.sum_y = np.zeros(grid)
        self.sum_x = np.zeros(grid)
        self.n_in = 0

    def add(
        self,
        plane: np.ndarray,
        mask: np.ndarray,
        black: float,
        level: float,
        white: float,
        block: int,
        step: int,
        dy: int,
        dx: int,
    ) -> None:
        """Add a sub-plane sampled every `step` pixels from offset (dy, dx) of the aligned box."""
        nby, nbx = self.grid
        k = block // step  # sub-plane pixels per block side
        good = mask & (plane < black + level * (white - black))
        self.n_in += int(np.count_nonzero(mask))
        signal = np.where(good, plane.astype(np.float32) - np.float32(black), np.float32(0))
        g4 = good.reshape(nby, k, nbx, k)
        counts = g4.sum(axis=(1, 3))
        self.counts += counts
        self.sums += signal.reshape(nby, k, nbx, k).sum(axis=(1, 3), dtype=np.float64)
        # pixel coordinates in the aligned box: block origin + offset inside the block
        offsets = np.arange(k) * step
        self.sum_y += np.einsum("akb,k->ab", g4.sum(axis=3), offsets + dy, dtype=np.float64)
        self.sum_y += counts * (np.arange(nby) * block)[:, None]
        self.sum_x += np.einsum("abk,k->ab", g4.sum(axis=1), offsets + dx, dtype=np.float64)
        self.sum_x += counts * (np.arange(nbx) * block)[None, :]

    def stats(self) -> ChannelStats:
        n_good = int(self.counts.sum())
        n_in = self.n_in
        if n_in == 0:
            return ChannelStats(math.nan, math.nan, 0, 0, 0, math.nan)
        sat_frac = 1.0 - n_good / n_in
        if n_good == 0:
            return ChannelStats(math.nan, math.nan, 0, 0, n_in, sat_frac)
        mean = float(self.sums.sum() / n_good)
        ok = self.counts > 0
        k = int(ok.sum())
        stderr = _block_stderr(self.counts, self.sums, self.sum_y, self.sum_x, ok)
        return ChannelStats(mean, stderr, n_good, k, n_in, sat_frac)

    def residuals(self) -> np.ndarray | None:
        """Block residual grid `e_b / N` of `_block_residuals` (None when it is undefined)."""
        ok = self.counts > 0
        if not np.any(ok):
            return None
        res = _block_residuals(self.counts, self.sums, self.sum_y, self.sum_x, ok)
        if res is None:
            return None
        grid_e, n_total, _k, _rank = res
        return grid_e / n_total


_LAG_WEIGHTS = ((0, 1, 0.5), (1, 0, 0.5), (1, 1, 0.25), (1, -1, 0.25))
"""Bartlett weights w(dy) w(dx) of the neighbouring-block covariances (one of each +- pair)."""


def _block_residuals(
    counts: np.ndarray, sums: np.ndarray, sum_y: np.ndarray, sum_x: np.ndarray, ok: np.ndarray
) -> tuple[np.ndarray, float, int, int] | None:
    """Block residuals `e_b = n_b (m_b - plane_b)` on the grid, N, K and the plane's rank.

    None when there are no more blocks than the plane has parameters (module docstring).
    """
    n = counts[ok]
    k = n.size
    n_total = float(n.sum())
    # Block means and pixel centroids; the plane a + b (x - xw) + c (y - yw) is fitted to the
    # block means with weights n, centred so that a is the ROI mean itself.
    m = sums[ok] / n
    xc = sum_x[ok] / n
    yc = sum_y[ok] / n
    design = np.stack([np.ones(k), xc - np.average(xc, weights=n), yc - np.average(yc, weights=n)])
    sw = np.sqrt(n)
    coef, _res, rank, _sv = np.linalg.lstsq((design * sw).T, m * sw, rcond=None)
    if k <= rank:
        return None
    grid_e = np.zeros(counts.shape)
    grid_e[ok] = n * (m - coef @ design)
    return grid_e, n_total, k, int(rank)


def _bartlett(a_grid: np.ndarray, b_grid: np.ndarray) -> float:
    """`sum_b sum_b' w(b - b') a_b b_b'` with the Bartlett weights (symmetrised in a, b)."""
    total = float(np.sum(a_grid * b_grid))
    h, w = a_grid.shape
    for dy, dx, wgt in _LAG_WEIGHTS:
        sl_a = (slice(0, h - dy), slice(max(0, -dx), w - max(0, dx)))
        sl_b = (slice(dy, h), slice(max(0, dx), w - max(0, -dx)))
        total += wgt * float(np.sum(a_grid[sl_a] * b_grid[sl_b]))
        total += wgt * float(np.sum(b_grid[sl_a] * a_grid[sl_b]))
    return total


def _block_stderr(
    counts: np.ndarray, sums: np.ndarray, sum_y: np.ndarray, sum_x: np.ndarray, ok: np.ndarray
) -> float:
    """Standard error of the mean from block means about a fitted plane (module docstring).

    All arrays are on the block grid; `sum_y`, `sum_x` are the sums of the pixels' coordinates
    (any common origin) in each block, `ok` marks the non-empty blocks.
    """
    res = _block_residuals(counts, sums, sum_y, sum_x, ok)
    if res is None:
        return math.nan
    grid_e, n_total, k, rank = res
    var = k / (k - rank) * max(_bartlett(grid_e, grid_e), 0.0) / n_total**2
    return math.sqrt(var)


def channel_correlation(residuals: list[np.ndarray | None]) -> float:
    """Mean pairwise correlation of the channels' errors of the mean within one ROI.

    The same Bartlett (HAC) estimate as the standard error, applied to the cross-covariance of
    two channels' block residuals: texture multiplies every channel alike, so the R, G and B
    means of one ROI err together (correlation near 1 when texture dominates, near 0 when
    pixel noise does). The mean of the defined pairs, clipped to [0, 1]; NaN when no pair is
    defined. See docs/imaging.md §Channel correlation.
    """
    corr = []
    for a in range(len(residuals)):
        for b in range(a + 1, len(residuals)):
            ea, eb = residuals[a], residuals[b]
            if ea is None or eb is None or ea.shape != eb.shape:
                continue
            vab = _bartlett(ea, eb)
            va, vb = _bartlett(ea, ea), _bartlett(eb, eb)
            if va > 0 and vb > 0:
                corr.append(vab / math.sqrt(va * vb))
    if not corr:
        return math.nan
    return float(np.clip(np.mean(corr), 0.0, 1.0))
