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
    "SIDES",
    "FACET_TAGS",
    "ELEMENT_FACES",
    "side_node_sets",
    "boundary_facets",
    "PeriodicPairs",
]

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
