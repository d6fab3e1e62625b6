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
(`_Accumulator.noise_variance`), or from the photo's noise model (`_noise`) when the caller
has one.

An ROI that shows its layer lines as stripes (`_stripes`) is measured on its pixels with the
fitted stripes subtracted; its blocks are then detrended by a quadratic surface, strips along
the layer lines may replace them (`_with_strips`), the noise the fitted stripes carry into the
mean is added (`finish_stats`), and so is, to R and B, what the stripes leave at the mosaic's
Nyquist frequency, which the two greens show (`_green_parity`). `roi_data` does the work that
needs the pixels, and `finish_stats` what needs the photo's noise model, so that the pipeline
can fit that model to all of a photo's ROIs in between.

See docs/imaging.md §Standard errors and §Layer stripes for the checks and for what they do not
cover.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from ._blockvar import (
    LEVELS,
    MAX_BLOCKS,
    BlockEstimate,
    Blocks,
    adaptive_covariance,
    curvature_f,
    edge_correlation,
)
from ._decode import RawFrame
from ._errors import ImagingError
from ._noise import NoiseModel
from ._roi import MAX_ERODE_PX, RoiMask, thickness_px
from ._stripes import MIN_FIT_STRIPS, Pixels, StripeFit, fit_stripes, strip_blocks


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
        stripes: find and fit layer stripes that the camera resolves (docs/imaging.md §Layer
            stripes); False measures every ROI as plain texture.
    """

    erode_px: int = 8
    block_px: int = 2
    saturation_level: float = 0.98
    max_saturated_fraction: float = 0.5
    min_blocks: int = 10
    stripes: bool = True

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
            (isinstance(self.stripes, bool), "stripes must be true or false"),
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
        stripe_period_px: the layer stripes' period in the image (px) when the ROI shows
            resolved layer lines and they were fitted (docs/imaging.md §Layer stripes), else NaN.
        stripe_angle_deg: the image direction across the stripes (deg from +x towards +y).
        stripe_amplitude: the stripes' relative amplitude (the fundamental's).
        stripe_offset: how far the ROI's own mean (its incomplete periods) lies above the
            period average that `mean_dn` is, relative (NaN without stripes).
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
    stripe_period_px: float = math.nan
    stripe_angle_deg: float = math.nan
    stripe_amplitude: float = math.nan
    stripe_offset: float = math.nan


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


@dataclass(frozen=True, eq=False)
class RoiData:
    """What one ROI's pixels give before the photo's noise model is known (`roi_data`).

    Attributes:
        blocks: the channels' block sums (of the de-striped pixels when stripes were fitted).
        estimate: the block covariance estimate at the chosen block size.
        base: per channel, mean and counts (`_Accumulator.stats`).
        noise_local: (3,) each channel's white-noise variance per pixel from its neighbour
            differences (DN^2; -1 where undefined).
        level: (3,) the channels' mean level (DN above black).
        weights: (3, 2) per channel sum_p w_p^2 and sum_p w_p^2 x_p for the pixel weights w_p
            by which pixel noise enters the channel's mean: 1 / N on its own pixels, plus the
            fitted stripes' coupling (`StripeFit.coupling`).
        plain: (3,) 1 / N, the same sum for the plain mean (weights 1 / N).
        stripes: the fitted stripes, or None.
        greens: with stripes, the de-striped sums of the two green sites (`_green_sites`),
            else None.
        site_factors: for an ROI too thin for the channels' planes (`THIN_SITES_PX`), per
            channel the ratio of green's mean over all the ROI's pixels to its mean at that
            channel's sites (`green_site_factors`), else None.
    """

    blocks: Blocks
    estimate: BlockEstimate
    base: tuple[ChannelStats, ChannelStats, ChannelStats]
    noise_local: np.ndarray
    level: np.ndarray
    weights: np.ndarray
    plain: np.ndarray
    stripes: StripeFit | None
    greens: GreenSites | None = None
    site_factors: SiteFactors | None = None


@dataclass(frozen=True)
class GreenSites:
    """The de-striped pixels of the two green sites of a Bayer tile (`_green_parity`).

    Attributes:
        counts: (2,) pixels of G1 (the green in R's row) and G2 (the green in B's row).
        sums: (2,) their de-striped sums (DN).
    """

    counts: np.ndarray
    sums: np.ndarray


def _green_sites(frame: RawFrame, px: Pixels, fit: StripeFit) -> GreenSites:
    """The two greens' de-striped sums (for a Bayer mosaic: `_bayer`)."""
    assert frame.cfa is not None
    (ry,), (rx,) = np.nonzero(frame.cfa == 0)
    y, x = px.y.astype(np.int64), px.x.astype(np.int64)
    green = px.good & (px.colour == 1)
    first = green & (y % 2 == ry)  # R's row, B's column
    second = green & (x % 2 == rx)  # B's row, R's column
    values = px.value - fit.periodic
    counts = np.array([first.sum(), second.sum()], dtype=np.float64)
    sums = np.array([values[first].sum(), values[second].sum()])
    return GreenSites(counts, sums)


THIN_SITES_PX = 6.0
"""An ROI thinner than this (px across, `thickness_px`) holds at most three rows or columns of
R's and of B's sites across it, too few for their planes (§Channel sites) to move their means
to the ROI's centroid; their means are then moved by green's profile (`green_site_factors`)."""


@dataclass(frozen=True)
class SiteFactors:
    """Green's profile across a thin ROI (`green_site_factors`).

    Attributes:
        factors: (3,) per channel, green's mean over all the ROI's pixels over its mean at that
            channel's sites.
        noise_gain: (3,) the relative variance of each factor per unit variance of one green
            pixel (1 / DN^2): `sum_p (a_p / g_all - b_p / g_c)^2` over the green pixels, `a_p`
            and `b_p` their weights in the two means.
    """

    factors: np.ndarray
    noise_gain: np.ndarray


def _spread(inv: np.ndarray, along_rows: bool) -> np.ndarray:
    """Per pixel, the sum of `inv` over its two neighbours along the rows (or the columns)."""
    pad = np.pad(inv, 1)
    if along_rows:
        return pad[1:-1, :-2] + pad[1:-1, 2:]
    return pad[:-2, 1:-1] + pad[2:, 1:-1]


def green_site_factors(data: np.ndarray, mask: np.ndarray, frame: RawFrame) -> SiteFactors | None:
    """Per channel, green's mean over all the ROI's pixels over green's mean at the channel's
    own sites: green at every pixel is its own value on a green site and, on an R or B site,
    the mean of its two green neighbours inside the ROI along the ROI's length (left and right
    when the ROI runs more along the rows, else above and below), which lie at the same
    position across it. A channel's mean times its factor is its mean over the whole ROI when
    the channels share one relative profile across it, however curved (a thin face's edge, a
    highlight): what a plane cannot do with one or two rows of sites (docs/imaging.md §Channel
    sites). With it, how much green's pixel noise moves each factor. None where an R or B site
    has no such neighbour or the frame is no Bayer mosaic."""
    if not _bayer(frame):
        return None
    assert frame.cfa is not None
    hb, wb = mask.shape
    yy, xx = np.mgrid[0:hb, 0:wb]
    colour = frame.cfa[yy % 2, xx % 2]
    black = frame.black[yy % 2, xx % 2].astype(np.float64)
    value = data.astype(np.float64) - black
    green = mask & (colour == 1)
    ys, xs = np.nonzero(mask)
    cov = np.cov(np.stack([xs, ys]).astype(np.float64)) if ys.size > 1 else np.eye(2)
    along_rows = bool(cov[0, 0] >= cov[1, 1])  # the ROI's length runs more along the rows
    total = _spread(np.where(green, value, 0.0), along_rows)
    count = _spread(green.astype(np.float64), along_rows)
    other = mask & (colour != 1)
    if np.any(count[other] == 0):
        return None
    inv = np.where(other, 1.0 / np.where(count > 0, count, 1.0), 0.0)
    g_at = np.where(green, value, total / np.where(count > 0, count, 1.0))
    n_all = float(mask.sum())
    g_all = float(g_at[mask].mean())
    weight_all = (green + _spread(inv, along_rows)) / n_all  # each green pixel's weight in g_all
    factors, gain = np.ones(3), np.zeros(3)
    for c in range(3):
        sites = mask & (colour == c)
        g_c = float(g_at[sites].mean()) if sites.any() else math.nan
        if not (math.isfinite(g_c) and g_c > 0 and g_all > 0):
            return None
        factors[c] = g_all / g_c
        if c == 1:
            weight_c = green / green.sum()
        else:  # each site's two green neighbours share its weight
            weight_c = _spread(np.where(sites, inv, 0.0), along_rows) / sites.sum()
        gain[c] = float(np.sum(((weight_all / g_all - weight_c / g_c) * green) ** 2))
    return SiteFactors(factors, gain)


def roi_channel_stats(
    frame: RawFrame,
    roi: RoiMask,
    settings: ExtractionSettings,
    *,
    across: np.ndarray | None = None,
    noise: NoiseModel | None = None,
) -> tuple[ChannelStats, ChannelStats, ChannelStats]:
    """R, G, B statistics of the frame's pixels inside `roi` (both greens together).

    Blocks are aligned to the image origin and hold whole CFA tiles; their side is chosen from
    the data, at least `block_size(frame, settings.block_px)` (docs/imaging.md §Standard
    errors). When the ROI shows resolved layer lines (`settings.stripes`), they are fitted and
    removed first (docs/imaging.md §Layer stripes); `across` is the image direction (x, y)
    across the layer lines when known (a face placed from markers), else it is estimated from
    the pixels. `noise` is the photo's noise model (`fit_noise_model` over its ROIs); without
    it each channel's white noise is its own neighbour-difference estimate.
    """
    return finish_stats(roi_data(frame, roi, settings, across=across), noise)


def _roi_pixels(
    data: np.ndarray, mask: np.ndarray, frame: RawFrame, box: tuple[int, int, int, int],
    settings: ExtractionSettings,
) -> tuple[Pixels, tuple[np.ndarray, np.ndarray]]:  # fmt: skip
    """The mosaic's pixels inside the ROI as `Pixels`, and their (row, column) in the box."""
    assert frame.cfa is not None
    y0, x0 = box[0], box[1]
    ys, xs = np.nonzero(mask)
    ph, pw = frame.cfa.shape
    colour = frame.cfa[(ys + y0) % ph, (xs + x0) % pw].astype(np.int64)
    black = frame.black[(ys + y0) % ph, (xs + x0) % pw].astype(np.float64)
    raw = data[ys, xs].astype(np.float64)
    white = frame.white_level
    limit = black + settings.saturation_level * (white - black)
    good = np.isfinite(raw) & (raw < limit)
    value = np.where(good, raw - black, 0.0)
    px = Pixels((xs + x0).astype(np.float64), (ys + y0).astype(np.float64), colour, value, good)
    return px, (ys, xs)


def _bayer(frame: RawFrame) -> bool:
    """Whether the frame is a mosaic with one R, two G and one B per 2 x 2 tile."""
    cfa = frame.cfa
    return cfa is not None and cfa.shape == (2, 2) and sorted(cfa.ravel().tolist()) == [0, 1, 1, 2]


def roi_data(
    frame: RawFrame, roi: RoiMask, settings: ExtractionSettings, *, across: np.ndarray | None = None
) -> RoiData:
    """The block sums, block covariance, stripes and noise ingredients of one ROI."""
    b = _start_block(roi, block_size(frame, settings.block_px))
    box, grid = _aligned_box(roi, b)
    y0, x0, hb, wb = box
    mask = _aligned_mask(roi, b, box)
    data = frame.data[y0 : y0 + hb, x0 : x0 + wb]
    if data.shape[:2] != (hb, wb):  # past the bottom or right edge: pad (outside the mask)
        pad = [(0, hb - data.shape[0]), (0, wb - data.shape[1])] + [(0, 0)] * (data.ndim - 2)
        data = np.pad(data, pad)
    periodic = None
    fit = None
    px = None
    if settings.stripes and _bayer(frame) and mask.any():
        px, (ys, xs) = _roi_pixels(data, mask, frame, box, settings)
        fit = fit_stripes(px, across)
        if fit is not None:
            periodic = np.zeros((hb, wb), dtype=np.float64)
            periodic[ys, xs] = fit.periodic
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
                    data[sub], mask[sub], float(frame.black[dy, dx]), level, white, b, ph, dy,
                    dx, None if periodic is None else periodic[sub],
                )  # fmt: skip
    step = 1 if frame.cfa is None else frame.cfa.shape[0]
    blocks = Blocks(
        np.stack([a.counts for a in acc]),
        np.stack([a.sums for a in acc]),
        np.stack([a.sum_y for a in acc]),
        np.stack([a.sum_x for a in acc]),
        acc[0].block,
    )
    # with stripes fitted, the level's curvature (a near lamp) is detrended as the stripes' fit
    # did; the plain path starts from the plane (docs/imaging.md §Standard errors)
    est = detrended_covariance(blocks, degree=2 if fit is not None else 1)
    if fit is not None and px is not None:
        est = _with_strips(est, px, fit)
    base = tuple(a.stats() for a in acc)
    noise_local = np.array([a.noise_variance(est.slopes[c], step) for c, a in enumerate(acc)])
    weights, plain, lev = _noise_weights(acc, fit, px)
    greens = _green_sites(frame, px, fit) if fit is not None and px is not None else None
    thin = fit is None and thickness_px(roi.mask) < THIN_SITES_PX
    factors = green_site_factors(data, mask, frame) if thin else None
    return RoiData(blocks, est, base, noise_local, lev, weights, plain, fit, greens, factors)  # type: ignore[arg-type]


MAX_DETREND_DEGREE = 3
"""The highest degree of the surface removed from the block means (`detrended_covariance`)."""

TREND_F = 100.0
"""A higher-degree surface is used only when its extra terms stand out this much (`curvature_f`
on green, at the block side it resolves): a near lamp's highlight gave F 106-5300 (the
variant set's faces, tests/imaging/test_blockvar.py's highlights); random texture correlated
over the ROI's own size, which such a surface would partly absorb and so hide, at most 62
(1440 ROIs of the calibration grid's cells, 2-8 px texture in 20-200 blocks)."""


def detrended_covariance(blocks: Blocks, degree: int) -> BlockEstimate:
    """`adaptive_covariance` at the lowest detrending degree, from `degree` up to
    MAX_DETREND_DEGREE, at which some channel's correlation is resolved (dof > 0) and, above
    `degree`, whose extra terms pass `TREND_F`; the first estimate when none does. A highlight
    from a near lamp curves a face's radiance beyond a plane or a quadratic: that smooth,
    deterministic change is not scatter of the mean, but left in the residuals it keeps
    neighbours correlated at every block size (docs/imaging.md §Standard errors, item 1)."""
    first = adaptive_covariance(blocks, degree=degree)
    if np.any(first.dof > 0):
        return first
    for d in range(degree + 1, MAX_DETREND_DEGREE + 1):
        est = adaptive_covariance(blocks, degree=d)
        if np.any(est.dof > 0) and curvature_f(blocks, est.size_px, d) >= TREND_F:
            return est
    return first


STRIP_OFFSETS = (0.0, 0.25, 0.5, 0.75)
"""Where the strips' edges are tried, in layers from the fitted phase's zero."""

RHO_INDEPENDENT = 0.2
"""Strips whose neighbours correlate by less than this (at the best of STRIP_OFFSETS) are taken
as independent (each holds its own layers)."""


def _with_strips(est: BlockEstimate, px: Pixels, fit: StripeFit) -> BlockEstimate:
    """The block estimate, or that of strips along the layer lines when it is larger than the
    blocks' by more than twice its own relative precision, or when the blocks could not
    resolve the correlation (docs/imaging.md §Layer stripes). Irregular layers are correlated
    along their whole line, beyond the 8 neighbours of square blocks."""
    values = px.value - fit.periodic
    options = [Blocks(*strip_blocks(px, fit, values, offset), 1) for offset in STRIP_OFFSETS]
    rho = [edge_correlation(b, degree=2, min_fit=MIN_FIT_STRIPS) for b in options]
    if all(math.isnan(r) for r in rho):
        return est
    k = int(np.nanargmin(rho))
    # strips aligned with the layers' edges are independent when each layer is its own: then
    # one covariance, about three times the degrees of freedom of a 1-dependent estimate
    strips = adaptive_covariance(
        options[k], degree=2, min_fit=MIN_FIT_STRIPS, max_rho=0.5,
        max_lag=0 if rho[k] < RHO_INDEPENDENT else 1,
    )  # fmt: skip
    g = 1  # green: the most pixels; the structure is the same in every channel
    v2, v1 = float(est.cov[g, g]), float(strips.cov[g, g])
    d2, d1 = float(est.dof[g]), float(strips.dof[g])
    if not (math.isfinite(v1) and d1 > 0):
        return est
    if not (math.isfinite(v2) and d2 > 0) or v1 > v2 * (1 + 2 * math.sqrt(2 / d1)):
        return BlockEstimate(strips.cov, strips.dof, strips.n_blocks, est.size_px, est.slopes)
    return est


def _noise_weights(
    acc: list[_Accumulator], fit: StripeFit | None, px: Pixels | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per channel (sum w^2, sum w^2 x) of the pixel weights w of its mean, 1 / N, and its
    mean level (DN). Without stripes w = 1 / N on the channel's own pixels."""
    weights = np.zeros((3, 2))
    plain = np.zeros(3)
    lev = np.full(3, math.nan)
    for c, a in enumerate(acc):
        n = float(a.counts.sum())
        if n == 0:
            continue
        lev[c] = float(a.sums.sum()) / n  # of the de-striped pixels: the period average
        plain[c] = 1.0 / n
        weights[c] = (1.0 / n, lev[c] / n)
    if fit is None or px is None:
        return weights, plain, lev
    x = np.maximum(px.value, 0.0)
    for c in range(3):
        on = px.good & (px.colour == c)
        n = int(on.sum())
        if n == 0:
            continue
        w = np.where(px.good, fit.coupling[c], 0.0)
        w[on] += 1.0 / n
        weights[c] = (float(np.sum(w * w)), float(np.sum(w * w * x)))
    return weights, plain, lev


def finish_stats(
    rd: RoiData, noise: NoiseModel | None = None
) -> tuple[ChannelStats, ChannelStats, ChannelStats]:
    """The three channels' statistics of one ROI, its pixel noise from `noise` (the photo's
    noise model) or, without one, from each channel's own neighbour differences."""
    blocks, est = rd.blocks, rd.estimate
    shifts = _centroid_shifts(blocks, est.slopes)
    fit = rd.stripes
    means, totals, noises = np.full(3, math.nan), np.full(3, math.nan), np.full(3, math.nan)
    for c, base in enumerate(rd.base):
        if base.n_pixels == 0:
            continue
        means[c] = _moved_mean(rd, c, base.mean_dn, shifts[c])
        var, nu = float(est.cov[c, c]), float(est.dof[c])
        # the variance of a pull (x - mu) / s with s^2 ~ V chi2_nu / nu is nu / (nu - 2)
        infl = nu / (nu - 2) if nu > 2 else 1.0
        total = max(var, 0.0) * infl if math.isfinite(var) else math.nan
        if noise is not None:
            w_var = noise.variance_of_mean(c, rd.weights[c, 0], rd.weights[c, 1])
            p_var = noise.variance_of_mean(c, rd.plain[c], rd.plain[c] * rd.level[c])
        elif rd.noise_local[c] >= 0:
            w_var = rd.noise_local[c] * rd.weights[c, 0]
            p_var = rd.noise_local[c] * rd.plain[c]
        else:
            w_var = p_var = math.nan
        if fit is not None and math.isfinite(total) and math.isfinite(w_var):
            # the fitted stripes move the mean by their own noise: what the pixel weights add
            # to the plain mean's noise (docs/imaging.md §Layer stripes)
            total = max(total + w_var - p_var, w_var)
        extra = _profile_variance(rd, noise, c, float(means[c]))
        total, w_var = total + extra, w_var + extra
        totals[c], noises[c] = total, w_var
    before = np.sqrt(totals)
    corrs = np.array(_correlations(est.cov))
    parity = _green_parity(rd, noise)
    if parity is not None:
        totals, extra = _parity_terms(means, totals, parity)
        # the R-B covariance that the fit builds from corr_rb and the stderrs, less the parity
        # term's (it moves R and B in opposite directions); the others keep their covariance
        after = np.sqrt(totals)
        pairs = ((0, 1), (0, 2), (1, 2))
        cov = [corrs[k] * before[a] * before[b] for k, (a, b) in enumerate(pairs)]
        cov[1] -= extra * means[0] * means[2]
        corrs = np.array(
            [np.clip(cov[k] / (after[a] * after[b]), -1, 1) for k, (a, b) in enumerate(pairs)]
        )
    corr_tuple = (float(corrs[0]), float(corrs[1]), float(corrs[2]))
    defined = [c for c in corr_tuple if math.isfinite(c)]
    mean_corr = float(np.clip(np.mean(defined), 0.0, 1.0)) if defined else math.nan
    out = []
    for c, base in enumerate(rd.base):
        if base.n_pixels == 0:
            out.append(base)
            continue
        stripe = {}
        if fit is not None:
            stripe = {
                "stripe_period_px": fit.period_px,
                "stripe_angle_deg": fit.angle_deg,
                "stripe_amplitude": fit.amplitude,
                "stripe_offset": float(fit.offset[c]),
            }
        total, w_var = float(totals[c]), float(noises[c])
        out.append(
            dataclasses.replace(
                base,
                mean_dn=float(means[c]),
                stderr_dn=math.sqrt(total) if math.isfinite(total) else math.nan,
                n_blocks=int(est.n_blocks[c]),
                channel_corr=mean_corr,
                stderr_noise_dn=math.sqrt(w_var) if w_var >= 0 else math.nan,
                dof=float(est.dof[c]),
                block_px=est.size_px,
                channel_corrs=corr_tuple,
                **stripe,
            )
        )
    return tuple(out)  # type: ignore[return-value]


def _moved_mean(rd: RoiData, c: int, plain: float, shift: float) -> float:
    """Channel c's mean moved to the whole ROI: by its plane (`_centroid_shifts`), or in an ROI
    too thin for one by green's profile (`THIN_SITES_PX`, `green_site_factors`)."""
    if rd.site_factors is None:
        return plain + shift
    return plain * float(rd.site_factors.factors[c])


def _profile_variance(rd: RoiData, noise: NoiseModel | None, c: int, mean: float) -> float:
    """The variance (DN^2) that green's pixel noise adds to channel c's mean through green's
    profile (`SiteFactors.noise_gain`; 0 without one), at the photo's noise model's variance
    for green's level, else green's own neighbour differences."""
    if rd.site_factors is None:
        return 0.0
    green_var = noise.variance(rd.level[1]) if noise is not None else rd.noise_local[1]
    extra = mean**2 * float(rd.site_factors.noise_gain[c]) * float(green_var)
    return extra if math.isfinite(extra) and extra > 0 else 0.0


def _green_parity(rd: RoiData, noise: NoiseModel | None) -> tuple[float, float] | None:
    """(d, its standard error) for an ROI with fitted stripes: d the relative difference of the
    de-striped means of the two greens, G1 (in R's row) less G2 (in B's row).

    The stripes' fit removes a pattern that is a function of the layer phase. What it leaves
    at a Nyquist frequency of the mosaic ((0, 1/2) or (1/2, 0) cycles per px) is a
    near-constant of opposite sign on the two halves of the Bayer tile (the rows, or the
    columns, of R and G1 against those of G2 and B). The channels' levels take up R's and B's
    part of it, which moves R and B apart by about d / 2 each; the two greens, one colour on
    both halves, show it as d. Seen on physically based renders of layer periods under a pixel
    (under a strong perspective) and of sharp highlights (docs/imaging.md §Layer stripes). The
    standard error is the pixel noise's (the photo's noise model or the greens' own neighbour
    differences, the larger)."""
    g = rd.greens
    if g is None or not np.all(g.counts > 0):
        return None
    level = float(g.sums.sum() / g.counts.sum())
    var = max(rd.noise_local[1], 0.0)
    if noise is not None:
        var = max(var, float(noise.variance(level)))
    if not (level > 0 and var > 0):
        return None
    m1, m2 = g.sums / g.counts
    d = float(m1 - m2) / level
    sd = math.sqrt(var * float(np.sum(1.0 / g.counts))) / level
    return d, sd


PARITY_Z = 2.0
"""The two greens' difference counts in R's and B's errors when it exceeds its noise's
standard error this many times (`_parity_terms`)."""


def _parity_terms(
    means: np.ndarray, totals: np.ndarray, parity: tuple[float, float]
) -> tuple[np.ndarray, float]:
    """R's and B's variances with the greens' parity difference (`_green_parity`) in them:
    `(d^2 - sd^2) / 4` of their values squared (d less its noise) when |d| exceeds PARITY_Z
    times its noise's standard error sd (pixel noise alone gives such a d in 5% of the ROIs;
    counting every d above sd made the errors of plain striped faces 5-8% too large), and that
    relative variance (their covariance is its negative: the pattern left at the Nyquist
    frequency moves R and B in opposite directions, by about d / 2 each)."""
    d, sd = parity
    extra = (d**2 - sd**2) / 4 if abs(d) > PARITY_Z * sd else 0.0
    totals = totals.copy()
    for c in (0, 2):
        totals[c] += extra * means[c] ** 2
    return totals, extra


def noise_points(rd: RoiData) -> list[tuple[int, float, float, float]]:
    """The ROI's (channel, mean level, white-noise variance, pixels) for a photo's noise model."""
    out = []
    for c in range(3):
        n = rd.base[c].n_pixels
        if n > 0 and rd.noise_local[c] >= 0 and math.isfinite(rd.level[c]):
            out.append((c, float(rd.level[c]), float(rd.noise_local[c]), float(n)))
    return out


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
        periodic: np.ndarray | None = None,
    ) -> None:
        """Add a sub-plane sampled every `step` pixels from offset (dy, dx) of the aligned box;
        `periodic` (DN, the fitted stripes) is subtracted from the signal, not from the test
        for saturation."""
        nby, nbx = self.grid
        self.block = block
        k = block // step  # sub-plane pixels per block side
        good = mask & (plane < black + level * (white - black))
        self.n_in += int(np.count_nonzero(mask))
        if periodic is None:
            signal = np.where(good, plane.astype(np.float32) - np.float32(black), np.float32(0))
        else:
            destriped = plane.astype(np.float64) - black - periodic
            signal = np.where(good, destriped, 0.0).astype(np.float32)
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
