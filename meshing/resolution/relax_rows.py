"""The rows of the relaxation's programme: each pair's, the floor's and each surface
contact's linearised constraints (bounds, planes, flush edges, corners) and how far
the current poses fall short of them."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from chipstack.geometry.contacts import GROUND
from chipstack.meshing.resolution.relax_settings import (
    _ALIGN_DEG,
    _FLUSH_MM,
    _LOWER_PENALTY,
    _SOFT_PENALTY,
    _SURFACE_PENALTY,
    _TOUCHING_PENALTY,
)
from chipstack.meshing.resolution.rigid import (
    CORNER_REACH_MM,
    REACH_MM,
    SLACK_MM,
    separating_axis,
)

log = logging.getLogger(__name__)


@dataclass
class _Row:
    """One linearised constraint: value = n . (x_b - x_a) of a point x_a on chip ``a``
    (-1: the conveyor) and x_b on chip ``b``; sense +1: value >= target, -1: <=, 0: ==;
    ``group``: the surface contact it belongs to (None: not a surface equality)."""

    a: int
    b: int
    normal: np.ndarray
    x_a: np.ndarray
    x_b: np.ndarray
    value: float
    sense: int
    target: float
    penalty: float
    group: object = None
    turn: bool = False  # a turn about ``normal``: d value = (w_b - w_a) . normal
    key: object = None  # an alignment, flush edge or corner on an edge (can be let go)


def _across_edge(point, s, t, normal):
    """The unit direction across edge s-t in the plane of ``normal``, and the foot of
    ``point`` on the edge's line."""
    edge = (t - s) / np.linalg.norm(t - s)
    return np.cross(normal, edge), s + edge * ((point - s) @ edge)


def _unmet(rows) -> tuple[float, float]:
    """(mm) the worst lower bound short of its target and the surface corner furthest out
    of its plane: what the result is judged by."""
    worst, off, _ = _shortfalls(rows)
    return max(0.0, -worst), off


def _shortfalls(rows) -> tuple[float, float, float]:
    """The worst lower bound's margin (mm; negative: short), the furthest surface contact
    out of its plane (mm) and the largest edge rule's violation."""
    worst = min(
        (row.value - row.target for row in rows if row.penalty == _LOWER_PENALTY),
        default=np.inf,
    )
    off_plane = max((abs(row.value) for row in rows if row.group is not None), default=0.0)
    turned = max((_violation(row) for row in rows if row.key is not None), default=0.0)
    return worst, off_plane, turned


def _stuck_groups(rows) -> set:
    """The surface contacts out of their plane by more than 10 um and by more than a tenth
    of the worst one: the ones that hold the rest up, not those still on their way."""
    off = {}
    for row in rows:
        if row.group is not None:
            off[row.group] = max(off.get(row.group, 0.0), abs(row.value))
    worst = max(off.values(), default=0.0)
    return {group for group, value in off.items() if value > max(1e-5, 0.1 * worst)}


def _misalignment(rotations, chip, partner, worlds, faces) -> float:
    """The angle (radians, in [-pi/4, pi/4)) by which the partner's edges are turned from
    the chip's about the partner's face normal, for two boxes (edges every 90 degrees)."""
    face_b = faces[1]
    normal = worlds[partner].normals[face_b[0]][face_b[1]]
    u_a = rotations[chip][:, 0] - (rotations[chip][:, 0] @ normal) * normal
    u_b = rotations[partner][:, 0] - (rotations[partner][:, 0] @ normal) * normal
    angle = np.arctan2(normal @ np.cross(u_a, u_b), u_a @ u_b)
    quarter = np.pi / 2
    return float((angle + quarter / 2) % quarter - quarter / 2)


def _violation(row) -> float:
    if row.sense > 0:
        return max(0.0, row.target - row.value)
    if row.sense < 0:
        return max(0.0, row.value - row.target)
    return abs(row.value - row.target)


def _facing_faces(worlds, chip, partner, contacts, positions, cos_snap):
    """((piece, face) of the chip, (piece, face) of the partner or None for the conveyor)
    that face each other in a surface contact, or None when no pair is within the snap
    angle."""

    rows = np.flatnonzero(
        ((contacts.chip_a == chip) & (contacts.chip_b == partner))
        | ((contacts.chip_a == partner) & (contacts.chip_b == chip))
    )
    centre = contacts.centre_mm[rows[0]]
    if partner == GROUND:
        target_normal, face_b = np.array([0.0, 0.0, 1.0]), None
    else:
        best = None
        other = worlds[partner]
        for p, (normals, offsets) in enumerate(zip(other.normals, other.offsets, strict=True)):
            distance = np.abs(normals @ centre - offsets)
            distance[normals @ (positions[chip] - centre) <= 0] = np.inf
            k = int(np.argmin(distance))
            if best is None or distance[k] < best[0]:
                best = (float(distance[k]), p, k)
        if best is None or not np.isfinite(best[0]):
            return None
        face_b = (best[1], best[2])
        target_normal = other.normals[best[1]][best[2]]
    best = None
    for p, (normals, offsets) in enumerate(
        zip(worlds[chip].normals, worlds[chip].offsets, strict=True)
    ):
        facing = -(normals @ target_normal)
        for k in np.flatnonzero(facing >= cos_snap):
            distance = abs(normals[k] @ centre - offsets[k])
            if best is None or distance < best[0]:
                best = (distance, p, int(k))
    if best is None:
        return None
    return (best[1], best[2]), face_b


def _near_flush(worlds, surface, align, known):
    """(pair, edge of the chip's face, edge of the partner's face) of every aligned
    surface pair whose edges run parallel within the flush distance alongside each other,
    not in ``known``."""
    out = []
    for pair in sorted(align):
        if pair not in surface:
            continue
        (pa, fa), (pb, fb) = surface[pair]
        edges_a = _face_edges(worlds[pair[0]], pa, fa)
        edges_b = _face_edges(worlds[pair[1]], pb, fb)
        normal = worlds[pair[1]].normals[pb][fb]
        for i, (p, q) in enumerate(edges_a):
            for j, (s, t) in enumerate(edges_b):
                value, overlap = _edge_offset(p, q, s, t, normal)
                if abs(value) < _FLUSH_MM and overlap > 0 and (pair, i, j) not in known:
                    out.append((pair, i, j))
    return out


def _near_corners(worlds, surface, align, known):
    """(pair, which face's corner, corner, edge, side) of every corner of a surface pair
    (not aligned) within the flush distance of the other face's edge, alongside it, and
    not in ``known`` (its first four entries)."""

    out = []
    for pair, ((pa, fa), face_b) in sorted(surface.items()):
        if pair[1] == GROUND or pair in align:
            continue
        pb, fb = face_b
        normal = worlds[pair[1]].normals[pb][fb]
        for first, (p1, f1), (p2, f2) in ((0, (pa, fa), (pb, fb)), (1, (pb, fb), (pa, fa))):
            corners = _face_edges(worlds[pair[first]], p1, f1)
            edges = _face_edges(worlds[pair[1 - first]], p2, f2)
            for i, (corner, _) in enumerate(corners):
                for j, (s, t) in enumerate(edges):
                    if (pair, first, i, j) in known:
                        continue
                    length = np.linalg.norm(t - s)
                    edge = (t - s) / length
                    along = (corner - s) @ edge
                    value = np.cross(normal, edge) @ (corner - s)
                    if abs(value) < _FLUSH_MM and 0 < along < length:
                        out.append((pair, first, i, j, 1.0 if value >= 0 else -1.0))
    return out


def _face_edges(world, piece, face):
    """The edges (corner, next corner) of a face, in order round its normal."""
    corners = _face_corners(world, piece, face)
    normal = world.normals[piece][face]
    centre = corners.mean(axis=0)
    e1 = corners[0] - centre
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    # Angles from the first corner in [0, 2 pi): the opposite corner of a rectangle sits
    # at pi, where arctan2 would flip between -pi and pi with the rounding.
    angles = np.arctan2((corners - centre) @ e2, (corners - centre) @ e1) % (2 * np.pi)
    angles[0] = 0.0
    order = np.argsort(angles)
    corners = corners[order]
    return [(corners[k], corners[(k + 1) % len(corners)]) for k in range(len(corners))]


def _edge_offset(p, q, s, t, normal):
    """How far (mm) edge p-q lies from the line of edge s-t across it, in the plane of
    ``normal``, and how long their common stretch is (mm; <= 0: none); inf when they are
    not nearly parallel."""
    edge = (t - s) / np.linalg.norm(t - s)
    along = q - p
    if abs(along @ edge) < np.cos(np.radians(_ALIGN_DEG)) * np.linalg.norm(along):
        return np.inf, 0.0
    across = np.cross(normal, edge)
    value = float(across @ ((p + q) / 2 - s))
    lo_a, hi_a = sorted(((p - s) @ edge, (q - s) @ edge))
    overlap = min(hi_a, float((t - s) @ edge)) - max(lo_a, 0.0)
    return value, overlap


def _face_corners(world, piece, face):
    v = world.vertices[piece]
    on = np.abs(v @ world.normals[piece][face] - world.offsets[piece][face]) < 1e-6
    return v[on]


def _surface_rows(worlds, chip, partner, face_a, face_b):
    """The chip's face corners in the partner's face plane (equalities)."""
    corners = _face_corners(worlds[chip], *face_a)
    if face_b is None:
        normal, offset, other = np.array([0.0, 0.0, 1.0]), 0.0, -1
    else:
        normal = worlds[partner].normals[face_b[0]][face_b[1]]
        offset = worlds[partner].offsets[face_b[0]][face_b[1]]
        other = partner
    out = []
    for x in corners:
        value = float(normal @ x - offset)
        out.append(
            _Row(
                other,
                chip,
                normal,
                x - value * normal,
                x,
                value,
                0,
                0.0,
                _SURFACE_PENALTY,
                (chip, partner),
            )
        )
    return out


def _floor_rows(world, chip, rule):
    up = np.array([0.0, 0.0, 1.0])
    out = []
    target = rule.lower + SLACK_MM
    lowest = None
    for v in world.vertices:
        for x in v:
            z = float(x[2])
            if lowest is None or z < lowest[0]:
                lowest = (z, x)
            if z < rule.lower + REACH_MM:
                out.append(_Row(-1, chip, up, x * [1, 1, 0], x, z, 1, target, _LOWER_PENALTY))
    if rule.upper < np.inf:
        z, x = lowest
        out.append(
            _Row(-1, chip, up, x * [1, 1, 0], x, z, -1, rule.upper - SLACK_MM, _SOFT_PENALTY)
        )
        if rule.parallel:
            edge = [x for v in world.vertices for x in v if x[2] <= z + CORNER_REACH_MM]
            if len(edge) >= 2:
                out += [
                    _Row(-1, chip, up, x * [1, 1, 0], x, float(x[2]), 0, target, _SOFT_PENALTY)
                    for x in edge[:3]
                ]
    return out


def _pair_rows(worlds, a, b, rule, chosen, piece_gaps):
    """Rows of a pair of chips along its separating axes (see :func:`.clearance._near_features`);
    ``piece_gaps``: the pair's entry of :func:`.rigid.batched_axis_gaps`."""
    wa, wb = worlds[a], worlds[b]
    candidates = []
    for pa_i, pb_i, gaps, sides in piece_gaps:
        k = int(np.argmax(gaps))
        kept = chosen.get((a, b, pa_i, pb_i))
        if kept is not None and gaps[kept[0]] >= gaps[k] - 0.003 and sides[kept[0]] == kept[1]:
            k = kept[0]
        chosen[(a, b, pa_i, pb_i)] = (k, bool(sides[k]))
        candidates.append((float(gaps[k]), pa_i, pb_i, k, bool(sides[k])))
    closest = min(candidates)
    out = []
    target = rule.lower + SLACK_MM
    for gap, pa_i, pb_i, k, ahead in candidates:
        nearest = (pa_i, pb_i) == closest[1:3]
        if gap >= rule.lower + REACH_MM and not (nearest and rule.upper < np.inf):
            continue
        axis = separating_axis(wa, wb, pa_i, pb_i, k)
        normal = axis if ahead else -axis  # from a towards b
        va, vb = wa.vertices[pa_i], wb.vertices[pb_i]
        sa, sb = va @ normal, vb @ normal
        top_a, bottom_b = sa.max(), sb.min()
        near_a = np.flatnonzero(sa >= top_a - CORNER_REACH_MM)
        near_b = np.flatnonzero(sb <= bottom_b + CORNER_REACH_MM)
        n_faces_a = len(wa.normals[pa_i])
        n_faces_b = len(wb.normals[pb_i])
        pairs = []
        if k < n_faces_a:  # a's face: its plane against b's corners
            for j in near_b:
                value = float(sb[j] - top_a)
                pairs.append((vb[j] - value * normal, vb[j], value))
        elif k < n_faces_a + n_faces_b:  # b's face against a's corners
            for i in near_a:
                value = float(bottom_b - sa[i])
                pairs.append((va[i], va[i] + value * normal, value))
        else:
            for i in near_a:
                for j in near_b:
                    pairs.append((va[i], vb[j], float(sb[j] - sa[i])))
        out += [
            _Row(a, b, normal, xa, xb, value, 1, target, _LOWER_PENALTY) for xa, xb, value in pairs
        ]
        if not nearest:
            continue
        first = min(pairs, key=lambda p: p[2])
        if rule.upper < np.inf:
            out.append(
                _Row(
                    a,
                    b,
                    normal,
                    first[0],
                    first[1],
                    first[2],
                    -1,
                    rule.upper - SLACK_MM,
                    _SOFT_PENALTY,
                )
            )
        if rule.parallel and len(pairs) >= 2:
            penalty = _TOUCHING_PENALTY if rule.touching else _SOFT_PENALTY
            for xa, xb, value in sorted(pairs, key=lambda p: p[2])[:3]:
                out.append(_Row(a, b, normal, xa, xb, value, 0, target, penalty))
    return out
