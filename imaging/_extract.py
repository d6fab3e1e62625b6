"""Per-ROI, per-channel statistics straight from the raw mosaic: mean and standard errors.

Each colour's pixels inside the eroded ROI are averaged after subtracting their black level;
saturated pixels are left out: `mean = sum_b S_b / N`, with S_b and n_b the sum and count of the
channel's unsaturated pixels in block b (square blocks aligned to the image origin, whole CFA
tiles) and N = sum_b n_b.

The standard error comes from the scatter of block sums, not of single pixels, so that texture
and noise correlated over several pixels count fully (`_blockvar`): a plane is fitted to the
block means (smooth, deterministic variation across the ROI adds no error to the mean); the
covariances of the residual block sums with themselves and their 8 neighbours are estimated
without bias, at a block size chosen from the data so that blocks further apart are
uncorrelated; their sum is the variance of the mean, with Satterthwaite degrees of freedom.
The same moments of two channels give the R, G, B covariance of the ROI.

The white-noise part of the error (shot, read and quantisation noise, which differ between
photos) comes from the differences of neighbouring same-colour pixels
(`_Accumulator.noise_variance`).

See docs/imaging.md §Standard errors for the checks and for what it does not cover.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from ._blockvar import LEVELS, MAX_BLOCKS, Blocks, adaptive_covariance
from ._decode import RawFrame
from ._errors import ImagingError
from ._roi import MAX_ERODE_PX, RoiMask


@dataclass(frozen=True)
class ExtractionSettings:
    """How pixels become measurements (the scene file's [extraction] table).

    Attributes:
        erode_px: ROI erosion radius in pixels (>= 0).
        block_px: the smallest side of the square blocks (raw pixels) whose sums give the
            standard error, rounded up to a multiple of the CFA tile (2 for Bayer) so that
            every block holds whole tiles. Larger blocks are chosen from the data where the
            texture needs them (docs/imaging.md §Standard errors); the default, one tile,
            lets small ROIs of fine texture keep the most blocks.
        saturation_level: a raw value at or above black + saturation_level * (white - black)
            counts as saturated and is left out (per pixel, with that pixel's black level).
        max_saturated_fraction: an ROI channel with a larger saturated fraction is flagged
            "saturated".
        min_blocks: an ROI channel whose standard error has fewer degrees of freedom
            (`ChannelStats.dof`: effectively independent blocks) is flagged "few_blocks": the
            ROI is too small for its texture to estimate its error.
    """

    erode_px: int = 8
    block_px: int = 2
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
        stderr_dn: its standard error, noise and texture (`_blockvar`), including the
            uncertainty of its own estimate: `sqrt(V nu / (nu - 2))` for an unbiased variance
            estimate V with nu degrees of freedom (NaN when undefined).
        n_pixels: unsaturated pixels used.
        n_blocks: non-empty blocks at the block size chosen for the standard error.
        n_in_roi: the channel's pixels inside the ROI, saturated or not.
        saturated_fraction: saturated / n_in_roi (NaN if n_in_roi is 0).
        channel_corr: mean correlation of the R, G, B errors of the mean in this ROI (the mean
            of `channel_corrs`, clipped to [0, 1]; the same for the three channels; NaN if
            undefined).
        stderr_noise_dn: the part of the standard error due to pixel noise that is white
            (independent from pixel to pixel): shot, read and quantisation noise, which differ
            between photos (docs/imaging.md §Standard errors); NaN if undefined.
        dof: Satterthwaite degrees of freedom of the variance estimate (0 when the error
            cannot be estimated from this ROI).
        block_px: the block side chosen for the standard error (raw pixels).
        channel_corrs: correlations of the errors of the (R, G), (R, B) and (G, B) means.
    """

    mean_dn: float
    stderr_dn: float
    n_pixels: int
    n_blocks: int
    n_in_roi: int
    saturated_fraction: float
    channel_corr: float = math.nan
    stderr_noise_dn: float = math.nan
    dof: float = 0.0
    block_px: int = 0
    channel_corrs: tuple[float, float, float] = (math.nan, math.nan, math.nan)


def block_size(frame: RawFrame, block_px: int) -> int:
    """The smallest block side used: `block_px` rounded up to a multiple of the CFA tile."""
    if frame.cfa is None:
        return block_px
    tile = math.lcm(*frame.cfa.shape)
    return -(-block_px // tile) * tile


def _start_block(roi: RoiMask, base: int) -> int:
    """The first block side (base x LEVELS) at which the ROI touches at most MAX_BLOCKS blocks."""
    for f in LEVELS:
        b = base * f
        if roi.n_pixels > MAX_BLOCKS * b * b * 4:
            continue  # certainly more blocks than that
        box, _ = _aligned_box(roi, b)
        mask = _aligned_mask(roi, b, box)
        hb, wb = mask.shape
        touched = mask.reshape(hb // b, b, wb // b, b).any(axis=(1, 3))
        if int(touched.sum()) <= MAX_BLOCKS:
            return b
    return base * LEVELS[-1]


def _aligned_box(roi: RoiMask, b: int) -> tuple[tuple[int, int, int, int], tuple[int, int]]:
    """(y0, x0, height, width) of the box of whole b x b blocks holding the ROI, and its grid."""
    h, w = roi.mask.shape
    by0, bx0 = roi.y0 // b, roi.x0 // b
    grid = (-(-(roi.y0 + h) // b) - by0, -(-(roi.x0 + w) // b) - bx0)
    return (by0 * b, bx0 * b, grid[0] * b, grid[1] * b), grid


def _aligned_mask(roi: RoiMask, b: int, box: tuple[int, int, int, int]) -> np.ndarray:
    y0, x0, hb, wb = box
    h, w = roi.mask.shape
    mask = np.zeros((hb, wb), dtype=bool)
    mask[roi.y0 - y0 : roi.y0 - y0 + h, roi.x0 - x0 : roi.x0 - x0 + w] = roi.mask
    return mask


def roi_channel_stats(
    frame: RawFrame, roi: RoiMask, settings: ExtractionSettings
) -> tuple[ChannelStats, ChannelStats, ChannelStats]:
    """R, G, B statistics of the frame's pixels inside `roi` (both greens together).

    Blocks are aligned to the image origin and hold whole CFA tiles; their side is chosen from
    the data, at least `block_size(frame, settings.block_px)` (docs/imaging.md §Standard
    errors).
    """
    b = _start_block(roi, block_size(frame, settings.block_px))
    box, grid = _aligned_box(roi, b)
    y0, x0, hb, wb = box
    mask = _aligned_mask(roi, b, box)
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
    step = 1 if frame.cfa is None else frame.cfa.shape[0]
    return _channel_stats(acc, step)


def _channel_stats(
    acc: list[_Accumulator], step: int
) -> tuple[ChannelStats, ChannelStats, ChannelStats]:
    """The three channels' statistics from their accumulated blocks."""
    blocks = Blocks(
        np.stack([a.counts for a in acc]),
        np.stack([a.sums for a in acc]),
        np.stack([a.sum_y for a in acc]),
        np.stack([a.sum_x for a in acc]),
        acc[0].block,
    )
    est = adaptive_covariance(blocks)
    corrs = _correlations(est.cov)
    defined = [c for c in corrs if math.isfinite(c)]
    mean_corr = float(np.clip(np.mean(defined), 0.0, 1.0)) if defined else math.nan
    shifts = _centroid_shifts(blocks, est.slopes)
    out = []
    for c, a in enumerate(acc):
        base = a.stats()
        if base.n_pixels == 0:
            out.append(base)
            continue
        base = dataclasses.replace(base, mean_dn=base.mean_dn + shifts[c])
        var, nu = float(est.cov[c, c]), float(est.dof[c])
        # the variance of a pull (x - mu) / s with s^2 ~ V chi2_nu / nu is nu / (nu - 2)
        infl = nu / (nu - 2) if nu > 2 else 1.0
        stderr = math.sqrt(max(var, 0.0) * infl) if math.isfinite(var) else math.nan
        noise = a.noise_variance(est.slopes[c], step)
        out.append(
            dataclasses.replace(
                base,
                stderr_dn=stderr,
                n_blocks=int(est.n_blocks[c]),
                channel_corr=mean_corr,
                stderr_noise_dn=math.sqrt(noise / base.n_pixels) if noise >= 0 else math.nan,
                dof=nu,
                block_px=est.size_px,
                channel_corrs=corrs,
            )
        )
    return tuple(out)  # type: ignore[return-value]


def _centroid_shifts(blocks: Blocks, slopes: np.ndarray) -> np.ndarray:
    """Per channel, what its fitted plane adds between its own pixels' centroid and the
    centroid of all the ROI's pixels: `slope . (c_all - c_channel)` (DN; 0 where no plane).

    The colours of a mosaic sit at different sites of the CFA tile (RGGB: R's centroid half a
    pixel up and left of the tile's centre, B's half a pixel down and right), so under a
    gradient across the ROI each channel's plain mean is the radiance at a slightly different
    point. Adding this term evaluates every channel's plane at one common point, the ROI's
    centroid, where the model evaluates the face (docs/imaging.md §Channel sites: without it,
    the demo's photos show an R minus B residual at the truth of a few 1e-4).
    """
    n = blocks.n.sum(axis=(1, 2))
    total = float(n.sum())
    if total == 0:
        return np.zeros(3)
    safe = np.where(n > 0, n, 1.0)
    own = np.stack([blocks.y.sum(axis=(1, 2)) / safe, blocks.x.sum(axis=(1, 2)) / safe], axis=1)
    common = np.array([blocks.y.sum() / total, blocks.x.sum() / total])
    shift = np.einsum("cd,cd->c", slopes, common[None, :] - own)
    return np.where((n > 0) & np.isfinite(shift), shift, 0.0)


def _correlations(cov: np.ndarray) -> tuple[float, float, float]:
    """(R, G), (R, B), (G, B) correlations from a covariance (NaN where undefined)."""
    out = []
    for a, b in ((0, 1), (0, 2), (1, 2)):
        d = cov[a, a] * cov[b, b]
        ok = math.isfinite(cov[a, b]) and math.isfinite(d) and d > 0
        out.append(float(np.clip(cov[a, b] / math.sqrt(d), -1.0, 1.0)) if ok else math.nan)
    return out[0], out[1], out[2]


_NUGGET_LAGS: tuple[tuple[int, int], ...] = ((0, 1), (1, 0), (1, 1), (1, -1))
"""Sub-plane lags of the noise estimate: two along the axes, two diagonal (x the CFA step)."""

NUGGET_PAIRS = 1 << 16
"""About this many pixel pairs per lag and sub-plane are used for the noise estimate."""


class _Accumulator:
    """Per-block sums of one channel, gathered from one or more CFA sub-planes.

    Besides the block sums it keeps, per lag of `_NUGGET_LAGS`, the sums of the differences of
    neighbouring same-colour pixels (both unsaturated, both in the ROI), their squares and
    their number, from which `noise_variance` estimates the white-noise variance.
    """

    def __init__(self, grid: tuple[int, int]) -> None:
        self.grid = grid
        self.block = 0
        self.counts = np.zeros(grid)
        self.sums = np.zeros(grid)
        self.sum_y = np.zeros(grid)
        self.sum_x = np.zeros(grid)
        self.n_in = 0
        self.diff = np.zeros((len(_NUGGET_LAGS), 3))  # per lag: pairs, sum d, sum d^2

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
        self.block = block
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
        self._add_differences(signal, good)

    def _add_differences(self, signal: np.ndarray, good: np.ndarray) -> None:
        h, w = signal.shape
        # every m-th row is plenty for a large ROI: NUGGET_PAIRS pairs fix g to ~1%
        m = max(1, int(np.count_nonzero(good)) // NUGGET_PAIRS)
        for i, (ly, lx) in enumerate(_NUGGET_LAGS):
            a = (slice(0, h - ly, m), slice(max(0, -lx), w - max(0, lx)))
            b = (slice(ly, h, m), slice(max(0, lx), w - max(0, -lx)))
            both = good[a] & good[b]
            d = np.where(both, signal[a] - signal[b], np.float32(0))
            self.diff[i] += (
                np.count_nonzero(both),
                np.sum(d, dtype=np.float64),
                np.sum(d * d, dtype=np.float64),
            )

    def noise_variance(self, slope: np.ndarray, step: int) -> float:
        """White-noise variance per pixel (DN^2) from neighbour differences; -1 if undefined.

        The semivariance `g(h) = E[(x_p - x_p+h)^2] / 2` of the plane-detrended pixels is
        `sigma_w^2 + sigma_t^2 (1 - rho_t(h))` for white noise sigma_w and a texture with
        correlation rho_t. With g1 at the axis lags (step px) and g2 at the diagonal ones
        (step sqrt 2 px), `2 g1 - g2` removes a texture term proportional to |h|^2, that of any
        texture smooth at the scale of the lag (docs/imaging.md §Standard errors).
        """
        g = []
        for i, (ly, lx) in enumerate(_NUGGET_LAGS):
            pairs, s1, s2 = self.diff[i]
            if pairs == 0 or not np.all(np.isfinite(slope)):
                return -1.0
            t = float(slope[0] * ly * step + slope[1] * lx * step)  # E[x_p - x_p+h] = -t
            g.append((s2 + 2 * t * s1 + t * t * pairs) / (2 * pairs))
        g1, g2 = (g[0] + g[1]) / 2, (g[2] + g[3]) / 2
        return float(min(max(2 * g1 - g2, 0.0), g1))

    def stats(self) -> ChannelStats:
        """Mean, counts and saturation (the standard error is filled in by the caller)."""
        n_good = int(self.counts.sum())
        n_in = self.n_in
        if n_in == 0:
            return ChannelStats(math.nan, math.nan, 0, 0, 0, math.nan)
        sat_frac = 1.0 - n_good / n_in
        if n_good == 0:
            return ChannelStats(math.nan, math.nan, 0, 0, n_in, sat_frac)
        mean = float(self.sums.sum() / n_good)
        return ChannelStats(mean, math.nan, n_good, int((self.counts > 0).sum()), n_in, sat_frac)
