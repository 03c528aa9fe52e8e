"""Voxel hexahedral mesh: the robust alternative that always succeeds.

Built from the geometry stage's voxel image (chip id per voxel, the first-deposited chip
keeping an overlap): one hexahedron per chip voxel, plus, with ``pore_space="box"``, one
per empty voxel inside the box from the conveyor to the stack's top over the chips'
footprint (the pore space, labelled ``PORE``). Neighbouring voxels share their nodes, so
the mesh is conformal by construction.

A crop (``region_mm``: x and y ranges) keeps the voxels whose centres lie inside it, the
chips cut at its sides; with the pore space, the box then spans the whole region, so that
its six sides are full faces (whole platens, periodic sides).
"""

from __future__ import annotations

import time

import numpy as np

from chipstack.core.arrangement import Arrangement
from chipstack.core.errors import InputError
from chipstack.geometry.voxels import voxelize
from chipstack.meshing.boundaries import PeriodicPairs, side_node_sets
from chipstack.meshing.mesh import VolumeMesh, element_attributes

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
    region_mm: tuple[float, float, float, float] | None = None,
    periodic: bool = False,
) -> VolumeMesh:
    """Hexahedral mesh of the stack at ``voxel_mm`` (see the module docstring).

    region_mm: (x_min, x_max, y_min, y_max) of a crop, or None for the whole stack.
    periodic: pair the nodes of opposite sides (a crop with the pore space only: the
    sides of anything else do not match)."""
    if pore_space not in ("none", "box"):
        raise InputError(f"pore_space: must be 'none' or 'box', got {pore_space!r}")
    if periodic and (region_mm is None or pore_space != "box"):
        raise InputError("mesh.periodic: needs a crop (mesh.crop) and mesh.pore_space = 'box'")
    start = time.perf_counter()
    image = voxelize(arrangement, voxel_mm)
    labels = image.labels
    origin = np.asarray(image.origin_mm, dtype=float)
    if region_mm is not None:
        labels, origin = _crop(labels, origin, voxel_mm, region_mm)
    # Where the (cropped) labels start on the whole image's lattice.
    offset = np.rint((origin - np.asarray(image.origin_mm)) / voxel_mm).astype(np.int64)
    keep = labels > 0
    if pore_space == "box":
        box = np.zeros_like(keep)
        top = int(np.nonzero(keep.any(axis=(0, 1)))[0].max()) + 1 if keep.any() else 0
        if region_mm is not None:  # the whole region: its sides are full faces
            box[:, :, :top] = True
        else:  # the chips' footprint
            ii, jj = np.nonzero(keep.any(axis=2))
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
    points = np.column_stack([ui, uj, uk]) * voxel_mm + origin
    chip = labels[i, j, k].astype(np.int64) - 1  # void (0) becomes PORE (-1)
    node_sets = side_node_sets(points)
    pairs = None
    if periodic:
        pairs = PeriodicPairs.of_box(points, np.union1d(node_sets["top"], node_sets["bottom"]))
        # One node to hold the box against sliding as a whole: the periodic ties leave
        # a rigid translation free (they already stop a rotation about z).
        corner = np.lexsort((points[:, 2], points[:, 1], points[:, 0]))[:1]
        node_sets["anchor"] = corner
    return VolumeMesh(
        points=points,
        cell_type="hexahedron",
        cells=cells.astype(np.int64),
        chip=chip,
        **element_attributes(arrangement, chip, layer_mm),
        quality=np.ones(len(cells)),
        node_sets=node_sets,
        n_chips=arrangement.n_chips,
        kind="voxel",
        periodic=pairs,
        voxel=np.column_stack([i, j, k]) + offset,
        info={
            "lattice": {
                "origin_mm": [float(v) for v in image.origin_mm],
                "voxel_mm": float(voxel_mm),
                "shape": [int(v) for v in image.labels.shape],
            },
            "voxel_mm": voxel_mm,
            "pore_space": pore_space,
            "region_mm": None if region_mm is None else _meshed_region(points),
            "periodic_pairs": 0 if pairs is None else len(pairs.dependent),
            "mesh_time_s": round(time.perf_counter() - start, 3),
        },
    )


def _crop(
    labels: np.ndarray, origin: np.ndarray, voxel_mm: float, region_mm
) -> tuple[np.ndarray, np.ndarray]:
    """The voxels whose centres lie in the region, and the new origin. The region is the
    user's: one that holds no chip is refused, naming it."""
    x0, x1, y0, y1 = (float(v) for v in region_mm)
    lo = np.ceil((np.array([x0, y0]) - origin[:2]) / voxel_mm - 0.5 - 1e-9).astype(int)
    hi = np.floor((np.array([x1, y1]) - origin[:2]) / voxel_mm - 0.5 + 1e-9).astype(int) + 1
    lo = np.maximum(lo, 0)
    hi = np.minimum(hi, labels.shape[:2])
    cropped = labels[lo[0] : hi[0], lo[1] : hi[1]] if np.all(hi > lo) else labels[:0, :0]
    if not np.any(cropped > 0):
        raise InputError(
            f"mesh.region_mm: the crop x {x0:g} to {x1:g}, y {y0:g} to {y1:g} mm holds no "
            "chip of the stack"
        )
    new_origin = origin.copy()
    new_origin[:2] += lo * voxel_mm
    return cropped, new_origin


def _meshed_region(points: np.ndarray) -> list[float]:
    """The crop as meshed (voxel boundaries): [x_min, x_max, y_min, y_max] mm."""
    low, high = points[:, :2].min(axis=0), points[:, :2].max(axis=0)
    return [float(low[0]), float(high[0]), float(low[1]), float(high[1])]
