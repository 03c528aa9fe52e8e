"""Orientation: tilt and in-plane direction of each chip, and fibre orientation tensors.

Future work named by the paper's conclusion (angle distribution of the chips, fibre
orientation among the chips). A chip's own frame has its plane at local z = 0, so:

* tilt: angle between the chip's normal (local z) and the vertical, 0 to 90 degrees;
* in-plane direction: azimuth of the chip's local x axis projected on the conveyor,
  0 to 180 degrees from the conveyor's x axis (undefined, reported as NaN, for a chip
  standing on edge with local x vertical);
* second-order orientation tensor of the fibres: A = mean of p (x) p over every fibre
  direction p of every chip (chips weighted equally, each fibre direction of a chip with
  weight 1 / its number of directions). trace(A) = 1; a flat stack of woven chips with
  random in-plane directions gives about diag(0.5, 0.5, 0).
"""

from __future__ import annotations

import numpy as np

from chipstack.core.arrangement import Arrangement

__all__ = ["tilt_deg", "in_plane_direction_deg", "fibre_tensor", "fibre_directions_world"]


def tilt_deg(rotations: np.ndarray) -> np.ndarray:
    """(n,) degrees in [0, 90]: angle of each chip's plane from the horizontal.

    ``rotations`` (n, 3, 3) chip-to-world matrices.
    """
    normal_z = np.abs(np.asarray(rotations)[:, 2, 2])
    return np.degrees(np.arccos(np.clip(normal_z, 0.0, 1.0)))


def in_plane_direction_deg(rotations: np.ndarray) -> np.ndarray:
    """(n,) degrees in [0, 180): azimuth of each chip's local x axis seen from above."""
    r = np.asarray(rotations)
    x, y = r[:, 0, 0], r[:, 1, 0]
    angle = np.degrees(np.arctan2(y, x)) % 180.0
    return np.where(np.hypot(x, y) < 1e-9, np.nan, angle)


def fibre_directions_world(arrangement: Arrangement) -> tuple[np.ndarray, np.ndarray]:
    """Every fibre direction in the world frame: (m, 3) unit vectors and their (m,) chips."""
    vectors, owners = [], []
    for chip in range(arrangement.n_chips):
        shape = arrangement.shapes[arrangement.shape_index[chip]]
        directions = shape.fibre_directions @ arrangement.rotations[chip].T
        vectors.append(directions)
        owners.append(np.full(len(directions), chip))
    if not vectors:
        return np.empty((0, 3)), np.empty(0, dtype=np.int64)
    return np.concatenate(vectors), np.concatenate(owners)


def fibre_tensor(directions: np.ndarray, owners: np.ndarray) -> np.ndarray:
    """(3, 3) second-order orientation tensor of fibre directions (dimensionless).

    ``directions`` (m, 3) unit vectors; ``owners`` (m,) the chip each belongs to. Each chip
    weighs the same. All zeros when there is no fibre.
    """
    d = np.asarray(directions, dtype=float)
    if not len(d):
        return np.zeros((3, 3))
    owners = np.asarray(owners)
    _, inverse, counts = np.unique(owners, return_inverse=True, return_counts=True)
    weights = 1.0 / counts[inverse]
    weights /= weights.sum()
    return np.einsum("m,mi,mj->ij", weights, d, d)
