"""The contact model of a stack: every chip meshed on its own, in its exact settled pose.

No repair is needed: small interpenetrations left by the physics are the solver's
contact business. Each box chip is a structured block of hexahedra (``through_thickness``
elements through the thickness, square-ish elements of ``element_mm`` in its plane), so
that bending is carried with few elements (C3D8I). Per chip the model holds an element
set, its outer surface (element faces), and its two fibre directions (for an
``*ORIENTATION``). Contact pairs join every pair of chips closer than a gap tolerance
(the geometry stage's contact search). Two rigid platens span the whole stack: the
conveyor just below the lowest chip and a press plate just above the highest.

Node order and face numbers are CalculiX's (and Abaqus's) for C3D8: nodes 1-4 the bottom
face counter-clockwise seen from above, 5-8 above them; face S1 bottom (1-2-3-4), S2 top,
S3 y-, S4 x+, S5 y+, S6 x-.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from chipstack.core.arrangement import Arrangement
from chipstack.core.errors import InputError
from chipstack.geometry.contacts import candidate_pairs, find_contacts
from chipstack.meshing.mesh import chip_attributes

__all__ = [
    "ContactModel",
    "Platen",
    "contact_model",
    "chip_block",
    "clear_overlaps",
    "separation",
    "faces_near_box",
    "faces_within",
    "FACE_NODES",
]

log = logging.getLogger(__name__)

# Local node indices (0-based, C3D8 order) of faces S1..S6.
FACE_NODES = (
    (0, 1, 2, 3),
    (4, 7, 6, 5),
    (0, 4, 5, 1),
    (1, 5, 6, 2),
    (2, 6, 7, 3),
    (3, 7, 4, 0),
)
MAX_LIFT_ROUNDS = 20
PLATEN_MARGIN = 0.1  # platens overhang the stack's footprint by this fraction of its width


@dataclass(frozen=True)
class Platen:
    """A rigid plate of hexahedra; ``face`` is its face toward the stack (S1 or S2)."""

    name: str
    cells: np.ndarray  # (m, 8) node indices
    face: int  # 1-based face number toward the stack
    reference_node: int  # node index of the rigid body's reference (translation) node
    rotation_node: int  # node index of its rotation node
    z_mm: float  # height of its face toward the stack


@dataclass(frozen=True, eq=False)
class ContactModel:
    """Chips meshed one by one, their surfaces and contact pairs, and two rigid platens.

    points: (N, 3) mm. cells: (M, 8) chip hexahedra (C3D8 order). chip: (M,) chip index.
    surfaces: per chip, (k, 2) rows of (element index, face number 1..6) on its outside.
    pairs: (P, 2) chips in contact or within ``gap_mm`` (each pair once, a < b).
    floor_chips: chips touching or within ``gap_mm`` of the conveyor (the bottom platen).
    fibres: (n, 2, 3) each chip's fibre directions in the world frame. anchors: (n, 4)
    node indices of each chip's mid-plane corners (where the weak springs go).
    height_mm: from the bottom platen's face to the top platen's.
    """

    points: np.ndarray
    cells: np.ndarray
    chip: np.ndarray
    surfaces: tuple[np.ndarray, ...]
    pairs: np.ndarray
    floor_chips: np.ndarray
    fibres: np.ndarray
    normals: np.ndarray
    anchors: np.ndarray
    bottom: Platen
    top: Platen
    element_mm: float
    through_thickness: int
    gap_mm: float
    info: dict = field(default_factory=dict)

    @property
    def n_chips(self) -> int:
        return len(self.surfaces)

    @property
    def height_mm(self) -> float:
        return self.top.z_mm - self.bottom.z_mm

    @property
    def n_elements(self) -> int:
        return len(self.cells)


def chip_block(half_extents: np.ndarray, divisions: tuple[int, int, int]) -> tuple:
    """A structured block of hexahedra over the box ``[-h, h]`` (local frame).

    Returns (points (N, 3), cells (M, 8) in C3D8 order, surface (k, 2) rows of (cell,
    face number), anchors (4,) node indices of the mid-plane corners).
    """
    nx, ny, nz = divisions
    axes = [np.linspace(-h, h, n + 1) for h, n in zip(half_extents, divisions, strict=True)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)

    def node(i, j, k):
        return (i * (ny + 1) + j) * (nz + 1) + k

    i, j, k = (a.ravel() for a in np.meshgrid(range(nx), range(ny), range(nz), indexing="ij"))
    cells = np.stack(
        [
            node(i, j, k),
            node(i + 1, j, k),
            node(i + 1, j + 1, k),
            node(i, j + 1, k),
            node(i, j, k + 1),
            node(i + 1, j, k + 1),
            node(i + 1, j + 1, k + 1),
            node(i, j + 1, k + 1),
        ],
        axis=1,
    )
    outside = [k == 0, k == nz - 1, j == 0, i == nx - 1, j == ny - 1, i == 0]
    surface = np.concatenate(
        [
            np.column_stack([np.flatnonzero(on), np.full(on.sum(), f + 1)])
            for f, on in enumerate(outside)
        ]
    )
    mid = nz // 2 if nz % 2 == 0 else None
    level = mid if mid is not None else 0  # odd counts: the bottom plane's corners
    anchors = np.array([node(a, b, level) for a, b in ((0, 0), (nx, 0), (nx, ny), (0, ny))])
    return grid, cells, surface, anchors


def _divisions(half_extents: np.ndarray, element_mm: float, through: int) -> tuple[int, int, int]:
    length, width = 2 * half_extents[0], 2 * half_extents[1]
    return (
        max(2, math.ceil(length / element_mm - 1e-9)),
        max(2, math.ceil(width / element_mm - 1e-9)),
        through,
    )


def _corners(arrangement: Arrangement, chip: int, lift: float = 0.0) -> np.ndarray:
    """(8, 3) mm, the world corners of a box chip."""
    shape = arrangement.shapes[arrangement.shape_index[chip]]
    h = np.asarray(shape.half_extents)
    signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    local = signs * h + np.asarray(shape.box_centre)
    return local @ arrangement.rotations[chip].T + arrangement.positions[chip] + [0, 0, lift]


def separation(
    a: np.ndarray, b: np.ndarray, axes_a: np.ndarray, axes_b: np.ndarray
) -> tuple[float, np.ndarray, bool]:
    """How two convex boxes (corners ``a``, ``b``) overlap: (depth mm, unit n with
    n_z >= 0, whether ``a`` is the upper one). Moving the upper box by ``depth`` along n
    separates them; depth 0: they do not overlap.

    Separating-axis test over the 15 axes of two boxes (3 + 3 face normals and their 9
    cross products); the axis of least overlap gives the minimal translation.
    """
    best, direction, a_upper = np.inf, np.array([0.0, 0.0, 1.0]), True
    candidates = [*axes_a, *axes_b] + [np.cross(u, v) for u in axes_a for v in axes_b]
    for n in candidates:
        norm = np.linalg.norm(n)
        if norm < 1e-9:
            continue
        m = n / norm if n[2] >= 0 else -n / norm  # point up (or level)
        pa, pb = a @ m, b @ m
        a_above, b_above = pa.max() - pb.min(), pb.max() - pa.min()
        overlap = min(a_above, b_above)
        if overlap <= 0:
            return 0.0, m, True  # a separating axis
        if overlap < best:
            # The box whose projection sits higher along m is the upper one.
            best, direction, a_upper = overlap, m, pa.mean() >= pb.mean()
    return float(best), direction, a_upper


def clear_overlaps(arrangement: Arrangement, clearance_mm: float = 1e-3) -> np.ndarray:
    """(n, 3) mm, small shifts that leave no two chips (and no chip and the conveyor)
    overlapping: bottom-up, of every overlapping pair the upper chip moves out along the
    axis of least overlap (plus ``clearance_mm``), until a sweep moves nothing.

    The physics leaves overlaps of a few hundredths of a millimetre; a penalty contact
    started overclosed pushes the chips apart violently."""
    n = arrangement.n_chips
    shifts = np.zeros((n, 3))
    pairs = candidate_pairs(arrangement.bounds, 0.1)
    rank = arrangement.bottom_up_rank()
    pairs = pairs[np.argsort(np.minimum(rank[pairs[:, 0]], rank[pairs[:, 1]]), kind="stable")]
    axes = np.transpose(arrangement.rotations, (0, 2, 1))  # rows: local axes in the world
    corners = [_corners(arrangement, k) for k in range(n)]
    for _ in range(MAX_LIFT_ROUNDS):
        moved = False
        for chip in arrangement.bottom_up_order():
            floor = clearance_mm - (corners[chip][:, 2] + shifts[chip, 2]).min()
            if floor > 0:
                shifts[chip, 2] += floor
                moved = True
        for a, b in pairs:
            depth, direction, a_upper = separation(
                corners[a] + shifts[a], corners[b] + shifts[b], axes[a], axes[b]
            )
            if depth > 0:
                shifts[a if a_upper else b] += (depth + clearance_mm) * direction
                moved = True
        if not moved:
            return shifts
    log.warning("contact model: overlaps left after %d rounds of clearing", MAX_LIFT_ROUNDS)
    return shifts


def default_element_mm(arrangement: Arrangement) -> float:
    """A tenth of the shortest in-plane side of any chip, at most 2 mm."""
    shortest = min(2 * float(min(s.half_extents[:2])) for s in arrangement.shapes)
    return min(2.0, shortest / 10)


def contact_model(
    arrangement: Arrangement,
    element_mm: float = 0.0,
    through_thickness: int = 2,
    gap_mm: float = 0.3,
    layer_mm: float = 2.0,
) -> ContactModel:
    """The contact model of ``arrangement`` (see the module docstring).

    element_mm: in-plane element size (0: :func:`default_element_mm`); it must not exceed
    half the chip's shortest side. through_thickness: elements through the thickness.
    gap_mm: chips (and chips and the conveyor) closer than this get a contact pair.
    """
    if arrangement.n_chips == 0:
        raise InputError("contact model: the stack has no chips")
    for shape in arrangement.shapes:
        if not shape.is_cuboid:
            raise InputError(
                f"mesh.kind = 'contact': box-shaped chips only so far (shape {shape.name!r}); "
                "use mesh.kind = 'voxel'"
            )
    size = element_mm or default_element_mm(arrangement)
    shortest = min(2 * float(min(s.half_extents[:2])) for s in arrangement.shapes)
    if size > shortest / 2:
        raise InputError(
            f"mesh.element_mm: {size:g} mm is more than half the shortest chip side "
            f"({shortest:g} mm); at least 2 elements across a chip are needed"
        )
    shifts = clear_overlaps(arrangement)
    arrangement = dataclasses.replace(arrangement, positions=arrangement.positions + shifts)
    moved = np.linalg.norm(shifts, axis=1)
    points, cells, chip, surfaces, anchors = _mesh_chips(arrangement, size, through_thickness)
    table = find_contacts(arrangement, gap_mm, extent_mm=5.0)
    on_chips = table.chip_b >= 0
    pairs = np.unique(
        np.sort(np.column_stack([table.chip_a, table.chip_b])[on_chips], axis=1), axis=0
    )
    floor = np.unique(table.chip_a[~on_chips])
    points, bottom, top = _add_platens(points, size)
    _, _, fibres, normals = chip_attributes(arrangement, layer_mm)
    return ContactModel(
        points=points,
        cells=cells,
        chip=chip,
        surfaces=tuple(surfaces),
        pairs=pairs.reshape(-1, 2),
        floor_chips=floor,
        fibres=fibres,
        normals=normals,
        anchors=np.array(anchors),
        bottom=bottom,
        top=top,
        element_mm=size,
        through_thickness=through_thickness,
        gap_mm=gap_mm,
        info={
            "element_mm": size,
            "through_thickness": through_thickness,
            "gap_mm": gap_mm,
            "chips_moved_apart": int((moved > 1e-9).sum()),
            "max_move_mm": float(moved.max()),
        },
    )


def save_contact_model(path: Path, model: ContactModel) -> Path:
    """Write ``model`` as a NumPy archive (no pickles): what the solve stage reads to
    write the compaction deck, so that the mesh stage does not depend on ``[solve]``."""
    arrays = {
        name: getattr(model, name)
        for name in ("points", "cells", "chip", "pairs", "floor_chips", "fibres", "normals")
    }
    arrays["anchors"] = model.anchors
    arrays["surface_rows"] = np.concatenate(model.surfaces) if model.surfaces else np.zeros((0, 2))
    arrays["surface_counts"] = np.array([len(s) for s in model.surfaces])
    for platen in (model.bottom, model.top):
        key = platen.name.lower()
        arrays[f"{key}_cells"] = platen.cells
        arrays[f"{key}_numbers"] = np.array(
            [platen.face, platen.reference_node, platen.rotation_node]
        )
        arrays[f"{key}_z_mm"] = np.array(platen.z_mm)
    arrays["sizes"] = np.array([model.element_mm, model.through_thickness, model.gap_mm])
    arrays["info"] = np.array(json.dumps(model.info, sort_keys=True))
    with open(path, "wb") as f:
        np.savez_compressed(f, **arrays)
    return Path(path)


def load_contact_model(path: Path) -> ContactModel:
    """The model :func:`save_contact_model` wrote."""
    with np.load(path, allow_pickle=False) as data:
        d = {k: data[k] for k in data.files}
    rows = d["surface_rows"].astype(int)
    edges = np.cumsum(d["surface_counts"])[:-1]
    platens = []
    for name in ("BOTTOM", "TOP"):
        face, reference, rotation = (int(v) for v in d[f"{name.lower()}_numbers"])
        platens.append(
            Platen(
                name,
                d[f"{name.lower()}_cells"],
                face,
                reference,
                rotation,
                float(d[f"{name.lower()}_z_mm"]),
            )
        )
    element_mm, through, gap = d["sizes"]
    return ContactModel(
        points=d["points"],
        cells=d["cells"],
        chip=d["chip"],
        surfaces=tuple(np.split(rows, edges)),
        pairs=d["pairs"],
        floor_chips=d["floor_chips"],
        fibres=d["fibres"],
        normals=d["normals"],
        anchors=d["anchors"],
        bottom=platens[0],
        top=platens[1],
        element_mm=float(element_mm),
        through_thickness=int(through),
        gap_mm=float(gap),
        info=json.loads(str(d["info"])),
    )


def _face_points(model: ContactModel, faces: np.ndarray) -> np.ndarray:
    """(k, 4, 3) mm, the corner points of surface faces (rows of element, face number)."""
    local = np.asarray(FACE_NODES)[faces[:, 1] - 1]
    return model.points[model.cells[faces[:, 0][:, None], local]]


def chip_box(model: ContactModel, chip: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The oriented box of a meshed chip: (centre (3,), axes (3, 3) rows, half sizes (3,))."""
    nodes = model.points[np.unique(model.cells[model.chip == chip])]
    first = model.fibres[chip][0]
    normal = model.normals[chip]
    axes = np.array([first, np.cross(normal, first), normal])
    centre = nodes.mean(axis=0)
    local = (nodes - centre) @ axes.T
    return centre, axes, np.abs(local).max(axis=0)


def faces_near_box(model: ContactModel, chip: int, box: tuple, reach_mm: float) -> np.ndarray:
    """Rows of ``model.surfaces[chip]`` with a corner within ``reach_mm`` of ``box`` (another
    chip's :func:`chip_box`): the part of a chip's surface that can meet that chip."""
    faces = model.surfaces[chip]
    centre, axes, half = box
    local = np.abs((_face_points(model, faces) - centre) @ axes.T)
    distance = np.linalg.norm(np.maximum(local - half, 0.0), axis=-1)
    return faces[(distance <= reach_mm).any(axis=1)]


def faces_within(model: ContactModel, chip: int, z_min: float, z_max: float) -> np.ndarray:
    """Rows of ``model.surfaces[chip]`` with a corner between two heights (mm)."""
    faces = model.surfaces[chip]
    z = _face_points(model, faces)[..., 2]
    return faces[((z >= z_min) & (z <= z_max)).any(axis=1)]


def _mesh_chips(arrangement: Arrangement, size: float, through: int):
    """Every chip's block of hexahedra in its pose, numbered chip after chip."""
    points, cells, chip, surfaces, anchors = [], [], [], [], []
    offset = n_cells = 0
    for k in range(arrangement.n_chips):
        shape = arrangement.shapes[arrangement.shape_index[k]]
        divisions = _divisions(np.asarray(shape.half_extents), size, through)
        local, block, surface, corners = chip_block(np.asarray(shape.half_extents), divisions)
        local = local + np.asarray(shape.box_centre)
        world = local @ arrangement.rotations[k].T + arrangement.positions[k]
        points.append(world)
        cells.append(block + offset)
        chip.append(np.full(len(block), k))
        surfaces.append(np.column_stack([surface[:, 0] + n_cells, surface[:, 1]]))
        anchors.append(corners + offset)
        offset += len(world)
        n_cells += len(block)
    return (
        np.concatenate(points),
        np.concatenate(cells),
        np.concatenate(chip),
        surfaces,
        anchors,
    )


def _add_platens(points: np.ndarray, size: float) -> tuple[np.ndarray, Platen, Platen]:
    """Two rigid plates spanning the stack's footprint (with a margin): the conveyor,
    its top face at the lowest chip point, and the press plate, its bottom face at the
    highest. Each is a grid of hexahedra about ``4 * size`` across and ``size`` thick."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    margin = PLATEN_MARGIN * max(hi[0] - lo[0], hi[1] - lo[1]) + size
    x0, y0 = lo[:2] - margin
    x1, y1 = hi[:2] + margin
    cells_across = max(2, math.ceil(max(x1 - x0, y1 - y0) / (4 * size)))
    platens = []
    for name, z_face, below in (("BOTTOM", lo[2], True), ("TOP", hi[2], False)):
        half = np.array([(x1 - x0) / 2, (y1 - y0) / 2, size / 2])
        local, block, _, _ = chip_block(half, (cells_across, cells_across, 1))
        centre = np.array(
            [(x0 + x1) / 2, (y0 + y1) / 2, z_face - size / 2 if below else z_face + size / 2]
        )
        offset = len(points)
        reference = np.array([[centre[0], centre[1], z_face], [centre[0], centre[1], z_face]])
        points = np.vstack([points, local + centre, reference])
        n_plate = len(local)
        platens.append(
            Platen(
                name=name,
                cells=block + offset,
                face=2 if below else 1,
                reference_node=offset + n_plate,
                rotation_node=offset + n_plate + 1,
                z_mm=float(z_face),
            )
        )
    return points, platens[0], platens[1]
