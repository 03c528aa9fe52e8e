"""The loose press's bodies: the contact model's chips (each its own block of bricks, in
its settled pose, overlaps cleared), a clearance between every two of them, their
stiffness in each chip's ply frame, and the two platens.

The contact model (:mod:`meshing.contact_model`) already meshes every chip on its own
and clears the physics' overlaps by moving chips apart; chips it leaves touching (a
distance of zero) would start the barrier at infinity. So every chip is shrunk about its
centre by ``clearance_mm`` on each face (half the barrier's activation distance: a
2 mm chip loses 0.05 % of its thickness), which leaves every two surfaces at least twice
that apart, and the platens start that far from the lowest and highest chip points.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from chipstack.meshing.contact_model import ContactModel
from chipstack.meshing.loose.elements import (
    assemble,
    brick_stiffness,
    hex_boundary_triangles,
    node_volumes,
    rotate_stiffness,
)
from chipstack.meshing.loose.ipc import Platens, PressBodies
from chipstack.meshing.loose.material import ChipMaterial

__all__ = ["press_bodies", "ply_frames", "PLATEN_MARGIN"]

PLATEN_MARGIN = 0.1  # platens overhang the chips' footprint by this share of its width


def ply_frames(model: ContactModel) -> np.ndarray:
    """(n, 3, 3) each chip's ply frame, rows: warp, weft, normal (world frame)."""
    normal = model.normals / np.linalg.norm(model.normals, axis=1, keepdims=True)
    warp = model.fibres[:, 0] - np.sum(model.fibres[:, 0] * normal, axis=1)[:, None] * normal
    warp /= np.linalg.norm(warp, axis=1, keepdims=True)
    weft = np.cross(normal, warp)
    return np.stack([warp, weft, normal], axis=1)


def _shrunk(points: np.ndarray, cells: np.ndarray, chip: np.ndarray, frames, clearance):
    """The chips' nodes moved towards their chip's centre by ``clearance`` along each
    of its axes (the faces of a box chip move in by that much)."""
    out = points.copy()
    node_chip = np.full(len(points), -1)
    node_chip[cells.ravel()] = np.repeat(chip, cells.shape[1])
    for k in range(len(frames)):
        nodes = np.flatnonzero(node_chip == k)
        if not len(nodes):
            continue
        local = (points[nodes] - points[nodes].mean(axis=0)) @ frames[k].T
        half = np.abs(local).max(axis=0)
        scale = np.where(half > 2 * clearance, 1 - clearance / np.maximum(half, 1e-12), 1.0)
        out[nodes] = points[nodes].mean(axis=0) + (local * scale) @ frames[k]
    return out


def press_bodies(
    model: ContactModel, material: ChipMaterial, clearance_mm: float
) -> tuple[PressBodies, Platens]:
    """The chips of ``model`` as separate elastic bodies of ``material`` and the two
    platens (see the module docstring)."""
    used = np.unique(model.cells)
    index = np.full(len(model.points), -1)
    index[used] = np.arange(len(used))
    cells = index[model.cells]
    frames = ply_frames(model)
    points = _shrunk(model.points[used], cells, model.chip, frames, clearance_mm)
    local = material.stiffness()
    world = rotate_stiffness(local, frames)[model.chip]
    stiffness = assemble(cells, brick_stiffness(points[cells], world), len(points))
    viscous = None
    if (eta := material.viscosity()) is not None:
        # Isotropic: the same tensor in every frame.
        matrices = brick_stiffness(points[cells], np.repeat(eta[None], len(cells), axis=0))
        viscous = sp.csr_matrix(assemble(cells, matrices, len(points)))
    bodies = PressBodies(
        points=points,
        cells=cells,
        chip=np.asarray(model.chip),
        stiffness=stiffness,
        viscous=viscous,
        node_volume=node_volumes(points, cells),
        surface=hex_boundary_triangles(cells),
    )
    lo, hi = points.min(axis=0), points.max(axis=0)
    margin = PLATEN_MARGIN * max(hi[0] - lo[0], hi[1] - lo[1])
    platens = Platens(
        bottom_z=float(lo[2] - clearance_mm),
        top_z=float(hi[2] + clearance_mm),
        xy=(lo[0] - margin, hi[0] + margin, lo[1] - margin, hi[1] + margin),
    )
    return bodies, platens
