"""Chip shapes, registered by name.

A shape is geometry in the chip's own frame (mm): centred on its centre of mass, turned
to its principal axes of inertia, with the chip's plane at local z = 0 for flat chips and
a fibre's axis along local x. It carries:

* the exact boundary (``vertices``, ``faces``) for pictures and files;
* an exact partition into convex pieces (``convex_pieces``): a non-convex chip (a star)
  is the union of its pieces, so the physics gets convex collision shapes and the geometry
  stage and the mesher the exact solid. Chips read from a geometry file that are not
  convex use an approximate decomposition (V-HACD); see :mod:`packing.shapefiles`;
* its fibre directions (unit vectors in its frame) and its inertia per unit mass.

Builders take a :class:`ChipSpec`, a random generator (for random outlines) and a size
factor (for size distributions), and are registered in ``SHAPES``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from packing.config import ChipSpec
from packing.errors import InputError
from packing.polygons import (
    check_simple,
    convex_partition,
    counter_clockwise,
    random_polygon,
    regular_polygon,
    star_polygon,
)
from packing.registry import Registry

__all__ = [
    "ChipShape",
    "SHAPES",
    "make_shape",
    "box_shape",
    "prism_shape",
    "shape_from_record",
    "shape_record",
    "DEFAULT_FIBRES_DEG",
]

CYLINDER_SIDES = 24  # polygon standing for a round fibre in the exact geometry


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


def _frozen(array: np.ndarray) -> np.ndarray:
    array = np.array(array, dtype=float)
    array.setflags(write=False)
    return array


DEFAULT_FIBRES_DEG = {"beam": (0.0,), "fibre": (0.0,)}  # others: woven twill (0, 90)


def _fibres(spec: ChipSpec, kind: str, axes: np.ndarray | None = None) -> np.ndarray:
    """Unit fibre directions in the chip frame; ``axes`` (2, 2): the frame's x and y axes
    (columns) in the coordinates the directions are given in."""
    degrees = spec.fibre_directions_deg or DEFAULT_FIBRES_DEG.get(kind, (0.0, 90.0))
    angles = np.radians(np.asarray(degrees, dtype=float))
    plane = np.column_stack([np.cos(angles), np.sin(angles)])
    if axes is not None:
        plane = plane @ axes
    return np.column_stack([plane, np.zeros(len(plane))])


def _at_height(outline: np.ndarray, z: float) -> np.ndarray:
    return np.column_stack([outline, np.full(len(outline), z)])


def _polygon_moments(points: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Area, centroid (2,) and second moments [Ixx, Iyy, Ixy] about the centroid (mm^4)."""
    x, y = points.T
    xn, yn = np.roll(x, -1), np.roll(y, -1)
    cross = x * yn - xn * y
    area = cross.sum() / 2
    cx = ((x + xn) * cross).sum() / (6 * area)
    cy = ((y + yn) * cross).sum() / (6 * area)
    x, y = x - cx, y - cy
    xn, yn = xn - cx, yn - cy
    cross = x * yn - xn * y
    ixx = ((y * y + y * yn + yn * yn) * cross).sum() / 12  # integral of y^2
    iyy = ((x * x + x * xn + xn * xn) * cross).sum() / 12  # integral of x^2
    ixy = ((x * yn + 2 * x * y + 2 * xn * yn + xn * y) * cross).sum() / 24
    return float(area), np.array([cx, cy]), np.array([ixx, iyy, ixy])


def prism_shape(
    name: str,
    kind: str,
    outline: np.ndarray,
    thickness_mm: float,
    spec: ChipSpec,
    collision: str = "hull",
    radius_mm: float = 0.0,
    principal: bool = True,
) -> ChipShape:
    """A flat chip: the plane ``outline`` (n, 2) mm extruded through ``thickness_mm``.

    The outline is centred on its centroid and (``principal``) turned to its principal
    axes; fibre directions are turned with it, so they keep their meaning in the outline
    as given.
    """
    outline = counter_clockwise(check_simple(outline, f"{name}: outline"))
    area, centroid, (ixx, iyy, ixy) = _polygon_moments(outline)
    outline = outline - centroid
    axes = np.eye(2)  # columns: the local x and y axes, in the outline's coordinates
    if principal and abs(ixy) > 1e-9 * max(ixx, iyy):
        # Principal axes: eigenvectors of the second moments, the long axis as local x.
        values, vectors = np.linalg.eigh(np.array([[iyy, ixy], [ixy, ixx]]))
        axes = vectors[:, ::-1]
        if np.linalg.det(axes) < 0:
            axes[:, 1] *= -1
        outline = outline @ axes
        area, _, (ixx, iyy, ixy) = _polygon_moments(outline)
    half_t = thickness_mm / 2
    n = len(outline)
    vertices = np.vstack(
        [
            np.column_stack([outline, np.full(n, -half_t)]),
            np.column_stack([outline, np.full(n, half_t)]),
        ]
    )
    faces = [tuple(range(n - 1, -1, -1)), tuple(range(n, 2 * n))]
    faces += [(i, (i + 1) % n, n + (i + 1) % n, n + i) for i in range(n)]
    pieces = tuple(
        _frozen(np.vstack([_at_height(p, -half_t), _at_height(p, half_t)]))
        for p in convex_partition(outline)
    )
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    thickness_term = thickness_mm**2 / 12
    inertia = np.array(
        [ixx / area + thickness_term, iyy / area + thickness_term, (ixx + iyy) / area]
    )
    return ChipShape(
        name=name,
        kind=kind,
        vertices=_frozen(vertices),
        faces=tuple(faces),
        convex_pieces=pieces,
        fibre_directions=_frozen(_fibres(spec, kind, axes)),
        volume_mm3=float(area * thickness_mm),
        inertia_mm2=_frozen(inertia),
        half_extents=_frozen((hi - lo) / 2),
        box_centre=_frozen((hi + lo) / 2),
        collision=collision,
        radius_mm=radius_mm,
    )


def _rectangle(length: float, width: float) -> np.ndarray:
    return np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=float) * [length / 2, width / 2]


def _box(name: str, kind: str, length: float, width: float, thickness: float, spec: ChipSpec):
    return prism_shape(name, kind, _rectangle(length, width), thickness, spec, collision="box")


def box_shape(spec: ChipSpec, rng: np.random.Generator | None = None, size: float = 1.0):
    """A rectangular plate ``length x width x thickness`` (a square when length == width)."""
    length, width = spec.length_mm * size, spec.width_mm * size
    name = f"box {length:g}x{width:g}x{spec.thickness_mm:g}"
    return _box(name, "box", length, width, spec.thickness_mm, spec)


def polygon_shape(spec: ChipSpec, rng: np.random.Generator | None = None, size: float = 1.0):
    """A regular polygon of ``sides`` sides inscribed in a circle of diameter ``length_mm``."""
    across = spec.length_mm * size
    outline = regular_polygon(spec.sides, across / 2)
    name = f"polygon {spec.sides} {across:g}x{spec.thickness_mm:g}"
    return prism_shape(name, "polygon", outline, spec.thickness_mm, spec, principal=False)


def star_shape(spec: ChipSpec, rng: np.random.Generator | None = None, size: float = 1.0):
    """A star with ``sides`` tips on a circle of diameter ``length_mm``, notches at
    ``inner_ratio`` of that radius (non-convex: split into convex pieces)."""
    across = spec.length_mm * size
    outline = star_polygon(spec.sides, across / 2, spec.inner_ratio * across / 2)
    name = f"star {spec.sides} {across:g}x{spec.thickness_mm:g}"
    return prism_shape(name, "star", outline, spec.thickness_mm, spec, principal=False)


def random_polygon_shape(spec: ChipSpec, rng: np.random.Generator | None = None, size: float = 1.0):
    """A seeded random polygon of ``sides`` corners within a circle of diameter
    ``length_mm``: convex, or radii spread by ``irregularity`` when ``convex`` is false."""
    if rng is None:
        raise InputError("chip.shape: random_polygon needs a random generator")
    across = spec.length_mm * size
    outline = random_polygon(rng, spec.sides, across / 2, spec.convex, spec.irregularity)
    name = f"random_polygon {spec.sides} {across:g}x{spec.thickness_mm:g}"
    return prism_shape(name, "random_polygon", outline, spec.thickness_mm, spec)


def _slender(kind: str):
    def build(spec: ChipSpec, rng: np.random.Generator | None = None, size: float = 1.0):
        length = spec.length_mm * size
        if spec.section == "box":
            name = f"{kind} {length:g}x{spec.width_mm:g}x{spec.thickness_mm:g}"
            return _box(name, kind, length, spec.width_mm, spec.thickness_mm, spec)
        # A round rod along local x. The exact geometry is a prism of CYLINDER_SIDES sides
        # with the circle's area, the physics a true PyBullet cylinder.
        diameter = spec.thickness_mm
        sides = CYLINDER_SIDES
        r_equal_area = diameter / 2 * np.sqrt(2 * np.pi / (sides * np.sin(2 * np.pi / sides)))
        section = regular_polygon(sides, r_equal_area)  # (y, z), counter-clockwise about +x
        ends = [np.column_stack([np.full(sides, x), section]) for x in (-length / 2, length / 2)]
        vertices = np.vstack(ends)
        faces = [tuple(range(sides - 1, -1, -1)), tuple(range(sides, 2 * sides))]
        faces += [(i, (i + 1) % sides, sides + (i + 1) % sides, sides + i) for i in range(sides)]
        r2 = (diameter / 2) ** 2
        inertia = np.array([r2 / 2, r2 / 4 + length**2 / 12, r2 / 4 + length**2 / 12])
        lo, hi = vertices.min(axis=0), vertices.max(axis=0)
        return ChipShape(
            name=f"{kind} {length:g}xd{diameter:g}",
            kind=kind,
            vertices=_frozen(vertices),
            faces=tuple(faces),
            convex_pieces=(_frozen(vertices),),
            fibre_directions=_frozen(_fibres(spec, kind)),
            volume_mm3=float(np.pi * r2 * length),
            inertia_mm2=_frozen(inertia),
            half_extents=_frozen((hi - lo) / 2),
            box_centre=_frozen((hi + lo) / 2),
            collision="cylinder",
            radius_mm=diameter / 2,
        )

    build.__doc__ = (
        f"A {kind}: ``length_mm`` long, ``section`` box (``width_mm`` x ``thickness_mm``) "
        "or cylinder (diameter ``thickness_mm``); fibres along its length by default."
    )
    return build


def file_shape(spec: ChipSpec, rng: np.random.Generator | None = None, size: float = 1.0):
    """A chip read from a geometry file (STL, OBJ, PLY); see :mod:`packing.shapefiles`."""
    from packing.shapefiles import shape_from_file

    return shape_from_file(spec, size)


Builder = Callable[[ChipSpec, "np.random.Generator | None", float], ChipShape]
SHAPES: Registry[Builder] = Registry("shape")
SHAPES.register("box", box_shape)
SHAPES.register("polygon", polygon_shape)
SHAPES.register("star", star_shape)
SHAPES.register("random_polygon", random_polygon_shape)
SHAPES.register("beam", _slender("beam"))
SHAPES.register("fibre", _slender("fibre"))
SHAPES.register("file", file_shape)

VARIES_PER_CHIP = {"random_polygon"}  # a new outline for every chip


def make_shape(
    spec: ChipSpec, rng: np.random.Generator | None = None, size: float = 1.0
) -> ChipShape:
    """Build the shape named by ``spec.shape`` from the registry."""
    return SHAPES.get(spec.shape, key="chip.shape")(spec, rng, size)


def shape_record(shape: ChipShape) -> dict:
    """A JSON-ready record of a shape, enough to rebuild it exactly (run directories)."""
    return {
        "name": shape.name,
        "kind": shape.kind,
        "vertices": shape.vertices.tolist(),
        "faces": [list(f) for f in shape.faces],
        "convex_pieces": [p.tolist() for p in shape.convex_pieces],
        "fibre_directions": shape.fibre_directions.tolist(),
        "volume_mm3": shape.volume_mm3,
        "inertia_mm2": shape.inertia_mm2.tolist(),
        "collision": shape.collision,
        "radius_mm": shape.radius_mm,
    }


def shape_from_record(record: dict, where: str) -> ChipShape:
    """Rebuild a shape from :func:`shape_record`'s output; errors name ``where``."""
    try:
        vertices = np.array(record["vertices"], dtype=float).reshape(-1, 3)
        pieces = tuple(
            _frozen(np.array(p, dtype=float).reshape(-1, 3)) for p in record["convex_pieces"]
        )
        faces = tuple(tuple(int(v) for v in f) for f in record["faces"])
        fibres = np.array(record["fibre_directions"], dtype=float).reshape(-1, 3)
        volume = float(record["volume_mm3"])
        inertia = np.array(record["inertia_mm2"], dtype=float).reshape(3)
        collision = str(record["collision"])
        radius = float(record["radius_mm"])
        name, kind = str(record["name"]), str(record["kind"])
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f"{where}: malformed shape record ({exc})") from None
    arrays = [vertices, fibres, inertia, *pieces]
    if not all(np.isfinite(a).all() for a in arrays) or not np.isfinite([volume, radius]).all():
        raise InputError(f"{where}: shape {name!r} holds NaN or infinite values")
    if volume <= 0 or not pieces or any(len(p) < 4 for p in pieces):
        raise InputError(f"{where}: shape {name!r} has no volume or no convex pieces")
    if collision not in ("box", "cylinder", "hull"):
        raise InputError(f"{where}: shape {name!r} has unknown collision {collision!r}")
    if any(v < 0 or v >= len(vertices) for f in faces for v in f):
        raise InputError(f"{where}: shape {name!r} has a face index out of range")
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    return ChipShape(
        name=name,
        kind=kind,
        vertices=_frozen(vertices),
        faces=faces,
        convex_pieces=pieces,
        fibre_directions=_frozen(fibres),
        volume_mm3=volume,
        inertia_mm2=_frozen(inertia),
        half_extents=_frozen((hi - lo) / 2),
        box_centre=_frozen((hi + lo) / 2),
        collision=collision,
        radius_mm=radius,
    )
