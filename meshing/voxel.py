"""Voxel hexahedral mesh: the robust alternative that always succeeds.

Built from the geometry stage's voxel image (chip id per voxel, the first-deposited chip
keeping an overlap): one hexahedron per chip voxel, plus, with ``pore_space="box"``, one
per empty voxel inside the box from the conveyor to the stack's top over the chips'
footprint (the pore space, labelled ``PORE``). Neighbouring voxels share their nodes, so
the mesh is conformal by construction.
"""

from __future__ import annotations

import time

import numpy as np

from core.errors import InputError
from geometry.arrangement import Arrangement
from geometry.voxels import voxelize
from meshing.mesh import VolumeMesh, boundary_node_sets, element_attributes

__all__ = ["voxel_mesh"]

# VTK hexahedron corner order as (di, dj, dk) offsets of the voxel's corner nodes.
_CORNERS = np.array(
    [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1)]
)
# About 1 kB per element at the peak (mesh, checks, writers): 8 million is 8 GB.
MAX_ELEMENTS = 8_000_000


def voxel_mesh(
    arrangement: Arrangement,
    voxel_mm: float = 0.5,
    pore_space: str = "none",
    layer_mm: float = 2.0,
) -> VolumeMesh:
    """Hexahedral mesh of the stack at ``voxel_mm`` (see the module docstring)."""
    if pore_space not in ("none", "box"):
        raise InputError(f"pore_space: must be 'none' or 'box', got {pore_space!r}")
    start = time.perf_counter()
    image = voxelize(arrangement, voxel_mm)
    labels = image.labels
    keep = labels > 0
    if pore_space == "box":
        covered = keep.any(axis=2)
        ii, jj = np.nonzero(covered)
        box = np.zeros_like(keep)
        top = int(np.nonzero(keep.any(axis=(0, 1)))[0].max()) + 1 if keep.any() else 0
        box[ii.min() : ii.max() + 1, jj.min() : jj.max() + 1, :top] = True
        keep = box
    count = int(keep.sum())
    if count > MAX_ELEMENTS:
        raise InputError(
            f"voxel_mm: {voxel_mm} mm gives {count:,} elements (over {MAX_ELEMENTS:,}); "
            "choose a larger voxel"
        )
    i, j, k = np.nonzero(keep)
    nx, ny, nz = (s + 1 for s in labels.shape)
    corner_ids = ((i[:, None] + _CORNERS[:, 0]) * ny + (j[:, None] + _CORNERS[:, 1])) * nz + (
        k[:, None] + _CORNERS[:, 2]
    )
    used, cells = np.unique(corner_ids, return_inverse=True)
    cells = cells.reshape(-1, 8)
    ui, rest = np.divmod(used, ny * nz)
    uj, uk = np.divmod(rest, nz)
    points = np.column_stack([ui, uj, uk]) * voxel_mm + np.asarray(image.origin_mm)
    chip = labels[i, j, k].astype(np.int64) - 1  # void (0) becomes PORE (-1)
    return VolumeMesh(
        points=points,
        cell_type="hexahedron",
        cells=cells.astype(np.int64),
        chip=chip,
        **element_attributes(arrangement, chip, layer_mm),
        quality=np.ones(len(cells)),
        node_sets=boundary_node_sets(points),
        n_chips=arrangement.n_chips,
        kind="voxel",
        info={
            "voxel_mm": voxel_mm,
            "pore_space": pore_space,
            "mesh_time_s": round(time.perf_counter() - start, 3),
        },
    )
