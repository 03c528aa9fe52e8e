"""The global route of the contact resolution: the relaxation (:func:`relax`) finished by an
exact snap of every kept surface contact, bottom-up."""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
from scipy.spatial.transform import Rotation

from chipstack.geometry.contacts import GROUND, candidate_pairs
from chipstack.meshing.resolution.relax import relax
from chipstack.meshing.resolution.result import Resolution
from chipstack.meshing.resolution.rigid import (
    SLACK_MM,
    SURFACE,
    convex_pieces,
    pair_rules,
    place_chip,
    separation_between,
)
from chipstack.meshing.resolution.snapping import TOUCHING_TOL_MM, snap, verify_rules

log = logging.getLogger(__name__)


def resolve_globally(
    arrangement, contacts, gap_mm, snap_angle_deg, contact_gap_mm, touching_lines=False
):
    """The global route (:func:`relax`) finished by an exact snap of every kept
    surface contact, bottom-up; None when it leaves any pair short of its rule."""
    out = relax(arrangement, contacts, gap_mm, snap_angle_deg, contact_gap_mm, touching_lines)
    # The relaxation's bounds carry the slack above the gap: a pair short of them by less
    # than the slack is still clear, and the check below is against the gap itself (half
    # the slack turned mixed-shapes, seed 0, over to the bottom-up route, which took more
    # than 25 minutes and failed, for a pair 0.1 um short of the slack and clear).
    if out is None or out.worst < -SLACK_MM:
        return None
    rotations, positions, start_rot, start_pos, surface, let_go, _ = out
    n = arrangement.n_chips
    pieces = [convex_pieces(s) for s in arrangement.shapes]
    rank = arrangement.bottom_up_rank()
    order = arrangement.bottom_up_order()
    rule = pair_rules(contacts, gap_mm, contact_gap_mm, touching_lines)
    cos_snap = np.cos(np.radians(snap_angle_deg))
    kept = [pair for pair in surface if pair not in let_go]
    partners: dict[int, list[int]] = {k: [] for k in range(n)}
    touching: dict[int, set[int]] = {k: set() for k in range(n)}
    for chip, partner in kept:
        partners[chip].append(partner)
        touching[chip].add(partner)
        if partner != GROUND:
            touching[partner].add(chip)
    placed = [
        place_chip(pieces[arrangement.shape_index[k]], rotations[k], positions[k]) for k in range(n)
    ]
    for chip in order:
        chip = int(chip)
        if not partners[chip]:
            continue
        # The first partner's face exactly: the relaxation leaves it nanometres off.
        partner = min(partners[chip], key=lambda k: -1 if k == GROUND else rank[k])
        faces = surface[(chip, partner)]
        if partner == GROUND:
            plane = (np.array([0.0, 0.0, 1.0]), 0.0, positions[chip] * [1, 1, 0])
        else:
            piece, face = faces[1]
            world = placed[partner]
            plane = (world.normals[piece][face], float(world.offsets[piece][face]), positions[chip])
        snapped = snap(
            pieces[arrangement.shape_index[chip]], rotations[chip], positions[chip], plane, cos_snap
        )
        if snapped is None:
            return None
        rotations[chip], positions[chip] = snapped
        placed[chip] = place_chip(pieces[arrangement.shape_index[chip]], *snapped)
    near: dict[int, set[int]] = {k: set() for k in range(n)}
    for a, b in candidate_pairs(arrangement.bounds, gap_mm + 1.0):
        near[int(a)].add(int(b))
        near[int(b)].add(int(a))
    unresolved = verify_rules(order, near, placed, touching, rule, touching_tol=TOUCHING_TOL_MM)
    if unresolved:
        log.info("contact resolution, global route: %d chips short", len(unresolved))
        return None
    start_worlds = [
        place_chip(pieces[arrangement.shape_index[k]], start_rot[k], start_pos[k]) for k in range(n)
    ]
    cleared = sum(
        1
        for a in range(n)
        for b in near[a]
        if a < b and separation_between(start_worlds[a], start_worlds[b]) < rule(a, b).lower
    )
    resolved = dataclasses.replace(
        arrangement, positions=positions, quaternions=Rotation.from_matrix(rotations).as_quat()
    )
    turned = (Rotation.from_matrix(rotations) * Rotation.from_matrix(start_rot).inv()).magnitude()
    surface_pairs = [
        (int(a), int(b))
        for a, b, k in zip(contacts.chip_a, contacts.chip_b, contacts.kind, strict=True)
        if k == SURFACE
    ]
    kept_sets = {frozenset(p) for p in kept}
    return Resolution(
        arrangement=resolved,
        translation_mm=np.linalg.norm(positions - start_pos, axis=1),
        rotation_deg=np.degrees(turned),
        snapped={
            "chip": sum(1 for _, p in kept if p != GROUND),
            "conveyor": sum(1 for _, p in kept if p == GROUND),
        },
        surface_cleared=tuple(p for p in surface_pairs if frozenset(p) not in kept_sets),
        cleared=cleared,
        gap_mm=gap_mm,
        snap_angle_deg=snap_angle_deg,
        info={"route": "global"},
    )
