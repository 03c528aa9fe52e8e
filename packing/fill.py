"""How full a cylindrical container is (paper, section 5; after Freeman et al. 2019)."""

from __future__ import annotations

import math

import numpy as np

from chipstack.packing.sites import reaches_rim

__all__ = ["container_fill"]


def container_fill(
    positions: np.ndarray, volumes_mm3: np.ndarray, radius_mm: float, height_mm: float
) -> dict:
    """Volume fraction of a container, counting a chip whole when its centre of mass is
    inside the cylinder (radius ``radius_mm``, from z = 0 to ``height_mm``) and not at all
    otherwise, as the paper does.

    positions (n, 3) mm; volumes_mm3 (n,) each chip's volume. Returns the counts and
    ``volume_fraction`` (dimensionless), and ``full`` (:func:`reaches_rim`).
    """
    positions = np.asarray(positions, dtype=float).reshape(-1, 3)
    volumes = np.asarray(volumes_mm3, dtype=float).reshape(-1)
    inside = (
        (np.hypot(positions[:, 0], positions[:, 1]) <= radius_mm)
        & (positions[:, 2] >= 0)
        & (positions[:, 2] <= height_mm)
    )
    capacity = math.pi * radius_mm**2 * height_mm
    return {
        "chips_poured": int(len(positions)),
        "chips_inside": int(inside.sum()),
        "container_volume_mm3": capacity,
        "volume_fraction": float(volumes[inside].sum() / capacity),
        "full": reaches_rim(positions, radius_mm, height_mm),
    }
