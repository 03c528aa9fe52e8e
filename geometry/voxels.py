"""Voxel image of the stack: chip id per voxel (0 for void), from the exact solids.

A voxel belongs to a chip when its centre lies inside the chip's exact solid (the same
convex pieces the manifold3d solids are built from, tested along vertical lines through
the voxel centres). Where the physics left two chips interpenetrating, the voxel goes to
the lower chip, the one that came to rest first (see
:meth:`Arrangement.bottom_up_order`), the rule the meshing stage also follows.
The grid is aligned on the target's corner and the conveyor (z = 0) and covers every chip.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from chipstack.core.arrangement import Arrangement
from chipstack.core.errors import InputError
from chipstack.geometry.rays import column_intervals

__all__ = ["VoxelImage", "voxelize", "voxel_solid_profile"]

MAX_VOXELS = 400_000_000


@dataclass(frozen=True)
class VoxelImage:
    """labels (nx, ny, nz) int32: 1 + chip index, 0 for void; voxel (i, j, k) spans
    origin + voxel_mm * [(i, j, k), (i + 1, j + 1, k + 1)] (mm). n_chips: the stack's chip
    count (the files give a void voxel the pore space's region id, n_chips + 1)."""

    labels: np.ndarray
    origin_mm: tuple[float, float, float]
    voxel_mm: float
    target_size_mm: float
    n_chips: int

    def centres(self, axis: int) -> np.ndarray:
        """(n,) mm, voxel centres along ``axis``."""
        return self.origin_mm[axis] + self.voxel_mm * (np.arange(self.labels.shape[axis]) + 0.5)

    def on_target(self) -> np.ndarray:
        """(nx, ny) bool: the voxel column's centre lies over the target."""
        half = self.target_size_mm / 2
        inside_x = np.abs(self.centres(0)) <= half
        inside_y = np.abs(self.centres(1)) <= half
        return inside_x[:, None] & inside_y[None, :]


def voxelize(arrangement: Arrangement, voxel_mm: float = 0.5) -> VoxelImage:
    """The stack as a voxel image of chip ids at ``voxel_mm`` (see the module docstring)."""
    if not (math.isfinite(voxel_mm) and voxel_mm > 0):
        raise InputError(f"voxel_mm: must be positive, got {voxel_mm!r}")
    half = arrangement.target_size_mm / 2
    low = np.array([-half, -half, 0.0])
    high = np.array([half, half, voxel_mm])
    if arrangement.n_chips:
        low[:2] = np.minimum(low[:2], arrangement.bounds[:, 0, :2].min(axis=0))
        high = np.maximum(high, arrangement.bounds[:, 1].max(axis=0))
    before = np.ceil((np.array([-half, -half]) - low[:2]) / voxel_mm)
    origin = np.array([-half - before[0] * voxel_mm, -half - before[1] * voxel_mm, 0.0])
    shape = np.ceil((high - origin) / voxel_mm - 1e-9).astype(int)
    if int(np.prod(shape)) > MAX_VOXELS:
        raise InputError(
            f"voxel_mm: {voxel_mm} mm gives {shape[0]} x {shape[1]} x {shape[2]} voxels "
            f"(over {MAX_VOXELS:,}); choose a larger voxel"
        )
    labels = np.zeros(tuple(shape), dtype=np.int32)
    x = origin[0] + voxel_mm * (np.arange(shape[0]) + 0.5)
    y = origin[1] + voxel_mm * (np.arange(shape[1]) + 0.5)
    z = voxel_mm * (np.arange(shape[2]) + 0.5)
    bounds = arrangement.bounds
    order = arrangement.bottom_up_order()
    for chip, sx, sy, bottom, top in column_intervals(arrangement, x, y, order):
        k0 = max(0, math.ceil(bounds[chip, 0, 2] / voxel_mm - 0.5))
        k1 = min(shape[2], math.floor(bounds[chip, 1, 2] / voxel_mm - 0.5) + 1)
        if k1 <= k0:
            continue
        zc = z[k0:k1]
        inside = (zc >= bottom[..., None]) & (zc <= top[..., None])
        block = labels[sx, sy, k0:k1]
        block[inside & (block == 0)] = chip + 1
    labels.setflags(write=False)
    return VoxelImage(
        labels,
        tuple(float(v) for v in origin),
        float(voxel_mm),
        float(arrangement.target_size_mm),
        arrangement.n_chips,
    )


def voxel_solid_profile(image: VoxelImage) -> np.ndarray:
    """(nz,) solid fraction of each voxel layer over the target (dimensionless)."""
    columns = image.on_target()
    if not columns.any():
        return np.zeros(image.labels.shape[2])
    solid = image.labels[columns] > 0  # (columns, nz)
    return solid.mean(axis=0)
