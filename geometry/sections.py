"""The geometry stage's scenario table, ``[geometry]`` (see :mod:`packing.sections`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from chipstack.core.keys import between, key
from chipstack.core.schema import Section

__all__ = ["GeometrySpec", "SECTIONS"]


@dataclass(frozen=True)
class GeometrySpec(Section):
    """How the geometry stage describes the stack (see README: Descriptors)."""

    table: ClassVar[str] = "geometry"

    pixel_mm: float = key(
        3.0, "mm", "pixel of the local stack thickness (NEH) map", between(0.05, 1000.0)
    )
    layer_mm: float = key(
        2.0, "mm", "thickness of a layer for layer filling and porosity", between(0.05, 1000.0)
    )
    contact_gap_mm: float = key(
        0.05, "mm", "surfaces closer than this touch (contact types)", between(1e-4, 10.0)
    )
    contact_extent_mm: float = key(
        5.0,
        "mm",
        "a contact patch this long is a line, this long and wide a surface",
        between(1e-3, 1000.0),
    )
    voxel_mm: float = key(1.0, "mm", "voxel of the stack's voxel image", between(0.05, 100.0))


SECTIONS = (GeometrySpec,)
