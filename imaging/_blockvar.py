"""The covariance of an ROI's R, G, B means from block sums (docs/imaging.md §Standard errors).

The pixels of one colour inside the ROI are summed in square blocks (sums S_b, counts n_b).
At a block size where blocks further apart than their 8 neighbours are uncorrelated (chosen
from the data, `adaptive_covariance`), the covariance of the block sums is *1-dependent*:

    Cov(S_b, S_b') = gamma_k sqrt(n_b n_b')   for b' - b in lag class k (0: the block itself,
                                              then the 4 neighbour directions of LAGS),

and the variance of the mean is `1' Sigma 1 / N^2 = sum_k gamma_k s_k / N^2`. The gammas are
estimated by the method of moments from the residuals `e = M S` of a plane fitted to the block
means (weights n_b): with q_j = e' B~_j e (B~_j: 0/1 indicator of the lag class j),
`E[q_j] = sum_k tr(B~_j M B_k M') gamma_k = (G gamma)_j` *exactly*, because the expectation of
a quadratic form in the residuals is known once the projection M is (the idea of MINQUE,
C. R. Rao, J. Multivariate Anal. 1, 257-275, 1971). Hence gamma = G^-1 q is unbiased for any
1-dependent covariance, whatever the number of blocks, and so is the variance of the mean: the
plane fit's loss of degrees of freedom, which biases kernel (HAC) estimators low in small ROIs,
is accounted for exactly rather than by a K / (K - 3) factor that holds for white noise only.
The same estimator applied to two channels' residuals gives their covariance.

The block size: starting from the finest level with at most MAX_BLOCKS blocks, coarser levels
are tried until the fitted correlation of edge neighbours is at most MAX_EDGE_RHO along both
axes (mean over the channels). For a separable Gaussian texture correlation
`exp(-r^2 / ell^2)` that happens at a block side of 1.67 ell, where the block and its 8
neighbours hold 99.5% of the texture's contribution to the variance of the mean (the rest is
what a 1-dependent model misses); for an exponential correlation `exp(-r / ell)` at 2.66 ell,
95%. Levels with fewer
than MIN_FIT_BLOCKS blocks are not fitted.

The estimate's own uncertainty is summarised by Satterthwaite's effective degrees of freedom
`nu = 2 E[V]^2 / Var(V)` (Var of the quadratic form for Gaussian data under the fitted
covariance; F. E. Satterthwaite, Biometrics Bull. 2, 110-114, 1946; for cluster-robust
variances, Bell & McCaffrey, Survey Methodology 28, 169-181, 2002).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

LAGS: tuple[tuple[int, int], ...] = ((0, 1), (1, 0), (1, 1), (1, -1))
"""The neighbour lag classes (dy, dx), one of each +- pair: left/right, up/down, two diagonals."""

LEVELS: tuple[int, ...] = (1, 2, 3, 4, 6, 8, 12, 16, 24, 32, 48, 64, 96, 128, 192, 256)
"""Block sides tried, in multiples of the base block (the CFA tile)."""

MAX_BLOCKS = 1024
"""The finest level tried is the first with at most this many non-empty blocks."""

MAX_EDGE_RHO = 0.25
"""Largest mean correlation of edge neighbours (either axis) accepted at a level."""

MIN_FIT_BLOCKS = 30
"""Levels with fewer non-empty blocks are not tried: 5 covariances fitted to fewer block
products are too noisy to say whether the correlation stays within the neighbours."""


class Blocks(NamedTuple):
    """Per-block sums of the three channels on one grid (arrays of shape (3, H, W)).

    Attributes:
        n: pixels counted in each block.
        s: their sum (DN above black).
        y, x: sums of their row and column coordinates (raw pixels, the grid's corner at 0).
        size_px: block side in raw pixels.
    """

    n: np.ndarray
    s: np.ndarray
    y: np.ndarray
    x: np.ndarray
    size_px: int


class BlockEstimate(NamedTuple):
    """The covariance of the three channel means and what it rests on.

    Attributes:
        cov: (3, 3) covariance of the R, G, B means (DN^2), unbiased; NaN where undefined.
        dof: (3,) Satterthwaite degrees of freedom of each variance (0 where undefined).
        n_blocks: (3,) non-empty blocks of each channel at the chosen size.
        size_px: the chosen block side (raw pixels).
        slopes: (3, 2) the fitted planes' gradients (d/dy, d/dx) in DN per raw pixel (NaN
            where no plane was fitted).
    """

    cov: np.ndarray
    dof: np.ndarray
    n_blocks: np.ndarray
    size_px: int
    slopes: np.ndarray


class _Fit(NamedTuple):
    """One channel's plane fit on a grid: design, (X' D X)^-1, residual block sums, weights."""

    n: np.ndarray
    r: np.ndarray  # sqrt(n)
    design: np.ndarray  # (3, H, W), zero on empty blocks
    ainv: np.ndarray  # (3, 3)
    e: np.ndarray  # residual block sums S_b - n_b plane_b
    k: int
    rank: int
    slope: tuple[float, float]  # the plane's gradient (d/dy, d/dx), DN per raw pixel


def aggregate(b: Blocks, f: int) -> Blocks:
    """Merge f x f blocks (the grid padded with empty blocks to a multiple of f)."""
    if f == 1:
        return b
    _, h, w = b.n.shape
    hp, wp = -(-h // f) * f, -(-w // f) * f

    def merge(a: np.ndarray) -> np.ndarray:
        a = np.pad(a, ((0, 0), (0, hp - h), (0, wp - w)))
        return a.reshape(3, hp // f, f, wp // f, f).sum(axis=(2, 4))

    return Blocks(merge(b.n), merge(b.s), merge(b.y), merge(b.x), b.size_px * f)


def _view(p: np.ndarray, dy: int, dx: int, m: int, shape: tuple[int, int]) -> np.ndarray:
    """u[..., y, x] = v[..., y + dy, x + dx] from p, v padded with m zero blocks (a view)."""
    return p[..., m + dy : m + dy + shape[0], m + dx : m + dx + shape[1]]


def _pad(v: np.ndarray, m: int) -> np.ndarray:
    """v with a border of m zero blocks on its last two axes."""
    h, w = v.shape[-2:]
    out = np.zeros((*v.shape[:-2], h + 2 * m, w + 2 * m))
    out[..., m : m + h, m : m + w] = v
    return out


def _shift(v: np.ndarray, dy: int, dx: int) -> np.ndarray:
    """u[..., y, x] = v[..., y + dy, x + dx] (zero outside the grid)."""
    m = max(abs(dy), abs(dx))
    return _view(_pad(v, m), dy, dx, m, v.shape[-2:]) if m else v


def _probes(v: np.ndarray) -> np.ndarray:
    """The 5 probes B~_j applied to v, stacked: the identity, then each lag class of LAGS.

    (B~_j v)[b] = v[b + lag_j] + v[b - lag_j]: the 0/1 matrix of one lag class applied to v.
    """
    p, shape = _pad(v, 1), v.shape[-2:]
    out = [v] + [_view(p, dy, dx, 1, shape) + _view(p, -dy, -dx, 1, shape) for dy, dx in LAGS]
    return np.stack(out)


def _structures(r_left: np.ndarray, r_right: np.ndarray, v: np.ndarray) -> np.ndarray:
    """B_k v for the 5 classes, B_k[b, b'] = r_left[b] r_right[b'] on lag class k (0: diagonal)."""
    return r_left * _probes(r_right * v)


def _inner(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(p, q) matrix sum_b a[p, b] b[q, b] of two stacks of grids."""
    return np.einsum("pyx,qyx->pq", a, b)


def _plane_fit(
    n: np.ndarray, s: np.ndarray, y: np.ndarray, x: np.ndarray, degree: int = 1
) -> _Fit | None:
    """Weighted least-squares plane (degree 1), quadratic (2) or cubic (3) surface through the
    block means; None if no block is left over."""
    ok = n > 0
    k = int(ok.sum())
    if k == 0:
        return None
    n_tot = float(n.sum())
    safe = np.where(ok, n, 1.0)
    yc, xc = y / safe, x / safe
    scale = max(float(np.ptp(xc[ok])), float(np.ptp(yc[ok])), 1.0)
    u = np.where(ok, (xc - x.sum() / n_tot) / scale, 0.0)
    v = np.where(ok, (yc - y.sum() / n_tot) / scale, 0.0)
    terms = [ok.astype(float), u, v]
    if degree >= 2:
        terms += [u * u, u * v, v * v]
    if degree >= 3:
        terms += [u * u * u, u * u * v, u * v * v, v * v * v]
    design = np.stack(terms)
    xtdx = _inner(design * n, design)
    lam, vec = np.linalg.eigh(xtdx)
    keep = lam > 1e-12 * lam[-1]  # a row or column of blocks leaves one slope undefined
    rank = int(keep.sum())
    if k <= rank:
        return None
    ainv = (vec[:, keep] / lam[keep]) @ vec[:, keep].T  # the pseudo-inverse
    coef = ainv @ np.einsum("pyx,yx->p", design, s)
    e = np.where(ok, s - n * np.einsum("p,pyx->yx", coef, design), 0.0)
    return _Fit(n, np.sqrt(n), design, ainv, e, k, rank, (coef[2] / scale, coef[1] / scale))


def _moment_matrix(fa: _Fit, fb: _Fit) -> tuple[np.ndarray, np.ndarray]:
    """G[j, k] = tr(B~_j M_a B_k M_b') for the 5 probes j and classes k, and s_k = 1'B_k 1.

    With P = D X (X'DX)^-1 X' and M = I - P, `tr(B~ M_a B M_b') = tr(B~ B) - tr(B~ P_a B)
    - tr(B~ B P_b') + tr(B~ P_a B P_b')`; P has rank 3, so every term is a 3 x 3 product of
    grids (module docstring).
    """
    xa, xb = fa.design, fb.design
    ks = range(1 + len(LAGS))
    pa = _probes(fa.n * xa)  # B~_j D_a X_a, (5, 3, H, W)
    pb = _probes(fb.n * xb)  # B~_j D_b X_b
    bk_xb = _structures(fa.r, fb.r, xb)  # B^ab_k X_b
    bkt_xa = _structures(fb.r, fa.r, xa)  # B^ba_k X_a = (B^ab_k)' X_a
    s = _structures(fa.r, fb.r, np.ones_like(fa.n)).sum(axis=(1, 2))
    flat = (len(ks), -1)
    # tr(A_a (B'X_a)' B~ D_a X_a) and tr(A_b (B~ D_b X_b)' B X_b), all (j, k) at once
    t1 = np.einsum("pq,jqyx->jpyx", fa.ainv, pa).reshape(flat) @ bkt_xa.reshape(flat).T
    t2 = np.einsum("pq,kqyx->kpyx", fb.ainv, bk_xb).reshape(flat) @ pb.reshape(flat).T
    c = np.einsum("pyx,kqyx->kpq", xa, bk_xb)  # X_a' B_k X_b
    e = np.einsum("pyx,jqyx->jpq", fb.n * xb, pa)  # X_b' D_b B~_j D_a X_a
    t3 = np.einsum("ab,kbc,cd,jda->jk", fa.ainv, c, fb.ainv, e)
    return np.diag(s) - t1 - t2.T + t3, s


def _quadratic(fa: _Fit, fb: _Fit) -> np.ndarray:
    """q_j = e_a' B~_j e_b for the 5 probes."""
    return np.einsum("yx,jyx->j", fa.e, _probes(fb.e))


_BAND_LAGS: tuple[tuple[int, int], ...] = tuple((dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1))
"""The 9 lags of a 1-dependent band (the block and its 8 neighbours)."""


def _class_of(lag: tuple[int, int]) -> int:
    """The lag class (0: the block itself, k: LAGS[k - 1]) of a lag or its opposite."""
    if lag == (0, 0):
        return 0
    neg = (-lag[0], -lag[1])
    return 1 + (LAGS.index(lag) if lag in LAGS else LAGS.index(neg))


def _model_gamma(gamma: np.ndarray) -> np.ndarray:
    """The gammas of the working covariance: gamma_0 >= 0, neighbour correlations in [0, 1]."""
    g0 = max(float(gamma[0]), 0.0)
    rho = np.clip(np.asarray(gamma[1:]) / g0, 0.0, 1.0) if g0 > 0 else np.zeros(len(LAGS))
    return np.concatenate([[g0], g0 * rho])


def _sigma_band(gamma: np.ndarray, f: _Fit) -> np.ndarray:
    """The fitted 1-dependent covariance of one channel's block sums: (9, H, W) over _BAND_LAGS.

    Entry [l, b] is Sigma[b, b + lag_l] = gamma_k r_b r_(b + lag). The neighbour correlations
    are clipped to [0, 1]: a noisy negative estimate would make the estimate look more precise
    than it is (texture and noise correlate neighbours positively or not at all).
    """
    coef = _model_gamma(gamma)
    p, shape = _pad(f.r, 1), f.r.shape
    return np.stack([coef[_class_of(lag)] * f.r * _view(p, *lag, 1, shape) for lag in _BAND_LAGS])


def _quad_form_var(c: np.ndarray, sigma: np.ndarray) -> float:
    """tr(Q Sigma Q Sigma) = Var(e' Q e) / 2 for Gaussian e, Q = sum_j c_j B~_j.

    Sigma as `_sigma_band`; F = Q Sigma is a band of lags up to 2:
    F[b, b + d] = sum_h Q[b, b + h] Sigma[b + h, b + d], and tr(F F) = sum_d sum_b
    F[b, b + d] F[b + d, b].
    """
    shape = sigma.shape[-2:]
    lags2 = [(dy, dx) for dy in range(-2, 3) for dx in range(-2, 3)]
    index = {lag: i for i, lag in enumerate(lags2)}
    f = np.zeros((len(lags2), *shape))
    sp = _pad(sigma, 1)
    for h in _BAND_LAGS:
        shifted = _view(sp, *h, 1, shape)  # Sigma[b + h, b + h + k] for every k
        rows = [index[(h[0] + k[0], h[1] + k[1])] for k in _BAND_LAGS]
        f[rows] += c[_class_of(h)] * shifted
    fp = _pad(f, 2)
    return float(
        sum(np.sum(f[index[d]] * _view(fp[index[(-d[0], -d[1])]], *d, 2, shape)) for d in lags2)
    )


class _ChannelLevel(NamedTuple):
    """One channel at one level: the moment system, the gammas and V N^2 = s' gamma."""

    g: np.ndarray
    s: np.ndarray
    gamma: np.ndarray
    v: float

    @property
    def edge_rho(self) -> np.ndarray:
        """Correlation of the edge neighbours along x and along y (gamma_k / gamma_0)."""
        g0 = self.gamma[0]
        return self.gamma[1:3] / g0 if g0 > 0 else np.zeros(2)  # no scatter: nothing to resolve


def _active(s: np.ndarray, max_lag: int = 1) -> list[int]:
    """The lag classes that have block pairs (the others are left out of the system); only the
    block itself (class 0) when `max_lag` is 0 (blocks taken as independent)."""
    return [k for k in range(len(s) if max_lag else 1) if s[k] > 0]


def _solve_gamma(
    g: np.ndarray, q: np.ndarray, s: np.ndarray, max_lag: int = 1
) -> np.ndarray | None:
    """gamma = G^-1 q over the active lag classes (the others are 0); None if singular."""
    act = _active(s, max_lag)
    try:
        sol = np.linalg.solve(g[np.ix_(act, act)], q[act])
    except np.linalg.LinAlgError:
        return None
    if not np.all(np.isfinite(sol)):
        return None
    gamma = np.zeros(len(s))
    gamma[act] = sol
    return gamma


def _channel_level(
    f: _Fit, min_fit: int = MIN_FIT_BLOCKS, max_lag: int = 1
) -> _ChannelLevel | None:
    """The 1-dependent (`max_lag` 0: independent) fit of one channel's block residuals (None
    with too few blocks)."""
    if f.k < min_fit:
        return None
    g, s = _moment_matrix(f, f)
    gamma = _solve_gamma(g, _quadratic(f, f), s, max_lag)
    if gamma is None:
        return None
    if not max_lag:
        s = np.where(np.arange(len(s)) == 0, s, 0.0)  # V counts the block itself only
    return _ChannelLevel(g, s, gamma, float(s @ gamma))


def _dof(f: _Fit, lv: _ChannelLevel) -> float:
    """Satterthwaite's nu = 2 E[V]^2 / Var(V) for V = c'q, under the fitted covariance.

    Var(e'Qe) = 2 tr(Q Sigma Q Sigma) for Gaussian residuals (the projection's O(1/K) effect
    on the variance is neglected). E[V] and Var(V) are both taken under the working covariance
    (`_model_gamma`), so that nu depends on the estimated correlations only, not on the chance
    scatter of V itself (a V low by chance would otherwise look imprecise).
    """
    if lv.v <= 0:
        return 0.0
    act = _active(lv.s)
    c = np.zeros(len(lv.s))  # V N^2 = c' q
    c[act] = np.linalg.solve(lv.g[np.ix_(act, act)].T, lv.s[act])
    model = _model_gamma(lv.gamma)
    var_v = 2 * _quad_form_var(c, _sigma_band(lv.gamma, f))
    return 2 * float(lv.s @ model) ** 2 / var_v if var_v > 0 else 0.0


def _start_factor(base: Blocks) -> int:
    """The first level (factor of LEVELS) with at most MAX_BLOCKS non-empty blocks."""
    occupied = (base.n.sum(axis=0) > 0).astype(np.int64)[None]
    for f in LEVELS:
        ones = Blocks(occupied, occupied, occupied, occupied, base.size_px)
        if int((aggregate(ones, f).n[0] > 0).sum()) <= MAX_BLOCKS:
            return f
    return LEVELS[-1]


def _fits(blocks: Blocks, degree: int = 1) -> list[_Fit | None]:
    return [
        _plane_fit(blocks.n[c], blocks.s[c], blocks.y[c], blocks.x[c], degree) for c in range(3)
    ]


def adaptive_covariance(
    base: Blocks,
    degree: int = 1,
    min_fit: int = MIN_FIT_BLOCKS,
    max_rho: float = MAX_EDGE_RHO,
    max_lag: int = 1,
) -> BlockEstimate:
    """The covariance of the three channel means at the block size the data call for.

    Levels (LEVELS x the base block) are tried from the first with at most MAX_BLOCKS blocks;
    the first at which edge neighbours are correlated by at most MAX_EDGE_RHO is used. When
    even the coarsest level with MIN_FIT_BLOCKS blocks fails that, the estimate is returned
    with dof 0 (the texture is correlated over more than the ROI allows to measure).
    `degree` 2 (3) detrends the block means by a quadratic (cubic) surface instead of a plane
    (a near lamp's fall-off, a radiance that changes steeply across a face); the moments stay
    exact.
    `min_fit` is the fewest blocks a level needs (MIN_FIT_BLOCKS for a 2-D grid; a row of
    strips has 2 covariances to fit instead of 5 and needs fewer), `max_rho` the largest edge
    correlation accepted (strips of whole layers may share a layer with their neighbours and
    no further one: their covariance is 1-dependent at any neighbour correlation up to 0.5).
    `max_lag` 0 takes the blocks as independent (strips aligned with the layers, whose
    neighbours were found uncorrelated): one covariance to fit, about 3 times the degrees of
    freedom.
    """
    f0 = _start_factor(base)
    chosen = None
    for f in (f for f in LEVELS if f >= f0 and f % f0 == 0):
        blocks = aggregate(base, f)
        fits = _fits(blocks, degree)
        levels = [_channel_level(x, min_fit, max_lag) if x is not None else None for x in fits]
        if chosen is not None and all(lv is None for lv in levels):
            break  # too few blocks to go coarser: keep the last level
        chosen = (blocks, fits, levels)
        if _resolved(levels, max_rho):
            break
    blocks, fits, levels = chosen  # type: ignore[misc]
    return _estimate(blocks, fits, levels, _resolved(levels, max_rho), max_lag)


def _resolved(levels: list[_ChannelLevel | None], max_rho: float = MAX_EDGE_RHO) -> bool:
    """Whether the correlation at this level stays within the 8 neighbours (module docstring)."""
    ok = [lv for lv in levels if lv is not None]
    if not ok:
        return True
    rho = np.mean([lv.edge_rho for lv in ok], axis=0)
    return float(np.max(rho)) <= max_rho


def _estimate(
    blocks: Blocks,
    fits: list[_Fit | None],
    levels: list[_ChannelLevel | None],
    resolved: bool,
    max_lag: int = 1,
) -> BlockEstimate:
    """The 3 x 3 covariance of the means at one level (variances from `levels`)."""
    n_tot = blocks.n.sum(axis=(1, 2))
    cov = np.full((3, 3), math.nan)
    dof = np.zeros(3)
    for a in range(3):
        lv, fa = levels[a], fits[a]
        if lv is not None and fa is not None:
            cov[a, a] = lv.v / n_tot[a] ** 2
            dof[a] = _dof(fa, lv) if resolved else 0.0
        for b in range(a + 1, 3):
            fb = fits[b]
            if fa is None or fb is None or levels[a] is None or levels[b] is None:
                continue
            g, s = _moment_matrix(fa, fb)
            gamma = _solve_gamma(g, _quadratic(fa, fb), s, max_lag)
            if gamma is not None:
                cov[a, b] = cov[b, a] = float(s @ gamma) / (n_tot[a] * n_tot[b])
    n_blocks = np.array([int((blocks.n[c] > 0).sum()) for c in range(3)])
    slopes = np.array([f.slope if f is not None else (math.nan, math.nan) for f in fits])
    return BlockEstimate(cov, dof, n_blocks, blocks.size_px, slopes)


def curvature_f(base: Blocks, size_px: int, degree: int, channel: int = 1) -> float:
    """The F statistic of the terms a `degree` surface adds to the plane through one channel's
    block means at the block side `size_px`: (the weighted residual sum of squares the terms
    remove, per term) over (what the surface leaves, per remaining degree of freedom). NaN
    when either fit is undefined or leaves no degree of freedom."""
    b = aggregate(base, max(1, size_px // base.size_px))
    n, s, y, x = b.n[channel], b.s[channel], b.y[channel], b.x[channel]
    plane, surface = _plane_fit(n, s, y, x, 1), _plane_fit(n, s, y, x, degree)
    if plane is None or surface is None or surface.k <= surface.rank or surface.rank <= plane.rank:
        return math.nan
    ok = n > 0

    def rss(f: _Fit) -> float:
        return float(np.sum(np.where(ok, f.e**2 / np.where(ok, n, 1.0), 0.0)))

    removed, left = rss(plane) - rss(surface), rss(surface)
    if not left > 0:
        return math.inf if removed > 0 else math.nan
    return (removed / (surface.rank - plane.rank)) / (left / (surface.k - surface.rank))


def edge_correlation(base: Blocks, degree: int = 1, min_fit: int = MIN_FIT_BLOCKS) -> float:
    """The mean correlation of edge neighbours (either axis, the larger) at the base level,
    over the channels that can be fitted; NaN when none can."""
    levels = [_channel_level(f, min_fit) if f is not None else None for f in _fits(base, degree)]
    ok = [lv for lv in levels if lv is not None and lv.gamma[0] > 0]
    if not ok:
        return math.nan
    return float(np.max(np.mean([lv.edge_rho for lv in ok], axis=0)))
