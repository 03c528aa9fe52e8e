"""Element sizes of a conformal mesh: the chips' size, the pore's larger one growing away
from the chips, finer elements on thin faces and toward corners near the box's planes."""

from __future__ import annotations

import logging

import numpy as np

from chipstack.meshing.boundaries import ON_PLANE_MM
from chipstack.meshing.conformal_quality import SLIVER_FLOOR

log = logging.getLogger(__name__)


PORE_SIZE_FACTOR = 4.0  # the pore's largest element over the chips' by default
# How fast the pore's elements grow away from the chips (mm of edge per mm of distance):
# gentle enough for HXT to fill the grading with well-shaped elements.
PORE_GROWTH = 0.3


def _pore_size(size_mm: float, pore_size_mm: float) -> float:
    return PORE_SIZE_FACTOR * size_mm if pore_size_mm <= 0 else max(pore_size_mm, size_mm)


def _set_mesh_size(
    gmsh,
    size_mm: float,
    planes: bool = False,
    pore_mm: float | None = None,
    chip_volumes: list[int] = (),
    whole_pore: bool = False,
) -> None:
    """Largest element ``size_mm``, graded down toward thin faces; with ``pore_mm`` above
    ``size_mm``, the pore space's elements graded up from ``size_mm`` at the faces of
    ``chip_volumes`` to ``pore_mm`` (most of the box is open air over a sparse stack:
    reference stack, seed 1, median distance of a pore element from a chip 11 mm, 87 %
    of the 4.0 million elements in the pore at ``size_mm`` everywhere).

    Where chips lie on each other in a plane, their outlines cut the shared faces into
    pieces; two outlines a gap apart leave a strip as narrow as the gap, and two crossing
    at a shallow angle a thin wedge. Triangles across such a face are as thin as it
    unless the elements near its edges are that small, so every face narrower than the
    element size (width: twice its area over its perimeter) gets a distance field that
    grades the size from its width at its edges to ``size_mm`` a few widths away.

    ``planes``: the model's bounding box is a crop's sides, the pore box's top and the
    conveyor, planes a chip corner can come near without lying on: graded there too.
    ``whole_pore``: the model is the whole stack with its pore space (millions of
    elements): gmsh's optimiser spends less on it."""
    option = gmsh.option.setNumber
    option("Mesh.MeshSizeMax", float(size_mm))
    option("Mesh.MeshSizeMin", float(size_mm) / 1000)
    # The size field integrated along each curve to a relative 1e-3, not gmsh's 1e-9: the
    # same edge nodes to within a few in a million (reference stack, seed 0), and the
    # curves meshed in 0.7 s instead of 5.9 s.
    option("Mesh.LcIntegrationPrecision", 1e-3)
    graded = pore_mm is not None and pore_mm > size_mm
    if graded:
        option("Mesh.MeshSizeMax", float(pore_mm))
    _grade_thin_faces(gmsh, float(size_mm), planes, pore_mm if graded else None, chip_volumes)
    option("Mesh.Algorithm", 6)
    option("Mesh.Algorithm3D", 10)
    option("Mesh.Optimize", 1)
    # The optimiser works on the elements under this quality. On the whole stack's pore
    # space, at SLIVER_FLOOR (the floor the node moves raise slivers to) it took 1.7 s
    # instead of 29.5 s of HXT's 63 s (reference stack, seed 0), the worst element after
    # the node moves the same (0.2006 against 0.2004); elsewhere gmsh's 0.3 costs little
    # and keeps the worst higher (an exact layup: 0.24 at 0.2, above 0.3 at 0.3).
    option("Mesh.OptimizeThreshold", SLIVER_FLOOR if whole_pore else 0.3)
    option("Mesh.OptimizeNetgen", 1)


def _grade_thin_faces(
    gmsh, size_mm: float, planes: bool = False, pore_mm=None, chip_volumes=()
) -> None:
    model, occ = gmsh.model, gmsh.model.occ
    classes: dict[int, list[int]] = {}  # width class (powers of 2 below size_mm): curves
    for _, surface in model.getEntities(2):
        curves = [abs(c) for _, c in model.getBoundary([(2, surface)], oriented=False)]
        perimeter = sum(occ.getMass(1, c) for c in curves)
        width = 2 * occ.getMass(2, surface) / max(perimeter, 1e-12)
        if width >= size_mm / 2:
            continue
        level = int(np.ceil(np.log2(size_mm / max(width, size_mm / 4096))))
        classes.setdefault(level, []).extend(curves)
    for _, curve in model.getEntities(1):  # a short edge: where two outlines nearly meet
        length = occ.getMass(1, curve)
        if length < size_mm / 2:
            level = int(np.ceil(np.log2(size_mm / max(length, size_mm / 4096))))
            classes.setdefault(level, []).append(curve)
    points: dict[int, list[int]] = {}  # width class: corners near an edge of their face
    near_points, near_curves = _corners_near_edges(gmsh, size_mm / 2)
    if planes:
        # A corner a little off a side, the top or the conveyor (the sides move to clear
        # corners by a quarter element where they can, not always: reference stack seed 6,
        # middle 50 x 50 mm, two pore elements of quality 0.093 without this, none below
        # 0.14 with it) leaves a thin layer of pore or chip between itself and the plane.
        for point, gap in _corners_near_box(gmsh, size_mm / 2).items():
            near_points[point] = min(near_points.get(point, np.inf), gap)
    for point, gap in near_points.items():
        level = int(np.ceil(np.log2(size_mm / max(gap, size_mm / 4096))))
        points.setdefault(level, []).append(point)
    for curve, gap in near_curves.items():
        # A corner on an edge (within 1.5 um at 1.5 mm), not a strip: the corner's own
        # field does (a whole edge graded to a nanometre would be millions of elements).
        # Strips 15 to 30 um wide were measured (reference stack, seeds 1 and 8).
        if gap < size_mm / 1024:
            continue
        level = int(np.ceil(np.log2(size_mm / max(gap, size_mm / 4096))))
        classes.setdefault(level, []).append(curve)
    fields = []
    for level in sorted(set(classes) | set(points)):
        width = size_mm / 2**level
        distance = model.mesh.field.add("Distance")
        if level in classes:
            model.mesh.field.setNumbers(distance, "CurvesList", sorted(set(classes[level])))
        if level in points:
            model.mesh.field.setNumbers(distance, "PointsList", sorted(set(points[level])))
        model.mesh.field.setNumber(distance, "Sampling", 20)
        # With the pore graded, beyond its reach the chips' field below rules.
        fields.append(
            _threshold(
                model,
                distance,
                (width, size_mm),
                (width, width + 1.5 * (size_mm - width)),
                stop_at_reach=pore_mm is not None,
            )
        )
    widths = len(fields)
    if pore_mm is not None:
        fields.append(_pore_grading(gmsh, size_mm, pore_mm, chip_volumes))
    if fields:
        smallest = model.mesh.field.add("Min")
        model.mesh.field.setNumbers(smallest, "FieldsList", fields)
        model.mesh.field.setAsBackgroundMesh(smallest)
        gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
        gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 0)
    log.info(
        "conformal mesh: %d width classes of thin faces graded, %d corners near an edge",
        widths,
        sum(len(v) for v in points.values()),
    )


def _pore_grading(gmsh, size_mm: float, pore_mm: float, chip_volumes) -> int:
    """A field of ``size_mm`` within one element of the chips' faces, growing by
    ``PORE_GROWTH`` per mm of distance to ``pore_mm``."""
    model = gmsh.model
    faces = model.getBoundary([(3, v) for v in chip_volumes], combined=False, oriented=False)
    distance = model.mesh.field.add("Distance")
    model.mesh.field.setNumbers(distance, "SurfacesList", sorted({abs(t) for _, t in faces}))
    # Samples a third of an element apart on a 30 mm face: the distance is meant to within
    # a fraction of the element, and sets where the sizes start growing, not the faces'.
    model.mesh.field.setNumber(distance, "Sampling", 60)
    reach = (size_mm, size_mm + (pore_mm - size_mm) / PORE_GROWTH)
    return _threshold(model, distance, (size_mm, pore_mm), reach)


def _threshold(model, distance: int, sizes, reach, stop_at_reach: bool = False) -> int:
    """A gmsh Threshold field on ``distance``: size ``sizes[0]`` up to ``reach[0]``,
    growing linearly to ``sizes[1]`` at ``reach[1]`` (and beyond, unless
    ``stop_at_reach``: then no size of its own there)."""
    field = model.mesh.field
    threshold = field.add("Threshold")
    field.setNumber(threshold, "InField", distance)
    field.setNumber(threshold, "SizeMin", sizes[0])
    field.setNumber(threshold, "SizeMax", sizes[1])
    field.setNumber(threshold, "DistMin", reach[0])
    field.setNumber(threshold, "DistMax", reach[1])
    if stop_at_reach:
        field.setNumber(threshold, "StopAtDistMax", 1)
    return threshold


def _corners_near_box(gmsh, reach_mm: float) -> dict[int, float]:
    """Points of the model closer than ``reach_mm`` to a plane of its bounding box without
    lying on it: point tag -> that distance (mm)."""
    model = gmsh.model
    points = [p for _, p in model.getEntities(0)]
    xyz_of = {p: np.asarray(model.getValue(0, p, []), dtype=float) for p in points}
    # From the points themselves: OpenCASCADE's bounding box is widened by its tolerance.
    every = np.array(list(xyz_of.values())).reshape(-1, 3)
    box = np.stack([every.min(axis=0), every.max(axis=0)])
    near: dict[int, float] = {}
    for point in points:
        xyz = xyz_of[point]
        distance = np.abs(xyz[None, :] - box).ravel()
        off = distance[distance > ON_PLANE_MM]
        if len(off) and off.min() < reach_mm:
            near[point] = float(off.min())
    return near


def _corners_near_edges(gmsh, reach_mm: float) -> tuple[dict[int, float], dict[int, float]]:
    """Corners of a face closer than ``reach_mm`` to an edge of the same face that does
    not end at them: (point tag -> that distance, curve tag -> the least such distance of
    the edge or of an edge ending at such a corner), mm.

    Such a corner leaves the face a sliver between itself and the edge (a corner of one
    outline on, or nearly on, another outline in a shared plane; or two outlines running
    side by side a gap apart, whose ends are such corners): with edge nodes an element
    apart, the triangle spanning the corner and two nodes of that edge is flat (measured:
    a corner 0.2 um off an edge gave a triangle of quality 2e-7 and a flat tetrahedron
    above it; two edges 0.03 mm apart along 1 mm, triangles of quality 0.002), unless the
    elements there, along both edges, are as small as the distance."""
    model = gmsh.model
    ends: dict[int, tuple[int, ...]] = {}
    polyline: dict[int, np.ndarray] = {}
    for _, curve in model.getEntities(1):
        ends[curve] = tuple(abs(t) for _, t in model.getBoundary([(1, curve)], oriented=False))
        if model.getType(1, curve) == "Line":
            low, high = 0.0, 1.0
            samples = [model.getValue(0, t, []) for t in ends[curve]]
        else:
            (low,), (high,) = model.getParametrizationBounds(1, curve)
            samples = model.getValue(1, curve, list(np.linspace(low, high, 17)))
        polyline[curve] = np.asarray(samples, dtype=float).reshape(-1, 3)
    where = {
        point: np.asarray(model.getValue(0, point, []), dtype=float)
        for _, point in model.getEntities(0)
    }
    near: dict[int, float] = {}
    near_curves: dict[int, float] = {}
    for _, surface in model.getEntities(2):
        curves = [abs(c) for _, c in model.getBoundary([(2, surface)], oriented=False)]
        corners = sorted({p for c in curves for p in ends[c]})
        if len(curves) < 3 or not corners:
            continue
        xyz = np.array([where[p] for p in corners])
        for curve in curves:
            line = polyline[curve]
            if len(line) < 2:
                continue
            a, b = line[:-1], line[1:]
            ab = b - a
            t = np.einsum("psk,sk->ps", xyz[:, None, :] - a[None], ab) / np.maximum(
                np.einsum("sk,sk->s", ab, ab), 1e-30
            )
            foot = a[None] + np.clip(t, 0.0, 1.0)[..., None] * ab[None]
            gap = np.linalg.norm(xyz[:, None, :] - foot, axis=2).min(axis=1)
            for point, d in zip(corners, gap, strict=True):
                if point not in ends[curve] and d < reach_mm:
                    d = float(d)
                    near[point] = min(near.get(point, np.inf), d)
                    for edge in [curve, *(c for c in curves if point in ends[c])]:
                        near_curves[edge] = min(near_curves.get(edge, np.inf), d)
    return near, near_curves


# Elements under this SICN after gmsh's polish have their nodes moved (meshing.slivers).
