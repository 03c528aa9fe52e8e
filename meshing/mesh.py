"""The meshing stage's result: a volume mesh of the stack with per-element chip data."""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from chipstack.core.errors import ChipstackError, InputError
from chipstack.geometry.orientation import fibre_directions_world
from chipstack.meshing.boundaries import PeriodicPairs, Surface, platen_surfaces

if TYPE_CHECKING:
    from chipstack.core.arrangement import Arrangement

__all__ = [
    "MeshingError",
    "VolumeMesh",
    "PORE",
    "region_name",
    "check_voxel_below_thinnest",
    "chip_attributes",
    "element_attributes",
]


class MeshingError(ChipstackError):
    """The stack cannot be meshed as asked (the message names the chips involved)."""


PORE = -1  # chip id of elements in the pore space (void or matrix-rich region)


def region_name(region: int, n_chips: int) -> str:
    """A region's name in the mesh files: ``chip_<id>`` for a chip (id = its packing row
    + 1), ``pore`` for the pore space (id = n_chips + 1)."""
    return f"chip_{region}" if region <= n_chips else "pore"


@dataclass(frozen=True, eq=False)
class VolumeMesh:
    """A volume mesh in millimetres.

    points: (N, 3) mm. cell_type: "tetra" (4 nodes) or "hexahedron" (8 nodes, VTK order).
    cells: (M, k) node indices. chip: (M,) chip index of each element, ``PORE`` (-1) for the
    pore space. batch, layer: (M,) the chip's batch (1-based) and layer (by its centre of
    mass; -1 for pores). fibres: (M, 2, 3) the chip's fibre directions in the world frame
    (zeros for pores; a chip with one direction repeats it). normals: (M, 3) the chip's
    normal (its local z) in the world frame, zeros for pores. quality: (M,) element quality
    (gmsh's SICN; 1 for a cube). node_sets: named node index arrays (``bottom``: on the
    conveyor, ``top``: on the top platen plane, ``xmin`` ... ``ymax`` and ``lateral``: on
    the sides of the domain).
    kind: "conformal" or "voxel". info: how it was made (sizes, tolerances, timings).
    periodic: for a box with periodic sides, the node pairs they tie. voxel: a voxel
    mesh's voxel index of each element (see ``info["lattice"]``).
    """

    points: np.ndarray
    cell_type: str
    cells: np.ndarray
    chip: np.ndarray
    batch: np.ndarray
    layer: np.ndarray
    fibres: np.ndarray
    normals: np.ndarray
    quality: np.ndarray
    node_sets: dict[str, np.ndarray]
    n_chips: int
    kind: str
    info: dict = field(default_factory=dict)
    periodic: PeriodicPairs | None = None  # the node pairs periodic sides tie, if asked
    # A voxel mesh's (M, 3) voxel index (i, j, k) of every hexahedron on the lattice its
    # info's ``lattice`` states (the geometry stage's voxel image at the same voxel size).
    voxel: np.ndarray | None = None

    def __post_init__(self) -> None:
        for name in ("points", "cells", "chip", "batch", "layer", "fibres", "normals", "quality"):
            getattr(self, name).setflags(write=False)

    @property
    def n_elements(self) -> int:
        return len(self.cells)

    @property
    def region(self) -> np.ndarray:
        """(M,) each element's region id, the one integer every mesh file stores for it:
        chip k (row k of the packing tables, 0-based) is k + 1, the pore space
        ``pore_region``."""
        return np.where(self.chip >= 0, self.chip + 1, self.n_chips + 1).astype(np.int64)

    @property
    def pore_region(self) -> int:
        """The pore space's region id: n_chips + 1 (whether or not the mesh has one)."""
        return self.n_chips + 1

    @functools.cached_property
    def surfaces(self) -> dict[str, Surface]:
        """The platen and support surfaces by name (``top``, ``bottom``; with a pore box or
        a crop also ``xmin`` ... ``ymax``), computed once (see
        :func:`meshing.boundaries.platen_surfaces`)."""
        fills_box = bool(np.any(self.chip == PORE))
        with_sides = fills_box or self.info.get("region_mm") is not None
        return platen_surfaces(
            self.points, self.cells, self.cell_type, self.node_sets, with_sides, fills_box
        )

    def element_volumes(self) -> np.ndarray:
        """(M,) mm3, signed volume of every element (positive when correctly oriented)."""
        p = self.points[self.cells]
        if self.cell_type == "tetra":
            return _tet_volumes(p[:, 0], p[:, 1], p[:, 2], p[:, 3])
        # A hexahedron (VTK order) split into five tetrahedra; exact for parallelepipeds.
        total = np.zeros(len(p))
        for a, b, c, d in ((0, 1, 3, 4), (1, 2, 3, 6), (1, 4, 5, 6), (3, 4, 6, 7), (1, 3, 4, 6)):
            total += _tet_volumes(p[:, a], p[:, b], p[:, c], p[:, d])
        return total

    def chip_volumes(self) -> np.ndarray:
        """(n_chips,) mm3, meshed volume of every chip."""
        volumes = self.element_volumes()
        mine = self.chip >= 0
        return np.bincount(self.chip[mine], weights=volumes[mine], minlength=self.n_chips)


def _tet_volumes(a: np.ndarray, b: np.ndarray, c: np.ndarray, d: np.ndarray) -> np.ndarray:
    return np.einsum("ij,ij->i", np.cross(b - a, c - a), d - a) / 6.0


def check_voxel_below_thinnest(
    key: str, voxel_mm: float, arrangement: Arrangement, advised_through: int
) -> None:
    """Refuse (naming ``key``) a voxel not below the thinnest chip dimension: sampled once
    through its thickness, a tilted chip falls apart into pieces joined at edges (half the
    reference stack at 2 mm). The message advises ``advised_through`` voxels through it."""
    thinnest = arrangement.thinnest_mm
    if voxel_mm >= thinnest:
        raise InputError(
            f"{key}: {voxel_mm:g} mm is not below the thinnest chip dimension ({thinnest:g} "
            f"mm); use at most {thinnest / advised_through:g} mm ({advised_through} voxels "
            "through a chip)"
        )


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


def element_attributes(
    arrangement: Arrangement, chip: np.ndarray, layer_mm: float
) -> dict[str, np.ndarray]:
    """batch, layer, fibres and normals of each element from its chip (``PORE``: none)."""
    batch_of, layer_of, fibres_of, normals_of = chip_attributes(arrangement, layer_mm)
    solid = chip >= 0
    safe = np.maximum(chip, 0)
    return {
        "batch": np.where(solid, batch_of[safe], 0),
        "layer": np.where(solid, layer_of[safe], PORE),
        "fibres": np.where(solid[:, None, None], fibres_of[safe], 0.0),
        "normals": np.where(solid[:, None], normals_of[safe], 0.0),
    }
