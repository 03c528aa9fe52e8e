"""The rigid chip every shape builder makes, in its own frame (see :mod:`packing.shapes`)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from chipstack.core.schema import ChipSpec

__all__ = [
    "ALONG_AXIS_DEG",
    "ChipShape",
    "WOVEN_DEG",
    "frozen_array",
    "spec_fibre_directions",
]


@dataclass(frozen=True, eq=False)
class ChipShape:
    """A rigid chip in its own frame.

    Attributes
    ----------
    name: unique name within a stack, e.g. ``box 20x20x2`` or ``star 5 30x2 #12``.
    kind: the registry name of the builder (``box``, ``star``, ...).
    vertices: (V, 3) mm, corners of the exact boundary.
    faces: vertex-index loops, counter-clockwise seen from outside.
    convex_pieces: (Vi, 3) mm corner arrays of convex pieces whose union is the chip.
    fibre_directions: (F, 3) unit vectors in the local frame.
    volume_mm3: exact volume (mm^3).
    inertia_mm2: (3,) principal moments of inertia per unit mass about the local axes
        (mm^2; multiply by the mass in g for g mm^2).
    half_extents: (3,) mm, half sizes of the local bounding box.
    box_centre: (3,) mm, centre of the local bounding box (0 for symmetric chips).
    collision: ``box`` (one PyBullet box), ``cylinder`` (a PyBullet cylinder along local
        x of radius ``radius_mm``) or ``hull`` (one convex hull per piece).
    thickness_mm: the chip's extent along local z.
    """

    name: str
    kind: str
    vertices: np.ndarray
    faces: tuple[tuple[int, ...], ...]
    convex_pieces: tuple[np.ndarray, ...]
    fibre_directions: np.ndarray
    volume_mm3: float
    inertia_mm2: np.ndarray
    half_extents: np.ndarray
    box_centre: np.ndarray
    collision: str = field(default="hull")
    radius_mm: float = field(default=0.0)

    @property
    def thickness_mm(self) -> float:
        return 2.0 * float(self.half_extents[2])

    @property
    def circumradius_mm(self) -> float:
        """Radius of the smallest centred sphere holding the chip (mm)."""
        return float(np.linalg.norm(self.vertices, axis=1).max())

    @property
    def plan_area_mm2(self) -> float:
        """Area of the chip's outline (mm^2): volume over thickness."""
        return self.volume_mm3 / self.thickness_mm

    @property
    def is_cuboid(self) -> bool:
        """One rectangular box along the chip's own axes (a box chip, a beam or fibre of
        box section): what the meshers that build boxes from their extents can take,
        asked of the geometry and not of the builder's name."""
        if len(self.convex_pieces) != 1 or len(self.vertices) != 8:
            return False
        offsets = np.abs(np.asarray(self.vertices) - self.box_centre)
        return bool(np.allclose(offsets, self.half_extents, rtol=0.0, atol=1e-9))

    @property
    def plan_symmetry(self) -> int:
        """How many times the chip maps onto itself in a turn about its own z axis (4 for
        a square, 2 for a rectangle or a rod, 6 for a hexagon, k for a k-pointed star, 1
        for an irregular polygon): a landed chip's yaw is defined modulo 360 deg over it."""
        corners = np.asarray(self.vertices, dtype=float)  # about the centre of mass
        # Loose enough for file chips whose corners were written rounded.
        tolerance = 1e-4 * max(1.0, float(np.abs(corners).max()))
        # A turn that maps the corners onto themselves permutes them in cycles of its
        # order (no corner lies on the axis): only divisors of their number can be.
        orders = [k for k in range(len(corners), 1, -1) if len(corners) % k == 0]
        for order in orders:
            angle = 2 * np.pi / order
            turn = np.array(
                [[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]]
            )
            turned = corners @ turn.T
            gaps = np.linalg.norm(turned[:, None, :] - corners[None, :, :], axis=2).min(axis=1)
            if gaps.max() <= tolerance:
                return order
        return 1


def frozen_array(array: np.ndarray) -> np.ndarray:
    """A read-only float copy of ``array`` (shapes are shared between chips)."""
    array = np.array(array, dtype=float)
    array.setflags(write=False)
    return array


# The fibre directions a shape builder gives when the spec names none: a woven twill
# plate's warp and weft, or a slender chip's fibres along its axis.
WOVEN_DEG = (0.0, 90.0)
ALONG_AXIS_DEG = (0.0,)


def spec_fibre_directions(
    spec: ChipSpec, default_deg: tuple[float, ...], axes: np.ndarray | None = None
) -> np.ndarray:
    """Unit fibre directions in the chip frame: the spec's, else the shape builder's
    ``default_deg``; ``axes`` (2, 2): the frame's x and y axes (columns) in the
    coordinates the directions are given in."""
    degrees = spec.fibre_directions_deg or default_deg
    angles = np.radians(np.asarray(degrees, dtype=float))
    plane = np.column_stack([np.cos(angles), np.sin(angles)])
    if axes is not None:
        plane = plane @ axes
    return np.column_stack([plane, np.zeros(len(plane))])
