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
from scipy.spatial.transform import Rotation

from chipstack.core.arrangement import Arrangement
from chipstack.core.errors import InputError
from chipstack.core.overlap import penetrating_pairs
from chipstack.meshing.boundaries import ON_PLANE_MM, side_node_sets
from chipstack.meshing.conformal_crop import _clear_crop, _clear_plane
from chipstack.meshing.conformal_quality import _check_quality, _move_sliver_nodes, _polish
from chipstack.meshing.conformal_sizes import _pore_size, _set_mesh_size
from chipstack.meshing.gmsh_session import GmshSession
from chipstack.meshing.kinds import CROP_SHIFT_MM
from chipstack.meshing.mesh import PORE, MeshingError, VolumeMesh, element_attributes
from chipstack.meshing.resolution import convex_pieces, place_chip, separation_between

__all__ = [
    "chips_near",
    "conformal_mesh",
    "overlapping_pairs",
]

log = logging.getLogger(__name__)
_TOUCHING_MM = 1e-7  # OpenCASCADE's own tolerance: closer surfaces are one


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
        if box[5] <= ON_PLANE_MM:
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
        node_sets=side_node_sets(points, ON_PLANE_MM),
        n_chips=n,
        kind="conformal",
        info={},
    )
