"""Contact resolution: the settled stack made ready for a conformal mesh.

The physics leaves chips a few hundredths of a millimetre into each other, and faces that
rest on each other a fraction of a degree apart. A conformal mesh cannot take either: an
interpenetration or a near-contact becomes a sliver of zero thickness. This operation moves
every chip by a small rigid motion (three translations, three rotations) so that

* surface contacts (the geometry stage's classification: two facing faces within the snap
  angle, touching over a real area) become exactly coplanar and touching, and a chip lying
  flat on the conveyor lies exactly on it;
* every other pair of chips, and every chip and the conveyor, is clear by at least
  ``gap_mm`` (measured by separating axes, a lower bound on the true distance, so the
  clearance holds for the exact solids);
* nothing interpenetrates and nothing goes below the conveyor.

Two routes. The global route (:mod:`geometry._relax`, tried first) moves every chip at
once, one sparse convex programme per step, and also turns two chips whose outlines cross
at a shallow angle in a shared plane until their edges are parallel; it is the one that
resolves the physics stacks. When it leaves a pair short, the bottom-up route below is
tried.

In the bottom-up route, chips are resolved one at a time (the chip that came to rest first is
placed first and then held): a chip with surface contacts is turned about its centre of
mass by the smallest rotation that lays its face on its largest partner's face and moved
along that face's normal; the motions left (in-plane translation and the turn about the
normal, or all six without a surface contact) are the smallest, in the mass-weighted
sense (translations in mm, rotations weighted by the chip's radius of gyration), that
clear the chip from every chip placed before it (sequential least squares, scipy's
SLSQP). A further surface contact whose partner's face lies exactly in the same plane is
snapped with it; one that does not is cleared like any other pair and counted.

The result is a new :class:`~core.arrangement.Arrangement` beside the settled one,
never in its place, with a report of the motions.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import minimize
from scipy.spatial.transform import Rotation

from chipstack.core.arrangement import Arrangement
from chipstack.core.errors import ChipstackError, InputError
from chipstack.geometry._rigid import (
    _CORNER_REACH_MM,
    _LINE,
    _MAX_MOVE_MM,
    _MAX_TURN_RAD,
    _REACH_MM,
    _SLACK_MM,
    _SURFACE,
    _TURN_WEIGHT,
    Rule,
    _axis,
    _axis_gaps,
    _pieces,
    _place,
    _rules,
    _separation,
    _World,
)
from chipstack.geometry.contacts import GROUND, ContactTable, candidate_pairs, find_contacts

__all__ = [
    "Resolution",
    "UnresolvedError",
    "resolve_contacts",
    "resolve_chips",
    "separation_mm",
]

log = logging.getLogger(__name__)

_PLANE_TOL_MM = 1e-9  # two snapped faces closer than this share their plane
_TOUCHING_TOL_MM = 1e-8  # chips in a shared plane may overlap this much (OCC merges 1e-7)
# How much further a chip may go into a chip not placed yet. Measured on the reference
# stack, seeds 0 to 5: with 0.1 mm seed 4 resolves and seed 0 does not; with none, the
# other way round.
_LATER_GIVE_MM = _SLACK_MM


class UnresolvedError(ChipstackError):
    """Some chips cannot be resolved by small motions (the message names them).

    unresolved: (chip, how far short of the gap, mm) of each."""

    def __init__(self, message: str, unresolved: tuple[tuple[int, float], ...] = ()) -> None:
        super().__init__(message)
        self.unresolved = unresolved


def _unresolved_error(unresolved, gap_mm: float) -> UnresolvedError:
    names = ", ".join(f"{c} ({-w:.3f} mm short)" for c, w in unresolved[:12])
    return UnresolvedError(
        f"contact resolution: {len(unresolved)} chips cannot be cleared by {gap_mm:g} mm "
        f"with small motions: chips {names}; use the voxel mesh (mesh.kind = 'voxel')",
        tuple(unresolved),
    )


def separation_mm(arrangement: Arrangement, i: int, j: int) -> float:
    """Separating-axis distance between chips ``i`` and ``j`` (mm; negative: they
    interpenetrate, by that depth)."""
    worlds = [
        _place(
            _pieces(arrangement.shapes[arrangement.shape_index[k]]),
            arrangement.rotations[k],
            arrangement.positions[k],
        )
        for k in (i, j)
    ]
    return _separation(*worlds)


@dataclass(frozen=True)
class Resolution:
    """A mesh-ready arrangement and what it took to make it.

    arrangement: the resolved chips (same shapes, order and batches as the settled ones).
    translation_mm: (n,) how far each centre of mass moved (mm).
    rotation_deg: (n,) the angle each chip turned (degrees).
    snapped: surface contacts made exactly coplanar and touching, by partner
        (``chip``, ``conveyor``).
    surface_cleared: surface contacts that could not share a plane with the chip's main
        contact (cleared by the gap instead): (chip, partner) pairs, partner -1: conveyor.
    cleared: pairs (conveyor included) that were closer than the gap and were moved to it.
    gap_mm, snap_angle_deg: the settings used.
    """

    arrangement: Arrangement
    translation_mm: np.ndarray
    rotation_deg: np.ndarray
    snapped: dict[str, int]
    surface_cleared: tuple[tuple[int, int], ...]
    cleared: int
    gap_mm: float
    snap_angle_deg: float
    seconds: float = 0.0
    info: dict = field(default_factory=dict)

    @property
    def max_translation_mm(self) -> float:
        return float(self.translation_mm.max(initial=0.0))

    @property
    def max_rotation_deg(self) -> float:
        return float(self.rotation_deg.max(initial=0.0))

    def summary(self) -> dict:
        """The figures a run reports (JSON-ready)."""
        return {
            "max_translation_mm": round(self.max_translation_mm, 5),
            "max_rotation_deg": round(self.max_rotation_deg, 4),
            "mean_translation_mm": round(float(self.translation_mm.mean()), 5),
            "snapped_chip_chip": self.snapped["chip"],
            "snapped_conveyor": self.snapped["conveyor"],
            "surface_contacts_cleared": len(self.surface_cleared),
            "pairs_cleared": self.cleared,
            "gap_mm": self.gap_mm,
            "snap_angle_deg": self.snap_angle_deg,
            "seconds": round(self.seconds, 3),
            **self.info,
        }


def check_settings(
    gap_mm: float, snap_angle_deg: float, thinnest_mm: float, gap_key: str = "mesh.gap_mm"
) -> None:
    """Refuse a gap or snap angle that cannot work (one line naming the key; ``gap_key``:
    the key the gap came from, ``mesh.pore_gap_mm`` with the pore space)."""
    if not (np.isfinite(gap_mm) and gap_mm > 0):
        raise InputError(f"{gap_key}: must be positive, got {gap_mm!r}")
    if gap_mm > thinnest_mm / 10:
        raise InputError(
            f"{gap_key}: {gap_mm:g} mm is above a tenth of the thinnest chip dimension "
            f"({thinnest_mm:g} mm): clearing every near-contact by it would move chips apart "
            "by more than the stack's own tolerance"
        )
    if not (np.isfinite(snap_angle_deg) and 0 <= snap_angle_deg <= 15):
        raise InputError(f"mesh.snap_angle_deg: must be between 0 and 15, got {snap_angle_deg!r}")


def resolve_chips(arrangement: Arrangement, chips, **settings) -> Resolution:
    """:func:`resolve_contacts` of ``chips`` alone (indices into ``arrangement``), as a
    resolution of the whole arrangement: the other chips keep their settled poses.

    For a crop: only the chips that reach into it are meshed, and resolving them alone
    is several times faster than the whole stack (their neighbours outside the crop are
    not meshed, so clearing them from those is of no use)."""
    chips = np.unique(np.asarray(chips, dtype=np.int64))
    part = dataclasses.replace(
        arrangement,
        shape_index=arrangement.shape_index[chips],
        positions=arrangement.positions[chips],
        quaternions=arrangement.quaternions[chips],
        batch=arrangement.batch[chips],
    )
    try:
        resolved = resolve_contacts(part, **settings)
    except UnresolvedError as exc:  # named by their indices in the whole arrangement
        if not exc.unresolved:
            raise
        named = [(int(chips[c]), w) for c, w in exc.unresolved]
        raise _unresolved_error(named, settings.get("gap_mm", 0.03)) from None
    positions = arrangement.positions.copy()
    quaternions = arrangement.quaternions.copy()
    positions[chips] = resolved.arrangement.positions
    quaternions[chips] = resolved.arrangement.quaternions
    translation = np.zeros(arrangement.n_chips)
    rotation = np.zeros(arrangement.n_chips)
    translation[chips] = resolved.translation_mm
    rotation[chips] = resolved.rotation_deg

    def whole(k: int) -> int:
        return int(chips[k]) if k >= 0 else k

    return dataclasses.replace(
        resolved,
        arrangement=dataclasses.replace(arrangement, positions=positions, quaternions=quaternions),
        translation_mm=translation,
        rotation_deg=rotation,
        surface_cleared=tuple((whole(a), whole(b)) for a, b in resolved.surface_cleared),
        info={
            **resolved.info,
            "chips_resolved": len(chips),
            "mean_translation_mm": round(float(resolved.translation_mm.mean()), 5),
        },
    )


def resolve_contacts(
    arrangement: Arrangement,
    gap_mm: float = 0.03,
    snap_angle_deg: float = 3.0,
    contacts: ContactTable | None = None,
    contact_gap_mm: float = 0.05,
    contact_extent_mm: float = 5.0,
    touching_lines: bool = False,
) -> Resolution:
    """The mesh-ready arrangement (see the module docstring).

    gap_mm: the clearance (mm) left between chips that are not in surface contact.
    touching_lines: keep every line contact between two chips touching (its edge laid
        parallel on its partner, within 0.2 um) instead of clearing it by the gap, so
        that it stays a line contact: for a mesh of the chips alone, with no pore space
        to mesh between them.
    snap_angle_deg: facing faces of a surface contact further apart than this (degrees)
        are not snapped. contacts: the settled stack's contact table (computed with
        ``contact_gap_mm`` and ``contact_extent_mm`` when not given).
    Raises :class:`UnresolvedError` naming the chips that cannot be cleared.
    """
    start = time.perf_counter()
    check_settings(gap_mm, snap_angle_deg, arrangement.thinnest_mm)
    if contacts is None:
        contacts = find_contacts(arrangement, contact_gap_mm, contact_extent_mm)
    resolved = _resolve_globally(
        arrangement, contacts, gap_mm, snap_angle_deg, contact_gap_mm, touching_lines
    )
    if resolved is not None:
        info = {**resolved.info, **_lines_touching(resolved.arrangement, contacts)}
        return dataclasses.replace(resolved, seconds=time.perf_counter() - start, info=info)
    log.info("contact resolution: the global route did not clear every pair; bottom-up route")
    n = arrangement.n_chips
    pieces = [_pieces(s) for s in arrangement.shapes]
    rotations = np.array(arrangement.rotations, dtype=float).reshape(n, 3, 3)
    positions = np.array(arrangement.positions, dtype=float).reshape(n, 3)
    order = arrangement.bottom_up_order()
    rank = arrangement.bottom_up_rank()
    surface = _surface_partners(contacts, rank)
    bounds = arrangement.bounds
    reach = gap_mm + 1.0  # neighbours: bounding boxes within this (motions stay far below)
    neighbours: dict[int, list[int]] = {k: [] for k in range(n)}  # placed before it
    near: dict[int, set[int]] = {k: set() for k in range(n)}  # every neighbour
    for a, b in candidate_pairs(bounds, reach):
        a, b = int(a), int(b)
        near[a].add(b)
        near[b].add(a)
        if rank[a] < rank[b]:
            neighbours[b].append(a)
        else:
            neighbours[a].append(b)
    placed: list[_World | None] = [None] * n
    touching: dict[int, set[int]] = {k: set() for k in range(n)}  # exactly, in a plane
    planes: dict[int, list[np.ndarray]] = {k: [] for k in range(n)}  # planes to keep
    snapped = {"chip": 0, "conveyor": 0}
    surface_cleared: list[tuple[int, int]] = []
    cleared = 0
    clusters = 0
    cos_snap = np.cos(np.radians(snap_angle_deg))
    rule = _rules(contacts, gap_mm, contact_gap_mm, touching_lines)
    for chip in order:
        chip = int(chip)
        body = pieces[arrangement.shape_index[chip]]
        inertia = arrangement.shapes[arrangement.shape_index[chip]].inertia_mm2
        # Chips not placed yet stay where they are for now: the chip may not sweep much
        # further into them than it already is (they would have to move as far).
        later = []
        for k in sorted(near[chip]):
            if placed[k] is None:
                world = _place(pieces[arrangement.shape_index[k]], rotations[k], positions[k])
                now = _separation(_place(body, rotations[chip], positions[chip]), world)
                later.append((world, Rule(min(now, rule(chip, k).lower) - _LATER_GIVE_MM)))
        attempt = _resolve_chip(
            later,
            chip,
            body,
            inertia,
            rotations[chip],
            positions[chip],
            surface[chip],
            neighbours[chip],
            placed,
            arrangement,
            contacts,
            cos_snap,
            rule,
        )
        rotation, position, plane, partners, closes, worst = attempt
        for partner, _ in surface[chip]:
            if partner in partners:
                snapped["conveyor" if partner == GROUND else "chip"] += 1
            else:
                surface_cleared.append((chip, partner))
        if plane is not None:
            planes[chip].append(plane[0])
            for k in partners:
                touching[chip].add(k)
                if k != GROUND:
                    touching[k].add(chip)
                    planes[k].append(plane[0])
        cleared += closes
        rotations[chip], positions[chip] = rotation, position
        placed[chip] = _place(body, rotation, position)
        if worst < 0:
            # Wedged between chips placed before it: move it together with them.
            group, size = [chip], 1
            for _ in range(4):
                group += [
                    k
                    for u in group
                    for k in near[u]
                    if placed[k] is not None
                    and k not in group
                    and k not in touching[u]
                    and _separation(placed[u], placed[k]) < rule(u, k).lower
                ]
                group = list(dict.fromkeys(group))
                if len(group) == size:
                    break  # nothing more to move with it
                size = len(group)
                worst = _solve_cluster(
                    group,
                    pieces,
                    arrangement,
                    rotations,
                    positions,
                    placed,
                    near,
                    touching,
                    planes,
                    rule,
                )
                if worst >= 0:
                    break
            if worst < 0 and plane is not None:
                # The snap itself wedges it: let the chip off its plane, clear the
                # contact by the gap instead, and move the cluster again.
                for k in partners:
                    touching[chip].discard(k)
                    if k != GROUND:
                        touching[k].discard(chip)
                        planes[k] = [v for v in planes[k] if v is not plane[0]]
                    if any(k == p for p, _ in surface[chip]):
                        snapped["conveyor" if k == GROUND else "chip"] -= 1
                        surface_cleared.append((chip, k))
                planes[chip] = [v for v in planes[chip] if v is not plane[0]]
                worst = _solve_cluster(
                    group,
                    pieces,
                    arrangement,
                    rotations,
                    positions,
                    placed,
                    near,
                    touching,
                    planes,
                    rule,
                )
            clusters += 1
    # A chip left short (or pushed short by a chip placed after it) is moved again with
    # the chips it is too close to, everything else around it held, until none is left.
    unresolved = _verify(order, near, placed, touching, rule)
    for _ in range(6):
        if not unresolved:
            break
        for chip, _ in unresolved:
            group = [chip] + [
                k
                for k in sorted(near[chip])
                if k not in touching[chip]
                and _separation(placed[chip], placed[k]) < rule(chip, k).lower
            ]
            if (
                _solve_cluster(
                    group,
                    pieces,
                    arrangement,
                    rotations,
                    positions,
                    placed,
                    near,
                    touching,
                    planes,
                    rule,
                )
                < 0
            ):
                # Moved too far to come back in small steps: start the free chips of the
                # group from where the physics left them (a few hundredths of a
                # millimetre into their neighbours) and try once more.
                saved = {k: (rotations[k].copy(), positions[k].copy(), placed[k]) for k in group}
                for k in group:
                    if not touching[k]:
                        rotations[k] = arrangement.rotations[k]
                        positions[k] = arrangement.positions[k]
                        placed[k] = _place(
                            pieces[arrangement.shape_index[k]], rotations[k], positions[k]
                        )
                if (
                    _solve_cluster(
                        group,
                        pieces,
                        arrangement,
                        rotations,
                        positions,
                        placed,
                        near,
                        touching,
                        planes,
                        rule,
                    )
                    < 0
                ):
                    for k, (r, p, w) in saved.items():
                        rotations[k], positions[k], placed[k] = r, p, w
            clusters += 1
        unresolved = _verify(order, near, placed, touching, rule)
    if unresolved:
        raise _unresolved_error(unresolved, gap_mm)
    resolved = dataclasses.replace(
        arrangement, positions=positions, quaternions=Rotation.from_matrix(rotations).as_quat()
    )
    moved = np.linalg.norm(positions - arrangement.positions, axis=1)
    turned = (
        Rotation.from_matrix(rotations) * Rotation.from_quat(arrangement.quaternions).inv()
    ).magnitude()
    return Resolution(
        arrangement=resolved,
        translation_mm=moved,
        rotation_deg=np.degrees(turned),
        snapped=snapped,
        surface_cleared=tuple(surface_cleared),
        cleared=cleared,
        gap_mm=gap_mm,
        snap_angle_deg=snap_angle_deg,
        seconds=time.perf_counter() - start,
        info={
            "coplanar_touching": sum(len(t) for t in touching.values()) // 2 - snapped["chip"],
            "clusters_solved": clusters,
            "route": "bottom-up",
            **_lines_touching(resolved, contacts),
        },
    )


def _lines_touching(resolved: Arrangement, contacts: ContactTable) -> dict[str, int]:
    """How many of the settled stack's line contacts between chips end touching (within
    a micrometre), measured on the resolved arrangement."""
    pairs = [
        (int(a), int(b))
        for a, b, k in zip(contacts.chip_a, contacts.chip_b, contacts.kind, strict=True)
        if k == _LINE and b != GROUND
    ]
    touching = sum(1 for a, b in pairs if separation_mm(resolved, a, b) <= 1e-3)
    return {"line_contacts": len(pairs), "line_contacts_touching": touching}


def _resolve_globally(
    arrangement, contacts, gap_mm, snap_angle_deg, contact_gap_mm, touching_lines=False
):
    """The global route (:mod:`geometry._relax`) finished by an exact snap of every kept
    surface contact, bottom-up; None when it leaves any pair short of its rule."""
    from chipstack.geometry._relax import relax

    out = relax(arrangement, contacts, gap_mm, snap_angle_deg, contact_gap_mm, touching_lines)
    # The relaxation's bounds carry the slack above the gap: a pair short of them by less
    # than the slack is still clear, and the check below is against the gap itself (half
    # the slack turned mixed-shapes, seed 0, over to the bottom-up route, which took more
    # than 25 minutes and failed, for a pair 0.1 um short of the slack and clear).
    if out is None or out[-1] < -_SLACK_MM:
        return None
    rotations, positions, start_rot, start_pos, surface, let_go, _ = out
    n = arrangement.n_chips
    pieces = [_pieces(s) for s in arrangement.shapes]
    rank = arrangement.bottom_up_rank()
    order = arrangement.bottom_up_order()
    rule = _rules(contacts, gap_mm, contact_gap_mm, touching_lines)
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
        _place(pieces[arrangement.shape_index[k]], rotations[k], positions[k]) for k in range(n)
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
        snap = _snap(
            pieces[arrangement.shape_index[chip]], rotations[chip], positions[chip], plane, cos_snap
        )
        if snap is None:
            return None
        rotations[chip], positions[chip] = snap
        placed[chip] = _place(pieces[arrangement.shape_index[chip]], *snap)
    near: dict[int, set[int]] = {k: set() for k in range(n)}
    for a, b in candidate_pairs(arrangement.bounds, gap_mm + 1.0):
        near[int(a)].add(int(b))
        near[int(b)].add(int(a))
    unresolved = _verify(order, near, placed, touching, rule, touching_tol=_TOUCHING_TOL_MM)
    if unresolved:
        log.info("contact resolution, global route: %d chips short", len(unresolved))
        return None
    start_worlds = [
        _place(pieces[arrangement.shape_index[k]], start_rot[k], start_pos[k]) for k in range(n)
    ]
    cleared = sum(
        1
        for a in range(n)
        for b in near[a]
        if a < b and _separation(start_worlds[a], start_worlds[b]) < rule(a, b).lower
    )
    resolved = dataclasses.replace(
        arrangement, positions=positions, quaternions=Rotation.from_matrix(rotations).as_quat()
    )
    turned = (Rotation.from_matrix(rotations) * Rotation.from_matrix(start_rot).inv()).magnitude()
    surface_pairs = [
        (int(a), int(b))
        for a, b, k in zip(contacts.chip_a, contacts.chip_b, contacts.kind, strict=True)
        if k == _SURFACE
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


def _verify(order, near, placed, touching, rule, touching_tol=1e-9) -> list[tuple[int, float]]:
    """(chip, worst margin) of every chip that breaks a lower bound of its rules in the end
    (a pair in a shared plane: that it does not interpenetrate)."""
    out = []
    for chip in order:
        chip = int(chip)
        worst = np.inf
        for k in near[chip]:
            separation = _separation(placed[chip], placed[k])
            lower = -touching_tol if k in touching[chip] else rule(chip, k).lower
            worst = min(worst, separation - lower)
        lowest = min(float(v[:, 2].min()) for v in placed[chip].vertices)
        lower = -touching_tol if GROUND in touching[chip] else rule(chip, GROUND).lower
        worst = min(worst, lowest - lower)
        if worst < 0:
            out.append((chip, worst))
    return out


def _solve_cluster(
    group, pieces, arrangement, rotations, positions, placed, near, touching, planes, rule
) -> float:
    """Move the chips of ``group`` together (each keeping the planes it lies in) so that
    each clears everything placed around it and the others; updates the poses in place
    when that succeeds. Returns the worst separation reached (mm)."""
    index = {chip: u for u, chip in enumerate(group)}
    movers = []
    for chip in group:
        shape = arrangement.shapes[arrangement.shape_index[chip]]
        fixed = [
            (placed[k], rule(chip, k))
            for k in sorted(near[chip])
            if placed[k] is not None and k not in index and k not in touching[chip]
        ]
        movers.append(
            _Mover(
                pieces[arrangement.shape_index[chip]],
                shape.inertia_mm2,
                rotations[chip],
                positions[chip],
                _motion_basis(planes[chip]),
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
    poses, _, worst = _clear_group(movers, pairs)
    if worst >= 0:
        for chip, (rotation, position) in zip(group, poses, strict=True):
            rotations[chip], positions[chip] = rotation, position
            placed[chip] = _place(pieces[arrangement.shape_index[chip]], rotation, position)
    return worst


def _surface_partners(
    contacts: ContactTable, rank: np.ndarray
) -> dict[int, list[tuple[int, float]]]:
    """For every chip, its surface-contact partners placed before it (the conveyor
    included), largest contact first."""
    out: dict[int, list[tuple[int, float]]] = {k: [] for k in range(contacts.n_chips)}
    for a, b, kind, area in zip(
        contacts.chip_a, contacts.chip_b, contacts.kind, contacts.area_mm2, strict=True
    ):
        if kind != _SURFACE:
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


def _resolve_chip(
    later,
    chip,
    body,
    inertia,
    rotation,
    position,
    surface,
    neighbours,
    placed,
    arrangement,
    contacts,
    cos_snap,
    rule,
):
    """One chip placed against the chips placed before it: snapped onto its largest
    surface contact when that can be cleared from the rest, else onto the next, else not
    snapped at all (its surface contacts cleared like any pair).

    Returns rotation, position, the snapped plane (or None), the partners lying exactly
    in it, how many pairs broke their rule, and the worst margin left (mm)."""
    best = None
    attempts = [(first, keep) for keep in (True, False) for first in [*range(len(surface)), None]]
    for first, keep_later in attempts:
        r, p, plane, partners = rotation, position, None, []
        if first is not None:
            partner = surface[first][0]
            target = _partner_plane(partner, placed, arrangement, contacts, chip)
            snap = None if target is None else _snap(body, r, p, target, cos_snap)
            if snap is None:
                continue
            r, p = snap
            plane, partners = target, [partner]
            # Every neighbour with a face exactly in the plane (a further surface contact
            # on the same plane, or a chip beside the partner) touches the chip there.
            for k in neighbours:
                if k != partner and _has_face_in(placed[k], plane):
                    partners.append(k)
        mover = _Mover(
            body,
            inertia,
            r,
            p,
            _motion_basis([] if plane is None else [plane[0]]),
            [(placed[k], rule(chip, k)) for k in neighbours if k not in partners]
            + (later if keep_later else []),
            None if GROUND in partners else rule(chip, GROUND),
        )
        ((r_clear, p_clear),), closes, worst = _clear_group([mover], [])
        if worst < 0:
            # Not cleared alone: keep the snapped pose, for the cluster to start from.
            r_clear, p_clear = r, p
        if best is None or worst > best[5]:
            best = (r_clear, p_clear, plane, partners, closes, worst)
        if worst >= 0:
            break
    return best


def _has_face_in(world, plane) -> bool:
    """Whether a placed chip has a face lying exactly in ``plane`` (facing the same way:
    the chip lies below the plane, on the partner's side)."""
    normal, offset = plane[0], plane[1]
    for normals, offsets in zip(world.normals, world.offsets, strict=True):
        same = (np.abs(normals - normal).max(axis=1) < 1e-12) & (
            np.abs(offsets - offset) < _PLANE_TOL_MM
        )
        if same.any():
            return True
    return False


def _partner_plane(partner, placed, arrangement, contacts, chip):
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


def _same_plane(a, b) -> bool:
    return bool(np.abs(a[0] - b[0]).max() < 1e-12 and abs(a[1] - b[1]) < _PLANE_TOL_MM)


def _snap(body, rotation, position, plane, cos_snap):
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
    if abs(along) > _MAX_MOVE_MM / 2:
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


def _motion_basis(planes: list[np.ndarray]) -> np.ndarray:
    """(6, d) the rigid motions (translation, rotation vector about the centre of mass)
    that keep a plate's faces in every plane whose normal is given: no motion along a
    normal, no turn except about it."""
    rows = []
    for normal in planes:
        helper = np.eye(3)[int(np.argmin(np.abs(normal)))]
        e1 = np.cross(normal, helper)
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(normal, e1)
        rows += [np.r_[normal, 0, 0, 0], np.r_[0, 0, 0, e1], np.r_[0, 0, 0, e2]]
    if not rows:
        return np.eye(6)
    from scipy.linalg import null_space

    return null_space(np.array(rows), rcond=1e-9)


@dataclass
class _Mover:
    """A chip free to move in a clearance solve."""

    pieces: tuple
    inertia: np.ndarray
    rotation: np.ndarray
    position: np.ndarray
    basis: np.ndarray  # (6, d)
    fixed: list  # (placed neighbour's world, Rule) it must keep
    floor: Rule | None  # None: lies in the conveyor's plane

    def place(self, q: np.ndarray) -> _World:
        rotation, position = self.pose(q)
        return _place(self.pieces, rotation, position)

    def pose(self, q: np.ndarray):
        motion = self.basis @ q
        return Rotation.from_rotvec(motion[3:]).as_matrix() @ self.rotation, self.position + motion[
            :3
        ]


def _clear_group(movers: list[_Mover], pairs: list[tuple[int, int, Rule]]):
    """The smallest motions of a group of chips that keep each pair's :class:`Rule`:
    every chip against its placed neighbours and the conveyor, and the group's chips
    against each other (``pairs``: mover, mover, rule).

    Sequential quadratic programming: at each step every near pair is linearised along its
    separating axis (the axis that separates it best, held fixed while it stays nearly the
    best), every corner near the extreme a constraint of its own, and the smallest
    mass-weighted motion meeting them within a trust region is taken, halved when the
    linearisation overshot. The lower bounds are hard (a step never breaks them once they
    hold); the upper bounds and parallel edges are met where the motions allow.

    Returns every chip's (rotation, position), how many lower bounds did not hold at the
    start, and the worst margin left over them (mm; negative: not cleared)."""
    sizes = [m.basis.shape[1] for m in movers]
    cuts = np.cumsum([0, *sizes])
    metric = np.zeros((cuts[-1], cuts[-1]))
    step_limit, limits = [], []
    for m, lo, hi in zip(movers, cuts[:-1], cuts[1:], strict=True):
        weight = np.zeros((6, 6))
        weight[:3, :3] = np.eye(3)
        weight[3:, 3:] = _TURN_WEIGHT * m.rotation @ np.diag(m.inertia) @ m.rotation.T
        metric[lo:hi, lo:hi] = m.basis.T @ weight @ m.basis
        translational = np.abs(m.basis[:3]).sum(axis=0) > np.abs(m.basis[3:]).sum(axis=0)
        step_limit.append(np.where(translational, 0.1, 0.01))  # mm, rad per step
        limits.append(np.where(translational, _MAX_MOVE_MM, _MAX_TURN_RAD))
    step_limit, limits = np.concatenate(step_limit), np.concatenate(limits)
    spans = list(zip(cuts[:-1], cuts[1:], strict=True))

    def place(q):
        return [m.place(q[lo:hi]) for m, (lo, hi) in zip(movers, spans, strict=True)]

    def against(worlds):
        """Per mover, what it must keep its rule with: placed neighbours, then the
        group's chips."""
        out = [list(m.fixed) for m in movers]
        for u, v, rule in pairs:
            out[u].append((worlds[v], rule))
        return out

    def margins(worlds):
        values = []
        for m, world, others in zip(movers, worlds, against(worlds), strict=True):
            values += [_separation(world, other) - rule.lower for other, rule in others]
            if m.floor is not None:
                lowest = min(float(v[:, 2].min()) for v in world.vertices)
                values.append(lowest - m.floor.lower)
        return np.array(values)

    q = np.zeros(cuts[-1])
    worlds = place(q)
    start = margins(worlds)
    closes = int(np.count_nonzero(start < _SLACK_MM))
    if not closes and _soft_violation(worlds, against(worlds), movers) == 0:
        return (
            [m.pose(q[lo:hi]) for m, (lo, hi) in zip(movers, spans, strict=True)],
            0,
            float(start.min(initial=np.inf)),
        )
    best_q, best_worst, best_score = q, float(start.min(initial=np.inf)), np.inf
    chosen: dict = {}  # each pair's separating axis, kept while it stays nearly the best
    for _ in range(60):
        others = against(worlds)
        features = []
        for u, (m, world) in enumerate(zip(movers, worlds, strict=True)):
            features += [(u, f) for f in _near_features(world, others[u], m.floor, chosen, u)]
        values = _feature_values(worlds, others, features)
        gradient = np.zeros((len(features), len(q)))
        for k in range(len(q)):
            dq = np.zeros_like(q)
            dq[k] = 1e-6
            moved = place(q + dq)
            gradient[:, k] = (_feature_values(moved, against(moved), features) - values) / 1e-6
        sense = np.array([f[-2] for _, f in features], dtype=float)
        targets = np.array([f[-1] for _, f in features], dtype=float)
        delta = _qp_step(metric, q, gradient, values, sense, targets, step_limit, limits)
        if delta is None:
            break
        # A step is taken when it keeps the cleared group clear, or brings an uncleared
        # one closer to clear; otherwise it is halved (the linearisation overshot).
        current = float(margins(worlds).min(initial=np.inf))
        for _ in range(8):
            trial = place(q + delta)
            worst = float(margins(trial).min(initial=np.inf))
            if worst >= 0 or (current < 0 and worst > current + 1e-9):
                break
            delta = delta / 2
        else:
            break
        q, worlds = q + delta, trial
        score = _soft_violation(worlds, against(worlds), movers) + 1e-3 * float(q @ metric @ q)
        if worst >= 0 and (best_worst < 0 or score < best_score):
            best_q, best_worst, best_score = q, worst, score
        elif best_worst < 0 and worst > best_worst:
            best_q, best_worst, best_score = q, worst, score
        if np.abs(delta).max() < 1e-8:
            break
    if best_worst >= 0:
        # The path to a feasible pose can overshoot: the shortest stretch of the way back
        # that still clears everything is kept.
        for fraction in (0.0, 0.25, 0.5, 0.75):
            trial = margins(place(fraction * best_q))
            if trial.min(initial=np.inf) >= 0:
                best_q, best_worst = fraction * best_q, float(trial.min(initial=np.inf))
                break
    poses = [m.pose(best_q[lo:hi]) for m, (lo, hi) in zip(movers, spans, strict=True)]
    return poses, closes, best_worst


def _soft_violation(worlds, others, movers) -> float:
    """How far the upper bounds are exceeded, summed (mm)."""
    total = 0.0
    for m, world, pairs in zip(movers, worlds, others, strict=True):
        for other, rule in pairs:
            if rule.upper < np.inf:
                total += max(0.0, _separation(world, other) - rule.upper)
        if m.floor is not None and m.floor.upper < np.inf:
            lowest = min(float(v[:, 2].min()) for v in world.vertices)
            total += max(0.0, lowest - m.floor.upper)
    return total


def _near_features(world, others, floor, chosen, tag):
    """The constraints of one chip at this step, each a tuple ending in (sense, target):
    sense +1, the feature's gap must be at least the target; -1, at most; 0, equal.

    A pair's features: ("pair", neighbour, piece of the chip, piece of the neighbour, axis
    index, side, corner of the chip, corner of the neighbour). Every corner pair near the
    extreme along the pair's separating axis is a lower bound of its own (the gap along
    an axis is a minimum over corners, so no step trades one corner for another); the
    nearest corner pair carries the upper bound; a parallel rule holds the touching edge
    or face's corners at the lower bound. The conveyor's: ("floor", piece, corner).

    A pair keeps the axis ``chosen`` for it before while that axis separates it within
    a few micrometres of the best one: switching between two nearly equal axes at every
    step would make the steps undo each other."""
    features = []
    for n, (other, rule) in enumerate(others):
        candidates = []
        for a, (va, na, ea) in enumerate(
            zip(world.vertices, world.normals, world.edges, strict=True)
        ):
            for b, (vb, nb, eb) in enumerate(
                zip(other.vertices, other.normals, other.edges, strict=True)
            ):
                gaps, sides = _axis_gaps(va, na, ea, vb, nb, eb)
                k = int(np.argmax(gaps))
                kept = chosen.get((tag, n, a, b))
                if (
                    kept is not None
                    and gaps[kept[0]] >= gaps[k] - 0.003
                    and sides[kept[0]] == kept[1]
                ):
                    k = kept[0]
                chosen[(tag, n, a, b)] = (k, bool(sides[k]))
                candidates.append((float(gaps[k]), a, b, k, bool(sides[k])))
        closest = min(candidates)
        for gap, a, b, k, ahead in candidates:
            nearest = (a, b) == closest[1:3]
            if gap >= rule.lower + _REACH_MM and not (nearest and rule.upper < np.inf):
                continue
            axis = _axis(world, other, a, b, k)
            pa, pb = world.vertices[a] @ axis, other.vertices[b] @ axis
            if ahead:
                near_a = np.argsort(-pa)[: int(np.sum(pa >= pa.max() - _CORNER_REACH_MM))]
                near_b = np.argsort(pb)[: int(np.sum(pb <= pb.min() + _CORNER_REACH_MM))]
            else:
                near_a = np.argsort(pa)[: int(np.sum(pa <= pa.min() + _CORNER_REACH_MM))]
                near_b = np.argsort(-pb)[: int(np.sum(pb >= pb.max() - _CORNER_REACH_MM))]
            head = ("pair", n, a, b, k, ahead)
            features += [
                (*head, int(i), int(j), 1, rule.lower + _SLACK_MM) for i in near_a for j in near_b
            ]
            if not nearest:
                continue
            if rule.upper < np.inf:
                features.append((*head, int(near_a[0]), int(near_b[0]), -1, rule.upper - _SLACK_MM))
            if rule.parallel:
                # The side holding the edge (or face) is the one with fewer near corners.
                if len(near_a) <= len(near_b):
                    corners = [(int(i), int(near_b[0])) for i in near_a[:3]]
                else:
                    corners = [(int(near_a[0]), int(j)) for j in near_b[:3]]
                if len(corners) >= 2:
                    features += [(*head, i, j, 0, rule.lower + _SLACK_MM) for i, j in corners]
    if floor is not None:
        for a, v in enumerate(world.vertices):
            z = v[:, 2]
            features.extend(
                ("floor", a, int(k), 1, floor.lower + _SLACK_MM)
                for k in np.flatnonzero(z < floor.lower + _REACH_MM)
            )
        lowest = min(
            (
                (float(v[k, 2]), a, int(k))
                for a, v in enumerate(world.vertices)
                for k in range(len(v))
            )
        )
        if floor.upper < np.inf:
            features.append(("floor", lowest[1], lowest[2], -1, floor.upper - _SLACK_MM))
        if floor.parallel:
            v = world.vertices[lowest[1]]
            edge = np.argsort(v[:, 2])[: int(np.sum(v[:, 2] <= lowest[0] + _CORNER_REACH_MM))]
            if len(edge) >= 2:
                features += [
                    ("floor", lowest[1], int(k), 0, floor.lower + _SLACK_MM) for k in edge[:3]
                ]
    return features


def _feature_values(worlds, others, features) -> np.ndarray:
    """The gap (mm) of every feature (see :func:`_near_features`); each separating axis
    is built once for all the corner pairs along it."""
    axes: dict = {}
    out = np.empty(len(features))
    for row, (u, feature) in enumerate(features):
        world = worlds[u]
        if feature[0] == "floor":
            out[row] = world.vertices[feature[1]][feature[2], 2]
            continue
        _, n, a, b, k, ahead, i, j = feature[:8]
        other = others[u][n][0]
        key = (u, n, a, b, k)
        axis = axes.get(key)
        if axis is None:
            axis = axes[key] = _axis(world, other, a, b, k)
        pa = world.vertices[a][i] @ axis
        pb = other.vertices[b][j] @ axis
        out[row] = pb - pa if ahead else pa - pb
    return out


def _linear(kind: str, matrix: np.ndarray, bound: np.ndarray) -> dict:
    """An SLSQP constraint ``matrix @ d - bound`` (>= 0 or == 0)."""
    return {"type": kind, "fun": lambda d: matrix @ d - bound, "jac": lambda d: matrix}


def _qp_step(metric, q, gradient, values, sense, targets, step_limit, limits):
    """The step ``delta`` minimising (q + delta)' M (q + delta) subject to the linearised
    constraints (``sense`` +1: value + gradient @ delta >= target; -1: <=; 0: ==),
    |delta| <= step_limit and |q + delta| <= limits.

    When they cannot all be met, the equalities (parallel edges) are dropped, then the
    upper bounds; when even the lower bounds cannot be met, the step that most reduces
    their worst violation is taken; None when that fails too."""
    lower = np.maximum(-step_limit, -limits - q)
    upper = np.minimum(step_limit, limits - q)
    bounds = list(zip(lower, upper, strict=True))
    rows = {
        "lower": (gradient[sense > 0], targets[sense > 0] - values[sense > 0]),
        "upper": (-gradient[sense < 0], values[sense < 0] - targets[sense < 0]),
    }
    a_eq, b_eq = gradient[sense == 0], targets[sense == 0] - values[sense == 0]
    for kept in (("lower", "upper", "eq"), ("lower", "upper"), ("lower",)):
        if "eq" in kept and not len(a_eq):
            continue
        a_in = np.vstack([rows[k][0] for k in kept if k != "eq"])
        b_in = np.concatenate([rows[k][1] for k in kept if k != "eq"])
        constraints = [_linear("ineq", a_in, b_in)]
        if "eq" in kept:
            constraints.append(_linear("eq", a_eq, b_eq))
        result = minimize(
            lambda d: float((q + d) @ metric @ (q + d)),
            np.zeros_like(q),
            jac=lambda d: 2 * metric @ (q + d),
            constraints=constraints,
            bounds=bounds,
            method="SLSQP",
            options={"maxiter": 100, "ftol": 1e-14},
        )
        if np.all(a_in @ result.x - b_in >= -1e-9) and (
            "eq" not in kept or np.abs(a_eq @ result.x - b_eq).max() < 1e-7
        ):
            return result.x
    # The lower bounds cannot all be met within the trust region: the smallest step that
    # comes closest, one shared slack s >= 0 heavily penalised (a linear programme
    # would jump to a corner of the trust region and wander).
    a_in, b_in = rows["lower"]
    if not len(a_in):
        return None
    dim = len(q)
    result = minimize(
        lambda x: float((q + x[:dim]) @ metric @ (q + x[:dim])) + 1e4 * x[dim] ** 2,
        np.zeros(dim + 1),
        jac=lambda x: np.r_[2 * metric @ (q + x[:dim]), 2e4 * x[dim]],
        constraints=[_linear("ineq", np.hstack([a_in, np.ones((len(a_in), 1))]), b_in)],
        bounds=[*bounds, (0, None)],
        method="SLSQP",
        options={"maxiter": 100, "ftol": 1e-14},
    )
    return result.x[:dim] if np.all(np.isfinite(result.x)) else None
