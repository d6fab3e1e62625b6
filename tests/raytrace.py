"""An independent brute-force 2-D ray tracer of the periodic staircase, for testing only.

Plain NumPy. It shares no code, and no formula, with `stairfit.model`: the profile is built from
the geometry of [conventions §1-§2], rays are intersected with exact line segments and circular
arcs (or with a polyline approximation of the arcs), reflected specularly until they escape, and
their s and p power is multiplied by Fresnel reflectances written here from the textbook form
with Snell's law [conventions §6]. Tests import it as `from raytrace import ...` (tests/ has no
`__init__.py`, so pytest's default import mode puts it on `sys.path`).

Frame [conventions §1]: `x` along the wedge face (uphill), `z` its outward normal. A direction
at angle `a` "from z" is `(sin a, cos a)`; the light shines along `(sin theta_i, -cos theta_i)`,
an escaped ray leaves along `(sin theta_o, cos theta_o)`.

Profile [conventions §2]: one period, along +x, is the tread (outward normal at `+beta2`, length
`l2 = l1 cot beta2`), the concave 90-degree corner, the riser (normal at `beta2 - 90 deg`, length
`l1`) and the convex tip. Optionally every tip is a circular arc of radius `r` tangent to both
facets and every concave corner a fillet of radius `r_f`; as the corners are right angles each
facet loses `r` (resp. `r_f`) at that end. The arcs' outward normals sweep the same 90 degrees,
`[beta2 - 90 deg, beta2]`.

Why one period of search suffices. The profile is the graph of a periodic function `z = f(x)`
(every normal has a positive z component). Cut the x axis into cells of length `L` at the
maxima of `f` (the tips, or the tops of the tip arcs). A ray leaving the surface, or entering
at the height of the maxima, either crosses `f` before it reaches the next maximum in its
direction of travel (the edge of its cell), or passes above that maximum and never comes back.
So only the primitives of the current cell are candidates; the tracer also tests both neighbours
to be safe at cell edges. A ray that finds nothing while moving up has escaped; one that finds
nothing while moving down would be a tracer bug and is counted as `lost`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

PRIMITIVE_NAMES: tuple[str, str, str, str] = ("tip", "tread", "fillet", "riser")
"""Names of the primitive kinds; `TraceResult.path` holds indices into this tuple."""

_TIP, _TREAD, _FILLET, _RISER = range(4)
_CHUNK = 4_000_000  # ray x segment pairs per vectorised block (memory bound, ~100 MB)


# --------------------------------------------------------------------------------------------
# Fresnel [conventions §6], written from the textbook amplitudes (Born & Wolf / Hecht):
#   n sin(theta_t) = sin(theta_i)                                   (Snell)
#   r_s = (cos_i - n cos_t) / (cos_i + n cos_t),  r_p = (n cos_i - cos_t) / (n cos_i + cos_t)
# The principal complex square root gives cos_t with Re >= 0 and, for k >= 0, Im(n cos_t) >= 0:
# the transmitted wave decays into the absorbing medium.
# --------------------------------------------------------------------------------------------


def fresnel_sp(cos_gamma: NDArray, n: complex | None) -> tuple[NDArray, NDArray]:
    """Power reflectances `(R_s, R_p)` at local incidence `gamma` [conventions §6].

    `cos_gamma` is the cosine of the local angle of incidence (clipped to [0, 1]); `n` the
    complex refractive index relative to air, or `None` for a perfect mirror (`R_s = R_p = 1`).
    """
    cos_i = np.clip(np.asarray(cos_gamma, dtype=float), 0.0, 1.0)
    if n is None:
        one = np.ones_like(cos_i)
        return one, one.copy()
    n_c = complex(n)
    sin_i = np.sqrt(1.0 - cos_i**2)
    sin_t = sin_i / n_c
    cos_t = np.sqrt(1.0 - sin_t**2 + 0j)
    r_s = (cos_i - n_c * cos_t) / (cos_i + n_c * cos_t)
    r_p = (n_c * cos_i - cos_t) / (n_c * cos_i + cos_t)
    return np.abs(r_s) ** 2, np.abs(r_p) ** 2


# --------------------------------------------------------------------------------------------
# Geometry
# --------------------------------------------------------------------------------------------


def _unit(angle_rad: float) -> NDArray:
    """The unit vector at `angle_rad` from z towards +x [conventions §1]."""
    return np.array([np.sin(angle_rad), np.cos(angle_rad)])


@dataclass(frozen=True)
class Staircase:
    """The periodic staircase profile [conventions §2], optionally with rounded corners.

    `beta2_deg` is the wedge angle (degrees, in (0, 90)); `layer_um` the riser length `l1`
    (micrometres); `tip_radius_um` the radius `r` of the arcs replacing the convex tips,
    `fillet_radius_um` the radius `r_f` of the fillets in the concave corners (both absolute,
    micrometres, 0 = sharp). `arc_segments=None` intersects true circles; an integer replaces
    every arc by a polyline of that many chords per 90 degrees of arc (vertices on the circle),
    a cross-check of the circle code. `r + r_f` must not exceed `min(l1, l2)`.
    """

    beta2_deg: float
    layer_um: float = 150.0
    tip_radius_um: float = 0.0
    fillet_radius_um: float = 0.0
    arc_segments: int | None = None

    def __post_init__(self) -> None:
        if not 0.0 < self.beta2_deg < 90.0:
            raise ValueError(
                f"Staircase.beta2_deg = {self.beta2_deg!r}: the wedge angle must lie strictly "
                "between 0 and 90 degrees"
            )
        if not self.layer_um > 0.0:
            raise ValueError(f"Staircase.layer_um = {self.layer_um!r}: must be positive")
        for name in ("tip_radius_um", "fillet_radius_um"):
            value = getattr(self, name)
            if not value >= 0.0:
                raise ValueError(f"Staircase.{name} = {value!r}: must be >= 0 (0 = sharp)")
        if self.arc_segments is not None and self.arc_segments < 1:
            raise ValueError(
                f"Staircase.arc_segments = {self.arc_segments!r}: use None (true circles) "
                "or a positive number of chords per 90 degrees"
            )
        total = self.tip_radius_um + self.fillet_radius_um
        if total > self.max_total_radius_um * (1 + 1e-12):
            raise ValueError(
                f"Staircase: tip_radius_um + fillet_radius_um = {total:g} um exceeds "
                f"min(l1, l2) = {self.max_total_radius_um:g} um for beta2 = {self.beta2_deg:g} "
                f"deg, l1 = {self.layer_um:g} um (l2 = l1 cot beta2 = {self.l2_um:g} um): the "
                "arcs would not fit on the facets; reduce the radii"
            )

    @property
    def beta2_rad(self) -> float:
        """Wedge angle in radians."""
        return float(np.deg2rad(self.beta2_deg))

    @property
    def l1_um(self) -> float:
        """Riser length `l1` (micrometres)."""
        return float(self.layer_um)

    @property
    def l2_um(self) -> float:
        """Tread length `l2 = l1 cot beta2` (micrometres) [conventions §2]."""
        return float(self.layer_um / np.tan(self.beta2_rad))

    @property
    def period_um(self) -> float:
        """Period along the wedge face, the distance between neighbouring tips (micrometres)."""
        # Sum of the facets' x extents; equals sqrt(l1^2 + l2^2) (checked in the self-tests).
        b2 = self.beta2_rad
        return float(self.l2_um * np.cos(b2) + self.l1_um * np.sin(b2))

    @property
    def max_total_radius_um(self) -> float:
        """Largest allowed `r + r_f`: each facet must keep a non-negative flat length."""
        return min(self.l1_um, self.l2_um)

    @property
    def top(self) -> tuple[float, float]:
        """`(x, z)` of the highest point of the profile in the base cell (micrometres)."""
        c = self._tip_centre()
        return float(c[0]), float(c[1] + self.tip_radius_um)

    def _tip_centre(self) -> NDArray:
        n_tread, n_riser = _unit(self.beta2_rad), _unit(self.beta2_rad - np.pi / 2)
        return -self.tip_radius_um * (n_tread + n_riser)

    def primitives(self) -> _Primitives:
        """The primitives of the base cell `[x_top, x_top + L]`, in order along +x."""
        return _build_primitives(self)


@dataclass(frozen=True)
class _Primitives:
    """Primitives of one cell. Segments: start `a`, vector `e`, outward unit normal.

    Arcs: centre, radius, `sigma` (+1 convex: outward normal = (q - c) / R; -1 concave:
    (c - q) / R) and the range `[lo, hi]` of the outward normal's angle from z (radians).
    """

    seg_a: NDArray
    seg_e: NDArray
    seg_normal: NDArray
    seg_kind: NDArray
    arc_centre: NDArray
    arc_radius: NDArray
    arc_sigma: NDArray
    arc_lo: NDArray
    arc_hi: NDArray
    arc_kind: NDArray


def _arc_points(centre: NDArray, radius: float, sigma: float, angles: NDArray) -> NDArray:
    """Points of an arc at outward-normal angles `angles` (radians from z)."""
    return centre + sigma * radius * np.stack([np.sin(angles), np.cos(angles)], axis=-1)


def _build_primitives(st: Staircase) -> _Primitives:
    b2 = st.beta2_rad
    l2, r, rf, L = st.l2_um, st.tip_radius_um, st.fillet_radius_um, st.period_um
    t_tread = np.array([np.cos(b2), -np.sin(b2)])  # along +x, descending into the groove
    t_riser = np.array([np.sin(b2), np.cos(b2)])  # along +x, ascending to the next tip
    n_tread, n_riser = _unit(b2), _unit(b2 - np.pi / 2)
    tip0, tip1 = np.zeros(2), np.array([L, 0.0])
    corner = tip0 + l2 * t_tread
    c_tip = st._tip_centre()
    c_fillet = corner + rf * (n_tread + n_riser)

    # (kind, payload) in order along +x. Arc payload: centre, radius, sigma, start, end angle
    # (the angles of the outward normal at the arc's start and end along +x).
    pieces: list[tuple[int, tuple]] = []
    if r > 0:
        pieces.append((_TIP, ("arc", c_tip, r, 1.0, 0.0, b2)))  # from the top down to the tread
    pieces.append((_TREAD, ("seg", tip0 + r * t_tread, corner - rf * t_tread)))
    if rf > 0:
        pieces.append((_FILLET, ("arc", c_fillet, rf, -1.0, b2, b2 - np.pi / 2)))
    pieces.append((_RISER, ("seg", corner + rf * t_riser, tip1 - r * t_riser)))
    if r > 0:
        pieces.append((_TIP, ("arc", c_tip + tip1, r, 1.0, b2 - np.pi / 2, 0.0)))

    segs: list[tuple[NDArray, NDArray, int]] = []
    arcs: list[tuple[NDArray, float, float, float, float, int]] = []
    for kind, payload in pieces:
        if payload[0] == "seg":
            a, b = payload[1], payload[2]
            if np.hypot(*(b - a)) > 1e-14 * L:  # a facet fully consumed by arcs is dropped
                segs.append((a, b, kind))
            continue
        _, centre, radius, sigma, a0, a1 = payload
        if abs(a1 - a0) < 1e-15:
            continue
        if st.arc_segments is None:
            arcs.append((centre, radius, sigma, min(a0, a1), max(a0, a1), kind))
        else:
            m = max(1, int(np.ceil(st.arc_segments * abs(a1 - a0) / (np.pi / 2) - 1e-9)))
            pts = _arc_points(centre, radius, sigma, np.linspace(a0, a1, m + 1))
            segs.extend((pts[i], pts[i + 1], kind) for i in range(m))

    seg_a = np.array([s[0] for s in segs]).reshape(-1, 2)
    seg_e = np.array([s[1] - s[0] for s in segs]).reshape(-1, 2)
    tangent = seg_e / np.hypot(seg_e[:, 0], seg_e[:, 1])[:, None]
    # Outward normal: the tangent (along +x, air above) turned by +90 degrees: (x, z) -> (-z, x)
    seg_normal = np.stack([-tangent[:, 1], tangent[:, 0]], axis=-1)
    return _Primitives(
        seg_a=seg_a,
        seg_e=seg_e,
        seg_normal=seg_normal,
        seg_kind=np.array([s[2] for s in segs], dtype=np.int8),
        arc_centre=np.array([a[0] for a in arcs]).reshape(-1, 2),
        arc_radius=np.array([a[1] for a in arcs], dtype=float),
        arc_sigma=np.array([a[2] for a in arcs], dtype=float),
        arc_lo=np.array([a[3] for a in arcs], dtype=float),
        arc_hi=np.array([a[4] for a in arcs], dtype=float),
        arc_kind=np.array([a[5] for a in arcs], dtype=np.int8),
    )


# --------------------------------------------------------------------------------------------
# Intersection
# --------------------------------------------------------------------------------------------

_SHIFTS = (-1, 0, 1)  # cells tested around the ray's own cell


def _hit_segments(
    p: NDArray,
    d: NDArray,
    prim: _Primitives,
    L: float,
    cell: tuple[float, float],
    self_seg: NDArray,
    eps: float,
) -> tuple[NDArray, NDArray, NDArray]:
    """Nearest segment hit: `(t, shift, index)`, `t = inf` for none.

    Only segments whose x range overlaps the part of the ray that lies inside the segments'
    z range, and inside the ray's own cell `cell = (x_lo, x_hi)` widened by 1% of a period
    on each side (the module docstring explains why the own cell suffices), are tested. The
    segments of cells -1, 0, +1 are sorted along x, so these candidates are one contiguous
    index range per ray; rays are processed in blocks of similar candidate counts.
    """
    S = len(prim.seg_a)
    m = len(p)
    if S == 0:  # e.g. beta2 = 45 deg with r = l1: the tip arcs use up both facets
        return np.full(m, np.inf), np.zeros(m, dtype=np.int64), np.zeros(m, dtype=np.int64)
    a_all = np.concatenate([prim.seg_a + np.array([s * L, 0.0]) for s in _SHIFTS])
    e_all = np.tile(prim.seg_e, (len(_SHIFTS), 1))
    xa_all = a_all[:, 0]
    xb_all = a_all[:, 0] + e_all[:, 0]
    z_ends = np.concatenate([a_all[:, 1], a_all[:, 1] + e_all[:, 1]])
    z_lo, z_hi = z_ends.min(), z_ends.max()
    self_col = np.where(self_seg >= 0, S * _SHIFTS.index(0) + self_seg, -1)

    # Parameter range [t0, t1] (t >= 0) in which the ray is inside the segments' z range.
    with np.errstate(divide="ignore", invalid="ignore"):
        ta = (z_hi - p[:, 1]) / d[:, 1]
        tb = (z_lo - p[:, 1]) / d[:, 1]
    flat = d[:, 1] == 0
    inside = (p[:, 1] >= z_lo - eps) & (p[:, 1] <= z_hi + eps)
    t0 = np.where(flat, 0.0, np.maximum(np.minimum(ta, tb), 0.0))
    t1 = np.where(flat, np.where(inside, np.inf, -np.inf), np.maximum(ta, tb))
    margin = 0.01 * L
    with np.errstate(invalid="ignore"):
        x0 = p[:, 0] + d[:, 0] * t0
        x1 = np.where(d[:, 0] == 0, p[:, 0], p[:, 0] + d[:, 0] * t1)
    x_lo = np.maximum(np.minimum(x0, x1), cell[0] - margin) - eps
    x_hi = np.minimum(np.maximum(x0, x1), cell[1] + margin) + eps
    i0 = np.searchsorted(xb_all, x_lo, side="left")
    i1 = np.searchsorted(xa_all, x_hi, side="right") - 1
    count = np.where(t1 >= t0, np.maximum(i1 - i0 + 1, 0), 0)

    t_best = np.full(m, np.inf)
    col_best = np.zeros(m, dtype=np.int64)
    order = np.argsort(count, kind="stable")
    order = order[count[order] > 0]
    sorted_count = count[order]
    pos = 0
    while pos < order.size:
        # the largest block whose (rays x largest candidate count) stays within _CHUNK
        block = np.arange(1, order.size - pos + 1) * sorted_count[pos:]
        n_take = max(1, int(np.count_nonzero(block <= _CHUNK)))
        rows = order[pos : pos + n_take]
        pos += rows.size
        k = int(count[rows].max())
        cols = i0[rows, None] + np.arange(k)[None, :]
        valid = np.arange(k)[None, :] < count[rows, None]
        cols = np.where(valid, cols, 0)
        px, pz = p[rows, 0:1], p[rows, 1:2]
        dx, dz = d[rows, 0:1], d[rows, 1:2]
        ex, ez = e_all[cols, 0], e_all[cols, 1]
        wx, wz = a_all[cols, 0] - px, a_all[cols, 1] - pz
        denom = dx * ez - dz * ex
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (wx * ez - wz * ex) / denom
            s = (wx * dz - wz * dx) / denom
        ok = valid & (denom != 0) & (s >= 0) & (s <= 1) & (t > eps)
        ok &= cols != self_col[rows, None]
        t = np.where(ok, t, np.inf)
        j = np.argmin(t, axis=1)
        t_best[rows] = t[np.arange(rows.size), j]
        col_best[rows] = cols[np.arange(rows.size), j]
    return t_best, np.asarray(_SHIFTS)[col_best // S], col_best % S


def _hit_arcs(
    p: NDArray, d: NDArray, prim: _Primitives, L: float, self_arc: NDArray, eps: float
) -> tuple[NDArray, NDArray, NDArray]:
    """Nearest arc hit in cells -1, 0, +1: `(t, shift, index)`; `t = inf` for none.

    Per circle, only the rays that meet it (real roots) or leave that very arc are tested
    further (every other ray has no candidate on it); of equal hits the first in the order
    (shift, arc, root) wins."""
    m = len(p)
    t_best = np.full(m, np.inf)
    shift_best = np.zeros(m, dtype=np.int64)
    j_best = np.zeros(m, dtype=np.int64)
    px, pz, dx, dz = p[:, 0].copy(), p[:, 1].copy(), d[:, 0].copy(), d[:, 1].copy()
    for shift in _SHIFTS:
        for j in range(len(prim.arc_radius)):
            cx, cz = prim.arc_centre[j, 0] + shift * L, prim.arc_centre[j, 1]
            radius, sigma = prim.arc_radius[j], prim.arc_sigma[j]
            wx, wz = px - cx, pz - cz
            b = dx * wx + dz * wz
            disc = b * b - ((wx * wx + wz * wz) - radius**2)
            meets = disc >= 0
            # A ray leaving this very arc: t = 0 is one root, the other is exactly -2 b.
            on_it = self_arc == j if shift == 0 else None
            rows = np.flatnonzero(meets if on_it is None else meets | on_it)
            if rows.size == 0:
                continue
            b, meets = b[rows], meets[rows]
            root = np.sqrt(np.maximum(disc[rows], 0.0))
            cands = [np.where(meets, -b - root, np.inf), np.where(meets, -b + root, np.inf)]
            if on_it is not None:
                on_it = on_it[rows]
                cands = [np.where(on_it, np.inf, c_) for c_ in cands]
                cands.append(np.where(on_it, -2.0 * b, np.inf))
            prx, prz, drx, drz = px[rows], pz[rows], dx[rows], dz[rows]
            for t in cands:
                t0 = np.where(np.isfinite(t), t, 0.0)
                ang = np.arctan2(sigma * ((prx + t0 * drx) - cx), sigma * ((prz + t0 * drz) - cz))
                ok = np.isfinite(t) & (t > eps)
                ok &= (ang >= prim.arc_lo[j] - 1e-12) & (ang <= prim.arc_hi[j] + 1e-12)
                better = ok & (t < t_best[rows])
                won = rows[better]
                t_best[won] = t[better]
                shift_best[won] = shift
                j_best[won] = j
    return t_best, shift_best, j_best


# --------------------------------------------------------------------------------------------
# Tracing
# --------------------------------------------------------------------------------------------

ACTIVE, ESCAPED, TRAPPED, LOST = 0, 1, 2, 3


@dataclass(frozen=True)
class TraceResult:
    """Every ray of one `trace` call; ray `j` carries `1 / n_rays` of the incident power.

    Per ray (arrays of length `n_rays`): `status` (`ESCAPED`, `TRAPPED` = still bouncing after
    `max_bounces`, `LOST` = found no surface while moving down, a tracer bug), `theta_o_deg`
    (direction of escape [conventions §1], NaN unless escaped), `power_s`, `power_p` (fraction
    of the ray's s and p power left, product of the Fresnel factors of its bounces
    [conventions §6]), `n_bounces`, `path` (`(n_rays, max_bounces)` indices into
    `PRIMITIVE_NAMES`, -1 after the last bounce), `x0_um` (where the ray crossed the height of
    the profile's top, in the base cell).
    """

    staircase: Staircase
    theta_i_deg: float
    n: complex | None
    status: NDArray
    theta_o_deg: NDArray
    power_s: NDArray
    power_p: NDArray
    n_bounces: NDArray
    path: NDArray
    x0_um: NDArray = field(repr=False)

    @property
    def n_rays(self) -> int:
        """Number of rays traced."""
        return len(self.status)

    @property
    def escaped(self) -> NDArray:
        """Boolean mask of the rays that escaped."""
        return self.status == ESCAPED

    @property
    def power(self) -> NDArray:
        """Unpolarised power left in each ray, the mean of s and p [conventions §6]."""
        return 0.5 * (self.power_s + self.power_p)

    @property
    def n_trapped(self) -> int:
        """Rays still bouncing after `max_bounces`."""
        return int(np.sum(self.status == TRAPPED))

    @property
    def n_lost(self) -> int:
        """Rays that found no surface while moving down (must be 0; a bug otherwise)."""
        return int(np.sum(self.status == LOST))

    @property
    def first_hit(self) -> NDArray:
        """Kind of the first primitive each ray hits (index into `PRIMITIVE_NAMES`)."""
        return self.path[:, 0]

    @property
    def last_hit(self) -> NDArray:
        """Kind of the last primitive each ray hit (-1 for none)."""
        k = np.maximum(self.n_bounces - 1, 0)
        return np.where(self.n_bounces > 0, self.path[np.arange(self.n_rays), k], -1)


def trace(
    staircase: Staircase,
    theta_i_deg: float,
    n: complex | None,
    *,
    n_rays: int = 200_000,
    max_bounces: int = 100,
    offset: float = 0.5,
    seed: int | None = None,
) -> TraceResult:
    """Trace `n_rays` parallel rays at incidence `theta_i_deg` (degrees) [conventions §1-§2, §6].

    The rays are spread evenly over the ray front of exactly one period: they cross the height
    of the profile's top at `x0 = x_top + (j + offset) L / n_rays` (nothing lies above that
    height, so a ray started far above reaches this line unchanged). `seed` draws one random
    `offset` in [0, 1) instead (stratified sampling with a random shift). `n` is the complex
    refractive index or `None` for a perfect mirror. `|theta_i_deg| < 90`: at exactly grazing
    incidence the beam has zero width and there is nothing to trace.
    """
    theta = float(theta_i_deg)
    if not abs(theta) < 90.0:
        raise ValueError(
            f"theta_i_deg = {theta_i_deg!r}: must satisfy |theta_i| < 90 deg (at grazing "
            "incidence the beam has zero width); use e.g. +-(90 - 1e-6) for the limit"
        )
    if n_rays < 1 or max_bounces < 1:
        raise ValueError(f"n_rays = {n_rays}, max_bounces = {max_bounces}: both must be >= 1")
    if seed is not None:
        offset = float(np.random.default_rng(seed).uniform())
    if not 0.0 <= offset < 1.0:
        raise ValueError(f"offset = {offset!r}: must lie in [0, 1)")

    prim = staircase.primitives()
    L = staircase.period_um
    eps = 1e-12 * L
    x_top, z_top = staircase.top
    cell = (x_top, x_top + L)  # the base cell; every ray is kept in its own cell's frame
    th = np.deg2rad(theta)

    x0 = x_top + (np.arange(n_rays) + offset) / n_rays * L
    p = np.stack([x0, np.full(n_rays, z_top)], axis=-1)  # relative to the ray's cell
    d = np.tile([np.sin(th), -np.cos(th)], (n_rays, 1))
    self_seg = np.full(n_rays, -1, dtype=np.int64)
    self_arc = np.full(n_rays, -1, dtype=np.int64)
    status = np.zeros(n_rays, dtype=np.int8)
    power_s, power_p = np.ones(n_rays), np.ones(n_rays)
    n_bounces = np.zeros(n_rays, dtype=np.int64)
    path = np.full((n_rays, max_bounces), -1, dtype=np.int8)
    n_arcs = len(prim.arc_radius)

    for bounce in range(max_bounces + 1):
        idx = np.flatnonzero(status == ACTIVE)
        if idx.size == 0:
            break
        pa, da = p[idx], d[idx]
        t_s, sh_s, j_s = _hit_segments(pa, da, prim, L, cell, self_seg[idx], eps)
        if n_arcs:
            t_a, sh_a, j_a = _hit_arcs(pa, da, prim, L, self_arc[idx], eps)
        else:
            t_a = np.full(idx.size, np.inf)
            sh_a = j_a = np.zeros(idx.size, dtype=np.int64)
        use_arc = t_a < t_s
        t = np.where(use_arc, t_a, t_s)
        shift = np.where(use_arc, sh_a, sh_s)

        miss = ~np.isfinite(t)
        status[idx[miss & (da[:, 1] > 0)]] = ESCAPED
        status[idx[miss & (da[:, 1] <= 0)]] = LOST
        hit = ~miss
        if bounce == max_bounces:
            status[idx[hit]] = TRAPPED
            break

        h = idx[hit]
        ua, th_, sh_ = use_arc[hit], t[hit], shift[hit]
        q = pa[hit] + th_[:, None] * da[hit] - np.stack([sh_ * L, np.zeros(h.size)], axis=-1)
        js, ja = j_s[hit], j_a[hit]
        if len(prim.seg_a):
            normal, kind = prim.seg_normal[js], prim.seg_kind[js]
        else:  # no segments at all: every hit is on an arc
            normal, kind = np.zeros((h.size, 2)), np.zeros(h.size, dtype=np.int8)
        if n_arcs:
            radial = (q - prim.arc_centre[ja]) / prim.arc_radius[ja][:, None]
            normal = np.where(ua[:, None], prim.arc_sigma[ja][:, None] * radial, normal)
            kind = np.where(ua, prim.arc_kind[ja], kind)
        dh = da[hit]
        dn = np.einsum("ij,ij->i", dh, normal)
        R_s, R_p = fresnel_sp(-dn, n)
        power_s[h] *= R_s
        power_p[h] *= R_p
        d[h] = dh - 2.0 * dn[:, None] * normal
        p[h] = q
        self_seg[h] = np.where(ua, -1, js)
        self_arc[h] = np.where(ua, ja, -1)
        path[h, bounce] = kind
        n_bounces[h] += 1

    esc = status == ESCAPED
    theta_o = np.full(n_rays, np.nan)
    theta_o[esc] = np.rad2deg(np.arctan2(d[esc, 0], d[esc, 1]))
    return TraceResult(
        staircase=staircase,
        theta_i_deg=theta,
        n=n,
        status=status,
        theta_o_deg=theta_o,
        power_s=power_s,
        power_p=power_p,
        n_bounces=n_bounces,
        path=path,
        x0_um=x0,
    )


# --------------------------------------------------------------------------------------------
# Summaries
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Lobe:
    """Escaped rays sharing one direction [conventions §3].

    `theta_o_deg` the mean direction, `spread_deg` max - min within the cluster, `weight` the
    fraction of all rays, `power` the unpolarised reflected power as a fraction of the incident
    power (the reflectance ratio, [conventions §4]); `fresnel = power / weight`.
    """

    theta_o_deg: float
    spread_deg: float
    weight: float
    power: float

    @property
    def fresnel(self) -> float:
        """Mean unpolarised Fresnel factor of the lobe's rays."""
        return self.power / self.weight


def lobes(result: TraceResult, tol_deg: float = 1e-6) -> list[Lobe]:
    """Cluster the escaped rays by direction: a gap above `tol_deg` starts a new lobe.

    Sorted by `theta_o_deg`. For the sharp profile there are at most three lobes (fewer when
    two coincide in direction, e.g. the retro and tread lobes at `theta_i = -beta2`).
    """
    esc = result.escaped
    th = result.theta_o_deg[esc]
    pw = result.power[esc]
    if th.size == 0:
        return []
    order = np.argsort(th, kind="stable")
    th, pw = th[order], pw[order]
    cuts = np.flatnonzero(np.diff(th) > tol_deg) + 1
    out = []
    for grp_th, grp_pw in zip(np.split(th, cuts), np.split(pw, cuts), strict=True):
        out.append(
            Lobe(
                theta_o_deg=float(grp_th.mean()),
                spread_deg=float(grp_th[-1] - grp_th[0]),
                weight=grp_th.size / result.n_rays,
                power=float(grp_pw.sum()) / result.n_rays,
            )
        )
    return out


@dataclass(frozen=True)
class PathStats:
    """Escaped rays that took one sequence of primitives (see `paths`)."""

    weight: float
    power: float
    power_s: float
    power_p: float
    theta_o_min_deg: float
    theta_o_max_deg: float


def paths(result: TraceResult) -> dict[tuple[str, ...], PathStats]:
    """Escaped rays grouped by the sequence of primitive kinds they hit, e.g.
    `("tread",)`, `("riser", "tread")`. Weights and powers are fractions of all rays /
    of the incident power; `power_s`, `power_p` are each relative to that polarisation.
    """
    esc = np.flatnonzero(result.escaped)
    out: dict[tuple[str, ...], PathStats] = {}
    if esc.size == 0:
        return out
    width = max(1, int(result.n_bounces[esc].max()))
    sub = result.path[esc, :width].astype(np.int64)
    if width <= 27:  # one base-5 integer per path (5**27 < 2**63): a fast 1-D unique
        codes = (sub + 1) @ (5 ** np.arange(width, dtype=np.int64))
        _, first, inverse = np.unique(codes, return_index=True, return_inverse=True)
        rows = sub[first]
    else:
        rows, inverse = np.unique(sub, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    for g, row in enumerate(rows):
        members = esc[inverse == g]
        key = tuple(PRIMITIVE_NAMES[k] for k in row if k >= 0)
        th = result.theta_o_deg[members]
        out[key] = PathStats(
            weight=members.size / result.n_rays,
            power=float(result.power[members].sum()) / result.n_rays,
            power_s=float(result.power_s[members].sum()) / result.n_rays,
            power_p=float(result.power_p[members].sum()) / result.n_rays,
            theta_o_min_deg=float(th.min()),
            theta_o_max_deg=float(th.max()),
        )
    return out


def histogram(result: TraceResult, bin_edges_deg: NDArray) -> NDArray:
    """Unpolarised reflected power per `theta_o` bin, as a fraction of the incident power.

    Bins follow `numpy.histogram` (half-open, the last one closed); rays escaping outside the
    edges are not counted. Divide by the bin width in radians for the in-plane density `rho`
    (1/rad) of [conventions §4]. Beware edges that coincide with a sharp lobe's direction.
    """
    esc = result.escaped
    counts, _ = np.histogram(
        result.theta_o_deg[esc],
        bins=np.asarray(bin_edges_deg, dtype=float),
        weights=result.power[esc] / result.n_rays,
    )
    return counts


def total_reflectance(result: TraceResult) -> float:
    """Unpolarised power of all escaped rays / the incident power [conventions §4]."""
    return float(result.power[result.escaped].sum()) / result.n_rays
