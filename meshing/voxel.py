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

from geometry.arrangement import Arrangement
from geometry.orientation import fibre_directions_world
from geometry.voxels import voxelize
from meshing.mesh import PORE, VolumeMesh
from packing.errors import InputError

__all__ = ["voxel_mesh", "chip_attributes"]

# VTK hexahedron corner order as (di, dj, dk) offsets of the voxel's corner nodes.
_CORNERS = np.array(
    [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1)]
)
# About 1 kB per element at the peak (mesh, checks, writers): 8 million is 8 GB.
MAX_ELEMENTS = 8_000_000


def chip_attributes(arrangement: Arrangement, layer_mm: float) -> tuple[np.ndarray, ...]:
    """Per chip: batch (n,), layer by centre of mass (n,), two fibre directions (n, 2, 3)
    and the chip's normal (n, 3), in the world frame."""
    n = arrangement.n_chips
    layer = np.maximum(np.floor(arrangement.positions[:, 2] / layer_mm), 0).astype(np.int64)
    vectors, owners = fibre_directions_world(arrangement)
    fibres = np.zeros((n, 2, 3))
    for chip in range(n):
        mine = vectors[owners == chip]
        fibres[chip, 0] = mine[0]
        fibres[chip, 1] = mine[1] if len(mine) > 1 else mine[0]
    normals = np.array(arrangement.rotations)[:, :, 2].reshape(n, 3)
    return arrangement.batch.astype(np.int64), layer, fibres, normals


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
    batch_of, layer_of, fibres_of, normals_of = chip_attributes(arrangement, layer_mm)
    solid = chip >= 0
    batch = np.where(solid, batch_of[np.maximum(chip, 0)], 0)
    layer = np.where(solid, layer_of[np.maximum(chip, 0)], PORE)
    fibres = np.where(solid[:, None, None], fibres_of[np.maximum(chip, 0)], 0.0)
    normals = np.where(solid[:, None], normals_of[np.maximum(chip, 0)], 0.0)
    z = points[:, 2]
    lateral = np.zeros(len(points), dtype=bool)
    for axis in (0, 1):
        lateral |= np.isclose(points[:, axis], points[:, axis].min())
        lateral |= np.isclose(points[:, axis], points[:, axis].max())
    node_sets = {
        "bottom": np.flatnonzero(np.isclose(z, z.min())),
        "top": np.flatnonzero(np.isclose(z, z.max())),
        "lateral": np.flatnonzero(lateral),
    }
    return VolumeMesh(
        points=points,
        cell_type="hexahedron",
        cells=cells.astype(np.int64),
        chip=chip,
        batch=batch,
        layer=layer,
        fibres=fibres,
        normals=normals,
        quality=np.ones(len(cells)),
        node_sets=node_sets,
        n_chips=arrangement.n_chips,
        kind="voxel",
        info={
            "voxel_mm": voxel_mm,
            "pore_space": pore_space,
            "mesh_time_s": round(time.perf_counter() - start, 3),
        },
    )
