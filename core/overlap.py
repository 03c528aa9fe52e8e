"""Exact interpenetration of oriented boxes (separating-axis theorem).

Independent of the physics engine: this is how the pipeline checks what PyBullet leaves
behind, and how release positions are kept from overlapping.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

__all__ = [
    "box_penetration_depth",
    "penetrating_pairs",
    "floor_penetration_mm",
    "vertex_heights_mm",
]


def box_penetration_depth(
    centre_a: np.ndarray,
    rotation_a: np.ndarray,
    half_a: np.ndarray,
    centre_b: np.ndarray,
    rotation_b: np.ndarray,
    half_b: np.ndarray,
) -> np.ndarray:
    """Penetration depth of pairs of oriented boxes (mm).

    The smallest translation that separates each pair, found over the 15 separating axes of
    two boxes (exact for convex polyhedra); 0 where the boxes do not overlap.

    Parameters: centres (n, 3) mm; rotations (n, 3, 3) whose columns are the boxes' local
    axes in the world frame; half sizes (n, 3) mm (or (3,), broadcast). Returns (n,) mm.
    """
    centre_a, centre_b = np.atleast_2d(centre_a), np.atleast_2d(centre_b)
    rotation_a = np.asarray(rotation_a).reshape(-1, 3, 3)
    rotation_b = np.asarray(rotation_b).reshape(-1, 3, 3)
    n = max(len(centre_a), len(centre_b))
    half_a = np.broadcast_to(half_a, (n, 3))
    half_b = np.broadcast_to(half_b, (n, 3))
    axes_a = np.swapaxes(rotation_a, 1, 2)  # (n, 3 axes, 3 coords)
    axes_b = np.swapaxes(rotation_b, 1, 2)
    cross = np.cross(axes_a[:, :, None, :], axes_b[:, None, :, :]).reshape(-1, 9, 3)
    norms = np.linalg.norm(cross, axis=2, keepdims=True)
    parallel = norms[..., 0] < 1e-9
    cross = np.where(norms > 1e-9, cross / np.where(norms > 1e-9, norms, 1.0), 0.0)
    axes = np.concatenate(
        [np.broadcast_to(axes_a, (n, 3, 3)), np.broadcast_to(axes_b, (n, 3, 3)), cross], axis=1
    )  # (n, 15, 3)
    radius_a = np.einsum("nk,nak->na", half_a, np.abs(np.einsum("nax,nkx->nak", axes, axes_a)))
    radius_b = np.einsum("nk,nak->na", half_b, np.abs(np.einsum("nax,nkx->nak", axes, axes_b)))
    distance = np.abs(np.einsum("nax,nx->na", axes, centre_b - centre_a))
    overlap = radius_a + radius_b - distance
    overlap[:, 6:][parallel] = np.inf  # a degenerate edge-edge axis separates nothing
    return np.maximum(overlap.min(axis=1), 0.0)


def penetrating_pairs(
    positions: np.ndarray, quaternions: np.ndarray, half_extents: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """All overlapping pairs of a set of boxes and their penetration depths.

    positions (n, 3) mm, quaternions (n, 4) as x, y, z, w, half_extents (n, 3) mm.
    Returns (pairs (m, 2) int, depth (m,) mm) for the pairs with depth > 0.
    """
    positions = np.asarray(positions, dtype=float)
    half_extents = np.broadcast_to(half_extents, positions.shape)
    if len(positions) < 2:
        return np.empty((0, 2), dtype=int), np.empty(0)
    radius = np.linalg.norm(half_extents, axis=1)
    pairs = cKDTree(positions).query_pairs(2 * radius.max(), output_type="ndarray")
    if len(pairs) == 0:
        return np.empty((0, 2), dtype=int), np.empty(0)
    rotations = Rotation.from_quat(quaternions).as_matrix()
    i, j = pairs[:, 0], pairs[:, 1]
    depth = box_penetration_depth(
        positions[i], rotations[i], half_extents[i], positions[j], rotations[j], half_extents[j]
    )
    keep = depth > 0
    return pairs[keep], depth[keep]


def vertex_heights_mm(
    positions: np.ndarray, quaternions: np.ndarray, vertices: np.ndarray
) -> np.ndarray:
    """Height z (mm) of every corner of every chip: (n, V).

    positions (n, 3) mm, quaternions (n, 4) x, y, z, w; vertices (V, 3) mm in the chip
    frame, shared by all chips.
    """
    if len(positions) == 0:
        return np.empty((0, len(vertices)))
    rotations = Rotation.from_quat(quaternions).as_matrix()
    return np.einsum("nij,vj->nvi", rotations, vertices)[..., 2] + np.asarray(positions)[:, None, 2]


def floor_penetration_mm(
    positions: np.ndarray, quaternions: np.ndarray, vertices: np.ndarray
) -> np.ndarray:
    """How far each chip reaches below the floor z = 0 (mm, 0 when it does not).

    vertices (V, 3) mm in the chip frame, shared by all chips.
    """
    return np.maximum(-vertex_heights_mm(positions, quaternions, vertices).min(axis=1), 0.0)
