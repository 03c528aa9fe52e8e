"""The voxel image of chip ids (``voxels.vti``) and its porosity profile against the exact one."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from chipstack.export.vtk import write_voxel_image
from chipstack.geometry.descriptors.base import (
    Context,
    Descriptor,
    profile,
    scalar,
)
from chipstack.geometry.layers import slab_fractions
from chipstack.geometry.voxels import VoxelImage, voxel_solid_profile, voxelize


def _voxel_files(image: VoxelImage, folder: Path) -> list[str]:
    write_voxel_image(folder / "voxels.vti", image)
    return ["voxels.vti"]


def _voxels(ctx: Context):
    image: VoxelImage = voxelize(ctx.final, ctx.spec.voxel_mm)
    profile_voxels = voxel_solid_profile(image)
    h = image.voxel_mm
    edges = h * np.arange(image.labels.shape[2] + 1)
    exact, _ = slab_fractions(ctx.union, ctx.final.target_size_mm, edges)
    scalars = {
        "voxel_mm": scalar(h, "mm", "voxel side"),
        "shape_x": scalar(image.labels.shape[0], "voxels", "image size along x"),
        "shape_y": scalar(image.labels.shape[1], "voxels", "image size along y"),
        "shape_z": scalar(image.labels.shape[2], "voxels", "image size along z"),
        "profile_max_difference": scalar(
            np.abs(profile_voxels - exact).max(initial=0.0),
            "",
            "largest difference between voxel and exact solid fraction of a voxel layer",
        ),
    }
    z = list(h * (np.arange(len(exact)) + 0.5))
    profiles = {
        "solid_fraction_voxels": profile(
            z, profile_voxels, "z (mm)", "", "solid fraction of each voxel layer over the target"
        ),
        "solid_fraction_exact": profile(
            z, exact, "z (mm)", "", "exact solid fraction of the same slabs (manifold3d)"
        ),
    }
    return image, {"scalars": scalars, "profiles": profiles}


DESCRIPTOR = Descriptor(
    "voxels",
    "voxel image of chip ids and its porosity profile against the exact one",
    files=_voxel_files,
    compute=_voxels,
)
