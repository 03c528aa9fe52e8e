"""The boundaries of a box-shaped volume mesh: its six faces as node sets and as facets
(tagged boundary faces, which FEniCS and gmsh users load with the mesh), and the node
pairs that periodic boundary conditions tie across opposite sides.

A voxel mesh cropped to a region with its pore space filled is a full box: every node on
one side has a twin on the opposite side at the same place shifted by the box's length,
which is what a representative volume element with periodic sides needs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = [
    "ON_PLANE_MM",
    "SIDES",
    "FACET_TAGS",
    "ELEMENT_FACES",
    "side_node_sets",
    "boundary_facets",
    "PeriodicPairs",
    "outer_faces",
    "face_vectors",
    "upper_envelope",
    "Surface",
    "platen_surfaces",
]

# Nodes this close to a plane lie on it, mm (float noise on coordinates of order 100 mm).
ON_PLANE_MM = 1e-6

# Side name -> (axis, which end); the facet tags FEniCS reads are 1-based in this order.
SIDES = {
    "bottom": (2, 0),
    "top": (2, 1),
    "xmin": (0, 0),
    "xmax": (0, 1),
    "ymin": (1, 0),
    "ymax": (1, 1),
}
FACET_TAGS = {name: tag for tag, name in enumerate(SIDES, start=1)}

# Outward faces of a VTK hexahedron and a tetrahedron (node positions in the element).
ELEMENT_FACES = {
    "hexahedron": (
        (0, 3, 2, 1),
        (4, 5, 6, 7),
        (0, 1, 5, 4),
        (1, 2, 6, 5),
        (2, 3, 7, 6),
        (3, 0, 4, 7),
    ),
    "tetra": ((0, 2, 1), (0, 1, 3), (1, 2, 3), (0, 3, 2)),
}


def side_node_sets(points: np.ndarray, tolerance_mm: float = 1e-6) -> dict[str, np.ndarray]:
    """Nodes on each of the six planes bounding ``points`` (mm): ``bottom`` (the conveyor),
    ``top`` (the press plate's plane), ``xmin`` ... ``ymax``, and ``lateral`` (the four
    sides together)."""
    sets = {}
    for name, (axis, end) in SIDES.items():
        value = points[:, axis].max() if end else points[:, axis].min()
        sets[name] = np.flatnonzero(np.abs(points[:, axis] - value) <= tolerance_mm)
    sets["lateral"] = np.unique(np.concatenate([sets[s] for s in ("xmin", "xmax", "ymin", "ymax")]))
    return sets


def boundary_facets(
    cells: np.ndarray, cell_type: str, node_sets: dict[str, np.ndarray]
) -> dict[str, np.ndarray]:
    """The boundary faces (faces of one element only) lying on each side: side name ->
    (k, 4) or (k, 3) node indices, ordered so that the face's normal points out."""
    local = ELEMENT_FACES[cell_type]
    faces = np.concatenate([cells[:, list(f)] for f in local])
    n_points = int(cells.max()) + 1 if len(cells) else 0
    # Only faces with every node on a side can lie on one: the count of faces shared by
    # two elements runs over those alone (a few percent of a large mesh's faces; the
    # result and its order are those of the count over all).
    on_any = np.zeros(n_points, dtype=bool)
    for name in SIDES:
        on_any[node_sets[name]] = True
    faces = faces[on_any[faces].all(axis=1)]
    key = np.sort(faces, axis=1)
    _, first, counts = np.unique(key, axis=0, return_index=True, return_counts=True)
    outer = faces[first[counts == 1]]
    facets = {}
    for name in SIDES:
        on_side = np.zeros(n_points, dtype=bool)
        on_side[node_sets[name]] = True
        facets[name] = outer[on_side[outer].all(axis=1)]
    return facets


@dataclass(frozen=True)
class PeriodicPairs:
    """Node pairs tied by periodic conditions: u(dependent) = u(independent) + the jump
    of each shifted axis (the displacement of the reference node of that axis).

    dependent, independent: (k,) node indices. shifts: (k, 2) bool, whether the pair
    crosses the box along x and along y (a node on the xmax-ymax edge crosses both).
    on_platen: (k,) bool, the pair lies on the top or bottom face, whose z the platens
    prescribe (so z is not tied there: a degree of freedom is prescribed or tied, never
    both)."""

    dependent: np.ndarray
    independent: np.ndarray
    shifts: np.ndarray
    on_platen: np.ndarray

    @classmethod
    def of_box(
        cls, points: np.ndarray, platen_nodes: np.ndarray, tolerance_mm: float = 1e-6
    ) -> PeriodicPairs:
        """The pairs of a box-shaped mesh: every node on ``xmax`` or ``ymax`` with its twin
        on the opposite side(s).

        Raises ValueError when a node has no twin (the mesh is not a full box)."""
        low, high = points[:, :2].min(axis=0), points[:, :2].max(axis=0)
        at_high = np.abs(points[:, :2] - high) <= tolerance_mm
        dependent = np.flatnonzero(at_high.any(axis=1))
        shifts = at_high[dependent]
        twins = points[dependent].copy()
        twins[:, :2] = np.where(shifts, low, twins[:, :2])
        # Twins by rounded position: a structured box's nodes sit on a grid.
        scale = 1.0 / max(tolerance_mm, 1e-9)
        grid = {tuple(k): i for i, k in enumerate(np.rint(points * scale).astype(np.int64))}
        keys = np.rint(twins * scale).astype(np.int64)
        independent = np.array([grid.get(tuple(k), -1) for k in keys], dtype=np.int64)
        if np.any(independent < 0):
            missing = int(np.count_nonzero(independent < 0))
            raise ValueError(f"{missing} nodes on the xmax or ymax side have no twin")
        on_platen = np.isin(dependent, platen_nodes)
        return cls(dependent, independent, shifts, on_platen)


def outer_faces(cells: np.ndarray, cell_type: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The faces that belong to one element only (the mesh's boundary): their element
    (k,), local face number (k,) (``ELEMENT_FACES`` order, which is the Abaqus face label
    S1 ... minus one) and nodes (k, n), ordered so that the face's normal points out."""
    local = ELEMENT_FACES[cell_type]
    m = len(cells)
    faces = np.concatenate([cells[:, list(f)] for f in local])
    key = np.ascontiguousarray(np.sort(faces, axis=1))
    # One void scalar per face: np.unique then sorts bytes, not rows (five times faster).
    rows = key.view(np.dtype((np.void, key.dtype.itemsize * key.shape[1]))).ravel()
    _, first, counts = np.unique(rows, return_index=True, return_counts=True)
    index = np.sort(first[counts == 1])
    return index % m, index // m, faces[index]


def face_vectors(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(k, 3) each face's area vector (mm²): its unit normal times its area, for triangles
    and for planar or nearly planar quadrilaterals (half the cross product of the
    diagonals)."""
    p = points[faces]
    if faces.shape[1] == 3:
        return 0.5 * np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    return 0.5 * np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 1])


def upper_envelope(
    points: np.ndarray, faces: np.ndarray, tolerance_mm: float = 1e-6, chunk: int = 4_000_000
) -> np.ndarray:
    """(k,) bool: which of the boundary ``faces`` a flat platen coming down from above
    meets first, i.e. the faces with an upward normal that no boundary face lies above.

    A face counts as covered when the vertical line through its centroid meets another
    face more than ``tolerance_mm`` higher: exact for the axis-aligned faces of a voxel
    mesh, and for a tetrahedral mesh it decides a face half covered by its centroid."""
    faces = np.asarray(faces)
    k = len(faces)
    if k == 0:
        return np.zeros(0, dtype=bool)
    up = face_vectors(points, faces)[:, 2] > 0
    query = np.flatnonzero(up)
    centre = points[faces[query]].mean(axis=1)
    # The covers: every face as triangles (a quadrilateral as two) whose projection on
    # the xy plane has an area; upright faces cover nothing.
    splits = [(0, 1, 2)] if faces.shape[1] == 3 else [(0, 1, 2), (0, 2, 3)]
    tri = np.concatenate([faces[:, list(s)] for s in splits])
    a, b, c = (points[tri[:, i]] for i in range(3))
    det = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])
    flat = np.abs(det) > 1e-12 * max(float(np.ptp(points[:, :2], axis=0).max()), 1.0) ** 2
    a, b, c, det = a[flat], b[flat], c[flat], det[flat]
    low = np.minimum(np.minimum(a, b), c)[:, :2]
    high = np.maximum(np.maximum(a, b), c)[:, :2]
    # Bin the covers on an xy grid of cells twice their typical size; a cover goes into
    # every cell its bounding box meets, a centroid looks in its own cell only.
    size = 2.0 * max(float(np.median((high - low).max(axis=1))), 1e-6)
    origin = points[:, :2].min(axis=0) - size
    i0, i1 = (np.floor((v - origin) / size).astype(np.int64) for v in (low, high))
    spans = i1 - i0 + 1
    n_cells = spans.prod(axis=1)
    width = int(max(i1[:, 1].max(), np.floor((centre[:, 1] - origin[1]) / size).max())) + 2
    owner = np.repeat(np.arange(len(a)), n_cells)
    step = np.arange(len(owner)) - np.repeat(np.cumsum(n_cells) - n_cells, n_cells)
    cell = (i0[owner, 0] + step // spans[owner, 1]) * width + i0[owner, 1] + step % spans[owner, 1]
    order = np.argsort(cell, kind="stable")
    cell, owner = cell[order], owner[order]
    q_cell = np.floor((centre[:, :2] - origin) / size).astype(np.int64)
    q_cell = q_cell[:, 0] * width + q_cell[:, 1]
    start = np.searchsorted(cell, q_cell, side="left")
    count = np.searchsorted(cell, q_cell, side="right") - start
    covered = np.zeros(len(query), dtype=bool)
    done = 0
    while done < len(query):
        # Chunks of queries with at most ``chunk`` (centroid, cover) pairs.
        total = np.cumsum(count[done:])
        stop = done + max(1, int(np.searchsorted(total, chunk, side="right")))
        q = np.repeat(np.arange(done, stop), count[done:stop])
        offset = np.arange(len(q)) - np.repeat(
            np.cumsum(count[done:stop]) - count[done:stop], count[done:stop]
        )
        t = owner[np.repeat(start[done:stop], count[done:stop]) + offset]
        x, y, z = centre[q, 0], centre[q, 1], centre[q, 2]
        # Barycentric coordinates of the centroid in the cover's projection.
        u = ((x - a[t, 0]) * (c[t, 1] - a[t, 1]) - (c[t, 0] - a[t, 0]) * (y - a[t, 1])) / det[t]
        v = ((b[t, 0] - a[t, 0]) * (y - a[t, 1]) - (x - a[t, 0]) * (b[t, 1] - a[t, 1])) / det[t]
        eps = 1e-9
        inside = (u >= -eps) & (v >= -eps) & (u + v <= 1 + eps)
        height = a[t, 2] + u * (b[t, 2] - a[t, 2]) + v * (c[t, 2] - a[t, 2])
        above = inside & (height > z + tolerance_mm)
        covered[np.unique(q[above])] = True
        done = stop
    result = np.zeros(k, dtype=bool)
    result[query[~covered]] = True
    return result


@dataclass(frozen=True)
class Surface:
    """A named set of boundary faces: element (k,) and local face number (k,) (the
    Abaqus face label is S + 1), nodes (k, n) ordered so that the normal points out of
    the mesh; area_mm2 and projected_area_mm2 (on the xy plane: what a platen presses)."""

    element: np.ndarray
    face: np.ndarray
    nodes: np.ndarray
    area_mm2: float
    projected_area_mm2: float

    @property
    def node_ids(self) -> np.ndarray:
        """The surface's nodes, each once, sorted."""
        return np.unique(self.nodes)


def platen_surfaces(
    points: np.ndarray,
    cells: np.ndarray,
    cell_type: str,
    node_sets: dict[str, np.ndarray],
    with_sides: bool,
    fills_box: bool = False,
) -> dict[str, Surface]:
    """The surfaces a press and its support use, by name (``SIDES``' names and order):
    ``top``, the faces a flat platen coming down from above meets (the upper envelope;
    with ``fills_box``, a mesh with its pore space, only those of them facing up within
    60 degrees, the box's top, which a tetrahedral mesh rounds at its edges); ``bottom``,
    the boundary faces on the conveyor plane (``node_sets["bottom"]``); with
    ``with_sides`` (a box or a crop) the boundary faces on each side plane, which are
    never part of ``top``. A surface with no face is left out."""
    element, face, nodes = outer_faces(cells, cell_type)
    vectors = face_vectors(points, nodes)
    on_plane = {}
    for name in SIDES:
        mark = np.zeros(len(points), dtype=bool)
        mark[node_sets.get(name, np.zeros(0, dtype=np.int64))] = True
        on_plane[name] = mark[nodes].all(axis=1)
    top = upper_envelope(points, nodes)
    if fills_box:
        cosine = vectors[:, 2] / np.maximum(np.linalg.norm(vectors, axis=1), 1e-300)
        top &= cosine > 0.5
    chosen = {"bottom": on_plane["bottom"] & (vectors[:, 2] < 0), "top": top}
    if with_sides:
        sides = {name: on_plane[name] for name in ("xmin", "xmax", "ymin", "ymax")}
        chosen.update(sides)
        # A tetrahedral mesh's side is not quite plane: a side face tilted a little
        # upward, with nothing over it, would otherwise be pressed as part of the top.
        chosen["top"] = top & ~np.any(list(sides.values()), axis=0)
    surfaces = {}
    for name in SIDES:
        pick = chosen.get(name)
        if pick is None or not pick.any():
            continue
        v = vectors[pick]
        surfaces[name] = Surface(
            element=element[pick],
            face=face[pick],
            nodes=nodes[pick],
            area_mm2=float(np.linalg.norm(v, axis=1).sum()),
            projected_area_mm2=float(np.abs(v[:, 2]).sum()),
        )
    return surfaces
