"""Conformal tetrahedral mesh of the stack with gmsh (OpenCASCADE kernel).

Every chip is its own volume; where chips touch, the volumes share their interface (the
OpenCASCADE ``fragment`` makes the shared faces one entity, so their nodes are shared).
The physics leaves chips a few hundredths of a millimetre into each other: the overlap
goes to the chip that came to rest first, taken as the lower one (the chips are ordered
by the height of their lowest point; the upper chip is cut by the lower). Optionally the
pore space (``pore_space="box"``: the box over the chips' footprint from the conveyor to
the top of the stack, minus the chips) is meshed as its own region.

gmsh is a global session: it is only ever used inside :class:`GmshSession`.
"""

from __future__ import annotations

import ctypes
import dataclasses
import logging
import os
import re
import sys
import tempfile
import time

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import ConvexHull
from scipy.spatial.transform import Rotation

from chipstack.core.arrangement import Arrangement
from chipstack.core.errors import ChipstackError, InputError
from chipstack.core.overlap import penetrating_pairs
from chipstack.meshing.boundaries import side_node_sets
from chipstack.meshing.gmsh_session import GmshSession
from chipstack.meshing.kinds import CROP_SHIFT_MM
from chipstack.meshing.mesh import PORE, VolumeMesh, element_attributes
from chipstack.meshing.resolution import convex_pieces, place_chip, separation_between
from chipstack.meshing.slivers import improve_tetrahedra

__all__ = [
    "GmshSession",
    "MeshingError",
    "chips_near",
    "conformal_mesh",
    "overlapping_pairs",
]

log = logging.getLogger(__name__)
_ON_PLANE_MM = 1e-6
_TOUCHING_MM = 1e-7  # OpenCASCADE's own tolerance: closer surfaces are one


class MeshingError(ChipstackError):
    """The stack cannot be meshed as asked (the message names the chips involved)."""


def _box_centres(arrangement: Arrangement) -> tuple[np.ndarray, np.ndarray]:
    """Each chip's local bounding box in the world: (n, 3) centres and (n, 3) half sizes
    (mm). A star's or a random polygon's box is not centred on its centre of mass."""
    offsets = np.array([arrangement.shapes[k].box_centre for k in arrangement.shape_index])
    centres = arrangement.positions + np.einsum("nij,nj->ni", arrangement.rotations, offsets)
    half = np.array([arrangement.shapes[k].half_extents for k in arrangement.shape_index])
    return centres.reshape(-1, 3), half.reshape(-1, 3)


def _pairs_closer_than(arrangement: Arrangement, inflate_mm: float, depth_mm: float):
    """Pairs (i, j) of chips that interpenetrate by more than ``depth_mm`` once each is
    grown by ``inflate_mm`` (mm): exact for boxes (separating axes on the boxes), and for
    other chips the boxes' test refined by the separating axes of their convex pieces."""
    centres, half = _box_centres(arrangement)
    pairs, depth = penetrating_pairs(centres, arrangement.quaternions, half + inflate_mm)
    boxes = np.array([_fills_box(arrangement.shapes[k]) for k in arrangement.shape_index])
    kept = []
    placed: dict[int, object] = {}

    def world(k: int):
        if k not in placed:
            shape = arrangement.shapes[arrangement.shape_index[k]]
            placed[k] = place_chip(
                convex_pieces(shape), arrangement.rotations[k], arrangement.positions[k]
            )
        return placed[k]

    for (i, j), d in zip(pairs.tolist(), depth, strict=True):
        if boxes[i] and boxes[j]:
            if d > depth_mm:
                kept.append((i, j))
        elif -separation_between(world(i), world(j)) + 2 * inflate_mm > depth_mm:
            kept.append((i, j))
    return kept


def overlapping_pairs(arrangement: Arrangement) -> list[tuple[int, int]]:
    """(lower, upper) chips that interpenetrate, lower first in the bottom-up order: the
    lower one keeps the shared material (see :meth:`Arrangement.bottom_up_order`).
    Faces made coplanar by the contact resolution overlap by rounding only: they touch."""
    rank = arrangement.bottom_up_rank()
    return [
        (i, j) if rank[i] < rank[j] else (j, i)
        for i, j in _pairs_closer_than(arrangement, 0.0, _TOUCHING_MM)
    ]


def _add_chip(occ, arrangement: Arrangement, chip: int) -> int:
    """The chip as an OpenCASCADE solid: a box, or built from its faces (stars, polygons,
    file shapes: every exact solid of the project is a polyhedron)."""
    shape = arrangement.shapes[arrangement.shape_index[chip]]
    if _fills_box(shape):
        low = np.asarray(shape.box_centre) - shape.half_extents
        tag = occ.addBox(*(float(v) for v in low), *(float(2 * v) for v in shape.half_extents))
    else:  # the exact solid is a polyhedron for every shape (a rod's: a 16-sided prism)
        tag = _add_polyhedron(occ, shape.vertices, shape.faces)
    # A rotation and a translation, not an affine transform: OpenCASCADE turns the planes
    # of a generally transformed box into B-spline surfaces, and fragmenting those was
    # ten times slower (reference stack, seed 0: 9.2 s against 0.85 s).
    turn = Rotation.from_matrix(arrangement.rotations[chip]).as_rotvec()
    angle = float(np.linalg.norm(turn))
    if angle > 0:
        occ.rotate([(3, tag)], 0.0, 0.0, 0.0, *(float(v) for v in turn / angle), angle)
    occ.translate([(3, tag)], *(float(v) for v in arrangement.positions[chip]))
    return tag


def _fills_box(shape) -> bool:
    """Whether the chip is its own bounding box (a square, a beam), where the boxes'
    separating axes are exact."""
    return abs(shape.volume_mm3 - 8 * float(np.prod(shape.half_extents))) <= 1e-9 * shape.volume_mm3


def _add_polyhedron(occ, vertices: np.ndarray, faces) -> int:
    """A solid bounded by planar face loops (vertex indices, counter-clockwise seen from
    outside), its corners and edges shared between faces."""
    points = [occ.addPoint(*(float(v) for v in corner)) for corner in vertices]
    lines: dict[tuple[int, int], int] = {}
    surfaces = []
    for loop in faces:
        curves = []
        for a, b in zip(loop, (*loop[1:], loop[0]), strict=True):
            if (b, a) in lines:
                curves.append(-lines[(b, a)])
            else:
                lines[(a, b)] = occ.addLine(points[a], points[b])
                curves.append(lines[(a, b)])
        surfaces.append(occ.addPlaneSurface([occ.addCurveLoop(curves)]))
    return occ.addVolume([occ.addSurfaceLoop(surfaces)])


def conformal_mesh(
    arrangement: Arrangement,
    size_mm: float = 1.5,
    pore_space: str = "none",
    layer_mm: float = 2.0,
    min_quality: float = 0.1,
    threads: int = 1,
    region_mm: tuple[float, float, float, float] | None = None,
    pore_size_mm: float = 0.0,
) -> VolumeMesh:
    """Tetrahedral mesh of the stack (see the module docstring).

    size_mm: largest element edge of the chips. pore_size_mm: with the pore space, the
    largest element edge of the pore away from the chips, graded from ``size_mm`` at
    their faces (0: ``PORE_SIZE_FACTOR`` times ``size_mm``; ``size_mm`` or less: no
    grading). threads: gmsh threads (1, the default, gives the same
    mesh every time; more are faster but not reproducible). min_quality: the smallest
    acceptable SICN (gmsh's signed inverse condition number, 1 for a regular
    tetrahedron); a mesh with a worse
    element raises :class:`MeshingError` naming the chips that hold them.
    region_mm: (x_min, x_max, y_min, y_max) of a crop: the chips are cut at its sides
    (OpenCASCADE intersections, so the cut faces are exact planes) and, with the pore
    space, the box spans the whole region, so each side is one full plane face.
    """
    if pore_space not in ("none", "box"):
        raise InputError(f"pore_space: must be 'none' or 'box', got {pore_space!r}")
    if not (np.isfinite(size_mm) and size_mm > 0):
        raise InputError(f"size_mm: must be positive, got {size_mm!r}")
    start = time.perf_counter()
    n = arrangement.n_chips
    cut_by: dict[int, list[int]] = {}  # upper chip: the lower chips it overlaps
    for lower, upper in overlapping_pairs(arrangement):
        cut_by.setdefault(upper, []).append(lower)
    if region_mm is not None:
        region_mm = _clear_crop(arrangement, tuple(float(v) for v in region_mm), size_mm)
        inside = {int(k) for k in _chips_reaching(arrangement, region_mm)}
        cut_by = {u: [c for c in low if c in inside] for u, low in cut_by.items() if u in inside}
        cut_by = {u: low for u, low in cut_by.items() if low}
    with GmshSession(threads) as gmsh:
        chips = sorted(inside) if region_mm is not None else list(range(n))
        owner = _build_geometry(
            gmsh, arrangement, cut_by, pore_space, chips, region_mm, size_mm / 4
        )
        pore_mm = _pore_size(size_mm, pore_size_mm) if pore_space != "none" else size_mm
        _set_mesh_size(
            gmsh,
            size_mm,
            planes=region_mm is not None or pore_space != "none",
            pore_mm=pore_mm,
            chip_volumes=sorted(owner),
            whole_pore=pore_space != "none" and region_mm is None,
        )
        geometry_s = time.perf_counter() - start
        _generate(gmsh, arrangement, owner, min_quality)
        mesh = _extract(gmsh, arrangement, owner, n, layer_mm)
    mesh = _move_sliver_nodes(mesh)
    _check_quality(mesh, min_quality)
    info = dict(mesh.info)
    info.update(
        size_mm=size_mm,
        pore_space=pore_space,
        **({"pore_size_mm": pore_mm} if pore_space != "none" else {}),
        **({"region_mm": list(region_mm)} if region_mm is not None else {}),
        overlaps_cut=sum(len(v) for v in cut_by.values()),
        geometry_time_s=round(geometry_s, 3),
        mesh_time_s=round(time.perf_counter() - start, 3),
    )
    return dataclasses.replace(mesh, info=info)


def chips_near(arrangement: Arrangement, region_mm) -> np.ndarray:
    """The chips that can reach into the crop (x_min, x_max, y_min, y_max) once its sides
    move to clear the chips' corners and the contact resolution has moved the chips:
    their bounding boxes reach within 3 mm of it."""
    return _chips_reaching(arrangement, region_mm, CROP_SHIFT_MM + 2.0)


def _chips_reaching(arrangement: Arrangement, region_mm, reach_mm: float = 0.0) -> np.ndarray:
    """The chips whose bounding boxes reach within ``reach_mm`` of the crop (x_min, x_max,
    y_min, y_max); none is refused in one line."""
    x0, x1, y0, y1 = region_mm
    low, high = arrangement.bounds[:, 0], arrangement.bounds[:, 1]
    near = (low[:, 0] < x1 + reach_mm) & (high[:, 0] > x0 - reach_mm)
    near &= (low[:, 1] < y1 + reach_mm) & (high[:, 1] > y0 - reach_mm)
    if not near.any():
        raise InputError(
            f"mesh.region_mm: the crop x {x0:g} to {x1:g}, y {y0:g} to {y1:g} mm holds no "
            "chip of the stack"
        )
    return np.flatnonzero(near)


_SHALLOW_DEG = 15.0  # a face closer than this to parallel with a crop side is not crossed
_HOPELESS_FRACTION = 0.01  # elements below the quality bar beyond which no polish is tried
_DELAUNAY_MAX_ELEMENTS = 100_000  # the largest volume meshed again by Delaunay for a sliver
_LEFT_TO_MOVES = 10  # at most this many slivers of a larger volume are left to the node moves


def _clear_crop(arrangement: Arrangement, region_mm, size_mm: float):
    """The crop with each side moved (by at most ``CROP_SHIFT_MM``) to where it passes
    furthest from every chip corner, up to a quarter element, and its vertical edges
    from every point where a chip's edge crosses a side; a side crosses no chip face
    within ``_SHALLOW_DEG`` of parallel to it, and cuts no chip into two pieces, where
    it can (mixed-shapes, middle 50 x 50 mm with the pore space: 2 of 5 seeds meshed
    before, 7 of 10 after).

    A side passing a few micrometres from a corner, or along a chip's face, cuts off a
    sliver of the chip or of the pore that no element can fill (reference stack, seed 0,
    middle 50 x 50 mm: 176 elements below quality 0.1, all within 0.02 mm of the side
    y = 25 mm, where two chips' faces ran within hundredths of it); so does a chip's edge
    crossing a side a hair from the crop's vertical edge (seed 1: three elements below
    0.1 at the corner x = -24.9, y = 25.6 mm)."""
    low, high = arrangement.bounds[:, 0], arrangement.bounds[:, 1]
    wanted = size_mm / 4
    shifts = np.linspace(-CROP_SHIFT_MM, CROP_SHIFT_MM, 81)
    corners = [_corners(arrangement, [k]) for k in range(arrangement.n_chips)]
    out = list(region_mm)
    splitting: dict[int, np.ndarray] = {}
    for sweep in range(2):  # the sides of one axis move the crossings on the other's
        for side, axis in enumerate((0, 0, 1, 1)):
            # Every corner of the chips that reach the side's span: an edge across the
            # crop can have both its corners outside it.
            lo, hi = out[2 - 2 * axis], out[3 - 2 * axis]
            reach = (low[:, 1 - axis] < hi + CROP_SHIFT_MM) & (
                high[:, 1 - axis] > lo - CROP_SHIFT_MM
            )
            along, across = [], []
            candidates = region_mm[side] + shifts
            if sweep == 0:  # the candidates do not depend on the sweep
                splitting[side] = np.zeros(len(shifts), dtype=bool)
            for k in np.flatnonzero(reach):
                points = [corners[k][:, axis]]
                crossed = low[k, axis] < candidates[-1] and high[k, axis] > candidates[0]
                if crossed:
                    across.extend(_shallow_faces(arrangement, k, corners[k], axis))
                if crossed and sweep == 0:
                    splitting[side] |= _splits(arrangement, k, axis, side % 2 == 1, candidates)
                if sweep:  # where its edges cross the other axis's two sides
                    edges = _edges(arrangement.shapes[arrangement.shape_index[k]])
                    for value in (lo, hi):
                        crossings = _edge_crossings(corners[k], edges, 1 - axis, value)
                        points.append(crossings[:, axis])
                # One group per chip: a face of it lying on the side exempts its crossings too.
                along.append(np.concatenate(points))
            if along:
                out[side] = _clear_plane(
                    along, candidates, wanted, region_mm[side], across, splitting[side]
                )
    if out[1] <= out[0] or out[3] <= out[2]:
        raise InputError(
            "mesh.region_mm: too narrow for the conformal mesh, whose sides move up to "
            f"{CROP_SHIFT_MM:g} mm to clear the chips' corners"
        )
    if out != list(region_mm):
        log.info(
            "conformal mesh: crop sides moved to clear the chips' corners: x %g to %g, "
            "y %g to %g mm",
            *out,
        )
    return tuple(out)


def _edges(shape) -> set[tuple[int, int]]:
    """The edges of a chip shape: pairs of vertex indices, lower first."""
    return {
        (min(a, b), max(a, b))
        for loop in shape.faces
        for a, b in zip(loop, (*loop[1:], loop[0]), strict=True)
    }


def _edge_crossings(corners: np.ndarray, edges, axis: int, value: float) -> np.ndarray:
    """(m, 3) the points where a chip's ``edges`` (between its ``corners``, mm) cross the
    plane where coordinate ``axis`` equals ``value``."""
    points = []
    for a, b in edges:
        da, db = corners[a, axis] - value, corners[b, axis] - value
        if da * db < 0:
            points.append(corners[a] + (corners[b] - corners[a]) * (da / (da - db)))
    return np.array(points).reshape(-1, 3)


def _shallow_faces(arrangement: Arrangement, chip: int, corners: np.ndarray, axis: int):
    """(low, high) along ``axis`` (mm) of each face of ``chip`` within
    ``_SHALLOW_DEG`` of a plane normal to that axis (``corners``: its corners, mm).

    A side crossing such a face meets it at that shallow angle: the chip's cut face and
    the crossed face, or the pore beside them, make a wedge no element fills well
    (mixed-shapes seed 4, middle 50 x 50 mm: a beam's face crossing the side y = -24 mm
    at a few degrees, pore elements of quality 0.08 with a node 0.04 mm off the side)."""
    shape = arrangement.shapes[arrangement.shape_index[chip]]
    out = []
    for loop in shape.faces:
        points = corners[list(loop)]
        normal = np.cross(points, np.roll(points, -1, axis=0)).sum(axis=0)  # Newell's
        length = np.linalg.norm(normal)
        if length > 0 and abs(normal[axis]) / length > np.cos(np.radians(_SHALLOW_DEG)):
            out.append((float(points[:, axis].min()), float(points[:, axis].max())))
    return out


def _splits(arrangement: Arrangement, chip: int, axis: int, keep_below: bool, planes):
    """(len(planes),) bool: whether a crop side at each of ``planes`` (coordinates along
    ``axis``, mm; the crop keeps what lies below it when ``keep_below``) cuts ``chip``
    into more than one piece. A chip made of several convex pieces (a star, a concave
    polygon), neighbours joined along a face or part of one: the pieces a side keeps are
    one piece of the chip as long as the faces joining them reach the kept side."""
    shape = arrangement.shapes[arrangement.shape_index[chip]]
    out = np.zeros(len(planes), dtype=bool)
    if len(shape.convex_pieces) < 2:
        return out
    rotation, position = arrangement.rotations[chip], arrangement.positions[chip]
    pieces = [p @ rotation.T + position for p in shape.convex_pieces]
    # Two pieces join where a face of one lies on a face of the other: the corners of
    # either lying on the other (whole shared faces, or a face along part of another).
    planes_of = [ConvexHull(p).equations for p in shape.convex_pieces]
    joins = []  # (a, b, the joining corners' coordinates along the axis)
    for a in range(len(pieces)):
        for b in range(a + 1, len(pieces)):
            on_b = _on_hull(shape.convex_pieces[a], planes_of[b])
            on_a = _on_hull(shape.convex_pieces[b], planes_of[a])
            if on_a.sum() + on_b.sum() >= 3:
                joins.append((a, b, np.concatenate([pieces[a][on_b, axis], pieces[b][on_a, axis]])))

    def groups(kept: np.ndarray, links) -> int:
        graph = coo_matrix(
            (np.ones(len(links)), ([a for a, _ in links], [b for _, b in links])),
            shape=(len(pieces), len(pieces)),
        )
        _, label = connected_components(graph, directed=False)
        return len(set(label[kept]))

    # Pieces that do not join even uncut (approximate pieces of a chip read from a file)
    # are not a cut's doing: only more groups than the whole chip has count.
    whole = groups(np.ones(len(pieces), dtype=bool), [(a, b) for a, b, _ in joins])
    sign = 1.0 if keep_below else -1.0
    for index, plane in enumerate(planes):
        kept = np.array([np.any(sign * (p[:, axis] - plane) < -_ON_PLANE_MM) for p in pieces])
        if kept.sum() < 2:
            continue
        links = [
            (a, b)
            for a, b, along in joins
            if kept[a] and kept[b] and np.any(sign * (along - plane) < -_ON_PLANE_MM)
        ]
        out[index] = groups(kept, links) > whole
    return out


def _on_hull(points: np.ndarray, equations: np.ndarray) -> np.ndarray:
    """(len(points),) bool: which ``points`` lie in or on the convex hull whose facet
    ``equations`` (scipy's: normal . x + offset <= 0 inside) are given (to 1e-7 mm)."""
    return (points @ equations[:, :3].T + equations[:, 3]).max(axis=1) <= 1e-7


def _clear_plane(
    coordinates: list[np.ndarray],
    planes: np.ndarray,
    wanted: float,
    preferred: float,
    shallow: list[tuple[float, float]] = (),
    splitting: np.ndarray | None = None,
) -> float:
    """Of the candidate ``planes`` (positions along one axis), the one nearest
    ``preferred`` that passes at least ``wanted`` from every chip corner (``coordinates``:
    each chip's corners along that axis), or else the one that passes furthest. A chip
    with a face on a plane (three corners) is cut along it, no sliver; a chip with only a
    corner or an edge on it leaves a wedge as thin as its tilt (reference stack, seed 8,
    middle 50 x 50 mm: the box's top through the highest corner of a chip tilted a few
    degrees, two elements below quality 0.1)."""
    score = np.full(len(planes), wanted)
    for corners in coordinates:
        distance = np.abs(corners[None, :] - planes[:, None])
        on = distance < _ON_PLANE_MM
        distance[on & (on.sum(axis=1, keepdims=True) >= 3)] = np.inf
        score = np.minimum(score, distance.min(axis=1))
    # Tiers: a plane through a face at a shallow angle is worse than any that is not, a
    # plane cutting a chip in two (kept as two pieces, a loose bit of chip) worse still;
    # within a tier the clearance of the corners decides.
    tier = wanted + 1.0
    through = np.zeros(len(planes), dtype=bool)
    for low, high in shallow:
        through |= (planes > low + _ON_PLANE_MM) & (planes < high - _ON_PLANE_MM)
    score = score - tier * through
    if splitting is not None:
        score = score - 2 * tier * splitting
    best = np.flatnonzero(score == score.max())
    return float(planes[best[np.argmin(np.abs(planes[best] - preferred))]])


def _corners(arrangement: Arrangement, chips) -> np.ndarray:
    """(m, 3) the corners of ``chips`` (mm)."""
    return np.concatenate(
        [
            arrangement.shapes[arrangement.shape_index[k]].vertices @ arrangement.rotations[k].T
            + arrangement.positions[k]
            for k in chips
        ]
    )


def _build_geometry(
    gmsh,
    arrangement: Arrangement,
    cut_by: dict[int, list[int]],
    pore_space: str,
    chips: list[int],
    region_mm=None,
    clearance_mm: float = 0.0,
) -> dict[int, int]:
    """The chips as gmsh volumes, overlaps cut away, fragmented so touching volumes share
    their faces, and tagged as physical groups; returns the chip owning each volume."""
    occ = gmsh.model.occ
    n = arrangement.n_chips
    rank = arrangement.bottom_up_rank()
    tags = {chip: _add_chip(occ, arrangement, chip) for chip in chips}
    _cut_overlaps(occ, tags, cut_by, rank)
    volumes = {chip: [tag] for chip, tag in tags.items()}  # a crop can leave a chip in pieces
    if region_mm is not None:
        _crop(occ, arrangement, volumes, region_mm)
        if not volumes:  # boxes reached into the crop, the solids do not
            raise InputError(
                "mesh.region_mm: the crop x {:g} to {:g}, y {:g} to {:g} mm holds no chip of "
                "the stack".format(*region_mm)
            )
    order = sorted(volumes)
    flat = [(chip, tag) for chip in order for tag in volumes[chip]]
    mapping = _fragment(
        occ,
        arrangement,
        [tag for _, tag in flat],
        pore_space,
        region_mm,
        [chip for chip, _ in flat],
        clearance_mm,
    )
    occ.synchronize()
    per_chip: dict[int, list] = {}
    for (chip, _), became in zip(flat, mapping[: len(flat)], strict=True):
        per_chip.setdefault(chip, []).extend(became)
    owner = _volume_owners(per_chip, rank)
    pores = []
    if pore_space == "box":
        pores = [v for _, v in mapping[len(flat)] if v not in owner]
    _volume_groups(gmsh.model, owner, pores, n, order)
    _surface_groups(gmsh, n + 2)
    return owner


def _crop(occ, arrangement: Arrangement, volumes: dict[int, list[int]], region_mm) -> None:
    """Cut the chips that cross the crop's sides to it (``volumes``, each chip's one volume,
    updated: a chip left with nothing inside is dropped, a concave one the crop cuts into
    pieces, a star's two arms say, keeps them all)."""
    x0, x1, y0, y1 = region_mm
    low, high = arrangement.bounds[:, 0], arrangement.bounds[:, 1]
    top = float(high[:, 2].max()) + 1.0
    for chip in sorted(volumes):
        if np.all(low[chip, :2] >= (x0, y0)) and np.all(high[chip, :2] <= (x1, y1)):
            continue
        box = occ.addBox(x0, y0, -1.0, x1 - x0, y1 - y0, top + 1.0)
        out, _ = occ.intersect([(3, t) for t in volumes[chip]], [(3, box)])
        if out:
            volumes[chip] = [t for _, t in out]
        else:
            del volumes[chip]


def _cut_overlaps(occ, tags: dict[int, int], cut_by: dict[int, list[int]], rank) -> None:
    """Cut each upper chip by the lower chips it overlaps, bottom up (``tags`` updated)."""
    for upper in sorted(cut_by, key=lambda c: rank[c]):
        tools = [(3, tags[lower]) for lower in cut_by[upper]]
        out, _ = occ.cut([(3, tags[upper])], tools, removeObject=True, removeTool=False)
        if len(out) != 1:
            raise MeshingError(
                f"chips {[upper, *cut_by[upper]]}: resolving their overlap splits chip "
                f"{upper} into {len(out)} pieces; use the voxel mesh (mesh.kind = 'voxel')"
            )
        tags[upper] = out[0][1]


def _fragment(
    occ,
    arrangement: Arrangement,
    tags: list[int],
    pore_space: str,
    region_mm,
    chips: list[int],
    clearance_mm: float = 0.0,
) -> list:
    """Fragment the chips' volumes (``tags``, of ``chips``, where a chip the crop cut in
    pieces appears once per piece; and the pore box, last) together; returns, per object,
    the volumes it became. The pore box's top is raised (by at most ``CROP_SHIFT_MM``),
    and the whole stack's box's sides moved out, to clear every corner by
    ``clearance_mm`` unless it lies exactly on it: at the highest corner itself, the top
    of a chip lying nearly flat up there left a wedge of pore a hundredth of a millimetre
    thick (reference stack, seed 3, middle 50 x 50 mm: 4 elements below quality 0.1)."""
    objects = [(3, t) for t in tags]
    if pore_space == "none":
        # Only chips that touch share faces: fragmenting each touching group on its own
        # is several times faster than fragmenting the whole stack at once.
        position: dict[int, list[int]] = {}  # a chip's volumes (several: cut in pieces)
        for k, chip in enumerate(chips):
            position.setdefault(chip, []).append(k)
        mapping: list = [None] * len(tags)
        for whole_group in _touching_groups(arrangement):
            group = [k for c in whole_group for k in position.get(c, [])]
            if not group:
                continue
            if len(group) == 1:
                mapping[group[0]] = [objects[group[0]]]
                continue
            _, pieces = occ.fragment([objects[group[0]]], [objects[k] for k in group[1:]])
            for k, entities in zip(group, pieces, strict=True):
                mapping[k] = entities
        return mapping
    # The corners of the chips as they are now, cut to the crop: a chip the crop cuts can
    # reach far higher outside it than inside.
    import gmsh  # the session's, open around this call

    occ.synchronize()
    corners = []
    for tag in tags:
        points = gmsh.model.getBoundary([(3, tag)], recursive=True)
        # A point's box is the point grown by OpenCASCADE's tolerance: its centre is it.
        boxes = np.array([occ.getBoundingBox(0, p) for _, p in points])
        corners.append((boxes[:, :3] + boxes[:, 3:]) / 2)
    heights = [c[:, 2] for c in corners]
    top = float(max(h.max() for h in heights))
    shifts = np.linspace(0, CROP_SHIFT_MM, 41)
    if clearance_mm > 0:
        top = _clear_plane(heights, top + shifts, clearance_mm, top)
    if pore_space == "box":
        if region_mm is None:
            lo = arrangement.bounds[:, 0, :2].min(axis=0)
            hi = arrangement.bounds[:, 1, :2].max(axis=0)
            # The sides moved out like the top: through the outermost corner, a side left
            # a wedge of pore 0.06 um thick along the nearly upright edge below it
            # (reference stack, seed 4: 138 elements below quality 0.1, worst 0.0005).
            if clearance_mm > 0:
                for axis in (0, 1):
                    along = [c[:, axis] for c in corners]
                    lo[axis] = _clear_plane(along, lo[axis] - shifts, clearance_mm, lo[axis])
                    hi[axis] = _clear_plane(along, hi[axis] + shifts, clearance_mm, hi[axis])
        else:
            x0, x1, y0, y1 = region_mm
            lo, hi = np.array([x0, y0]), np.array([x1, y1])
        objects.append((3, occ.addBox(lo[0], lo[1], 0.0, *(hi - lo), top)))
    if len(objects) > 1:
        _, mapping = occ.fragment(objects[:1], objects[1:])
    else:  # one chip: nothing to fragment
        mapping = [objects]
    return mapping


def _touching_groups(arrangement: Arrangement) -> list[list[int]]:
    """The chips in groups that touch or overlap (connected components; singletons too)."""
    n = arrangement.n_chips
    pairs = np.array(_pairs_closer_than(arrangement, 10 * _TOUCHING_MM, 0.0), dtype=int)
    pairs = pairs.reshape(-1, 2)
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    count, label = connected_components(graph, directed=False)
    return [np.flatnonzero(label == k).tolist() for k in range(count)]


def _volume_owners(chip_volumes: dict[int, list], rank) -> dict[int, int]:
    """Volume tag -> chip, from the volumes each chip became."""
    owner: dict[int, int] = {}
    for k, entities in chip_volumes.items():
        for _, volume in entities:
            if volume in owner:  # an overlap the cuts missed: the lower chip keeps it
                if rank[k] < rank[owner[volume]]:
                    owner[volume] = k
            else:
                owner[volume] = k
    return owner


def _volume_groups(
    model, owner: dict[int, int], pores: list[int], n: int, chips: list[int] | None = None
) -> None:
    """Physical volumes: ``chip_<k + 1>`` (tag k + 1, the region id of the mesh files)
    for every chip meshed (all ``n``, or ``chips`` in a crop), ``pore`` (n + 1)."""
    chips = list(range(n)) if chips is None else chips
    kept = set(owner.values())
    lost = [chip for chip in chips if chip not in kept]
    if lost:
        # The same first words as every other conformal failure: with mesh.kind = "both"
        # this is a warning, and it must say which mesh failed.
        raise MeshingError(
            f"conformal mesh failed near chips {', '.join(map(str, lost[:12]))}: lost when "
            "the stack was fragmented (each nearly coincides with another chip); use the "
            "voxel mesh (mesh.kind = 'voxel')"
        )
    for chip in chips:
        volumes = [v for v, k in owner.items() if k == chip]
        model.setPhysicalName(3, model.addPhysicalGroup(3, volumes, chip + 1), f"chip_{chip + 1}")
    if pores:
        model.setPhysicalName(3, model.addPhysicalGroup(3, pores, n + 1), "pore")


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
        off = distance[distance > _ON_PLANE_MM]
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
SLIVER_FLOOR = 0.2


def _move_sliver_nodes(mesh: VolumeMesh) -> VolumeMesh:
    """The slivers gmsh's polish leaves (a few, in the pore space's thin gaps between
    chips: 8 of 170,000 elements under 0.1 on a 24-chip stack; 19 of 3.96 million under
    0.2 on the reference stack) have their nodes moved: inside a region freely, on a
    face of a chip or an interface within its plane, on an edge along it, corners kept
    (:func:`meshing.slivers.improve_tetrahedra` without its gmsh step: the volumes were
    optimised already). No element is added or reconnected; every chip's faces stay in
    their planes, so the volumes and the shared faces are kept. A move is kept only when
    it raises the worst of the node's elements, so the worst element never gets worse."""
    quality = np.asarray(mesh.quality)
    if not (quality < SLIVER_FLOOR).any():
        return mesh

    improved = improve_tetrahedra(
        mesh.points, mesh.cells, mesh.chip, floor=SLIVER_FLOOR, rounds=1, optimise=False
    )
    # The node sets stand: a node on a side of the box moves within that side.
    info = dict(mesh.info, slivers=improved.info)
    return dataclasses.replace(mesh, points=improved.points, quality=improved.quality, info=info)


def _check_quality(mesh: VolumeMesh, min_quality: float) -> None:
    """Refuse a mesh with elements below ``min_quality``, naming the chips that hold them."""
    bad = mesh.quality < min_quality
    if bad.any():
        chips = sorted({int(c) for c in mesh.chip[bad]})
        shown = ", ".join(map(str, chips[:12])) + (" ..." if len(chips) > 12 else "")
        raise MeshingError(
            f"conformal mesh: {int(bad.sum())} elements below quality {min_quality:g} "
            f"(worst {mesh.quality.min():.2g}) in chips {shown}, where chips nearly touch; "
            "use the voxel mesh (mesh.kind = 'voxel')"
        )


def _polish(gmsh, min_quality: float) -> None:
    """HXT leaves a flat tetrahedron (a sliver) here and there, often through a chip's
    thickness where nodes of its top and bottom faces lie one above the other. gmsh's own
    optimiser, run again on the volumes that hold one, removes most; a volume that still
    holds one is meshed again by gmsh's Delaunay mesher (slower, but it does not leave
    such slivers) inside its own surface mesh, which stays as it is, so the volume stays
    conformal with its neighbours."""
    model = gmsh.model
    counts = [0, 0]  # elements below the bar, all elements (at the last look)

    per_volume: dict[int, tuple[int, int]] = {}  # volume: (elements, below the bar)

    def poor() -> list[tuple[int, int]]:
        out = []
        counts[:] = [0, 0]
        for _, volume in model.getEntities(3):
            _, tags, _ = model.mesh.getElements(3, volume)
            if tags and len(tags[0]):
                quality = model.mesh.getElementQualities(np.concatenate(tags), "minSICN")
                per_volume[volume] = (len(quality), int(np.sum(quality < min_quality)))
                counts[0] += per_volume[volume][1]
                counts[1] += len(quality)
                if np.min(quality) < min_quality:
                    out.append((3, volume))
        return out

    # The polish removes slivers here and there (measured: at most a few hundred in
    # 200,000 elements); a mesh with more than 1 % of its elements below the bar asks for
    # a quality the mesher does not reach (and more than 200, for small meshes), and
    # polishing every volume would only delay the refusal (by 10 s on the 24-chip test
    # stack at a bar of 0.9).
    volumes = poor()
    if counts[0] > max(_HOPELESS_FRACTION * counts[1], 200):
        log.info(
            "conformal mesh: %d of %d elements below quality %g, not polished",
            *counts,
            min_quality,
        )
        return
    for attempt in range(2):
        if attempt:
            volumes = poor()
        if not volumes:
            return
        model.mesh.optimize("", force=True, dimTags=volumes)
    volumes = poor()
    # A volume of the size of a whole stack's pore space is left to the node moves that
    # follow (``_move_sliver_nodes``): Delaunay takes minutes on it for a sliver or two
    # (reference stack, seed 3: 390 s for one element of quality 0.084 in 951,650 of the
    # pore, which the node moves took to 0.20 in 13 s).
    # A cluster of slivers is beyond the node moves (reference stack, seed 4: 138 elements
    # under 0.1 near one chip, worst 0.0005, after them), so only a few are left to them.
    large = [
        (dim, volume)
        for dim, volume in volumes
        if per_volume[volume][0] > _DELAUNAY_MAX_ELEMENTS
        and per_volume[volume][1] <= _LEFT_TO_MOVES
    ]
    if large:
        log.info(
            "conformal mesh: %d volumes of more than %d elements left to the node moves "
            "(at most %d slivers each)",
            len(large),
            _DELAUNAY_MAX_ELEMENTS,
            _LEFT_TO_MOVES,
        )
    volumes = [dv for dv in volumes if dv not in large]
    if volumes:
        _remesh_delaunay(gmsh, volumes)
        volumes = poor()
        volumes = [dv for dv in volumes if dv not in large]
        if volumes:
            model.mesh.optimize("", force=True, dimTags=volumes)
    # Netgen's optimiser is not tried any more: on a mesh holding a flat tetrahedron
    # (quality ~1e-14) it crashed the process (reference stack, seeds 3 and 5), and a
    # crash cannot be turned into a one-line error. The quality check refuses the mesh.


def _shells(model, volume: int) -> list[list[int]]:
    """The surfaces bounding ``volume`` grouped into closed shells (surfaces that share a
    curve are in one shell)."""
    surfaces = [abs(t) for _, t in model.getBoundary([(3, volume)], oriented=False)]
    curves = [[abs(c) for _, c in model.getBoundary([(2, s)], oriented=False)] for s in surfaces]
    index = {c: [] for group in curves for c in group}
    for k, group in enumerate(curves):
        for c in group:
            index[c].append(k)
    links = [(ks[0], k) for ks in index.values() for k in ks[1:]]
    graph = coo_matrix(
        (np.ones(len(links)), ([a for a, _ in links], [b for _, b in links])),
        shape=(len(surfaces), len(surfaces)),
    )
    _, label = connected_components(graph, directed=False)
    return [[s for s, g in zip(surfaces, label, strict=True) if g == k] for k in np.unique(label)]


def _remesh_delaunay(gmsh, volumes: list[tuple[int, int]]) -> None:
    """Mesh ``volumes`` again with gmsh's Delaunay mesher inside their surface meshes,
    which are kept (so each stays conformal with its neighbours).

    Each volume is meshed in a model of its own, built from its surface triangles: in the
    stack's model, gmsh's Delaunay meshes the whole connected group of volumes again
    (measured: 77 s for one chip of the reference stack, against 1 s alone)."""
    model, option = gmsh.model, gmsh.option
    log.info("conformal mesh: %d volumes meshed again with Delaunay (slivers)", len(volumes))
    stack = model.getCurrent()
    node_tags, node_xyz, _ = model.mesh.getNodes()
    order = np.argsort(node_tags)
    node_tags, node_xyz = node_tags[order], node_xyz.reshape(-1, 3)[order]
    next_node = int(model.mesh.getMaxNodeTag()) + 1
    next_element = int(model.mesh.getMaxElementTag()) + 1
    surface_xyz = dict(zip(node_tags.tolist(), node_xyz, strict=True))  # once, not per volume
    saved = {
        name: option.getNumber(name)
        for name in ("Mesh.Algorithm3D", "Mesh.MeshSizeExtendFromBoundary", "Mesh.Renumber")
    }
    for _, volume in volumes:
        shells = []  # the triangles of each closed shell of the volume's boundary
        for group in _shells(model, volume):
            triangles = []
            for surface in group:
                types, _, nodes = model.mesh.getElements(2, surface)
                triangles += [n for t, n in zip(types, nodes, strict=True) if t == 2]
            shells.append(np.concatenate(triangles).astype(np.int64))
        # The outer shell first, the holes after it (the pore's box around its chips): as
        # one surface, the holes would be filled too (measured: mixed-shapes seed 4,
        # 2,372 faces shared by three elements after the pore was meshed again).
        extent = [
            np.ptp(node_xyz[np.searchsorted(node_tags, np.unique(t))], axis=0).sum() for t in shells
        ]
        shells = [shells[k] for k in np.argsort(extent)[::-1]]
        model.add("chipstack-remesh")
        try:
            option.setNumber("Mesh.Algorithm3D", 1)
            option.setNumber("Mesh.MeshSizeExtendFromBoundary", 1)  # no field here
            option.setNumber("Mesh.Renumber", 0)  # the surface's nodes keep their tags
            loops = []
            for triangles in shells:
                boundary = np.unique(triangles)
                xyz = node_xyz[np.searchsorted(node_tags, boundary)]
                surface = model.addDiscreteEntity(2)
                model.mesh.addNodes(2, surface, boundary, xyz.ravel())
                model.mesh.addElementsByType(surface, 2, [], triangles)
                loops.append(model.geo.addSurfaceLoop([surface]))
            # A volume of the geo kernel over the discrete surfaces: a discrete volume is
            # not meshed, and the surfaces' own triangles are kept as they are.
            alone = model.geo.addVolume(loops)
            model.geo.synchronize()
            model.mesh.generate(3)
            inner, inner_xyz, _ = model.mesh.getNodes(3, alone)
            _, _, tets = model.mesh.getElements(3, alone)
        finally:
            for name, value in saved.items():
                option.setNumber(name, value)
            model.remove()
            model.setCurrent(stack)
        if not len(tets) or not len(tets[0]):
            continue
        renumber = dict(zip(inner.tolist(), range(next_node, next_node + len(inner)), strict=True))
        tets = np.array([renumber.get(int(t), int(t)) for t in tets[0]], dtype=np.int64)
        new_inner = np.arange(next_node, next_node + len(inner))
        # A new mesh that does not fill the volume exactly once (a hole filled, a part
        # left empty) is not taken: the quality check then refuses the old one.
        added = dict(zip(new_inner.tolist(), np.asarray(inner_xyz).reshape(-1, 3), strict=True))
        corners = np.array([added.get(int(t), surface_xyz.get(int(t))) for t in tets])
        corners = corners.reshape(-1, 4, 3)
        filled = np.abs(np.linalg.det(corners[:, 1:] - corners[:, :1])).sum() / 6
        exact = model.occ.getMass(3, volume)
        if abs(filled - exact) > 1e-6 * exact:
            log.warning(
                "conformal mesh: volume %d meshed again fills %.6g mm3 of %.6g; kept as it was",
                volume,
                filled,
                exact,
            )
            continue
        elements = np.arange(next_element, next_element + len(tets) // 4)
        next_node += len(inner)
        next_element += len(elements)
        model.mesh.clear([(3, volume)])
        model.mesh.addNodes(3, volume, new_inner, np.asarray(inner_xyz).ravel())
        model.mesh.addElementsByType(volume, 4, elements, tets)


def _generate(gmsh, arrangement: Arrangement, owner: dict[int, int], min_quality: float) -> None:
    """Mesh in 3-D; a failure becomes a :class:`MeshingError` naming the chips at fault.

    The mesher's own diagnostics (printed from C) are captured, not shown, and searched
    for the place or the surfaces where it failed.
    """
    with tempfile.TemporaryFile(mode="w+") as captured:
        sys.stdout.flush()
        sys.stderr.flush()
        saved = os.dup(1), os.dup(2)
        os.dup2(captured.fileno(), 1)
        os.dup2(captured.fileno(), 2)
        try:
            gmsh.model.mesh.generate(3)
            _polish(gmsh, min_quality)
            failure = None
        except Exception as exc:  # gmsh raises a bare Exception with its last error
            failure = str(exc)
        finally:
            ctypes.CDLL(None).fflush(None)
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            os.close(saved[0])
            os.close(saved[1])
        if failure is None:
            return
        captured.seek(0)
        text = captured.read() + "\n" + failure
    chips: set[int] = set()
    for match in re.finditer(r"point \(([-+\d.eE]+),\s*([-+\d.eE]+),\s*([-+\d.eE]+)\)", text):
        point = np.array([float(v) for v in match.groups()])
        near = np.all(
            (arrangement.bounds[:, 0] - 0.1 <= point) & (point <= arrangement.bounds[:, 1] + 0.1),
            axis=1,
        )
        chips.update(int(c) for c in np.flatnonzero(near))
    for match in re.finditer(r"surface (\d+)", text):
        for volume in gmsh.model.getAdjacencies(2, int(match.group(1)))[0]:
            if int(volume) in owner:
                chips.add(owner[int(volume)])
    where = ", ".join(map(str, sorted(chips)[:12])) if chips else "unknown"
    reason = failure.splitlines()[0] if failure else "failed"
    raise MeshingError(
        f"conformal mesh failed ({reason}) near chips {where}, where chips nearly touch; "
        "use the voxel mesh (mesh.kind = 'voxel')"
    )


def _surface_groups(gmsh, first_tag: int) -> None:
    """Physical surfaces: bottom (on the conveyor), top (facing up), lateral (the rest)."""
    model = gmsh.model
    boundary = model.getBoundary(model.getEntities(3), combined=True, oriented=False)
    groups: dict[str, list[int]] = {"bottom": [], "top": [], "lateral": []}
    for _, surface in boundary:
        surface = abs(surface)
        box = model.getBoundingBox(2, surface)
        if box[5] <= _ON_PLANE_MM:
            groups["bottom"].append(surface)
            continue
        u, v = model.getParametrizationBounds(2, surface)
        normal = model.getNormal(surface, [(u[0] + u[1]) / 2, (v[0] + v[1]) / 2])
        groups["top" if abs(normal[2]) > 0.5 and _faces_up(gmsh, surface) else "lateral"].append(
            surface
        )
    for k, (name, surfaces) in enumerate(groups.items()):
        if surfaces:
            model.setPhysicalName(2, model.addPhysicalGroup(2, surfaces, first_tag + k), name)


def _faces_up(gmsh, surface: int) -> bool:
    """Whether the solid lies below this exterior surface (its outside faces up)."""
    model = gmsh.model
    (up,) = model.getAdjacencies(2, surface)[0][:1] or (None,)
    if up is None:
        return False
    box = model.getBoundingBox(3, int(up))
    face = model.getBoundingBox(2, surface)
    return (face[2] + face[5]) / 2 >= (box[2] + box[5]) / 2


def _extract(gmsh, arrangement: Arrangement, owner: dict[int, int], n: int, layer_mm: float):
    model = gmsh.model
    node_tags, coords, _ = model.mesh.getNodes()
    points = np.asarray(coords, dtype=float).reshape(-1, 3)
    index = np.full(int(node_tags.max()) + 1, -1, dtype=np.int64)
    index[node_tags] = np.arange(len(node_tags))
    cells, chips, elements = [], [], []
    for _, volume in model.getEntities(3):
        types, tags, nodes = model.mesh.getElements(3, volume)
        for t, et, en in zip(types, tags, nodes, strict=True):
            if t != 4:  # 4-node tetrahedra only
                raise MeshingError(f"volume {volume}: gmsh made element type {t}, not tetrahedra")
            cells.append(index[np.asarray(en, dtype=np.int64).reshape(-1, 4)])
            chips.append(np.full(len(et), owner.get(volume, PORE), dtype=np.int64))
            elements.append(np.asarray(et))
    cells = np.concatenate(cells)
    chip = np.concatenate(chips)
    quality = np.asarray(model.mesh.getElementQualities(np.concatenate(elements), "minSICN"))
    used = np.unique(cells)
    remap = np.full(len(points), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    points, cells = points[used], remap[cells]
    return VolumeMesh(
        points=points,
        cell_type="tetra",
        cells=cells,
        chip=chip,
        **element_attributes(arrangement, chip, layer_mm),
        quality=quality,
        node_sets=side_node_sets(points, _ON_PLANE_MM),
        n_chips=n,
        kind="conformal",
        info={},
    )
