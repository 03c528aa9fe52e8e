"""Exact chip solids: convex pieces as half-spaces (for rays and voxels) and manifold3d solids.

A chip is the union of convex pieces (one for a plate). Each piece is kept two ways that
describe the same solid: as half-spaces ``n . p <= d`` (fast vectorised point and ray
tests) and as a manifold3d solid (booleans, volumes, slices).
"""

from __future__ import annotations

import atexit
from dataclasses import dataclass
from functools import lru_cache

import manifold3d as m3
import numpy as np
from scipy.spatial import ConvexHull, HalfspaceIntersection

from chipstack.core.arrangement import Arrangement
from chipstack.core.chipshape import ChipShape

__all__ = [
    "ConvexPiece",
    "shape_pieces",
    "chip_solid",
    "chip_solids",
    "union_solid",
    "target_prism",
    "transform_matrix",
]


@dataclass(frozen=True, eq=False)
class ConvexPiece:
    """A convex polyhedron in a chip's frame (mm): corners and outward half-spaces."""

    vertices: np.ndarray  # (V, 3)
    normals: np.ndarray  # (F, 3) unit, outward
    offsets: np.ndarray  # (F,) the piece is {p : normals @ p <= offsets}

    def inflated(self, distance_mm: float) -> ConvexPiece:
        """Every face moved outwards by ``distance_mm`` (sharp corners kept)."""
        if distance_mm == 0:
            return self
        offsets = self.offsets + distance_mm
        halfspaces = np.column_stack([self.normals, -offsets])
        interior = self.vertices.mean(axis=0)
        vertices = HalfspaceIntersection(halfspaces, interior).intersections
        return _piece_from_points(vertices)


def _piece_from_points(points: np.ndarray) -> ConvexPiece:
    hull = ConvexHull(points)
    # Coplanar facets of the hull repeat a plane; keep each plane once.
    planes = np.unique(np.round(hull.equations, 9), axis=0)
    vertices = points[hull.vertices]
    for array in (vertices, planes):
        array.setflags(write=False)
    return ConvexPiece(vertices, planes[:, :3], -planes[:, 3])


@lru_cache(maxsize=64)
def _pieces_cached(shape: ChipShape, inflate_mm: float) -> tuple[ConvexPiece, ...]:
    pieces = getattr(shape, "convex_pieces", None) or (shape.vertices,)
    return tuple(
        _piece_from_points(np.asarray(p, dtype=float)).inflated(inflate_mm) for p in pieces
    )


def shape_pieces(shape: ChipShape, inflate_mm: float = 0.0) -> tuple[ConvexPiece, ...]:
    """The convex pieces of a chip shape in its own frame, optionally inflated (mm)."""
    return _pieces_cached(shape, float(inflate_mm))


@lru_cache(maxsize=64)
def _local_solid(shape: ChipShape, inflate_mm: float) -> m3.Manifold:
    solids = [m3.Manifold.hull_points(p.vertices) for p in shape_pieces(shape, inflate_mm)]
    return solids[0] if len(solids) == 1 else m3.Manifold.batch_boolean(solids, m3.OpType.Add)


# Cached solids must go before the interpreter tears manifold3d down, or nanobind reports
# them as leaked (a page of stderr after a one-line error).
atexit.register(_local_solid.cache_clear)


def transform_matrix(rotation: np.ndarray, position: np.ndarray) -> np.ndarray:
    """The (3, 4) affine matrix [R | t] manifold3d takes."""
    return np.hstack([rotation, np.asarray(position, dtype=float).reshape(3, 1)])


def chip_solid(arrangement: Arrangement, chip: int, inflate_mm: float = 0.0) -> m3.Manifold:
    """One chip as an exact solid in the world frame (mm)."""
    shape = arrangement.shapes[arrangement.shape_index[chip]]
    return _local_solid(shape, float(inflate_mm)).transform(
        transform_matrix(arrangement.rotations[chip], arrangement.positions[chip])
    )


def chip_solids(arrangement: Arrangement, inflate_mm: float = 0.0) -> list[m3.Manifold]:
    """Every chip as an exact solid in the world frame (mm), in chip order."""
    return [chip_solid(arrangement, i, inflate_mm) for i in range(arrangement.n_chips)]


def union_solid(solids: list[m3.Manifold]) -> m3.Manifold:
    """The union of solids: the space the stack fills, overlaps counted once."""
    if not solids:
        return m3.Manifold()
    return m3.Manifold.batch_boolean(list(solids), m3.OpType.Add)


def target_prism(target_size_mm: float, z_low: float, z_high: float) -> m3.Manifold:
    """The box over the square target between two heights (mm)."""
    side = float(target_size_mm)
    return m3.Manifold.cube([side, side, z_high - z_low], center=True).translate(
        [0.0, 0.0, (z_low + z_high) / 2]
    )
