"""Chip shapes the shape effects build: a flat convex chip's outline, convex pieces
turned into a chip (volume, centre of mass, inertia), an outline inset or clipped."""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial import ConvexHull

from chipstack.core.chipshape import ChipShape
from chipstack.core.errors import InputError


def prism_outline(shape: ChipShape, effect: str) -> tuple[np.ndarray, float]:
    """The convex outline (n, 2) mm and thickness of a flat convex prism, or a clear
    refusal. What the chip can take is read from its geometry, whatever its kind: one
    convex piece whose corners all lie on its two faces, the top outline above the
    bottom one (a box, a regular or convex random polygon, a box-section beam, a plugin's
    flat triangle); a star, a round fibre or a mesh from a file is refused."""
    half = shape.thickness_mm / 2
    z = shape.vertices[:, 2]
    bottom = shape.vertices[np.isclose(z, -half)][:, :2]
    top = shape.vertices[np.isclose(z, half)][:, :2]
    prism = (
        len(shape.convex_pieces) == 1
        and len(bottom) + len(top) == len(z)
        and len(bottom) == len(top) >= 3
        and np.allclose(np.sort(bottom, axis=0), np.sort(top, axis=0))
    )
    if not prism:
        raise InputError(
            f"effect {effect!r}: supports flat convex chips (a convex outline extruded "
            f"through the thickness), not {shape.kind!r} chips"
        )
    hull = ConvexHull(bottom)
    return bottom[hull.vertices], 2 * half


def _hull_properties(pieces: list[np.ndarray]) -> tuple[float, np.ndarray, np.ndarray]:
    """Volume (mm^3), centre of mass (3,) and inertia tensor per unit mass about it
    (3, 3) mm^2 of a union of disjoint convex pieces."""
    import trimesh

    volume, first, second = 0.0, np.zeros(3), np.zeros((3, 3))
    for piece in pieces:
        mesh = trimesh.convex.convex_hull(piece)
        v = float(mesh.volume)
        c = np.asarray(mesh.center_mass)
        inertia = np.asarray(mesh.moment_inertia) / 1.0  # density 1: per unit volume * v
        volume += v
        first += v * c
        # Parallel axis back to the origin.
        second += inertia + v * (np.dot(c, c) * np.eye(3) - np.outer(c, c))
    centre = first / volume
    about_centre = second - volume * (np.dot(centre, centre) * np.eye(3) - np.outer(centre, centre))
    return volume, centre, about_centre / volume


def shape_from_pieces(shape: ChipShape, pieces: list[np.ndarray], name: str) -> ChipShape:
    """A chip made of convex pieces, centred on its centre of mass, local axes kept (the
    effects below keep the chip's mirror symmetries, so its axes stay principal)."""
    volume, centre, inertia = _hull_properties(pieces)
    pieces = [np.ascontiguousarray(p - centre) for p in pieces]
    points = np.vstack(pieces)
    hull = ConvexHull(points)
    lo, hi = points.min(axis=0), points.max(axis=0)
    for p in pieces:
        p.setflags(write=False)
    return dataclasses.replace(
        shape,
        name=name,
        vertices=points[hull.vertices],
        faces=tuple(tuple(int(i) for i in f) for f in _remap(hull)),
        convex_pieces=tuple(pieces),
        volume_mm3=volume,
        inertia_mm2=np.diag(inertia).copy(),
        half_extents=(hi - lo) / 2,
        box_centre=(hi + lo) / 2,
        collision="hull",
    )


def _remap(hull: ConvexHull) -> np.ndarray:
    index = {v: k for k, v in enumerate(hull.vertices)}
    return np.array([[index[i] for i in simplex] for simplex in hull.simplices])


def inset(outline: np.ndarray, distance: float) -> np.ndarray:
    """A convex counter-clockwise outline moved inwards by ``distance`` (mm)."""
    n = len(outline)
    area = 0.5 * np.sum(
        outline[:, 0] * np.roll(outline[:, 1], -1) - np.roll(outline[:, 0], -1) * outline[:, 1]
    )
    if area < 0:
        outline = outline[::-1]
    lines = []
    for i in range(n):
        a, b = outline[i], outline[(i + 1) % n]
        d = (b - a) / np.linalg.norm(b - a)
        inward = np.array([-d[1], d[0]])
        lines.append((a + distance * inward, d))
    corners = []
    for i in range(n):
        (p1, d1), (p2, d2) = lines[i - 1], lines[i]
        t = np.linalg.solve(np.column_stack([d1, -d2]), p2 - p1)[0]
        corners.append(p1 + t * d1)
    return np.array(corners)


def clip_x(outline: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """The part of a convex outline between x = lo and x = hi (Sutherland-Hodgman)."""

    def clip(points, keep, cross):
        out = []
        for i in range(len(points)):
            p, q = points[i - 1], points[i]
            if keep(q):
                if not keep(p):
                    out.append(cross(p, q))
                out.append(q)
            elif keep(p):
                out.append(cross(p, q))
        return out

    def at(x):
        return lambda p, q: p + (x - p[0]) / (q[0] - p[0]) * (q - p)

    points = clip(list(outline), lambda p: p[0] >= lo - 1e-12, at(lo))
    points = clip(points, lambda p: p[0] <= hi + 1e-12, at(hi))
    return np.array(points)
