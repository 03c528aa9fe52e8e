"""A conformal mesh's crop: its sides moved clear of the chips' corners and of faces nearly
parallel to them, and the chips a side cuts split along it into convex pieces."""

from __future__ import annotations

import logging

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import ConvexHull

from chipstack.core.arrangement import Arrangement
from chipstack.core.errors import InputError
from chipstack.meshing.boundaries import ON_PLANE_MM
from chipstack.meshing.kinds import CROP_SHIFT_MM

log = logging.getLogger(__name__)


_SHALLOW_DEG = 15.0  # a face closer than this to parallel with a crop side is not crossed


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
        kept = np.array([np.any(sign * (p[:, axis] - plane) < -ON_PLANE_MM) for p in pieces])
        if kept.sum() < 2:
            continue
        links = [
            (a, b)
            for a, b, along in joins
            if kept[a] and kept[b] and np.any(sign * (along - plane) < -ON_PLANE_MM)
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
        on = distance < ON_PLANE_MM
        distance[on & (on.sum(axis=1, keepdims=True) >= 3)] = np.inf
        score = np.minimum(score, distance.min(axis=1))
    # Tiers: a plane through a face at a shallow angle is worse than any that is not, a
    # plane cutting a chip in two (kept as two pieces, a loose bit of chip) worse still;
    # within a tier the clearance of the corners decides.
    tier = wanted + 1.0
    through = np.zeros(len(planes), dtype=bool)
    for low, high in shallow:
        through |= (planes > low + ON_PLANE_MM) & (planes < high - ON_PLANE_MM)
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
