"""Layer stripes that the camera resolves: found in an ROI, fitted, and removed from its pixels.

A face whose layer period spans a few pixels shows stripes along its layer lines, sampled by the
pixel grid and, per colour, by the sub-lattices of the Bayer mosaic: red sites on even rows and
columns, blue on odd ones. A plain mean over one colour's sites then depends on which phases of
the stripes those sites happen to sample (R and B of a grey face disagree), and an ROI's edges
cut the stripes in incomplete periods. Both are removed by fitting the stripes
(docs/imaging.md §Layer stripes):

    x_p = m_c(q_p) (1 + P_c(phi_p, q_p))

for pixel p of colour c at q_p = p - the ROI's centroid: `m_c = a_c (1 + q' C q) + b_c . q` the
channel's level (a near lamp's gradient and curvature), P the pattern across a layer, a Fourier
series in the
layer phase `phi = 2 pi (nu . q + q' K q / 2)` with zero mean: harmonics shared by the three
channels (multiplicative: a grey face's stripes are the same in every channel, relatively),
their first two with amplitudes that change linearly across the ROI, plus R's and B's own
deviations for the harmonics that their sites sample evenly (a coloured body under a white
highlight). `nu` is the wave vector of the layer lines in cycles per pixel (the true one when
the direction across the layers is known, otherwise the alias nearest zero; on the pixel grid
both give the same phases), `K` a chirp (perspective changes the period across a face and turns
the lines). The fitted periodic part `m_c P_c` is what the caller subtracts from each pixel
(`StripeFit.periodic`): the de-striped mean of a colour is its period-averaged level, what a
model of the face predicts, whatever phases its sites sample.

The stripes are found in the green sites alone (a quincunx lattice that sees every stripe
orientation, including the 2-px period that puts red and blue sites on opposite phases): the
highest peak of their periodogram, if it stands `DETECT_RATIO` times above the periodogram's
median around it and at the same distance from zero (a random texture does not). The fit is
Gauss-Newton on all parameters (phase included) over at most `FIT_PIXELS` pixels; its harmonics
are those of wavelength at least 0.4 px, at most `max_harmonics`, less those that the pixel grid
folds onto the smooth level (`_orders`), and then the shorter ones (up to order `MAX_ORDER`) that
its residuals show (`_extra_orders`: a sharp highlight without lens blur keeps them after the
pixel's square, and one folded near a Bayer Nyquist frequency splits R from B).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

MIN_PERIOD_PX = 0.9
"""The shortest true layer period looked for, when the direction across the layers is known."""

MAX_PERIOD_PX = 16.0
"""The longest period looked for (px): longer stripes are left to the block errors."""

MIN_PERIODS = 4.0
"""Stripes are fitted only when the ROI holds at least this many periods across the layers."""

DETECT_RATIO = 40.0
"""A periodogram peak counts as stripes when it is this many times its local median: for a
Gaussian texture or noise the ratio exceeds 40 with probability ~1e-12 per frequency."""

FIT_PIXELS = 12_000
"""At most this many pixels (an even sample of the ROI) are used to fit the pattern."""

MIN_FIT_PIXELS = 400
"""An ROI with fewer pixels is not searched for stripes."""

MIN_AMPLITUDE = 1e-4
"""Stripes whose harmonics are all weaker than this (relative) are not fitted: they cannot
matter, and a noiseless test image would otherwise show stripes of rounding error."""

GRADIENT_HARMONICS = 2
"""Harmonics whose amplitude may change linearly across the ROI (lamp, viewing angle)."""

MAX_ORDER = 64
"""The highest harmonic tested beyond the fitted ones (`_extra_orders`)."""

EXTRA_Z = 5.0
"""A harmonic beyond the fitted ones is added when its amplitude, fitted to the residuals with
the channels' levels, stands this many standard errors above zero."""

EXTRA_MIN_CYCLES = 4.0
"""... and when the pixel grid folds it to at least this many cycles across the ROI (fewer, it
is a change of the level, which the fit cannot tell from the face's own)."""


@dataclass(frozen=True)
class Pixels:
    """The used pixels of one ROI, flattened.

    Attributes:
        x, y: image coordinates (px, pixel centres).
        colour: 0 R, 1 G, 2 B.
        value: DN above black.
        good: unsaturated (the saturated ones are not fitted).
    """

    x: np.ndarray
    y: np.ndarray
    colour: np.ndarray
    value: np.ndarray
    good: np.ndarray


@dataclass(frozen=True)
class StripeFit:
    """Stripes fitted in one ROI.

    Attributes:
        nu: (2,) wave vector (cycles per px, along image x and y) at `origin`.
        curvature: (2, 2) K of the phase `2 pi (nu . q + q' K q / 2)`.
        origin: (2,) the ROI's centroid (x, y), where q = 0.
        harmonics: the number of harmonics fitted.
        period_px: 1 / |nu| (the true period when the direction was known, else the alias's).
        angle_deg: image direction of nu (across the layer lines), from +x towards +y.
        amplitude: the fundamental's relative amplitude in the shared pattern.
        levels: (3,) a_c, the channels' period-averaged levels at the centroid (DN).
        periodic: (n,) the fitted periodic part m_c P_c at every pixel of `Pixels` (DN).
        offset: (3,) the fitted pattern's mean over all the ROI's pixels relative to a_c: how
            far the ROI's own mean radiance (incomplete periods at its edges) lies from the
            period average.
        coupling: (3, n) per channel, the pixel weights by which the fitted pattern's own noise
            moves the channel's de-striped mean (first order; `StripeFit.noise_weights`).
        ratio: the detection's peak-to-median ratio.
    """

    nu: np.ndarray
    curvature: np.ndarray
    origin: np.ndarray
    harmonics: int
    period_px: float
    angle_deg: float
    amplitude: float
    levels: np.ndarray
    periodic: np.ndarray
    offset: np.ndarray
    coupling: np.ndarray
    ratio: float


# --- detection ------------------------------------------------------------------------------------


def _box_image(px: Pixels, sel: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, int, int]:
    """values at the selected pixels placed in their bounding box (zeros elsewhere)."""
    xs, ys = px.x[sel].astype(int), px.y[sel].astype(int)
    x0, y0 = int(xs.min()), int(ys.min())
    img = np.zeros((int(ys.max()) - y0 + 1, int(xs.max()) - x0 + 1))
    img[ys - y0, xs - x0] = values
    return img, x0, y0


def _plane_residual(x: np.ndarray, y: np.ndarray, v: np.ndarray) -> np.ndarray:
    design = np.stack([np.ones_like(x), x - x.mean(), y - y.mean()], axis=1)
    coef = np.linalg.lstsq(design, v, rcond=None)[0]
    return v - design @ coef


def _fft_size(n: int) -> int:
    """A size at least twice n (zero padding) made of small factors."""
    target = 2 * n if n < 512 else n + 64
    size = 8
    while size < target:
        size *= 2
    for cand in (size * 3 // 4, size * 5 // 8):
        if cand >= target:
            size = cand
    return size


def _periodogram(px: Pixels) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The periodogram of the green sites (relative, plane removed): (power, fx, fy) with the
    frequencies in cycles per px of the full grid, fftshifted."""
    sel = (px.colour == 1) & px.good
    if sel.sum() < MIN_FIT_PIXELS // 2:
        return None
    v = px.value[sel].astype(np.float64)
    mean = float(v.mean())
    if not mean > 0:
        return None
    rel = _plane_residual(px.x[sel].astype(float), px.y[sel].astype(float), v / mean)
    img, _, _ = _box_image(px, sel, rel)
    h, w = img.shape
    fh, fw = _fft_size(h), _fft_size(w)
    spec = np.fft.fftshift(np.abs(np.fft.fft2(img, s=(fh, fw))) ** 2)
    fy = np.fft.fftshift(np.fft.fftfreq(fh))
    fx = np.fft.fftshift(np.fft.fftfreq(fw))
    return spec, fx, fy


def _wrap(v: np.ndarray) -> np.ndarray:
    """Frequencies wrapped into [-0.5, 0.5) (the full pixel grid's aliases)."""
    return v - np.round(v)


def _local_ratio(
    spec: np.ndarray, fx: np.ndarray, fy: np.ndarray, iy: int, ix: int, pad: tuple[float, float]
) -> float:
    """The peak's power over the larger of two medians: of the periodogram around it (a square
    of a few resolution cells, less the peak's own) and of the ring of frequencies as far from
    zero as the peak (a random texture is isotropic or nearly: its power at that distance in
    every direction; a texture's steep spectrum would otherwise stand out against the weaker
    frequencies beside it)."""
    h, w = spec.shape
    ry, rx = max(2, round(2 * pad[0])), max(2, round(2 * pad[1]))
    wy, wx = max(12, round(10 * pad[0])), max(12, round(10 * pad[1]))
    ys = np.arange(iy - wy, iy + wy + 1) % h
    xs = np.arange(ix - wx, ix + wx + 1) % w
    win = spec[np.ix_(ys, xs)]
    dy = np.abs(np.arange(-wy, wy + 1))[:, None]
    dx = np.abs(np.arange(-wx, wx + 1))[None, :]
    local = float(np.median(win[(dy > ry) | (dx > rx)]))
    radius = np.hypot(fx[None, :], fy[:, None])
    cell = 2 * max(fx[1] - fx[0], fy[1] - fy[0]) * max(pad)
    ring = np.abs(radius - radius[iy, ix]) <= cell
    ring &= np.hypot(fx[None, :] - fx[ix], fy[:, None] - fy[iy]) > cell
    ring &= np.hypot(fx[None, :] + fx[ix], fy[:, None] + fy[iy]) > cell  # its mirror image
    around = float(np.median(spec[ring])) if ring.any() else 0.0
    med = max(local, around)
    return float(spec[iy, ix]) / med if med > 0 else math.inf


def _candidates(
    px: Pixels, across: np.ndarray | None, extent: float
) -> tuple[list[np.ndarray], float] | None:
    """Wave vectors (cycles/px) that may be the stripes', and the highest peak's ratio; None
    when the green sites show no peak standing DETECT_RATIO above its surroundings.

    Each peak of the green sites' periodogram is one frequency on their lattice, which has
    two on the full grid (nu and nu + (0.5, 0.5): red and blue sites tell them apart), and
    along a known direction possibly several true frequencies; all are returned for the fit to
    choose from, with the peak's half frequency (a pattern whose fundamental is weaker than its
    second harmonic).
    """
    got = _periodogram(px)
    if got is None:
        return None
    spec, fx, fy = got
    h, w = spec.shape
    pad = (h / max(1.0, np.ptp(px.y) + 1), w / max(1.0, np.ptp(px.x) + 1))
    nu_min = max(1.0 / MAX_PERIOD_PX, MIN_PERIODS / max(extent, 1.0))
    step = (fx[1] - fx[0], fy[1] - fy[0])

    def index(nu: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        al = _wrap(nu)
        ix = np.clip(np.round((al[..., 0] - fx[0]) / step[0]).astype(int), 0, w - 1)
        iy = np.clip(np.round((al[..., 1] - fy[0]) / step[1]).astype(int), 0, h - 1)
        return iy, ix

    if across is not None:
        # the true wave vector lies along `across`, f from 1/MAX_PERIOD to 1/MIN_PERIOD
        f = np.arange(nu_min, 1.0 / MIN_PERIOD_PX, 0.25 / max(extent, 1.0))
        if f.size == 0:  # narrower across the layers than MIN_PERIODS of the shortest period
            return None
        line = f[:, None] * across[None, :]
        iy, ix = index(line)
        power = spec[iy, ix]
        k = int(np.argmax(power))
        ratio = _local_ratio(spec, fx, fy, int(iy[k]), int(ix[k]), pad)
        if not ratio >= DETECT_RATIO:
            return None
        # the lines' direction may be a little off (a pose, perspective): climb to the
        # periodogram's local maximum near the line's best point
        cy, cx = _climb(spec, int(iy[k]), int(ix[k]), 3 * max(1, round(max(pad))))
        peak = _refine_peak(spec, fx, fy, cy, cx)
        # every f along the line whose alias on the green lattice is this peak
        hits = [j for j in range(f.size) if power[j] >= 0.5 * power[k]]
        out = []
        for j in hits:
            for shift in (np.zeros(2), np.array([0.5, 0.5])):
                d = _wrap(peak + shift - line[j])
                if np.hypot(*d) < 0.2 * float(np.hypot(*line[j])) + 2 * max(step):
                    out.append(line[j] + d)
        out = _distinct(out) or [line[k]]
        out += [v / 2 for v in out if np.hypot(*v) / 2 >= nu_min]
        return out, ratio
    gx, gy = np.meshgrid(fx, fy)
    far = np.hypot(gx, gy) >= nu_min
    far &= np.hypot(*_wrap(np.stack([gx - 0.5, gy - 0.5]))) >= nu_min
    masked = np.where(far, spec, 0.0)
    iy0, ix0 = np.unravel_index(int(np.argmax(masked)), masked.shape)
    ratio = _local_ratio(spec, fx, fy, int(iy0), int(ix0), pad)
    if not ratio >= DETECT_RATIO:
        return None
    best = _refine_peak(spec, fx, fy, int(iy0), int(ix0))
    out = [best, _wrap(best + 0.5)]
    out += [v / 2 for v in out if np.hypot(*v) / 2 >= nu_min]
    return _distinct(out), ratio


def _climb(spec: np.ndarray, iy: int, ix: int, reach: int) -> tuple[int, int]:
    """The local maximum of `spec` reached from (iy, ix) by steps to the largest neighbour,
    at most `reach` steps."""
    h, w = spec.shape
    for _ in range(reach):
        ys = np.arange(iy - 1, iy + 2) % h
        xs = np.arange(ix - 1, ix + 2) % w
        win = spec[np.ix_(ys, xs)]
        j = int(np.argmax(win))
        if j == 4:
            break
        iy, ix = int(ys[j // 3]), int(xs[j % 3])
    return iy, ix


def _distinct(vs: list[np.ndarray]) -> list[np.ndarray]:
    """The wave vectors without near repeats (the same up to sign within 1e-3 cycles/px)."""
    out: list[np.ndarray] = []
    for v in vs:
        if all(min(np.hypot(*(v - u)), np.hypot(*(v + u))) > 1e-3 for u in out):
            out.append(v)
    return out


def _refine_peak(spec: np.ndarray, fx: np.ndarray, fy: np.ndarray, iy: int, ix: int) -> np.ndarray:
    """The peak's frequency (x, y) by a parabola through it and its neighbours on each axis."""
    h, w = spec.shape

    def vertex(a: float, b: float, c: float) -> float:
        den = a - 2 * b + c
        return 0.5 * (a - c) / den if den < 0 else 0.0

    la = np.log(np.maximum(spec, 1e-300))
    dx = vertex(la[iy, (ix - 1) % w], la[iy, ix], la[iy, (ix + 1) % w])
    dy = vertex(la[(iy - 1) % h, ix], la[iy, ix], la[(iy + 1) % h, ix])
    return np.array([fx[ix] + dx * (fx[1] - fx[0]), fy[iy] + dy * (fy[1] - fy[0])])


# --- the fit -------------------------------------------------------------------------------------


LEVEL_PARAMS = 12
"""a_c (3), b_c (3 x 2) and the shared relative curvature of the level (3: xx, xy, yy)."""


@dataclass
class _Design:
    """The model's columns for a set of pixels at given parameters.

    Attributes:
        cols: (n, k) the Jacobian of x-hat in theta.
        model: (n,) x-hat.
        periodic: (n,) the periodic part m P.
        dperiodic: (n, k) the Jacobian of m P in theta (the level columns less d m).
    """

    cols: np.ndarray
    model: np.ndarray
    periodic: np.ndarray
    dperiodic: np.ndarray


class _Layout:
    """Where each parameter sits in the parameter vector: the levels, the shared harmonics of
    `orders` (their first GRADIENT_HARMONICS with amplitudes changing across the ROI), R's and
    B's own harmonics (`colour`), the phase."""

    def __init__(self, orders: tuple[int, ...], colour: dict[int, list[int]]) -> None:
        self.orders = orders
        self.harmonics = len(orders)
        self.colour = colour
        k = LEVEL_PARAMS
        self.shared = k
        k += 2 * self.harmonics
        self.gradient = k
        self.n_grad = min(GRADIENT_HARMONICS, self.harmonics)
        k += 4 * self.n_grad
        self.colour_start: dict[int, int] = {}
        for c in (0, 2):
            self.colour_start[c] = k
            k += 2 * len(colour.get(c, []))
        self.phase = k
        k += 5
        self.size = k


def _phase(q: np.ndarray, nu: np.ndarray, kmat: np.ndarray) -> np.ndarray:
    """2 pi (nu . q + q' K q / 2) for q (n, 2) = (x, y)."""
    qx, qy = q[:, 0], q[:, 1]
    quad = kmat[0, 0] * qx**2 + 2 * kmat[0, 1] * qx * qy + kmat[1, 1] * qy**2
    return 2 * np.pi * (q @ nu + 0.5 * quad)


def _design(
    q: np.ndarray, colour: np.ndarray, theta: np.ndarray, lay: _Layout, nu: np.ndarray,
    kmat: np.ndarray, scale: float, jacobian: bool = True,
) -> _Design:  # fmt: skip
    """The model at theta for pixels at q (n, 2) of the given colours, and its Jacobian."""
    n = q.shape[0]
    qs = q / scale
    phi = _phase(q, nu, kmat)
    orders = lay.orders
    hmax = len(orders)
    top = max([*orders, *(h for c in (0, 2) for h in lay.colour.get(c, []))], default=1)
    every_c = np.empty((top, n))
    every_s = np.empty((top, n))
    c1, s1 = np.cos(phi), np.sin(phi)
    ch, sh = c1, s1
    for h in range(top):  # cos(h phi), sin(h phi) by the angle-addition recursion
        every_c[h], every_s[h] = ch, sh
        ch, sh = ch * c1 - sh * s1, sh * c1 + ch * s1
    idx = np.asarray(orders, dtype=int) - 1
    cos, sin = every_c[idx], every_s[idx]
    onehot = np.stack([colour == c for c in range(3)]).astype(float)  # (3, n)
    a = onehot.T @ theta[0:3]
    b = theta[3:9].reshape(3, 2)
    quad_terms = np.stack([qs[:, 0] ** 2, qs[:, 0] * qs[:, 1], qs[:, 1] ** 2])  # (3, n)
    curv = 1 + theta[9:12] @ quad_terms
    m = a * curv + np.einsum("cn,cd,nd->n", onehot, b, qs)
    al = theta[lay.shared : lay.shared + 2 * hmax].reshape(hmax, 2)
    harm = np.asarray(orders, dtype=float)
    pat = al[:, 0] @ cos + al[:, 1] @ sin
    dpat = (harm * al[:, 1]) @ cos - (harm * al[:, 0]) @ sin
    g = theta[lay.gradient : lay.gradient + 4 * lay.n_grad].reshape(lay.n_grad, 2, 2)
    for h in range(lay.n_grad):
        amp_c = g[h, 0] @ qs.T  # the cos amplitude's change across the ROI
        amp_s = g[h, 1] @ qs.T
        pat = pat + amp_c * cos[h] + amp_s * sin[h]
        dpat = dpat + orders[h] * (amp_s * cos[h] - amp_c * sin[h])
    full, dfull = pat.copy(), dpat.copy()
    for c in (0, 2):
        start = lay.colour_start[c]
        for j, h in enumerate(lay.colour.get(c, [])):
            e, z = theta[start + 2 * j], theta[start + 2 * j + 1]
            full += onehot[c] * (e * every_c[h - 1] + z * every_s[h - 1])
            dfull += onehot[c] * h * (z * every_c[h - 1] - e * every_s[h - 1])
    one_p = 1 + full
    if not jacobian:
        empty = np.zeros((n, 0))
        return _Design(empty, m * one_p, m * full, empty)
    dm = np.zeros((n, lay.size))
    for c in range(3):
        dm[:, c] = onehot[c] * curv
        dm[:, 3 + 2 * c] = onehot[c] * qs[:, 0]
        dm[:, 4 + 2 * c] = onehot[c] * qs[:, 1]
    dm[:, 9:12] = (a * quad_terms).T
    cols = dm * one_p[:, None]
    for h in range(hmax):
        cols[:, lay.shared + 2 * h] = m * cos[h]
        cols[:, lay.shared + 2 * h + 1] = m * sin[h]
    for h in range(lay.n_grad):
        base = lay.gradient + 4 * h
        cols[:, base + 0] = m * qs[:, 0] * cos[h]
        cols[:, base + 1] = m * qs[:, 1] * cos[h]
        cols[:, base + 2] = m * qs[:, 0] * sin[h]
        cols[:, base + 3] = m * qs[:, 1] * sin[h]
    for c in (0, 2):
        start = lay.colour_start[c]
        for j, h in enumerate(lay.colour.get(c, [])):
            cols[:, start + 2 * j] = m * onehot[c] * every_c[h - 1]
            cols[:, start + 2 * j + 1] = m * onehot[c] * every_s[h - 1]
    # phase: d phi / d (nu_x, nu_y) = 2 pi q (steps in units of 1 / scale), d / dK likewise
    dphi = m * dfull * 2 * np.pi
    p0 = lay.phase
    cols[:, p0 + 0] = dphi * qs[:, 0]
    cols[:, p0 + 1] = dphi * qs[:, 1]
    cols[:, p0 + 2] = dphi * 0.5 * qs[:, 0] ** 2
    cols[:, p0 + 3] = dphi * qs[:, 0] * qs[:, 1]
    cols[:, p0 + 4] = dphi * 0.5 * qs[:, 1] ** 2
    return _Design(cols, m * one_p, m * full, cols - dm)


def _solve(cols: np.ndarray, r: np.ndarray, damping: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares step and the pseudo-inverse of the (column-scaled) normal matrix."""
    norm = np.sqrt(np.sum(cols * cols, axis=0))
    norm = np.where(norm > 0, norm, 1.0)
    cs = cols / norm
    ata = cs.T @ cs
    lam, vec = np.linalg.eigh(ata + damping * np.diag(np.diag(ata)))
    keep = lam > 1e-10 * lam[-1]
    inv = (vec[:, keep] / lam[keep]) @ vec[:, keep].T
    step = inv @ (cs.T @ r)
    return step / norm, inv / np.outer(norm, norm)


COLOUR_HARMONICS = 4
"""R's and B's own deviations from the shared pattern are fitted up to this harmonic."""


def _colour_harmonics(q: np.ndarray, colour: np.ndarray, nu: np.ndarray, kmat: np.ndarray,
                      orders: tuple[int, ...]) -> dict[int, list[int]]:  # fmt: skip
    """For R and B, the harmonics whose phases their own sites sample evenly enough that a
    channel-specific amplitude costs its mean at most 10% more variance."""
    out: dict[int, list[int]] = {}
    phi = _phase(q, nu, kmat)
    for c in (0, 2):
        sel = colour == c
        if sel.sum() < 20:
            out[c] = []
            continue
        qc = q[sel] - q[sel].mean(axis=0)
        keep = []
        for h in (h for h in orders if h <= COLOUR_HARMONICS):
            design = np.column_stack(
                [np.ones(sel.sum()), qc, np.cos(h * phi[sel]), np.sin(h * phi[sel])]
            )
            ata = design.T @ design
            try:
                inv = np.linalg.inv(ata)
            except np.linalg.LinAlgError:
                continue
            vif = inv[0, 0] * sel.sum()
            if vif < 1.1:
                keep.append(h)
        out[c] = keep
    return out


@dataclass(frozen=True)
class _Start:
    """A fit's parameters (`theta` in layout `lay`) and the amplitudes (cos, sin) of harmonics
    it lacks, to start a fit with more harmonics from."""

    theta: np.ndarray
    lay: _Layout
    added: dict[int, tuple[float, float]]

    def embed(self, lay: _Layout) -> np.ndarray:
        """The parameters in `lay`: the levels, each harmonic's amplitudes (shared, their
        change across the ROI, R's and B's own) where the fit had it, the added ones', phase
        steps zero."""
        old, theta = self.lay, np.zeros(lay.size)
        theta[:LEVEL_PARAMS] = self.theta[:LEVEL_PARAMS]
        for j, h in enumerate(lay.orders):
            k = lay.shared + 2 * j
            if h in old.orders:
                i = old.shared + 2 * old.orders.index(h)
                theta[k : k + 2] = self.theta[i : i + 2]
            elif h in self.added:
                theta[k : k + 2] = self.added[h]
        for g in range(min(lay.n_grad, old.n_grad)):
            if lay.orders[g] == old.orders[g]:
                i, k = old.gradient + 4 * g, lay.gradient + 4 * g
                theta[k : k + 4] = self.theta[i : i + 4]
        for c in (0, 2):
            mine, theirs = lay.colour.get(c, []), old.colour.get(c, [])
            for j, h in enumerate(mine):
                if h in theirs:
                    i = old.colour_start[c] + 2 * theirs.index(h)
                    k = lay.colour_start[c] + 2 * j
                    theta[k : k + 2] = self.theta[i : i + 2]
        return theta


def _fit(
    q: np.ndarray, colour: np.ndarray, v: np.ndarray, nu: np.ndarray,
    orders: tuple[int, ...], scale: float, iterations: int = 8,
    kmat: np.ndarray | None = None, start: _Start | None = None,
) -> tuple[np.ndarray, _Layout, np.ndarray, np.ndarray, float] | None:  # fmt: skip
    """Gauss-Newton from the wave vector nu (and chirp K, default none): (theta, layout, nu,
    K, rss) or None. `start`: a fit with fewer harmonics to start from (`_Start`)."""
    kmat = np.zeros((2, 2)) if kmat is None else kmat
    lay = _Layout(orders, _colour_harmonics(q, colour, nu, kmat, orders))
    if start is not None:
        theta = start.embed(lay)
    else:
        theta = np.zeros(lay.size)
        for c in range(3):  # start: each channel's plane, no curvature
            sel = colour == c
            if sel.sum() < 3:
                return None
            design = np.column_stack([np.ones(sel.sum()), q[sel] / scale])
            coef = np.linalg.lstsq(design, v[sel], rcond=None)[0]
            theta[c], theta[3 + 2 * c : 5 + 2 * c] = coef[0], coef[1:]
        # the pattern alone, linear given the levels and the phase
        d = _design(q, colour, theta, lay, nu, kmat, scale)
        sl = slice(lay.shared, lay.shared + 2 * lay.harmonics)
        step, _ = _solve(d.cols[:, sl], v - d.model)
        theta[sl] = step
    rss = math.inf
    damping = 1e-3
    for _ in range(iterations):
        d = _design(q, colour, theta, lay, nu, kmat, scale)
        r = v - d.model
        rss_now = float(r @ r)
        step, _ = _solve(d.cols, r, damping)
        trial = theta + step
        nu_t, k_t = _phase_params(trial, lay, nu, kmat, scale)
        trial_phase = trial.copy()
        trial_phase[lay.phase :] = 0.0
        d_t = _design(q, colour, trial_phase, lay, nu_t, k_t, scale)
        rt = v - d_t.model
        rss_t = float(rt @ rt)
        if rss_t < rss_now:
            theta, nu, kmat = trial_phase, nu_t, k_t
            damping = max(damping / 3, 1e-6)
            done = rss_now - rss_t < 1e-7 * rss_now
            rss = rss_t
            if done:
                break
        else:
            damping *= 10
            rss = rss_now
            if damping > 1e3:
                break
    return theta, lay, nu, kmat, rss


def _phase_params(theta: np.ndarray, lay: _Layout, nu: np.ndarray, kmat: np.ndarray,
                  scale: float) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Fold a step's phase parameters into nu and K (they are kept at 0 in theta)."""
    p = theta[lay.phase : lay.phase + 5]
    nu2 = nu + p[:2] / scale
    k2 = kmat + np.array([[p[2], p[3]], [p[3], p[4]]]) / scale**2
    return nu2, k2


def _sample(n: int, limit: int) -> np.ndarray:
    """An even sample of at most `limit` of n indices."""
    if n <= limit:
        return np.arange(n)
    return np.linspace(0, n - 1, limit).round().astype(int)


def _orders(nu: np.ndarray, q: np.ndarray, limit: int) -> tuple[int, ...]:
    """The harmonics to fit: those whose wavelength is at least 0.4 px on the true period
    (shorter ones are averaged away by the pixel's square; the alias's period stands in for the
    true one when the direction is unknown), at least 2 of them, less those that the pixel grid
    folds to fewer than 2 cycles across the ROI (pixels at q): on the grid they are a smooth
    change of the level, which the fit cannot tell from the face's own, and the pixel's square
    averages them away (exactly, for a whole number of cycles per pixel)."""
    f = float(np.hypot(*nu))
    top = int(min(limit, max(2, math.floor(2.5 / f))))
    kept = []
    for h in range(1, top + 1):
        alias = _wrap(h * nu)
        if float(np.ptp(q @ alias)) >= 2.0:  # cycles of the folded harmonic across the ROI
            kept.append(h)
    return tuple(kept)


def _extra_orders(
    q: np.ndarray, colour: np.ndarray, v: np.ndarray, theta: np.ndarray, lay: _Layout,
    nu: np.ndarray, kmat: np.ndarray, scale: float,
) -> dict[int, tuple[float, float]]:  # fmt: skip
    """Harmonics beyond `lay.orders` (up to MAX_ORDER) that the fit's residuals show, with
    their amplitudes (cos, sin; relative to the level).

    A sharp pattern (a narrow highlight, the tread's edge) seen without lens blur keeps about
    1/h of its harmonic h after the pixel's square when its lines run along the pixel rows or
    columns, however short the wavelength; on the pixel grid such a harmonic is its alias. One
    that the grid folds near a Bayer Nyquist frequency ((1/2, 0) or (0, 1/2) cycles per px) is
    nearly a constant of opposite sign on the R and the B sites: left out, it moves R and B
    apart (a grey face's channels split). Each candidate's alias must differ by at least a cycle
    across the ROI from those of the fitted harmonics and of the candidates before it (else an
    earlier one already stands for it on the grid) and lie EXTRA_MIN_CYCLES from zero; all are
    fitted at once to the residuals at the fitted phase, with the channels' levels and slopes
    (a harmonic at a Nyquist frequency is told from the levels by the two greens, which see it
    with opposite signs), and those whose amplitude (both quadratures, with their covariance)
    stands EXTRA_Z standard errors above zero are kept."""
    aliases = [_wrap(h * nu) for h in lay.orders]
    cands = []
    for h in range(max(lay.orders) + 1, MAX_ORDER + 1):
        alias = _wrap(h * nu)
        if float(np.ptp(q @ alias)) < EXTRA_MIN_CYCLES:
            continue
        if any(min(np.ptp(q @ (alias - a)), np.ptp(q @ (alias + a))) < 1.0 for a in aliases):
            continue
        cands.append(h)
        aliases.append(alias)
    if not cands:
        return {}
    d = _design(q, colour, theta, lay, nu, kmat, scale, jacobian=False)
    level = d.model - d.periodic
    phi = _phase(q, nu, kmat)
    onehot = [(colour == c).astype(float) for c in range(3)]
    cols = [level * f(h * phi) for h in cands for f in (np.cos, np.sin)]
    cols += onehot + [o * q[:, k] / scale for o in onehot for k in (0, 1)]
    design = np.column_stack(cols)
    coef, inv = _solve(design, v - d.model)
    r = v - d.model - design @ coef
    sigma2 = float(r @ r) / max(1, v.size - lay.size - len(cands) * 2)
    keep = {}
    for j, h in enumerate(cands):
        c2 = coef[2 * j : 2 * j + 2]
        cov = sigma2 * inv[2 * j : 2 * j + 2, 2 * j : 2 * j + 2]
        z2 = float(c2 @ np.linalg.pinv(cov, rcond=1e-8) @ c2)  # a quadrature may be unseen
        if z2 > EXTRA_Z**2:
            keep[h] = (float(c2[0]), float(c2[1]))
    return keep


def _quick_rss(
    q: np.ndarray, colour: np.ndarray, v: np.ndarray, nu: np.ndarray,
    orders: tuple[int, ...], scale: float,
) -> tuple[float, np.ndarray, np.ndarray]:  # fmt: skip
    """RSS of a linear fit (each channel's plane times 1 + a pattern of the harmonics
    `orders`, the planes from the data without stripes), the harmonics' amplitudes over their
    errors, and their amplitudes (relative)."""
    hmax = len(orders)
    phi = _phase(q, nu, np.zeros((2, 2)))
    plane = np.zeros_like(v)
    for c in range(3):
        sel = colour == c
        design = np.column_stack([np.ones(sel.sum()), q[sel] / scale])
        plane[sel] = design @ np.linalg.lstsq(design, v[sel], rcond=None)[0]
    cols = [plane * f(h * phi) for h in orders for f in (np.cos, np.sin)]
    onehot = [(colour == c).astype(float) for c in range(3)]
    cols += onehot + [o * q[:, d] / scale for o in onehot for d in (0, 1)]
    design = np.column_stack(cols)
    coef, inv = _solve(design, v)
    r = v - design @ coef
    rss = float(r @ r)
    sigma2 = rss / max(1, v.size - design.shape[1])
    z = np.empty(hmax)
    amp = np.empty(hmax)
    for h in range(hmax):
        var = sigma2 * 0.5 * (inv[2 * h, 2 * h] + inv[2 * h + 1, 2 * h + 1])
        amp[h] = math.hypot(coef[2 * h], coef[2 * h + 1])
        z[h] = amp[h] / math.sqrt(max(var, 1e-300))
    return rss, z, amp


def fit_stripes(
    px: Pixels, across: np.ndarray | None = None, max_harmonics: int = 12
) -> StripeFit | None:
    """The stripes of one ROI, or None when it shows none (module docstring).

    Args:
        px: the ROI's pixels.
        across: the unit image vector (x, y) across the layer lines when known (a face placed
            from markers: its layer lines run along the face's y axis), else None: the
            orientation is then estimated from the image.
        max_harmonics: the most harmonics of wavelength 0.4 px or more fitted (shorter ones are
            added when the residuals show them, `_extra_orders`).
    """
    good = px.good
    if good.sum() < MIN_FIT_PIXELS:
        return None
    origin = np.array([px.x[good].mean(), px.y[good].mean()])
    q_all = np.column_stack([px.x - origin[0], px.y - origin[1]]).astype(np.float64)
    span = np.ptp(q_all[good], axis=0)
    if across is not None:
        a = np.asarray(across, dtype=float)
        across = a / np.hypot(*a)
        extent = float(np.ptp(q_all[good] @ across))
    else:
        extent = float(min(span)) if min(span) > 0 else 0.0
    found = _candidates(px, across, extent)
    if found is None:
        return None
    cands, ratio = found
    idx = np.flatnonzero(good)
    sub = idx[_sample(idx.size, FIT_PIXELS)]
    q, colour, v = q_all[sub], px.colour[sub], px.value[sub].astype(np.float64)
    scale = 0.5 * float(max(span.max(), 1.0))
    scored = []
    for nu0 in cands:
        f = float(np.hypot(*nu0))
        if float(np.ptp(q_all[good] @ (nu0 / f))) * f < MIN_PERIODS:
            continue
        orders = _orders(nu0, q, max_harmonics)
        if not orders:
            continue
        rss, z, amp = _quick_rss(q, colour, v, nu0, orders, scale)
        scored.append((rss, nu0, z, amp, orders))
    if not scored:
        return None
    halves = [item for item in scored if any(np.allclose(2 * item[1], o[1]) for o in scored)]
    whole = [item for item in scored if not any(item is h for h in halves)] or scored
    best = min(whole, key=lambda item: item[0])
    for half in halves:
        # the peak was the pattern's second harmonic if half its frequency shows odd harmonics
        # comparable to the even ones (irregular layers give the half small odd ones only)
        odd_h = np.array([h % 2 == 1 for h in half[4]])
        odd, even = half[3][odd_h].sum(), half[3][~odd_h].sum()
        first = half[2][0] if half[4][0] == 1 else 0.0
        if np.allclose(2 * half[1], best[1]) and first > 5 and odd > 0.3 * even:
            best = half
    _, nu0, z, amp, orders = best
    if not np.any(z > 3.0) or amp.max() < MIN_AMPLITUDE:
        return None
    got = _fit(q, colour, v, nu0, orders, scale)
    if got is None:
        return None
    theta, lay, nu, kmat, _ = got
    extra = _extra_orders(q, colour, v, theta, lay, nu, kmat, scale)
    if extra:
        start = _Start(theta, lay, extra)
        more = tuple(sorted(orders + tuple(extra)))
        refit = _fit(q, colour, v, nu, more, scale, iterations=4, kmat=kmat, start=start)
        if refit is not None:
            theta, lay, nu, kmat, _ = refit
    return _result(px, q_all, good, origin, theta, lay, nu, kmat, scale, across, ratio, sub)


CHUNK = 20_000
"""Pixels evaluated at a time when the fit is applied to a whole ROI."""


def _result(
    px: Pixels, q_all: np.ndarray, good: np.ndarray, origin: np.ndarray, theta: np.ndarray,
    lay: _Layout, nu: np.ndarray, kmat: np.ndarray, scale: float, across: np.ndarray | None,
    ratio: float, sub: np.ndarray,
) -> StripeFit:  # fmt: skip
    """The fit evaluated at every pixel, the offsets and the coupling weights."""
    n = q_all.shape[0]
    periodic = np.zeros(n)
    levels = theta[0:3].copy()
    offset_sum = np.zeros(3)
    g = np.zeros((3, lay.size))
    counts = np.zeros(3)
    for lo in range(0, n, CHUNK):
        sl = slice(lo, min(n, lo + CHUNK))
        q, colour, ok = q_all[sl], px.colour[sl], good[sl]
        d = _design(q, colour, theta, lay, nu, kmat, scale)
        periodic[sl] = d.periodic
        for c in range(3):
            on = ok & (colour == c)
            g[c] += d.dperiodic[on].sum(axis=0)
            counts[c] += on.sum()
            # the ROI's mean of channel c's own pattern over all its pixels (every site)
            dc = _design(q[ok], np.full(int(ok.sum()), c), theta, lay, nu, kmat, scale,
                         jacobian=False)  # fmt: skip
            offset_sum[c] += dc.periodic.sum()
    n_good = max(1, int(good.sum()))
    offset = np.where(levels > 0, offset_sum / n_good / np.where(levels > 0, levels, 1), np.nan)
    # coupling: channel c's de-striped mean over its sites moves by -mean_c(d(mP)/d theta)
    # dtheta, dtheta = (J'J)^-1 J' eps over the fitted sample: weights on the sample's pixels
    d = _design(q_all[sub], px.colour[sub], theta, lay, nu, kmat, scale)
    _, inv = _solve(d.cols, np.zeros(sub.size))
    coupling = np.zeros((3, n))
    for c in range(3):
        if counts[c] > 0:
            coupling[c, sub] = -(d.cols @ (inv @ (g[c] / counts[c])))
    fund = np.hypot(theta[lay.shared], theta[lay.shared + 1])
    f = float(np.hypot(*nu))
    return StripeFit(
        nu=nu,
        curvature=kmat,
        origin=origin,
        harmonics=lay.harmonics,
        period_px=1.0 / f if f > 0 else math.inf,
        angle_deg=float(np.degrees(np.arctan2(nu[1], nu[0]))),
        amplitude=float(fund),
        levels=levels,
        periodic=periodic,
        offset=offset,
        coupling=coupling,
        ratio=ratio,
    )


MIN_FIT_STRIPS = 12
"""A row of strips needs at least this many to estimate its 2 covariances."""


def layer_coordinate(fit: StripeFit, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The fitted layer phase in cycles at image points: nu . q + q' K q / 2, q from the
    ROI's centroid. It grows by 1 from one layer line to the next (when nu is the true wave
    vector: always with a known direction, otherwise for periods of at least 2 px)."""
    q = np.column_stack([x - fit.origin[0], y - fit.origin[1]])
    return _phase(q, fit.nu, fit.curvature) / (2 * np.pi)


def strip_blocks(
    px: Pixels, fit: StripeFit, values: np.ndarray, offset: float = 0.0
) -> tuple[np.ndarray, ...]:
    """Per channel sums over strips along the layer lines, each a whole number of layers and
    at least 2 px wide, their edges `offset` layers from the fitted phase's zero: (n, s, y, x)
    arrays of shape (3, K, 1) for `_blockvar.Blocks`, from the de-striped `values` of the good
    pixels. Irregular layers are correlated along their whole line; strips hold each layer's
    pixels together, so that such structure counts in full."""
    width = max(1, math.ceil(2.0 / fit.period_px)) if math.isfinite(fit.period_px) else 1
    good = px.good
    layer = layer_coordinate(fit, px.x[good], px.y[good]) - offset
    k = np.floor((layer - math.floor(layer.min())) / width).astype(int)
    n_strips = int(k.max()) + 1
    out = np.zeros((4, 3, n_strips, 1))
    colour = px.colour[good]
    for c in range(3):
        on = colour == c
        kc = k[on]
        out[0, c, :, 0] = np.bincount(kc, minlength=n_strips)
        out[1, c, :, 0] = np.bincount(kc, values[good][on], minlength=n_strips)
        out[2, c, :, 0] = np.bincount(kc, px.y[good][on] - fit.origin[1], minlength=n_strips)
        out[3, c, :, 0] = np.bincount(kc, px.x[good][on] - fit.origin[0], minlength=n_strips)
    return out[0], out[1], out[2], out[3]
