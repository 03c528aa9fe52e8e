"""Plane polygons for chip outlines: checks, convex partition and seeded generators.

Pure functions on (n, 2) arrays of corners in millimetres, counter-clockwise once
normalised. A flat chip is its outline extruded through its thickness; a non-convex
outline (a star, a random polygon) is partitioned *exactly* into convex pieces, so the
physics gets convex collision shapes and the geometry stage the exact outline (the union
of the pieces).
"""

from __future__ import annotations

import numpy as np

from chipstack.core.errors import InputError

__all__ = [
    "signed_area",
    "counter_clockwise",
    "check_simple",
    "is_convex",
    "convex_partition",
    "regular_polygon",
    "star_polygon",
    "random_polygon",
]

_EPS = 1e-9


def signed_area(points: np.ndarray) -> float:
    """Area (mm^2) of a polygon, positive when its corners run counter-clockwise."""
    x, y = np.asarray(points, dtype=float).T
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y))


def counter_clockwise(points: np.ndarray) -> np.ndarray:
    """The polygon with its corners in counter-clockwise order (a new array)."""
    points = np.array(points, dtype=float)
    return points if signed_area(points) > 0 else points[::-1].copy()


def _cross(o: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    return float((a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]))


def _segments_touch(p1, p2, q1, q2, tol: float) -> bool:
    """Closed segments p1p2 and q1q2 share a point (collinear overlaps included)."""
    d1, d2 = _cross(q1, q2, p1), _cross(q1, q2, p2)
    d3, d4 = _cross(p1, p2, q1), _cross(p1, p2, q2)
    if ((d1 > tol and d2 < -tol) or (d1 < -tol and d2 > tol)) and (
        (d3 > tol and d4 < -tol) or (d3 < -tol and d4 > tol)
    ):
        return True

    def on(a, b, c, d) -> bool:  # c on segment ab, given cross d ~ 0
        return (
            abs(d) <= tol
            and min(a[0], b[0]) - tol <= c[0] <= max(a[0], b[0]) + tol
            and (min(a[1], b[1]) - tol <= c[1] <= max(a[1], b[1]) + tol)
        )

    return on(q1, q2, p1, d1) or on(q1, q2, p2, d2) or on(p1, p2, q1, d3) or on(p1, p2, q2, d4)


def check_simple(points: np.ndarray, key: str) -> np.ndarray:
    """The outline as a float array, or :class:`InputError` naming ``key`` if unusable.

    Refused: fewer than 3 corners, non-finite values, repeated corners, zero area, and
    edges that cross or touch anywhere but at their shared corner (self-intersection).
    """
    try:
        points = np.array(points, dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"{key}: corners must be pairs of numbers") from None
    if points.ndim != 2 or points.shape[1] != 2:
        raise InputError(
            f"{key}: corners must be [x, y] pairs, got an array of shape {points.shape}"
        )
    n = len(points)
    if n < 3:
        raise InputError(f"{key}: a polygon needs at least 3 corners, got {n}")
    if not np.isfinite(points).all():
        raise InputError(f"{key}: corners hold NaN or infinite values")
    scale = float(np.ptp(points, axis=0).max()) or 1.0
    tol = 1e-9 * scale * scale
    edges = np.roll(points, -1, axis=0) - points
    if (np.linalg.norm(edges, axis=1) <= 1e-9 * scale).any():
        raise InputError(f"{key}: two consecutive corners coincide")
    if abs(signed_area(points)) <= 1e-9 * scale * scale:
        raise InputError(f"{key}: the polygon has no area")
    for i in range(n):
        for j in range(i + 1, n):
            if j == i + 1 or (i == 0 and j == n - 1):
                continue  # neighbours share a corner
            if _segments_touch(points[i], points[(i + 1) % n], points[j], points[(j + 1) % n], tol):
                raise InputError(
                    f"{key}: the polygon intersects itself (edges {i}-{(i + 1) % n} and "
                    f"{j}-{(j + 1) % n} cross)"
                )
    return points


def is_convex(points: np.ndarray) -> bool:
    """Whether a counter-clockwise polygon is convex (collinear corners allowed)."""
    points = np.asarray(points, dtype=float)
    n = len(points)
    scale = float(np.ptp(points, axis=0).max()) or 1.0
    return all(
        _cross(points[i - 1], points[i], points[(i + 1) % n]) >= -_EPS * scale * scale
        for i in range(n)
    )


def _triangulate(points: np.ndarray) -> list[list[int]]:
    """Ear clipping of a simple counter-clockwise polygon: index triangles."""
    remaining = list(range(len(points)))
    triangles: list[list[int]] = []
    scale = float(np.ptp(points, axis=0).max()) or 1.0
    tol = _EPS * scale * scale
    guard = 0
    while len(remaining) > 3:
        guard += 1
        if guard > 10 * len(points) ** 2:
            raise InputError("polygon: could not be triangulated (is it simple?)")
        m = len(remaining)
        for k in range(m):
            a, b, c = remaining[k - 1], remaining[k], remaining[(k + 1) % m]
            pa, pb, pc = points[a], points[b], points[c]
            if _cross(pa, pb, pc) <= tol:
                continue  # reflex or flat: not an ear
            inside = False
            for other in remaining:
                if other in (a, b, c):
                    continue
                p = points[other]
                if (
                    _cross(pa, pb, p) >= -tol
                    and _cross(pb, pc, p) >= -tol
                    and _cross(pc, pa, p) >= -tol
                ):
                    inside = True
                    break
            if not inside:
                triangles.append([a, b, c])
                remaining.pop(k)
                break
        else:
            # Only flat corners left where an ear was expected: drop one collinear corner.
            for k in range(m):
                a, b, c = remaining[k - 1], remaining[k], remaining[(k + 1) % m]
                if abs(_cross(points[a], points[b], points[c])) <= tol:
                    remaining.pop(k)
                    break
            else:
                raise InputError("polygon: could not be triangulated (is it simple?)")
    triangles.append(remaining)
    return triangles


def convex_partition(points: np.ndarray) -> list[np.ndarray]:
    """Exact partition of a simple counter-clockwise polygon into convex polygons.

    Ear-clipping triangulation followed by Hertel-Mehlhorn merging (drop a diagonal when
    both sides stay convex): at most four times the minimum number of pieces, and the
    union of the pieces is exactly the polygon. A convex polygon comes back whole.
    """
    points = counter_clockwise(points)
    if is_convex(points):
        return [points]
    pieces = _triangulate(points)
    merged = True
    while merged:
        merged = False
        for i in range(len(pieces)):
            for j in range(i + 1, len(pieces)):
                joined = _join(pieces[i], pieces[j])
                if joined is not None and is_convex(points[joined]):
                    pieces[i] = joined
                    pieces.pop(j)
                    merged = True
                    break
            if merged:
                break
    return [points[p] for p in pieces]


def _join(a: list[int], b: list[int]) -> list[int] | None:
    """Two counter-clockwise index polygons sharing an edge, merged across it (or None)."""
    for i in range(len(a)):
        u, v = a[i], a[(i + 1) % len(a)]
        for j in range(len(b)):
            if b[j] == v and b[(j + 1) % len(b)] == u:
                # a from v around to u, then b from u around to v (excluding the shared edge)
                rest_a = [a[(i + 1 + k) % len(a)] for k in range(len(a))]  # starts at v
                rest_b = [b[(j + 1 + k) % len(b)] for k in range(len(b))]  # starts at u
                return rest_a[:-1] + rest_b[:-1]
    return None


def regular_polygon(sides: int, radius_mm: float) -> np.ndarray:
    """A regular polygon with ``sides`` corners on a circle of ``radius_mm``, one on +x."""
    angles = 2 * np.pi * np.arange(sides) / sides
    return radius_mm * np.column_stack([np.cos(angles), np.sin(angles)])


def star_polygon(points: int, outer_mm: float, inner_mm: float) -> np.ndarray:
    """A star: ``points`` tips on ``outer_mm``, notches on ``inner_mm``, a tip on +x."""
    angles = np.pi * np.arange(2 * points) / points
    radii = np.where(np.arange(2 * points) % 2 == 0, outer_mm, inner_mm)
    return np.column_stack([radii * np.cos(angles), radii * np.sin(angles)])


def random_polygon(
    rng: np.random.Generator,
    corners: int,
    radius_mm: float,
    convex: bool,
    irregularity: float,
) -> np.ndarray:
    """A seeded random polygon with ``corners`` corners within a circle of ``radius_mm``.

    Corners at sorted random angles (each gap at least a quarter of the even gap, so no
    sliver edges); ``convex``: all on the circle (a polygon inscribed in a circle is
    convex); otherwise radii uniform in [(1 - irregularity) r, r], a star-shaped and
    therefore simple outline.
    """
    even = 2 * np.pi / corners
    gaps = even * (0.25 + 0.75 * rng.uniform(size=corners))
    angles = np.cumsum(gaps)
    angles *= 2 * np.pi / angles[-1]
    angles += rng.uniform(0, 2 * np.pi)
    radii = (
        np.full(corners, radius_mm)
        if convex
        else radius_mm * (1 - irregularity * rng.uniform(size=corners))
    )
    return np.column_stack([radii * np.cos(angles), radii * np.sin(angles)])
