"""Faces laid exactly on their partners' planes, and the final check of every pair's
rule (shared by the bottom-up and the global route)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from chipstack.geometry.contacts import GROUND, ContactTable
from chipstack.meshing.resolution.rigid import MAX_MOVE_MM, SURFACE, separation_between

__all__ = [
    "PLANE_TOL_MM",
    "TOUCHING_TOL_MM",
    "has_face_in",
    "partner_plane",
    "snap",
    "surface_partners",
    "verify_rules",
]

PLANE_TOL_MM = 1e-9  # two snapped faces closer than this share their plane
TOUCHING_TOL_MM = 1e-8  # chips in a shared plane may overlap this much (OCC merges 1e-7)


def snap(body, rotation, position, plane, cos_snap):
    """The chip turned about its centre of mass by the smallest rotation that lays its
    face facing ``plane`` on it, and moved along the plane's normal onto it; None when no
    face is within the snap angle."""
    normal, offset, centre = plane
    best = None
    for piece in body:
        normals = piece.normals @ rotation.T
        facing = -(normals @ normal)
        for k in np.flatnonzero(facing >= cos_snap):
            face_offset = piece.offsets[k] + normals[k] @ position
            distance = abs(normals[k] @ centre - face_offset)
            if best is None or distance < best[0]:
                best = (distance, piece, k)
    if best is None:
        return None
    _, piece, k = best
    current = rotation @ piece.normals[k]
    axis = np.cross(current, -normal)
    sine = np.linalg.norm(axis)
    angle = np.arctan2(sine, float(current @ -normal))
    turn = np.eye(3) if sine < 1e-15 else Rotation.from_rotvec(axis / sine * angle).as_matrix()
    rotation = turn @ rotation
    # The face exactly on the plane: rotation @ local normal = -normal, so the face's
    # world offset is local offset + (-normal) . position; it must equal -offset.
    face_normal = rotation @ piece.normals[k]
    rotation = _exact_normal(rotation, piece.normals[k], -normal, face_normal)
    along = -offset - (piece.offsets[k] - normal @ position)
    if abs(along) > MAX_MOVE_MM / 2:
        return None  # not the face it rests on: snapping would carry it through a chip
    position = position - along * normal
    return rotation, position


def _exact_normal(rotation, local, target, current):
    """Remove the rounding left in ``rotation @ local == target`` (a second tiny turn)."""
    axis = np.cross(current, target)
    sine = np.linalg.norm(axis)
    if sine < 1e-18:
        return rotation
    return Rotation.from_rotvec(axis / sine * np.arcsin(min(sine, 1.0))).as_matrix() @ rotation


def has_face_in(world, plane) -> bool:
    """Whether a placed chip has a face lying exactly in ``plane`` (facing the same way:
    the chip lies below the plane, on the partner's side)."""
    normal, offset = plane[0], plane[1]
    for normals, offsets in zip(world.normals, world.offsets, strict=True):
        same = (np.abs(normals - normal).max(axis=1) < 1e-12) & (
            np.abs(offsets - offset) < PLANE_TOL_MM
        )
        if same.any():
            return True
    return False


def partner_plane(partner, placed, arrangement, contacts, chip):
    """The face the chip lies on: (outward unit normal, offset, centre of the patch) of the
    partner's face nearest the contact patch (the conveyor: z = 0, normal up)."""
    rows = np.flatnonzero(
        ((contacts.chip_a == chip) & (contacts.chip_b == partner))
        | ((contacts.chip_a == partner) & (contacts.chip_b == chip))
    )
    centre = contacts.centre_mm[rows[0]]
    if partner == GROUND:
        return np.array([0.0, 0.0, 1.0]), 0.0, centre
    world = placed[partner]
    best = None
    chip_centre = arrangement.positions[chip]
    for normals, offsets in zip(world.normals, world.offsets, strict=True):
        distance = np.abs(normals @ centre - offsets)
        # Only a face the chip lies outside of: a tilted partner that came to rest first
        # can lie over the chip, and its top face is then not the one the chip touches.
        distance[normals @ (chip_centre - centre) <= 0] = np.inf
        k = int(np.argmin(distance))
        if best is None or distance[k] < best[0]:
            best = (float(distance[k]), normals[k], float(offsets[k]))
    if best is None or not np.isfinite(best[0]):
        return None
    return best[1], best[2], centre


def surface_partners(
    contacts: ContactTable, rank: np.ndarray
) -> dict[int, list[tuple[int, float]]]:
    """For every chip, its surface-contact partners placed before it (the conveyor
    included), largest contact first."""
    out: dict[int, list[tuple[int, float]]] = {k: [] for k in range(contacts.n_chips)}
    for a, b, kind, area in zip(
        contacts.chip_a, contacts.chip_b, contacts.kind, contacts.area_mm2, strict=True
    ):
        if kind != SURFACE:
            continue
        a, b = int(a), int(b)
        if b == GROUND:
            out[a].append((GROUND, float(area)))
        elif rank[a] < rank[b]:
            out[b].append((a, float(area)))
        else:
            out[a].append((b, float(area)))
    for partners in out.values():
        partners.sort(key=lambda p: -p[1])
    return out


def verify_rules(order, near, placed, touching, rule, touching_tol=1e-9) -> list[tuple[int, float]]:
    """(chip, worst margin) of every chip that breaks a lower bound of its rules in the end
    (a pair in a shared plane: that it does not interpenetrate)."""
    out = []
    for chip in order:
        chip = int(chip)
        worst = np.inf
        for k in near[chip]:
            separation = separation_between(placed[chip], placed[k])
            lower = -touching_tol if k in touching[chip] else rule(chip, k).lower
            worst = min(worst, separation - lower)
        lowest = min(float(v[:, 2].min()) for v in placed[chip].vertices)
        lower = -touching_tol if GROUND in touching[chip] else rule(chip, GROUND).lower
        worst = min(worst, lowest - lower)
        if worst < 0:
            out.append((chip, worst))
    return out
