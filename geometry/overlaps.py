"""Overlaps between chips: what the physics left (volumes) and what lies over what (areas).

* Interpenetration volume of a pair: the volume of the intersection of the two exact
  solids (mm3). Rigid chips cannot share space; this measures the solver's residual error.
* Projected overlap area of a pair: the area of the intersection of the two chips'
  footprints on the conveyor plane (mm2), for chips stacked over one another. This is the
  "overlap area between objects" the paper's conclusion asks for: the area over which one
  chip will be pressed onto another in consolidation.
"""

from __future__ import annotations

from dataclasses import dataclass

import manifold3d as m3
import numpy as np

from chipstack.core.arrangement import Arrangement
from chipstack.geometry.contacts import candidate_pairs
from chipstack.geometry.solids import chip_solid, shape_pieces

__all__ = ["Overlaps", "footprint", "find_overlaps"]


def footprint(arrangement: Arrangement, chip: int) -> m3.CrossSection:
    """The chip's shadow on the plane z = 0 (mm): union of its pieces' projected hulls."""
    shape = arrangement.shapes[arrangement.shape_index[chip]]
    rotation, position = arrangement.rotations[chip], arrangement.positions[chip]
    hulls = [
        m3.CrossSection.hull_points((piece.vertices @ rotation.T + position)[:, :2])
        for piece in shape_pieces(shape)
    ]
    return hulls[0] if len(hulls) == 1 else m3.CrossSection.batch_boolean(hulls, m3.OpType.Add)


@dataclass(frozen=True)
class Overlaps:
    """Pairwise overlaps of one stack.

    pairs: (k, 2) chip indices i < j whose footprints overlap.
    projected_mm2: (k,) area of the two footprints' intersection (mm2).
    penetration_mm3: (k,) volume of the two solids' intersection (mm3).
    per_chip_projected_mm2, per_chip_penetration_mm3: (n,) sums over each chip's pairs.
    """

    pairs: np.ndarray
    projected_mm2: np.ndarray
    penetration_mm3: np.ndarray
    per_chip_projected_mm2: np.ndarray
    per_chip_penetration_mm3: np.ndarray

    @property
    def total_projected_mm2(self) -> float:
        return float(self.projected_mm2.sum())

    @property
    def total_penetration_mm3(self) -> float:
        return float(self.penetration_mm3.sum())


def find_overlaps(arrangement: Arrangement) -> Overlaps:
    """Projected overlap areas and interpenetration volumes of every pair of chips."""
    n = arrangement.n_chips
    bounds = arrangement.bounds
    # Footprints overlap only if the plan bounding boxes do.
    candidates = candidate_pairs(bounds[:, :, :2], 0.0)
    shadows: dict[int, m3.CrossSection] = {}

    def shadow(chip: int) -> m3.CrossSection:
        if chip not in shadows:
            shadows[chip] = footprint(arrangement, chip)
        return shadows[chip]

    keep, areas, volumes = [], [], []
    for i, j in candidates:
        area = (shadow(i) ^ shadow(j)).area()
        if area <= 0:
            continue
        volume = 0.0
        boxes_meet = (bounds[i, 0] <= bounds[j, 1]).all() and (bounds[j, 0] <= bounds[i, 1]).all()
        if boxes_meet:
            volume = (chip_solid(arrangement, i) ^ chip_solid(arrangement, j)).volume()
        keep.append((i, j))
        areas.append(area)
        volumes.append(volume)
    pairs = np.array(keep, dtype=np.int64).reshape(-1, 2)
    projected = np.array(areas, dtype=float)
    penetration = np.array(volumes, dtype=float)
    per_area = np.zeros(n)
    per_volume = np.zeros(n)
    for column in (0, 1):
        np.add.at(per_area, pairs[:, column], projected)
        np.add.at(per_volume, pairs[:, column], penetration)
    result = Overlaps(pairs, projected, penetration, per_area, per_volume)
    for array in (pairs, projected, penetration, per_area, per_volume):
        array.setflags(write=False)
    return result
