"""Contact types (paper section 3.1.1): point, line or surface, and where the partner is.

The classification is geometric, not read from the physics engine's contact manifold:
two chips touch when their surfaces come closer than ``gap_mm``. Each solid is inflated by
half the gap, and the contact patch is the intersection of the two inflated solids (exact,
manifold3d). The patch's extents along its principal axes give its dimension:

* surface: the second-largest extent is at least ``extent_mm`` (an area of contact);
* line: only the largest extent reaches ``extent_mm`` (an edge lying on a face or edge);
* point: no extent reaches ``extent_mm`` (a corner on a face, crossed edges).

The floor (the conveyor, z = 0) is a partner like any other. Where the partner is, seen from
a chip: ``ground``; else ``below`` or ``above`` when the patch's centre lies more than half
the chip's own vertical half-height below or above the chip's centre; else ``around``.
"""

from __future__ import annotations

from dataclasses import dataclass

import manifold3d as m3
import numpy as np
from scipy.spatial import ConvexHull, QhullError, cKDTree

from chipstack.core.arrangement import Arrangement
from chipstack.core.errors import InputError
from chipstack.geometry.solids import chip_solid

__all__ = [
    "KINDS",
    "PLACES",
    "GROUND",
    "ContactTable",
    "classify_patch",
    "patch_extents",
    "find_contacts",
    "contact_counts",
    "candidate_pairs",
]

KINDS = ("point", "line", "surface")
PLACES = ("below", "above", "around", "ground")
GROUND = -1


def patch_extents(vertices: np.ndarray) -> np.ndarray:
    """(3,) mm: length, width and thickness of a contact patch, largest first.

    The patch's plane is the one across which its corners spread least (the smallest
    principal axis is its normal, and the thickness is the corners' span along it). In that
    plane, length and width are the sides of the narrowest rectangle holding the corners
    (rotating calipers), so the extents do not depend on how the stack is turned.
    """
    points = np.asarray(vertices, dtype=float)
    if len(points) < 2:
        return np.zeros(3)
    centred = points - points.mean(axis=0)
    _, _, axes = np.linalg.svd(centred, full_matrices=False)
    if len(axes) < 3:
        axes = np.vstack([axes, np.zeros((3 - len(axes), 3))])
    thickness = float(np.ptp(centred @ axes[2]))
    plane = centred @ axes[:2].T
    length, width = _length_and_width(plane)
    return np.array([length, width, thickness])


def _length_and_width(points: np.ndarray) -> tuple[float, float]:
    """Sides (mm) of the narrowest rectangle around points in the plane, longest first.

    The rectangle is aligned with the hull edge across which the points are narrowest
    (rotating calipers): its width is the points' minimum width, its length their span
    along that edge.
    """
    try:
        hull = points[ConvexHull(points).vertices]
    except QhullError:  # collinear or coincident: a segment or a point
        spread = points - points.mean(axis=0)
        if not np.any(spread):
            return 0.0, 0.0
        direction = np.linalg.svd(spread, full_matrices=False)[2][0]
        return float(np.ptp(spread @ direction)), 0.0
    edges = np.roll(hull, -1, axis=0) - hull
    edges /= np.linalg.norm(edges, axis=1, keepdims=True)
    normals = np.column_stack([-edges[:, 1], edges[:, 0]])
    across = np.ptp(hull @ normals.T, axis=0)  # width across each edge
    along = np.ptp(hull @ edges.T, axis=0)
    k = int(np.argmin(across))
    return float(max(along[k], across[k])), float(min(along[k], across[k]))


def classify_patch(vertices: np.ndarray, extent_mm: float) -> tuple[int, np.ndarray]:
    """Kind (index into :data:`KINDS`) and extents (3,) mm of a contact patch.

    ``vertices`` (k, 3) mm are the corners of the patch solid; see :func:`patch_extents`.
    """
    extents = patch_extents(vertices)
    if extents[1] >= extent_mm:
        return 2, extents
    if extents[0] >= extent_mm:
        return 1, extents
    return 0, extents


@dataclass(frozen=True)
class ContactTable:
    """All contacts of an arrangement, one row per touching pair (floor included).

    chip_a, chip_b: (m,) chip indices, ``chip_a < chip_b``; chip_b is GROUND (-1) for the floor.
    kind: (m,) index into KINDS. extents_mm: (m, 3) patch extents, largest first.
    centre_mm: (m, 3) centre of the patch. area_mm2: (m,) half the patch's surface area
    (the contact area at the gap tolerance). place_a, place_b: (m,) index into PLACES, where
    the partner lies seen from chip_a and from chip_b (-1 for the floor's side).
    """

    n_chips: int
    chip_a: np.ndarray
    chip_b: np.ndarray
    kind: np.ndarray
    extents_mm: np.ndarray
    centre_mm: np.ndarray
    area_mm2: np.ndarray
    place_a: np.ndarray
    place_b: np.ndarray

    def __len__(self) -> int:
        return len(self.chip_a)


def candidate_pairs(bounds: np.ndarray, margin_mm: float) -> np.ndarray:
    """(k, 2) pairs i < j whose bounding boxes, grown by ``margin_mm``, overlap.

    ``bounds`` (n, 2, d) mm: low and high corners in d dimensions (3 for solids, 2 for
    footprints on the conveyor).
    """
    if len(bounds) < 2:
        return np.empty((0, 2), dtype=int)
    centres = bounds.mean(axis=1)
    half = (bounds[:, 1] - bounds[:, 0]) / 2
    reach = 2 * np.linalg.norm(half, axis=1).max() + margin_mm
    pairs = cKDTree(centres).query_pairs(reach, output_type="ndarray")
    if not len(pairs):
        return np.empty((0, 2), dtype=int)
    i, j = pairs[:, 0], pairs[:, 1]
    apart = (np.abs(centres[i] - centres[j]) > half[i] + half[j] + margin_mm).any(axis=1)
    pairs = np.sort(pairs[~apart], axis=1)
    return pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]


def find_contacts(
    arrangement: Arrangement, gap_mm: float = 0.05, extent_mm: float = 5.0
) -> ContactTable:
    """Every touching pair of chips, and every chip touching the floor, classified.

    gap_mm: surfaces closer than this touch (mm). extent_mm: patch extent from which a
    contact is a line or a surface (mm). See the module docstring for the definitions.
    """
    if not (np.isfinite(gap_mm) and gap_mm > 0):
        raise InputError(f"gap_mm: must be positive, got {gap_mm!r}")
    if not (np.isfinite(extent_mm) and extent_mm > 0):
        raise InputError(f"extent_mm: must be positive, got {extent_mm!r}")
    inflate = gap_mm / 2
    bounds = arrangement.bounds
    half_height = (bounds[:, 1, 2] - bounds[:, 0, 2]) / 2
    solids: dict[int, m3.Manifold] = {}

    def solid(chip: int) -> m3.Manifold:
        if chip not in solids:
            solids[chip] = chip_solid(arrangement, chip, inflate)
        return solids[chip]

    rows = []
    for a, b in candidate_pairs(bounds, gap_mm):
        patch = solid(a) ^ solid(b)
        if patch.is_empty():
            continue
        rows.append((int(a), int(b), patch))
    floor_candidates = np.flatnonzero(bounds[:, 0, 2] < gap_mm)
    for a in floor_candidates:
        lo, hi = bounds[a, 0, :2] - 1.0, bounds[a, 1, :2] + 1.0
        floor = m3.Manifold.cube([*(hi - lo), 1.0]).translate([lo[0], lo[1], inflate - 1.0])
        patch = solid(a) ^ floor
        if patch.is_empty():
            continue
        rows.append((int(a), GROUND, patch))
    rows.sort(key=lambda r: (r[0], r[1] if r[1] != GROUND else -1))
    m = len(rows)
    kind = np.zeros(m, dtype=np.int64)
    extents = np.zeros((m, 3))
    centre = np.zeros((m, 3))
    area = np.zeros(m)
    for k, (_, _, patch) in enumerate(rows):
        vertices = np.asarray(patch.to_mesh().vert_properties)[:, :3]
        kind[k], extents[k] = classify_patch(vertices, extent_mm)
        lo, hi = (np.asarray(v) for v in _box(patch))
        centre[k] = (lo + hi) / 2
        area[k] = patch.surface_area() / 2
    chip_a = np.array([r[0] for r in rows], dtype=np.int64)
    chip_b = np.array([r[1] for r in rows], dtype=np.int64)
    place_a = np.full(m, 3, dtype=np.int64)
    place_b = np.full(m, -1, dtype=np.int64)
    chips = chip_b != GROUND
    if m:
        place_a[chips] = _place(centre[chips, 2], arrangement, chip_a[chips], half_height)
        # The same patch seen from chip b (its partner a is below when the patch is low on b).
        place_b[chips] = _place(centre[chips, 2], arrangement, chip_b[chips], half_height)
    table = ContactTable(
        arrangement.n_chips, chip_a, chip_b, kind, extents, centre, area, place_a, place_b
    )
    for array in (chip_a, chip_b, kind, extents, centre, area, place_a, place_b):
        array.setflags(write=False)
    return table


def _box(patch: m3.Manifold) -> tuple[tuple[float, ...], tuple[float, ...]]:
    box = patch.bounding_box()
    return box[:3], box[3:]


def _place(
    patch_z: np.ndarray, arrangement: Arrangement, chips: np.ndarray, half_height: np.ndarray
) -> np.ndarray:
    offset = patch_z - arrangement.positions[chips, 2]
    limit = half_height[chips] / 2
    return np.where(offset < -limit, 0, np.where(offset > limit, 1, 2))


def contact_counts(table: ContactTable) -> np.ndarray:
    """(n_chips, 3 kinds, 4 places) int: each chip's contacts by kind and partner place.

    A contact between two chips appears in both chips' rows (once each); a floor contact in
    its chip's row only.
    """
    counts = np.zeros((table.n_chips, len(KINDS), len(PLACES)), dtype=np.int64)
    np.add.at(counts, (table.chip_a, table.kind, table.place_a), 1)
    chips = table.chip_b != GROUND
    np.add.at(counts, (table.chip_b[chips], table.kind[chips], table.place_b[chips]), 1)
    return counts
