"""The polygon check (app/_polygons.py) in about linear time, with the answers of testing every
pair of edges (issue 42, case 6: a 100,000-point ROI took longer than 300 s to check)."""

from __future__ import annotations

import time

import numpy as np
import pytest

from stairfit._polygons import _distinct, _first_crossing, polygon_problem, segments_meet


def _every_pair(points: np.ndarray) -> tuple[int, int] | None:
    """The first pair of non-neighbouring edges that meet, testing every pair (the reference)."""
    pts = [(float(x), float(y)) for x, y in points]
    n = len(pts)
    for i in range(n):
        for j in range(i + 2, n):
            if i == 0 and j == n - 1:
                continue
            if segments_meet(pts[i], pts[(i + 1) % n], pts[j], pts[(j + 1) % n]):
                return i, j
    return None


def _outline(kind: int, n: int, rng: np.random.Generator) -> np.ndarray:
    if kind == 0:  # star-shaped: simple
        angle, radius = np.sort(rng.uniform(0, 2 * np.pi, n)), rng.uniform(1, 10, n)
        return np.stack([radius * np.cos(angle), radius * np.sin(angle)], axis=1)
    if kind == 1:  # integer points: many touching and collinear edges
        return rng.integers(0, 6, (n, 2)).astype(float)
    return rng.uniform(0, 100, (n, 2))  # random order: mostly crossing


def test_the_check_finds_the_pair_that_testing_every_pair_finds() -> None:
    rng = np.random.default_rng(0)
    checked = crossing = 0
    for trial in range(1500):
        pts = _distinct(_outline(trial % 3, int(rng.integers(3, 40)), rng))
        if len(pts) < 3:
            continue
        expected = _every_pair(pts)
        assert _first_crossing(pts) == expected, pts.tolist()
        checked += 1
        crossing += expected is not None
    assert checked > 1000 and 200 < crossing < checked - 200  # both answers exercised


def _wavy_circle(n: int) -> list[tuple[float, float]]:
    angle = np.linspace(0, 2 * np.pi, n, endpoint=False)
    radius = 100 + 10 * np.sin(37 * angle)
    return list(zip(500 + radius * np.cos(angle), 500 + radius * np.sin(angle), strict=True))


def test_a_100000_point_outline_is_checked_in_a_second() -> None:
    points = _wavy_circle(100_000)
    t0 = time.perf_counter()
    assert polygon_problem(points) is None
    elapsed = time.perf_counter() - t0
    points[10], points[50_000] = points[50_000], points[10]  # two corners swapped: crossing
    problem = polygon_problem(points)
    assert problem is not None and problem.startswith("crosses itself (edge 9-10 meets edge")
    assert elapsed < 3.0  # 0.2 s on the 2-core machine; every pair of edges: minutes


def test_a_rectangle_of_many_collinear_corners_is_simple() -> None:
    side = np.linspace(0, 1, 25_000, endpoint=False)
    zero, one = np.zeros_like(side), np.ones_like(side)
    pts = np.concatenate([
        np.stack([side * 1000, zero], 1), np.stack([1000 * one, side * 500], 1),
        np.stack([1000 - side * 1000, 500 * one], 1), np.stack([zero, 500 - side * 500], 1),
    ])  # fmt: skip
    assert polygon_problem([tuple(p) for p in pts]) is None


def test_an_outline_too_intricate_to_check_is_refused_with_a_limit() -> None:
    x = np.repeat(np.arange(25_000) * 1e-3, 2)  # a comb of 25,000 teeth 0.001 apart, 1 long
    y = np.tile([1.0, 2.0, 2.0, 1.0], 12_501)[: len(x)]
    pts = [*zip(x, y, strict=True), (x[-1], 0.0), (0.0, 0.0)]
    t0 = time.perf_counter()
    problem = polygon_problem(pts)
    assert time.perf_counter() - t0 < 3.0
    assert problem is not None and "too intricate to check" in problem
    assert "simplify the outline" in problem


@pytest.mark.parametrize(
    ("points", "start"),
    [
        ([(0, 0), (1, 0)], "has fewer than 3 distinct corners"),
        ([(0, 0), (2, 0), (1, 0)], "folds back on itself at corner 0 (0.0, 0.0)"),
        ([(0, 0), (2, 2), (2, 0), (0, 2)], "crosses itself (edge 0-1 meets edge 2-3)"),
        ([(0, 0), (4, 0), (4, 4), (2, 0), (0, 4)], "crosses itself (edge 0-1 meets edge 2-3)"),
        ([(0, 0), (1, 1), (2, 2), (0, 0)], "folds back on itself at corner 0"),
    ],
)
def test_the_messages_say_what_is_wrong(points: list, start: str) -> None:
    problem = polygon_problem(points)
    assert problem is not None and problem.startswith(start), problem
