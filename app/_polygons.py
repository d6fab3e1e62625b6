"""Is a polygon simple? ROI and face outlines must not cross themselves.

A self-intersecting outline (corners listed out of order, e.g. a bow tie) is filled by OpenCV's
even-odd rule into something other than the face, silently; a marker whose four corners cross
is a wrong corner order. `polygon_problem` says what is wrong, for a one-line error.

The check runs in about linear time (a traced outline may have 100,000 points; testing every
pair of edges took minutes): each edge is cut into pieces no longer than a grid cell, edges
whose pieces share a cell are the candidates, and only those are tested exactly, all at once
with NumPy. An outline so intricate that more than `MAX_CANDIDATES` pairs remain is refused
with a clear limit rather than checked slowly.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

Point = tuple[float, float]

MAX_PIECES = 4_000_000
"""The most grid pieces the edges are cut into (about 40 per edge of a 100,000-point outline)."""
MAX_CANDIDATES = 20_000_000
"""The most pairs of edges tested exactly; an outline needing more is refused as too intricate."""


class PolygonTooIntricateError(ValueError):
    """An outline whose check would need more than `MAX_CANDIDATES` exact tests."""


def _cross(o: Point, a: Point, b: Point) -> float:
    """z of (a - o) x (b - o): > 0 when o -> a -> b turns left."""
    return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])


def _within(a: Point, b: Point, p: Point) -> bool:
    """Whether p (collinear with a, b) lies on the closed segment a-b."""
    return min(a[0], b[0]) <= p[0] <= max(a[0], b[0]) and min(a[1], b[1]) <= p[1] <= max(a[1], b[1])


def segments_meet(p1: Point, p2: Point, q1: Point, q2: Point) -> bool:
    """Whether the closed segments p1-p2 and q1-q2 share a point (crossing or touching)."""
    d1, d2 = _cross(q1, q2, p1), _cross(q1, q2, p2)
    d3, d4 = _cross(p1, p2, q1), _cross(p1, p2, q2)
    if ((d1 > 0) != (d2 > 0)) and d1 != 0 and d2 != 0 and ((d3 > 0) != (d4 > 0)) and d3 and d4:
        return True
    return (
        (d1 == 0 and _within(q1, q2, p1))
        or (d2 == 0 and _within(q1, q2, p2))
        or (d3 == 0 and _within(p1, p2, q1))
        or (d4 == 0 and _within(p1, p2, q2))
    )


def _distinct(points: Sequence[Point]) -> np.ndarray:
    """The vertices (n, 2) without consecutive repeats (a repeated vertex adds a zero-length
    edge) and without a closing vertex that repeats the first."""
    pts = np.asarray(points, dtype=float).reshape(-1, 2)
    if len(pts) > 1:
        keep = np.concatenate([[True], np.any(pts[1:] != pts[:-1], axis=1)])
        pts = pts[keep]
    if len(pts) > 1 and np.all(pts[0] == pts[-1]):
        pts = pts[:-1]
    return pts


def twice_area(points: Sequence[Point] | np.ndarray) -> float:
    """Twice the signed area (shoelace formula)."""
    pts = np.asarray(points, dtype=float).reshape(-1, 2)
    nxt = np.roll(pts, -1, axis=0)
    return float(np.sum(pts[:, 0] * nxt[:, 1] - nxt[:, 0] * pts[:, 1]))


def _fold(pts: np.ndarray) -> int | None:
    """The first corner where the outline turns straight back on itself, or None."""
    a, c = np.roll(pts, 1, axis=0), np.roll(pts, -1, axis=0)
    u, v = a - pts, c - pts
    cross = u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]
    folds = np.flatnonzero((cross == 0) & (np.sum(u * v, axis=1) > 0))
    return int(folds[0]) if folds.size else None


def _pieces(p: np.ndarray, q: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each edge cut into pieces no longer than `h`: (edge index, piece start, piece end)."""
    length = np.hypot(*(q - p).T)
    m = np.maximum(1, np.ceil(length / h)).astype(np.int64)
    total = int(m.sum())
    if total > MAX_PIECES:
        raise PolygonTooIntricateError(f"its edges cross {total:,} grid cells")
    edge = np.repeat(np.arange(len(p)), m)
    first = np.repeat(np.cumsum(m) - m, m)
    k = np.arange(total) - first
    steps = np.repeat(m, m).astype(float)
    d = (q - p)[edge]
    return edge, p[edge] + d * (k / steps)[:, None], p[edge] + d * ((k + 1) / steps)[:, None]


def _cells(edge: np.ndarray, a: np.ndarray, b: np.ndarray, origin: np.ndarray, h: float):
    """(cell key, edge) of every grid cell each piece's padded bounding box touches."""
    pad = 0.01 * h + 1e-12 * float(np.max(np.abs(origin)) + h)
    lo = np.floor((np.minimum(a, b) - pad - origin) / h).astype(np.int64)
    hi = np.floor((np.maximum(a, b) + pad - origin) / h).astype(np.int64)
    width = int(hi[:, 0].max()) + 3
    keys, edges = [], []
    for dx in range(3):
        for dy in range(3):
            cx, cy = lo[:, 0] + dx, lo[:, 1] + dy
            ok = (cx <= hi[:, 0]) & (cy <= hi[:, 1])
            keys.append(cx[ok] * width + cy[ok])
            edges.append(edge[ok])
    return np.concatenate(keys), np.concatenate(edges)


def _candidate_pairs(keys: np.ndarray, edges: np.ndarray, n: int) -> np.ndarray:
    """Pairs (i, j), i < j, of edges that share a grid cell and are not neighbours."""
    _, keys = np.unique(keys, return_inverse=True)  # small cell numbers: no overflow below
    cell_edge = np.unique(keys.astype(np.int64) * n + edges)  # each edge once per cell
    cell, edge = cell_edge // n, cell_edge % n
    start = np.flatnonzero(np.concatenate([[True], cell[1:] != cell[:-1]]))
    size = np.diff(np.concatenate([start, [len(cell)]]))
    if int(np.sum(size * (size - 1) // 2)) > MAX_CANDIDATES:
        raise PolygonTooIntricateError("too many of its edges lie close together")
    end = np.repeat(start + size, size)
    pairs = []
    for r in range(1, int(size.max())):
        i = np.flatnonzero(np.arange(len(cell)) + r < end)
        pairs.append(np.stack([edge[i], edge[i + r]], axis=1))
    if not pairs:
        return np.empty((0, 2), dtype=np.int64)
    both = np.sort(np.concatenate(pairs), axis=1)
    both = np.unique(both[:, 0] * n + both[:, 1])
    i, j = both // n, both % n
    neighbours = (j - i == 1) | ((i == 0) & (j == n - 1))
    return np.stack([i[~neighbours], j[~neighbours]], axis=1)


def _meet(p1: np.ndarray, p2: np.ndarray, q1: np.ndarray, q2: np.ndarray) -> np.ndarray:
    """`segments_meet` of arrays of segments (the same arithmetic, row by row)."""

    def cross(o: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return (a[:, 0] - o[:, 0]) * (b[:, 1] - o[:, 1]) - (a[:, 1] - o[:, 1]) * (b[:, 0] - o[:, 0])

    def within(a: np.ndarray, b: np.ndarray, p: np.ndarray) -> np.ndarray:
        return np.all((np.minimum(a, b) <= p) & (p <= np.maximum(a, b)), axis=1)

    d1, d2, d3, d4 = cross(q1, q2, p1), cross(q1, q2, p2), cross(p1, p2, q1), cross(p1, p2, q2)
    proper = ((d1 > 0) != (d2 > 0)) & (d1 != 0) & (d2 != 0) & ((d3 > 0) != (d4 > 0))
    proper &= (d3 != 0) & (d4 != 0)
    touch = (d1 == 0) & within(q1, q2, p1)
    touch |= (d2 == 0) & within(q1, q2, p2)
    touch |= (d3 == 0) & within(p1, p2, q1)
    touch |= (d4 == 0) & within(p1, p2, q2)
    return proper | touch


def _first_crossing(pts: np.ndarray) -> tuple[int, int] | None:
    """The first pair of non-neighbouring edges (by index) that share a point, or None."""
    n = len(pts)
    p, q = pts, np.roll(pts, -1, axis=0)
    length = np.hypot(*(q - p).T)
    extent = float(np.max(pts.max(axis=0) - pts.min(axis=0)))
    h = max(float(np.median(length)), extent * 1e-8)  # cells: about one edge long
    edge, a, b = _pieces(p, q, h)
    keys, edges = _cells(edge, a, b, pts.min(axis=0), h)
    pairs = _candidate_pairs(keys, edges, n)
    i, j = pairs[:, 0], pairs[:, 1]
    hit = np.flatnonzero(_meet(p[i], q[i], p[j], q[j]))
    if not hit.size:
        return None
    first = hit[np.lexsort((j[hit], i[hit]))[0]]
    return int(i[first]), int(j[first])


def polygon_problem(points: Sequence[Point]) -> str | None:
    """Why the closed polygon through `points` is not a simple polygon with area, or None."""
    pts = _distinct(points)
    n = len(pts)
    if n < 3:
        return "has fewer than 3 distinct corners"
    fold = _fold(pts)
    if fold is not None:
        corner = (float(pts[fold, 0]), float(pts[fold, 1]))
        return (
            f"folds back on itself at corner {fold} {corner}; list the corners in order around it"
        )
    try:
        crossing = _first_crossing(pts)
    except PolygonTooIntricateError as e:
        return (
            f"has {n:,} corners and is too intricate to check ({e}); simplify the outline "
            f"(fewer corners, e.g. one every few pixels)"
        )
    if crossing is not None:
        i, j = crossing
        return (
            f"crosses itself (edge {i}-{(i + 1) % n} meets edge {j}-{(j + 1) % n}); "
            "list the corners in order around it"
        )
    if twice_area(pts) == 0.0:
        return "has no area (all corners on one line)"
    return None
