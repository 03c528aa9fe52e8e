"""Sliver removal for a labelled tetrahedral mesh (the image route's Mesh_3 output).

CGAL's Mesh_3 leaves slivers (flat tetrahedra, SICN down to 1e-4) at the label
boundaries of a voxel image; a consolidation solver wants none below 0.1. Two steps, each
keeping every region's elements in that region, the faces every pair of regions shares,
and the regions' volumes (on the reference crop: within 0.04 % for every chip above
10 mm3, 0.25 % for a 3 mm3 corner the crop cuts off):

1. gmsh's tetrahedral optimiser on the labelled mesh, each region one discrete volume
   bounded by one discrete surface per pair of regions (``optimize("", force=True)``):
   edge and face swaps and moves of interior nodes. On the reference crop with the pore
   space (474,742 elements) it takes the elements below 0.1 from 2,763 to 13 in seconds.
   The slivers it leaves have three or four nodes on region boundaries, which it does
   not move.
2. Those boundary nodes moved within their boundary: a node on one interface (one pair of
   regions, its faces within ``max_turn_deg`` of their mean plane) slides in that plane;
   a node where two flat boundaries meet (a chip's edge, two interfaces at an angle)
   slides along the line they share; a node on a flat side of the meshed box (the
   conveyor, a crop's or the pore space's sides and top) slides within that side; a node
   at a corner (three boundaries or more) stays. Each
   move is the best of ``tries`` seeded random trial moves by the worst quality of the
   node's elements, kept only when it raises it; nodes of the elements under ``floor``
   are tried, in a fixed order, so that the same mesh and seed give the same result.

The two alternate for ``rounds`` (a move lets a swap through, and a swap frees a node).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np

from chipstack.meshing.gmsh_session import GmshSession

__all__ = ["ImprovedTetrahedra", "improve_tetrahedra", "tetra_sicn"]

log = logging.getLogger(__name__)

# A tetrahedron's faces, each as three local node indices.
_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])
_OUTSIDE = -1  # the label beyond the mesh's outer boundary
# The regular tetrahedron's edge vectors (columns), the reference of the SICN.
_REGULAR = np.array(
    [
        [1.0, 0.5, 0.5],
        [0.0, math.sqrt(3) / 2, math.sqrt(3) / 6],
        [0.0, 0.0, math.sqrt(2 / 3)],
    ]
)
_REGULAR_INVERSE = np.linalg.inv(_REGULAR)


def _cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(M, 3) row-wise cross products: ``np.cross``'s arithmetic, without its set-up, which
    was most of the node moves' time on a few elements at a time (2,596 slivers: 675,000
    calls, 133 of 227 s)."""
    u0, u1, u2 = u[:, 0], u[:, 1], u[:, 2]
    v0, v1, v2 = v[:, 0], v[:, 1], v[:, 2]
    return np.stack([u1 * v2 - u2 * v1, u2 * v0 - u0 * v2, u0 * v1 - u1 * v0], axis=1)


def tetra_sicn(points: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """(M,) signed inverse condition number of every tetrahedron (1: regular, <= 0:
    flat or inverted); dimensionless."""
    return _corner_sicn(points[cells])


def _corner_sicn(p: np.ndarray) -> np.ndarray:
    """:func:`tetra_sicn` of tetrahedra given by their corners, ``p`` (M, 4, 3): each row's
    arithmetic is the same whatever the other rows (the node moves measure all their
    trial moves in one call)."""
    edges = np.stack([p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]], axis=2)
    shape = edges @ _REGULAR_INVERSE  # (M, 3, 3), rows r0, r1, r2
    r0, r1, r2 = shape[:, 0], shape[:, 1], shape[:, 2]
    # The inverse's columns are the rows' cross products over the determinant, so
    # |S| |S^-1| = |S| |adj S| / |det S| without inverting (millions of elements).
    adjugate = np.stack([_cross(r1, r2), _cross(r2, r0), _cross(r0, r1)], axis=1)
    det = np.einsum("ij,ij->i", r0, adjugate[:, 0])
    norms = np.sqrt(
        np.einsum("ijk,ijk->i", shape, shape) * np.einsum("ijk,ijk->i", adjugate, adjugate)
    )
    flat = np.abs(det) < 1e-300
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(flat, 0.0, 3 * det / np.where(flat, 1.0, norms))


@dataclass(frozen=True)
class ImprovedTetrahedra:
    """The improved mesh: ``points`` (n, 3), ``cells`` (m, 4), ``labels`` (m,) (the
    input's labels) and ``quality`` (m,) (each element's SICN), and what was done
    (``info``)."""

    points: np.ndarray
    cells: np.ndarray
    labels: np.ndarray
    quality: np.ndarray
    info: dict = field(default_factory=dict)


def improve_tetrahedra(
    points: np.ndarray,
    cells: np.ndarray,
    labels: np.ndarray,
    *,
    floor: float = 0.2,
    rounds: int = 2,
    passes: int = 3,
    tries: int = 60,
    max_turn_deg: float = 30.0,
    side_tolerance_mm: float = 0.05,
    seed: int = 0,
    optimise: bool = True,
) -> ImprovedTetrahedra:
    """Remove slivers from a labelled tetrahedral mesh (see the module docstring).

    Parameters
    ----------
    points : (n, 3) array
        Node coordinates (mm).
    cells : (m, 4) int array
        Tetrahedra, positively oriented.
    labels : (m,) int array
        Each element's region (a chip, the pore space): kept per element.
    floor : float
        Elements with a signed inverse condition number below this have their boundary
        nodes moved.
    rounds, passes, tries : int
        Alternations of the two steps; passes of node moves per round; trial moves per
        node.
    max_turn_deg : float
        A boundary node moves only when its boundary faces are within this angle of
        their mean plane (deg); the flat sides of the bounding box are followed exactly.
    side_tolerance_mm : float
        A node this close to a side of the mesh's bounding box lies on that side (mm).
    seed : int
        Seed of the trial moves.
    optimise : bool
        Run step 1 (gmsh's optimiser) in every round; False: node moves only (a mesh
        gmsh has optimised already, whose few slivers are local: no element is added,
        removed or reconnected).

    Returns
    -------
    ImprovedTetrahedra
    """
    start = time.perf_counter()
    points = np.asarray(points, dtype=float)
    cells = np.asarray(cells, dtype=np.int64)
    names, labels = np.unique(np.asarray(labels), return_inverse=True)
    rng = np.random.default_rng(seed)
    before = tetra_sicn(points, cells)
    info = dict(
        elements_before=len(cells),
        below_0_1_before=int((before < 0.1).sum()),
        worst_before=float(before.min()),
        moved=0,
    )
    after = before
    box = points.min(axis=0), points.max(axis=0)
    for _ in range(rounds):
        if optimise:
            points, cells, labels = _gmsh_optimise(points, cells, labels)
            after = tetra_sicn(points, cells)
        # Only the elements near the slivers take part: finding the region boundaries of
        # the whole mesh took 9 of the 15 s of a pass over the reference stack's 1.5
        # million elements that held none. The result is the same as over the whole mesh.
        near = _around(cells, after < floor, passes)
        if not len(near):
            break
        points, moved_quality, moved = _move_boundary_nodes(
            points,
            cells[near],
            labels[near],
            after[near],
            floor,
            passes,
            tries,
            max_turn_deg,
            side_tolerance_mm,
            rng,
            box,
        )
        after = after.copy()
        after[near] = moved_quality
        info["moved"] += moved
    info.update(
        elements=len(cells),
        below_0_1=int((after < 0.1).sum()),
        worst=float(after.min()),
        seconds=round(time.perf_counter() - start, 3),
    )
    log.info(
        "slivers: below 0.1 from %d to %d, worst %.4f to %.4f, in %.1f s",
        info["below_0_1_before"],
        info["below_0_1"],
        info["worst_before"],
        info["worst"],
        info["seconds"],
    )
    return ImprovedTetrahedra(points, cells, names[labels], after, info)


def _around(cells: np.ndarray, chosen: np.ndarray, rings: int) -> np.ndarray:
    """Indices, in order, of the elements within ``rings`` + 1 rings of the ``chosen``
    elements (bool, per element): every node that ``rings`` passes of node moves can
    reach (a pass moves the nodes of the elements under the floor; a moved node's
    elements can fall under it) keeps all its elements, so its region boundaries and its
    moves are those it has in the whole mesh."""
    inside = chosen.copy()
    reached = np.zeros(int(cells.max()) + 1, dtype=bool)
    for _ in range(rings + 1):
        reached[cells[inside]] = True
        inside = reached[cells].any(axis=1)
    return np.flatnonzero(inside)


def _boundary_faces(cells: np.ndarray, labels: np.ndarray):
    """The faces between two regions or on the outer boundary: (k, 3) nodes and the two
    regions' labels (``_OUTSIDE`` beyond the outer boundary), the lower first."""
    faces = cells[:, _FACES].reshape(-1, 3)
    owner = np.repeat(np.arange(len(cells)), 4)
    key = np.sort(faces, axis=1)
    order = np.lexsort(key.T[::-1])
    key, faces, owner = key[order], faces[order], owner[order]
    first = np.ones(len(key), dtype=bool)
    first[1:] = np.any(key[1:] != key[:-1], axis=1)
    index = np.flatnonzero(first)
    shared = np.diff(np.append(index, len(key))) == 2
    mine = labels[owner[index]]
    other = np.where(shared, labels[owner[np.minimum(index + 1, len(key) - 1)]], _OUTSIDE)
    boundary = ~shared | (mine != other)
    low = np.minimum(mine, other)[boundary]
    high = np.maximum(mine, other)[boundary]
    return faces[index[boundary]], low, high


def _incidence(items: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """CSR map from node to the rows of ``items`` (k, j) that hold it."""
    flat = items.ravel()
    order = np.argsort(flat, kind="stable")
    indptr = np.searchsorted(flat[order], np.arange(n + 1))
    return indptr, order // items.shape[1]


def _gmsh_optimise(points, cells, labels):
    """gmsh's tetrahedral optimiser on the labelled mesh (each region a discrete volume
    bounded by one discrete surface per pair of regions); returns the new mesh."""

    tris, low, high = _boundary_faces(cells, labels)
    pairs, surface_of = np.unique(np.column_stack([low, high]), axis=0, return_inverse=True)
    surface_of = surface_of.ravel()
    regions = np.unique(labels)
    # Each node belongs to one entity: its first boundary surface, else its region.
    entity = np.full(len(points), -1, dtype=np.int64)
    for s in range(len(pairs)):
        nodes = np.unique(tris[surface_of == s])
        entity[nodes[entity[nodes] < 0]] = s
    surfaces = len(pairs)
    order = np.argsort(labels, kind="stable")
    bounds = np.searchsorted(labels[order], np.append(regions, regions[-1] + 1))
    with GmshSession() as gmsh:
        gmsh.option.setNumber("General.Verbosity", 1)
        for s in range(surfaces):
            gmsh.model.addDiscreteEntity(2, s + 1)
        for k, region in enumerate(regions):
            touching = np.flatnonzero((pairs[:, 0] == region) | (pairs[:, 1] == region))
            gmsh.model.addDiscreteEntity(3, k + 1, (touching + 1).tolist())
            mine = cells[order[bounds[k] : bounds[k + 1]]]
            nodes = np.unique(mine)
            free = nodes[entity[nodes] < 0]
            entity[free] = surfaces + k
        for e in range(surfaces + len(regions)):
            nodes = np.flatnonzero(entity == e)
            dim, tag = (2, e + 1) if e < surfaces else (3, e - surfaces + 1)
            gmsh.model.mesh.addNodes(dim, tag, nodes + 1, points[nodes].ravel())
        for s in range(surfaces):
            gmsh.model.mesh.addElementsByType(s + 1, 2, [], (tris[surface_of == s] + 1).ravel())
        for k in range(len(regions)):
            mine = cells[order[bounds[k] : bounds[k + 1]]]
            gmsh.model.mesh.addElementsByType(k + 1, 4, [], (mine + 1).ravel())
        gmsh.model.mesh.optimize("", force=True)
        tags, coords, _ = gmsh.model.mesh.getNodes()
        out_cells, out_labels = [], []
        for k, region in enumerate(regions):
            _, nodes = gmsh.model.mesh.getElementsByType(4, k + 1)
            block = nodes.reshape(-1, 4).astype(np.int64)
            out_cells.append(block)
            out_labels.append(np.full(len(block), region))
    where = np.zeros(int(tags.max()) + 1, dtype=np.int64)
    where[tags.astype(np.int64)] = np.arange(len(tags))
    new_points = coords.reshape(-1, 3)
    new_cells = where[np.concatenate(out_cells)]
    used, new_cells = np.unique(new_cells, return_inverse=True)
    return new_points[used], new_cells.reshape(-1, 4), np.concatenate(out_labels)


def _planes(normals: np.ndarray, cos_turn: float) -> np.ndarray | None:
    """The mean unit normals (k, 3) of the flat groups the faces around a node fall into
    (each face within the turn of its group's first face, orientation ignored), or None
    when a face lies farther than the turn from its group's mean."""
    groups: list[list[np.ndarray]] = []
    for n in normals:
        for group in groups:
            if abs(n @ group[0]) >= cos_turn:
                group.append(n * np.sign(n @ group[0]))
                break
        else:
            groups.append([n])
    means = []
    for group in groups:
        mean = np.mean(group, axis=0)
        mean /= np.linalg.norm(mean)
        if np.min(np.asarray(group) @ mean) < cos_turn:
            return None
        means.append(mean)
    return np.array(means)


def _move_boundary_nodes(
    points, cells, labels, quality, floor, passes, tries, max_turn, tol, rng, box
):
    """Step 2 of the module docstring, given every element's SICN (``quality``): returns
    the moved points, their elements' SICN and the number of moves. Only the elements
    of a moved node are measured again (a mesh of millions holds a few slivers).
    ``cells`` may be a part of the mesh (see :func:`_around`); ``box`` is the whole
    mesh's (lowest, highest corner), whose sides the nodes on them keep to."""
    points = points.copy()
    quality = quality.copy()
    tris, low, high = _boundary_faces(cells, labels)
    n = len(points)
    node_cells = _incidence(cells, n)
    node_tris = _incidence(tris, n)
    lo_box, hi_box = box
    cos_turn = np.cos(np.radians(max_turn))
    stride = int(labels.max()) + 2  # a pair of regions (the outside -1) as one integer
    moved = 0

    def constraint(v: int) -> np.ndarray | None:
        """The directions a node may not move along (rows), or None if it stays."""
        faces = node_tris[1][node_tris[0][v] : node_tris[0][v + 1]]
        if not len(faces):
            return np.zeros((0, 3))  # inside a region: free
        sides = [
            np.eye(3)[axis]
            for axis in range(3)
            for bound in (lo_box[axis], hi_box[axis])
            if abs(points[v, axis] - bound) < tol
        ]
        if sides:
            return np.array(sides)
        p = points[tris[faces]]
        normals = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        pairs = (low[faces] + 1) * stride + high[faces]
        per_pair = [_planes(normals[pairs == q], cos_turn) for q in np.unique(pairs)]
        if any(planes is None for planes in per_pair):
            return None  # a boundary that is not flat around the node
        planes = _planes(np.vstack(per_pair), cos_turn)
        if planes is None or len(planes) > 2:
            return None  # a corner
        if len(planes) == 1 and len(per_pair) > 1:
            return None  # where interfaces meet within one plane: the node stays on both
        if len(planes) == 2:
            # Where two flat boundaries meet (a chip's edge, two interfaces): along the
            # line they share, when they are not nearly parallel (a step of the image)
            # and the faces themselves, whatever pair they bound, fall into just those
            # two planes (a move along a bent edge changes the volumes).
            line = np.cross(planes[0], planes[1])
            if np.linalg.norm(line) < np.sin(np.radians(max_turn)):
                return None
            faces_planes = _planes(normals, cos_turn)
            if faces_planes is None or len(faces_planes) != 2:
                return None
        return planes

    for _ in range(passes):
        bad = np.flatnonzero(quality < floor)
        if not len(bad):
            break
        for element in bad:
            for v in cells[element]:
                fixed = constraint(v)
                if fixed is None:
                    continue
                elements = node_cells[1][node_cells[0][v] : node_cells[0][v + 1]]
                around = cells[elements]
                best_quality = tetra_sicn(points, around).min()
                neighbours = np.unique(around)
                scale = np.median(np.linalg.norm(points[neighbours] - points[v], axis=1))
                steps = rng.normal(size=(tries, 3))
                for normal in fixed:
                    steps -= np.outer(steps @ normal, normal)
                lengths = np.maximum(np.linalg.norm(steps, axis=1, keepdims=True), 1e-12)
                steps *= scale * rng.uniform(0.02, 0.5, size=(tries, 1)) / lengths
                origin = points[v].copy()
                # Every trial's elements at once (the node at origin + step in each): the
                # same SICN as one trial at a time, in 1 call instead of ``tries``.
                corners = np.repeat(points[around][None], tries, axis=0)
                at = around == v
                corners[:, at] = (origin + steps)[:, None, :]
                trials = _corner_sicn(corners.reshape(-1, 4, 3)).reshape(tries, -1).min(axis=1)
                best = None
                for step, trial in zip(steps, trials.tolist(), strict=True):
                    if trial > best_quality:
                        best, best_quality = step, trial
                points[v] = origin if best is None else origin + best
                if best is not None:
                    moved += 1
                    quality[elements] = tetra_sicn(points, around)
    return points, quality, moved
