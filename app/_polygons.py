"""Is a polygon simple? ROI and face outlines must not cross themselves.

A self-intersecting outline (corners listed out of order, e.g. a bow tie) is filled by OpenCV's
even-odd rule into something other than the face, silently; a marker whose four corners cross
is a wrong corner order. `polygon_problem` says what is wrong, for a one-line error.
"""

from __future__ import annotations

from collections.abc import Sequence

Point = tuple[float, float]


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


def _distinct(points: Sequence[Point]) -> list[Point]:
    """The vertices without consecutive repeats (a repeated vertex adds a zero-length edge)."""
    out: list[Point] = []
    for p in points:
        if not out or p != out[-1]:
            out.append(p)
    if len(out) > 1 and out[0] == out[-1]:
        out.pop()  # a closing vertex repeating the first
    return out


def twice_area(points: Sequence[Point]) -> float:
    """Twice the signed area (shoelace formula)."""
    n = len(points)
    return sum(
        points[i][0] * points[(i + 1) % n][1] - points[(i + 1) % n][0] * points[i][1]
        for i in range(n)
    )


def polygon_problem(points: Sequence[Point]) -> str | None:
    """Why the closed polygon through `points` is not a simple polygon with area, or None."""
    pts = _distinct(points)
    n = len(pts)
    if n < 3:
        return "has fewer than 3 distinct corners"
    for i in range(n):
        a, b, c = pts[i - 1], pts[i], pts[(i + 1) % n]
        folds = (
            _cross(b, a, c) == 0
            and (a[0] - b[0]) * (c[0] - b[0]) + (a[1] - b[1]) * (c[1] - b[1]) > 0
        )
        if folds:
            return f"folds back on itself at corner {i} {b}; list the corners in order around it"
    for i in range(n):
        for j in range(i + 2, n):
            if i == 0 and j == n - 1:
                continue  # adjacent through the closing edge
            if segments_meet(pts[i], pts[(i + 1) % n], pts[j], pts[(j + 1) % n]):
                return (
                    f"crosses itself (edge {i}-{(i + 1) % n} meets edge {j}-{(j + 1) % n}); "
                    "list the corners in order around it"
                )
    if twice_area(pts) == 0.0:
        return "has no area (all corners on one line)"
    return None
