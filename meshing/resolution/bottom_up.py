"""The bottom-up route of contact resolution (tried when the global route leaves a pair
short).

Chips are resolved one at a time (the chip that came to rest first is placed first and
then held): a chip with surface contacts is turned about its centre of mass by the
smallest rotation that lays its face on its largest partner's face and moved along that
face's normal; the motions left (in-plane translation and the turn about the normal, or
all six without a surface contact) are the smallest, in the mass-weighted sense
(translations in mm, rotations weighted by the chip's radius of gyration), that clear the
chip from every chip placed before it (:mod:`.clearance`). A further surface contact whose
partner's face lies exactly in the same plane is snapped with it; one that does not is
cleared like any other pair and counted. A chip wedged between chips placed before it is
moved together with them.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np
from scipy.spatial.transform import Rotation

from chipstack.core.arrangement import Arrangement
from chipstack.geometry.contacts import GROUND, ContactTable, candidate_pairs
from chipstack.meshing.resolution.clearance import Mover, clear_group, motion_basis
from chipstack.meshing.resolution.result import Resolution, unresolved_error
from chipstack.meshing.resolution.rigid import (
    SLACK_MM,
    Rule,
    convex_pieces,
    pair_rules,
    place_chip,
    separation_between,
)
from chipstack.meshing.resolution.snapping import (
    has_face_in,
    partner_plane,
    snap,
    surface_partners,
    verify_rules,
)

__all__ = ["resolve_bottom_up"]

# How much further a chip may go into a chip not placed yet. Measured on the reference
# stack, seeds 0 to 5: with 0.1 mm seed 4 resolves and seed 0 does not; with none, the
# other way round.
_LATER_GIVE_MM = SLACK_MM
_REPAIR_ROUNDS = 6  # rounds of moving the chips left short again, at the end


def resolve_bottom_up(
    arrangement: Arrangement,
    contacts: ContactTable,
    gap_mm: float,
    snap_angle_deg: float,
    contact_gap_mm: float,
    touching_lines: bool,
) -> Resolution:
    """The bottom-up route (see the module docstring); raises
    :class:`~.result.UnresolvedError` naming the chips it cannot clear."""
    return _BottomUp(
        arrangement, contacts, gap_mm, snap_angle_deg, contact_gap_mm, touching_lines
    ).run()


class _BottomUp:
    """The route's state: every chip's pose so far, the chips placed (their placed solids),
    the chips each one touches in a shared plane and the planes it must keep."""

    def __init__(
        self, arrangement, contacts, gap_mm, snap_angle_deg, contact_gap_mm, touching_lines
    ):
        self.start = time.perf_counter()
        self.arrangement, self.contacts, self.gap_mm = arrangement, contacts, gap_mm
        self.snap_angle_deg = snap_angle_deg
        n = arrangement.n_chips
        self.pieces = [convex_pieces(s) for s in arrangement.shapes]
        self.rotations = np.array(arrangement.rotations, dtype=float).reshape(n, 3, 3)
        self.positions = np.array(arrangement.positions, dtype=float).reshape(n, 3)
        self.order = arrangement.bottom_up_order()
        rank = arrangement.bottom_up_rank()
        self.surface = surface_partners(contacts, rank)
        reach = gap_mm + 1.0  # neighbours: bounding boxes within this (motions stay far below)
        self.neighbours: dict[int, list[int]] = {k: [] for k in range(n)}  # placed before it
        self.near: dict[int, set[int]] = {k: set() for k in range(n)}  # every neighbour
        for a, b in candidate_pairs(arrangement.bounds, reach):
            a, b = int(a), int(b)
            self.near[a].add(b)
            self.near[b].add(a)
            if rank[a] < rank[b]:
                self.neighbours[b].append(a)
            else:
                self.neighbours[a].append(b)
        self.placed: list = [None] * n
        self.touching: dict[int, set[int]] = {k: set() for k in range(n)}  # exactly, in a plane
        self.planes: dict[int, list[np.ndarray]] = {k: [] for k in range(n)}  # planes to keep
        self.snapped = {"chip": 0, "conveyor": 0}
        self.surface_cleared: list[tuple[int, int]] = []
        self.cleared = 0
        self.clusters = 0
        self.cos_snap = np.cos(np.radians(snap_angle_deg))
        self.rule = pair_rules(contacts, gap_mm, contact_gap_mm, touching_lines)

    def run(self) -> Resolution:
        for chip in self.order:
            self._place(int(chip))
        # A chip left short (or pushed short by a chip placed after it) is moved again with
        # the chips it is too close to, everything else around it held, until none is left.
        unresolved = self._verify()
        for _ in range(_REPAIR_ROUNDS):
            if not unresolved:
                break
            for chip, _ in unresolved:
                self._move_again(chip)
                self.clusters += 1
            unresolved = self._verify()
        if unresolved:
            raise unresolved_error(unresolved, self.gap_mm)
        return self._resolution()

    def _body(self, chip: int):
        return self.pieces[self.arrangement.shape_index[chip]]

    def _verify(self) -> list[tuple[int, float]]:
        return verify_rules(self.order, self.near, self.placed, self.touching, self.rule)

    def _place(self, chip: int) -> None:
        """One chip against the chips placed before it, then, when it is wedged between
        them, moved together with them."""
        rule = self.rule
        body = self._body(chip)
        # Chips not placed yet stay where they are for now: the chip may not sweep much
        # further into them than it already is (they would have to move as far).
        later = []
        for k in sorted(self.near[chip]):
            if self.placed[k] is None:
                world = place_chip(self._body(k), self.rotations[k], self.positions[k])
                now = separation_between(
                    place_chip(body, self.rotations[chip], self.positions[chip]), world
                )
                later.append((world, Rule(min(now, rule(chip, k).lower) - _LATER_GIVE_MM)))
        rotation, position, plane, partners, closes, worst = self._resolve_chip(chip, later)
        for partner, _ in self.surface[chip]:
            if partner in partners:
                self.snapped["conveyor" if partner == GROUND else "chip"] += 1
            else:
                self.surface_cleared.append((chip, partner))
        if plane is not None:
            self.planes[chip].append(plane[0])
            for k in partners:
                self.touching[chip].add(k)
                if k != GROUND:
                    self.touching[k].add(chip)
                    self.planes[k].append(plane[0])
        self.cleared += closes
        self.rotations[chip], self.positions[chip] = rotation, position
        self.placed[chip] = place_chip(body, rotation, position)
        if worst < 0:
            self._free_wedged(chip, plane, partners)

    def _free_wedged(self, chip: int, plane, partners) -> None:
        """A chip wedged between chips placed before it: moved together with them (the
        group grown by the chips too close to it, four times at most); when even that
        fails with the chip snapped onto a plane, the snap is undone and tried again."""
        worst = -np.inf
        group, size = [chip], 1
        for _ in range(4):
            group += [
                k
                for u in group
                for k in self.near[u]
                if self.placed[k] is not None
                and k not in group
                and k not in self.touching[u]
                and separation_between(self.placed[u], self.placed[k]) < self.rule(u, k).lower
            ]
            group = list(dict.fromkeys(group))
            if len(group) == size:
                break  # nothing more to move with it
            size = len(group)
            worst = self._solve_cluster(group)
            if worst >= 0:
                break
        if worst < 0 and plane is not None:
            # The snap itself wedges it: let the chip off its plane, clear the contact by
            # the gap instead, and move the cluster again.
            for k in partners:
                self.touching[chip].discard(k)
                if k != GROUND:
                    self.touching[k].discard(chip)
                    self.planes[k] = [v for v in self.planes[k] if v is not plane[0]]
                if any(k == p for p, _ in self.surface[chip]):
                    self.snapped["conveyor" if k == GROUND else "chip"] -= 1
                    self.surface_cleared.append((chip, k))
            self.planes[chip] = [v for v in self.planes[chip] if v is not plane[0]]
            self._solve_cluster(group)
        self.clusters += 1

    def _move_again(self, chip: int) -> None:
        """A chip left short, moved again with the chips it is too close to; when they
        have moved too far to come back in small steps, the free chips of the group start
        again from where the physics left them (a few hundredths of a millimetre into
        their neighbours), and are put back when that fails too."""
        group = [chip] + [
            k
            for k in sorted(self.near[chip])
            if k not in self.touching[chip]
            and separation_between(self.placed[chip], self.placed[k]) < self.rule(chip, k).lower
        ]
        if self._solve_cluster(group) >= 0:
            return
        saved = {
            k: (self.rotations[k].copy(), self.positions[k].copy(), self.placed[k]) for k in group
        }
        for k in group:
            if not self.touching[k]:
                self.rotations[k] = self.arrangement.rotations[k]
                self.positions[k] = self.arrangement.positions[k]
                self.placed[k] = place_chip(self._body(k), self.rotations[k], self.positions[k])
        if self._solve_cluster(group) < 0:
            for k, (r, p, w) in saved.items():
                self.rotations[k], self.positions[k], self.placed[k] = r, p, w

    def _solve_cluster(self, group) -> float:
        """Move the chips of ``group`` together (each keeping the planes it lies in) so
        that each clears everything placed around it and the others; updates the poses in
        place when that succeeds. Returns the worst separation reached (mm)."""
        arrangement, near, touching, rule = self.arrangement, self.near, self.touching, self.rule
        index = {chip: u for u, chip in enumerate(group)}
        movers = []
        for chip in group:
            shape = arrangement.shapes[arrangement.shape_index[chip]]
            fixed = [
                (self.placed[k], rule(chip, k))
                for k in sorted(near[chip])
                if self.placed[k] is not None and k not in index and k not in touching[chip]
            ]
            movers.append(
                Mover(
                    self._body(chip),
                    shape.inertia_mm2,
                    self.rotations[chip],
                    self.positions[chip],
                    motion_basis(self.planes[chip]),
                    fixed,
                    None if GROUND in touching[chip] else rule(chip, GROUND),
                )
            )
        pairs = [
            (index[a], index[b], rule(a, b))
            for a in group
            for b in group
            if index[a] < index[b] and b in near[a] and b not in touching[a]
        ]
        poses, _, worst = clear_group(movers, pairs)
        if worst >= 0:
            for chip, (rotation, position) in zip(group, poses, strict=True):
                self.rotations[chip], self.positions[chip] = rotation, position
                self.placed[chip] = place_chip(self._body(chip), rotation, position)
        return worst

    def _resolve_chip(self, chip: int, later):
        """One chip placed against the chips placed before it: snapped onto its largest
        surface contact when that can be cleared from the rest, else onto the next, else
        not snapped at all (its surface contacts cleared like any pair).

        Returns rotation, position, the snapped plane (or None), the partners lying
        exactly in it, how many pairs broke their rule, and the worst margin left (mm)."""
        body, surface, rule = self._body(chip), self.surface[chip], self.rule
        inertia = self.arrangement.shapes[self.arrangement.shape_index[chip]].inertia_mm2
        rotation, position = self.rotations[chip], self.positions[chip]
        best = None
        attempts = [
            (first, keep) for keep in (True, False) for first in [*range(len(surface)), None]
        ]
        for first, keep_later in attempts:
            r, p, plane, partners = rotation, position, None, []
            if first is not None:
                partner = surface[first][0]
                target = partner_plane(partner, self.placed, self.arrangement, self.contacts, chip)
                snapped = None if target is None else snap(body, r, p, target, self.cos_snap)
                if snapped is None:
                    continue
                r, p = snapped
                plane, partners = target, [partner]
                # Every neighbour with a face exactly in the plane (a further surface
                # contact on the same plane, or a chip beside the partner) touches the chip
                # there.
                for k in self.neighbours[chip]:
                    if k != partner and has_face_in(self.placed[k], plane):
                        partners.append(k)
            mover = Mover(
                body,
                inertia,
                r,
                p,
                motion_basis([] if plane is None else [plane[0]]),
                [
                    (self.placed[k], rule(chip, k))
                    for k in self.neighbours[chip]
                    if k not in partners
                ]
                + (later if keep_later else []),
                None if GROUND in partners else rule(chip, GROUND),
            )
            ((r_clear, p_clear),), closes, worst = clear_group([mover], [])
            if worst < 0:
                # Not cleared alone: keep the snapped pose, for the cluster to start from.
                r_clear, p_clear = r, p
            if best is None or worst > best[5]:
                best = (r_clear, p_clear, plane, partners, closes, worst)
            if worst >= 0:
                break
        return best

    def _resolution(self) -> Resolution:
        arrangement = self.arrangement
        resolved = dataclasses.replace(
            arrangement,
            positions=self.positions,
            quaternions=Rotation.from_matrix(self.rotations).as_quat(),
        )
        moved = np.linalg.norm(self.positions - arrangement.positions, axis=1)
        turned = (
            Rotation.from_matrix(self.rotations) * Rotation.from_quat(arrangement.quaternions).inv()
        ).magnitude()
        return Resolution(
            arrangement=resolved,
            translation_mm=moved,
            rotation_deg=np.degrees(turned),
            snapped=self.snapped,
            surface_cleared=tuple(self.surface_cleared),
            cleared=self.cleared,
            gap_mm=self.gap_mm,
            snap_angle_deg=self.snap_angle_deg,
            seconds=time.perf_counter() - self.start,
            info={
                "coplanar_touching": sum(len(t) for t in self.touching.values()) // 2
                - self.snapped["chip"],
                "clusters_solved": self.clusters,
                "route": "bottom-up",
            },
        )
