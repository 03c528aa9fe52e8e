"""The chip shapes' declarations, registered by name: each shape's own keys, what it can
do, which sizes make one and how big it is, with its builder named by module (the
builders and their numerics are in :mod:`packing.shapes`, imported when a chip is built):
reading and checking a scenario loads no numerical library."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from chipstack.core.errors import InputError
from chipstack.core.keys import LENGTH_UNITS_MM, between, key, length, one_of
from chipstack.core.lazy import named
from chipstack.core.registry import Registry
from chipstack.core.schema import ChipSpec, KindChoice, Parameters

if TYPE_CHECKING:
    import numpy as np

    from chipstack.core.chipshape import ChipShape

__all__ = [
    "SHAPES",
    "SHAPE_CHOICE",
    "ShapeKind",
    "BoxKeys",
    "PolygonKeys",
    "StarKeys",
    "RandomPolygonKeys",
    "SlenderKeys",
    "FileKeys",
    "check_chip",
    "varies_per_chip",
]

Builder = Callable[[ChipSpec, "np.random.Generator | None", float], "ChipShape"]
SizeCheck = Callable[[ChipSpec, str], None]


def _thickness(doc: str = "thickness (local z)"):
    return key(2.0, "mm", doc, length)


@dataclass(frozen=True)
class BoxKeys(Parameters):
    length_mm: float = key(20.0, "mm", "length (local x)", length)
    width_mm: float = key(20.0, "mm", "width (local y)", length)
    thickness_mm: float = _thickness()


@dataclass(frozen=True)
class PolygonKeys(Parameters):
    length_mm: float = key(20.0, "mm", "diameter of the circle through the corners", length)
    thickness_mm: float = _thickness()
    sides: int = key(6, "", "sides", between(3, 64))


@dataclass(frozen=True)
class StarKeys(Parameters):
    length_mm: float = key(20.0, "mm", "diameter of the circle through the tips", length)
    thickness_mm: float = _thickness()
    sides: int = key(6, "", "points", between(3, 64))
    inner_ratio: float = key(
        0.5, "", "radius of the notches over the radius of the tips", between(0.05, 0.95)
    )


@dataclass(frozen=True)
class RandomPolygonKeys(Parameters):
    length_mm: float = key(20.0, "mm", "diameter of the circle the corners lie within", length)
    thickness_mm: float = _thickness()
    sides: int = key(6, "", "corners", between(3, 64))
    convex: bool = key(True, "", "convex outline (else star-shaped)")
    irregularity: float = key(
        0.5,
        "",
        "non-convex: corner radii uniform in [1 - irregularity, 1] x radius",
        between(0.0, 0.9),
    )


@dataclass(frozen=True)
class SlenderKeys(Parameters):
    length_mm: float = key(20.0, "mm", "length (local x, the fibres' direction)", length)
    width_mm: float = key(20.0, "mm", "width (local y) of a box section", length)
    thickness_mm: float = _thickness("thickness (local z) of a box section; a cylinder's diameter")
    section: str = key("box", "", "cross-section `box` or `cylinder`", one_of("box", "cylinder"))


@dataclass(frozen=True)
class FileKeys(Parameters):
    file: str = key("", "", "an STL, OBJ or PLY file (relative to the scenario file)", path=True)
    units: str = key(
        "mm",
        "",
        f"the length unit of the file's coordinates ({', '.join(LENGTH_UNITS_MM)})",
        one_of(*LENGTH_UNITS_MM),
    )


@dataclass(frozen=True)
class LegacyShapeKeys(Parameters):
    """The keys every shape had before each declared its own: what a shape from a plugin
    that declares none reads."""

    length_mm: float = key(20.0, "mm", "length (local x), or the outline's diameter", length)
    width_mm: float = key(20.0, "mm", "width (local y)", length)
    thickness_mm: float = _thickness()
    sides: int = key(6, "", "sides, points or corners of an outline", between(3, 64))
    inner_ratio: float = key(
        0.5, "", "a star's notch radius over its tip radius", between(0.05, 0.95)
    )
    convex: bool = key(True, "", "convex outline (else star-shaped)")
    irregularity: float = key(0.5, "", "corner radii spread (non-convex)", between(0.0, 0.9))
    section: str = key("box", "", "cross-section `box` or `cylinder`", one_of("box", "cylinder"))


@dataclass(frozen=True)
class ShapeKind:
    """One registered shape: how to build it, its own keys, which sizes make one, and how
    big it is.

    ``parameters`` is its own table of keys (a :class:`core.schema.Parameters`), read in
    ``[chip]`` when ``shape`` names it; ``check(spec, key)`` refuses sizes that do not
    make this shape (``key`` names the scenario table); ``extent(spec)`` is (largest
    in-plane extent, circumradius) in mm of a chip of nominal size, used to check it fits
    the target and clears the floor.
    """

    build: Builder | str  # or "module:function", imported when the first chip is built
    check: SizeCheck
    extent: Callable[[ChipSpec], tuple[float, float]]
    varies_per_chip: bool = False  # a new outline for every chip
    reads_file: bool = False  # built from a geometry file (a key declared with path)
    # Its own keys; a shape declared before shapes owned their keys reads the keys every
    # shape then had (LegacyShapeKeys).
    parameters: type[Parameters] = field(default=None)  # type: ignore[assignment]

    def __post_init__(self) -> None:
        if self.parameters is None:
            object.__setattr__(self, "parameters", LegacyShapeKeys)

    @property
    def builder(self) -> Builder:
        """The builder function (imported from its module the first time, if named)."""
        return named(self.build) if isinstance(self.build, str) else self.build


def _plate_check(spec: ChipSpec, key: str) -> None:
    if spec.thickness_mm >= spec.length_mm:
        raise InputError(f"{key}.thickness_mm: a chip must be thinner than it is across")


def _box_check(spec: ChipSpec, key: str) -> None:
    if spec.thickness_mm >= min(spec.length_mm, spec.width_mm):
        raise InputError(f"{key}.thickness_mm: a chip must be thinner than it is long and wide")


def _slender_check(spec: ChipSpec, key: str) -> None:
    if spec.section == "box" and spec.width_mm > spec.length_mm:
        raise InputError(f"{key}.width_mm: a {spec.shape} must not be wider than it is long")
    if spec.section == "box" and spec.thickness_mm > spec.width_mm:
        raise InputError(f"{key}.thickness_mm: a {spec.shape} must not be thicker than it is wide")
    if spec.thickness_mm >= spec.length_mm:
        raise InputError(f"{key}.thickness_mm: a {spec.shape} must be longer than it is thick")


def _file_check(spec: ChipSpec, key: str) -> None:
    if not spec.file:
        raise InputError(f"{key}.file: give the geometry file of a `file` chip")


def _rectangle_extent(spec: ChipSpec) -> tuple[float, float]:
    width = spec.thickness_mm if getattr(spec, "section", "box") == "cylinder" else spec.width_mm
    across = math.hypot(spec.length_mm, width)
    return across, 0.5 * math.hypot(across, spec.thickness_mm)


def _round_extent(spec: ChipSpec) -> tuple[float, float]:
    return spec.length_mm, 0.5 * math.hypot(spec.length_mm, spec.thickness_mm)


def _file_extent(spec: ChipSpec) -> tuple[float, float]:
    # The file is read with numpy and trimesh: only when a file chip is checked.
    return named("chipstack.packing.shapefiles:file_extent")(spec)


SHAPES: Registry[ShapeKind] = Registry("shape", "chipstack.shapes")
_BUILDERS = "chipstack.packing.shapes"  # numpy and the polygon code: imported when used
SHAPES.register(
    "box", ShapeKind(f"{_BUILDERS}:box_shape", _box_check, _rectangle_extent, parameters=BoxKeys)
)
SHAPES.register(
    "polygon",
    ShapeKind(f"{_BUILDERS}:polygon_shape", _plate_check, _round_extent, parameters=PolygonKeys),
)
SHAPES.register(
    "star", ShapeKind(f"{_BUILDERS}:star_shape", _plate_check, _round_extent, parameters=StarKeys)
)
SHAPES.register(
    "random_polygon",
    ShapeKind(
        f"{_BUILDERS}:random_polygon_shape",
        _plate_check,
        _round_extent,
        parameters=RandomPolygonKeys,
        varies_per_chip=True,
    ),
)
SHAPES.register(
    "beam",
    ShapeKind(f"{_BUILDERS}:beam_shape", _slender_check, _rectangle_extent, parameters=SlenderKeys),
)
SHAPES.register(
    "fibre",
    ShapeKind(
        f"{_BUILDERS}:fibre_shape", _slender_check, _rectangle_extent, parameters=SlenderKeys
    ),
)
SHAPES.register(
    "file",
    ShapeKind(
        f"{_BUILDERS}:file_shape", _file_check, _file_extent, parameters=FileKeys, reads_file=True
    ),
)


# How [chip] (and each [[mix]] table) chooses its shape: the packing stage declares it.
SHAPE_CHOICE = KindChoice.of_registry(SHAPES)


def varies_per_chip(spec: ChipSpec) -> bool:
    """Whether every chip of this spec gets its own outline (random polygons)."""
    return spec.chosen.varies_per_chip


def check_chip(spec: ChipSpec, key: str) -> tuple[float, float]:
    """Refuse a chip spec that makes no chip (naming ``key``); returns its nominal
    (largest in-plane extent, circumradius) in mm."""
    kind = spec.chosen
    kind.check(spec, key)
    if spec.size_distribution != "fixed" and spec.size_spread == 0:
        raise InputError(f"{key}.size_spread: a {spec.size_distribution} size needs a spread > 0")
    return kind.extent(spec)
