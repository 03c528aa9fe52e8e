"""Checks of the loose press that do not trust its solver: chips built as boxes (the
verification cases' bodies) and an intersection check on the deformed surfaces by
manifold3d, a library other than the solver's ipctk.

The check takes every chip's deformed outer surface as a closed manifold3d solid and,
for every pair of chips whose boxes come within ``reach_mm``, their intersection's
volume and their smallest gap (manifold3d's ``min_gap``); the platens are the planes
``bottom_z`` and ``top_z``. A chip pushed 0.05 mm into another is reported, with the
volume they share (``tests/test_loose_press.py``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from chipstack.meshing.contact_model import chip_block
from chipstack.meshing.loose.elements import (
    assemble,
    brick_stiffness,
    hex_boundary_triangles,
    node_volumes,
)
from chipstack.meshing.loose.ipc import Platens, PressBodies
from chipstack.meshing.loose.material import ChipMaterial

__all__ = ["box_bodies", "platens_over", "IntersectionCheck", "check_intersections"]


def box_bodies(centres, half_extents, material: ChipMaterial, divisions) -> PressBodies:
    """Axis-aligned box chips as loose-press bodies, each chip's ply frame the world's.

    Parameters
    ----------
    centres, half_extents : array_like, (n, 3) mm
        Every chip's centre and half sizes.
    material : ChipMaterial
        The chips' material.
    divisions : tuple of int, or a sequence of them
        Bricks along x, y and z, in every chip or chip by chip.
    """
    centres = np.atleast_2d(np.asarray(centres, dtype=float))
    half_extents = np.atleast_2d(np.asarray(half_extents, dtype=float))
    if np.ndim(divisions) == 1:
        divisions = [tuple(divisions)] * len(centres)
    points, cells, chips = [], [], []
    offset = 0
    for k, (centre, half, cuts) in enumerate(zip(centres, half_extents, divisions, strict=True)):
        grid, block, _surface, _anchors = chip_block(half, tuple(cuts))
        points.append(grid + centre)
        cells.append(block + offset)
        chips.append(np.full(len(block), k))
        offset += len(grid)
    points, cells, chip = np.vstack(points), np.vstack(cells), np.concatenate(chips)
    local = np.repeat(material.stiffness()[None], len(cells), axis=0)
    return PressBodies(
        points=points,
        cells=cells,
        chip=chip,
        stiffness=assemble(cells, brick_stiffness(points[cells], local), len(points)),
        viscous=None,
        node_volume=node_volumes(points, cells),
        surface=hex_boundary_triangles(cells),
    )


def platens_over(bodies: PressBodies, gap_mm: float, margin_mm: float = 2.0) -> Platens:
    """Platens ``gap_mm`` below and above the bodies, overhanging them by ``margin_mm``."""
    lo, hi = bodies.points.min(axis=0), bodies.points.max(axis=0)
    return Platens(
        bottom_z=float(lo[2] - gap_mm),
        top_z=float(hi[2] + gap_mm),
        xy=(lo[0] - margin_mm, hi[0] + margin_mm, lo[1] - margin_mm, hi[1] + margin_mm),
    )


@dataclass(frozen=True)
class IntersectionCheck:
    """What :func:`check_intersections` found: the pairs of chips that share volume
    (a, b, mm^3), the chips through a platen (chip, depth mm), the smallest gap between
    two chips within reach (mm; the reach when none is) and how many pairs were tested."""

    overlapping: tuple[tuple[int, int, float], ...]
    through_platens: tuple[tuple[int, float], ...]
    min_gap_mm: float
    pairs_checked: int

    @property
    def valid(self) -> bool:
        return not self.overlapping and not self.through_platens


def _solid(points: np.ndarray, triangles: np.ndarray):
    import manifold3d as m3

    used, local = np.unique(triangles, return_inverse=True)
    mesh = m3.Mesh64(
        vert_properties=np.ascontiguousarray(points[used], dtype=np.float64),
        tri_verts=np.ascontiguousarray(local.reshape(-1, 3), dtype=np.uint64),
    )
    solid = m3.Manifold(mesh)
    if solid.status() != m3.Error.NoError:
        raise ValueError(f"a chip's deformed surface is not a closed manifold ({solid.status()})")
    return solid


def check_intersections(
    points: np.ndarray,
    bodies: PressBodies,
    bottom_z: float,
    top_z: float,
    reach_mm: float = 0.01,
    volume_tol_mm3: float = 1e-9,
) -> IntersectionCheck:
    """Whether the chips at ``points`` (n, 3) mm, the deformed nodes of ``bodies``,
    intersect one another or the platens at ``bottom_z`` and ``top_z`` (see the module
    docstring); shared volumes below ``volume_tol_mm3`` are round-off."""
    triangles = bodies.surface
    owner = bodies.node_chip[triangles[:, 0]]
    chips = np.unique(owner)
    solids, boxes = {}, {}
    for k in chips:
        tri = triangles[owner == k]
        solids[k] = _solid(points, tri)
        corners = points[np.unique(tri)]
        boxes[k] = (corners.min(axis=0), corners.max(axis=0))
    through = []
    for k in chips:
        lo, hi = boxes[k]
        depth = max(bottom_z - lo[2], hi[2] - top_z)
        if depth > 0:
            through.append((int(k), float(depth)))
    overlapping, gap, checked = [], reach_mm, 0
    for i, a in enumerate(chips):
        for b in chips[i + 1 :]:
            (lo_a, hi_a), (lo_b, hi_b) = boxes[a], boxes[b]
            if np.any(lo_a > hi_b + reach_mm) or np.any(lo_b > hi_a + reach_mm):
                continue
            checked += 1
            shared = (solids[a] ^ solids[b]).volume()
            if shared > volume_tol_mm3:
                overlapping.append((int(a), int(b), float(shared)))
                gap = 0.0
                continue
            gap = min(gap, solids[a].min_gap(solids[b], reach_mm))
    return IntersectionCheck(tuple(overlapping), tuple(through), float(gap), checked)
