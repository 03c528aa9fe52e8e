"""Chip shapes: their builders (declared and registered by name in
:mod:`packing.shape_kinds`, which names these functions).

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
factor (for size distributions); ``SHAPES`` (re-exported here) names them.
"""

from __future__ import annotations

import numpy as np

from chipstack.core.chipshape import (
    ALONG_AXIS_DEG,
    WOVEN_DEG,
    ChipShape,
    frozen_array,
    spec_fibre_directions,
)
from chipstack.core.errors import InputError, printable
from chipstack.core.keys import MAX_LENGTH_MM
from chipstack.core.schema import ChipSpec
from chipstack.packing.polygons import (
    check_simple,
    convex_partition,
    counter_clockwise,
    random_polygon,
    regular_polygon,
    star_polygon,
)
from chipstack.packing.shape_kinds import (
    SHAPE_CHOICE,
    SHAPES,
    ShapeKind,
    check_chip,
    varies_per_chip,
)
from chipstack.packing.shapefiles import shape_from_file

__all__ = [
    "ChipShape",
    "SHAPES",
    "SHAPE_CHOICE",
    "ShapeKind",
    "check_chip",
    "varies_per_chip",
    "make_shape",
    "box_shape",
    "prism_shape",
    "shape_from_record",
    "shape_record",
]

CYLINDER_SIDES = 24  # polygon standing for a round fibre in the exact geometry


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
    default_fibres_deg: tuple[float, ...] = WOVEN_DEG,
) -> ChipShape:
    """A flat chip: the plane ``outline`` (n, 2) mm extruded through ``thickness_mm``.

    The outline is centred on its centroid and (``principal``) turned to its principal
    axes; fibre directions (the spec's, else ``default_fibres_deg``: a woven plate's
    warp and weft) are turned with it, so they keep their meaning in the outline as
    given.
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
        frozen_array(np.vstack([_at_height(p, -half_t), _at_height(p, half_t)]))
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
        vertices=frozen_array(vertices),
        faces=tuple(faces),
        convex_pieces=pieces,
        fibre_directions=frozen_array(spec_fibre_directions(spec, default_fibres_deg, axes)),
        volume_mm3=float(area * thickness_mm),
        inertia_mm2=frozen_array(inertia),
        half_extents=frozen_array((hi - lo) / 2),
        box_centre=frozen_array((hi + lo) / 2),
        collision=collision,
        radius_mm=radius_mm,
    )


def _rectangle(length: float, width: float) -> np.ndarray:
    return np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=float) * [length / 2, width / 2]


def _box(name, kind, length, width, thickness, spec, fibres_deg=WOVEN_DEG) -> ChipShape:
    outline = _rectangle(length, width)
    return prism_shape(
        name, kind, outline, thickness, spec, collision="box", default_fibres_deg=fibres_deg
    )


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
            return _box(name, kind, length, spec.width_mm, spec.thickness_mm, spec, ALONG_AXIS_DEG)
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
            vertices=frozen_array(vertices),
            faces=tuple(faces),
            convex_pieces=(frozen_array(vertices),),
            fibre_directions=frozen_array(spec_fibre_directions(spec, ALONG_AXIS_DEG)),
            volume_mm3=float(np.pi * r2 * length),
            inertia_mm2=frozen_array(inertia),
            half_extents=frozen_array((hi - lo) / 2),
            box_centre=frozen_array((hi + lo) / 2),
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
    return shape_from_file(spec, size)


beam_shape = _slender("beam")
fibre_shape = _slender("fibre")


def make_shape(
    spec: ChipSpec, rng: np.random.Generator | None = None, size: float = 1.0
) -> ChipShape:
    """Build the shape named by ``spec.shape`` from the registry."""
    return spec.chosen.builder(spec, rng, size)


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
            frozen_array(np.array(p, dtype=float).reshape(-1, 3)) for p in record["convex_pieces"]
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
    name = printable(name)
    arrays = [vertices, fibres, inertia, *pieces]
    if not all(np.isfinite(a).all() for a in arrays) or not np.isfinite([volume, radius]).all():
        raise InputError(f"{where}: shape {name!r} holds NaN or infinite values")
    if len(vertices) < 4:
        raise InputError(f"{where}: shape {name!r} has {len(vertices)} vertices (a solid needs 4)")
    if max(np.abs(a).max(initial=0.0) for a in (vertices, *pieces)) > MAX_LENGTH_MM:
        raise InputError(f"{where}: shape {name!r} has coordinates beyond {MAX_LENGTH_MM:g} mm")
    if volume <= 0 or not pieces or any(len(p) < 4 for p in pieces):
        raise InputError(f"{where}: shape {name!r} has no volume or no convex pieces")
    for k, piece in enumerate(pieces):  # a flat piece has no hull (Qhull fails on it)
        extent = float(np.ptp(piece, axis=0).max())
        if np.linalg.matrix_rank(piece - piece.mean(axis=0), tol=1e-9 * max(extent, 1.0)) < 3:
            raise InputError(f"{where}: shape {name!r}: convex piece {k} is flat (no volume)")
    if collision not in ("box", "cylinder", "hull"):
        raise InputError(f"{where}: shape {name!r} has unknown collision {collision!r}")
    if any(v < 0 or v >= len(vertices) for f in faces for v in f):
        raise InputError(f"{where}: shape {name!r} has a face index out of range")
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    return ChipShape(
        name=name,
        kind=kind,
        vertices=frozen_array(vertices),
        faces=faces,
        convex_pieces=pieces,
        fibre_directions=frozen_array(fibres),
        volume_mm3=volume,
        inertia_mm2=frozen_array(inertia),
        half_extents=frozen_array((hi - lo) / 2),
        box_centre=frozen_array((hi + lo) / 2),
        collision=collision,
        radius_mm=radius,
    )
