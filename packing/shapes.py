"""Chip shapes, registered by name.

A shape is geometry in the chip's own frame (mm, centred on the centre of mass, the chip's
plane is local z = 0) plus the fibre directions it carries. Packing needs the collision
description (``half_extents`` for boxes); geometry, meshing and export need the exact
polyhedron (``vertices``, ``faces``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from packing.config import ChipSpec
from packing.registry import Registry

__all__ = ["ChipShape", "SHAPES", "make_shape", "box_shape"]


@dataclass(frozen=True, eq=False)
class ChipShape:
    """A rigid chip in its own frame.

    Attributes
    ----------
    name: registry name and parameters, e.g. ``box 20x20x2``.
    half_extents: (3,) mm, half sizes along local x, y, z (boxes).
    vertices: (V, 3) mm, corners in the local frame.
    faces: list of vertex-index loops, counter-clockwise seen from outside.
    fibre_directions: (F, 3) unit vectors in the local frame (in-plane for woven chips).
    volume_mm3: exact volume.
    """

    name: str
    half_extents: np.ndarray
    vertices: np.ndarray
    faces: tuple[tuple[int, ...], ...]
    fibre_directions: np.ndarray
    volume_mm3: float
    kind: str = field(default="box")

    @property
    def circumradius_mm(self) -> float:
        """Radius of the smallest centred sphere holding the chip (mm)."""
        return float(np.linalg.norm(self.vertices, axis=1).max())


_BOX_FACES = (
    (0, 2, 3, 1),  # -z
    (4, 5, 7, 6),  # +z
    (0, 1, 5, 4),  # -y
    (2, 6, 7, 3),  # +y
    (0, 4, 6, 2),  # -x
    (1, 3, 7, 5),  # +x
)


def box_shape(spec: ChipSpec) -> ChipShape:
    """A rectangular plate ``length x width x thickness`` (a square when length == width)."""
    half = np.array([spec.length_mm, spec.width_mm, spec.thickness_mm]) / 2.0
    signs = np.array([[sx, sy, sz] for sz in (-1, 1) for sy in (-1, 1) for sx in (-1, 1)])
    angles = np.radians(np.asarray(spec.fibre_directions_deg, dtype=float))
    fibres = np.column_stack([np.cos(angles), np.sin(angles), np.zeros_like(angles)])
    for array in (half, fibres):
        array.setflags(write=False)
    vertices = signs * half
    vertices.setflags(write=False)
    name = f"box {spec.length_mm:g}x{spec.width_mm:g}x{spec.thickness_mm:g}"
    return ChipShape(
        name=name,
        half_extents=half,
        vertices=vertices,
        faces=_BOX_FACES,
        fibre_directions=fibres,
        volume_mm3=float(np.prod(2 * half)),
    )


SHAPES: Registry = Registry("shape")
SHAPES.register("box", box_shape)


def make_shape(spec: ChipSpec) -> ChipShape:
    """Build the shape named by ``spec.shape`` from the registry."""
    return SHAPES.get(spec.shape, key="chip.shape")(spec)
