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

Two routes. The global route (:mod:`.relax`, tried first) moves every chip at
once, one sparse convex programme per step, and also turns two chips whose outlines cross
at a shallow angle in a shared plane until their edges are parallel; it is the one that
resolves the physics stacks. When it leaves a pair short, the bottom-up route below is
tried (:mod:`.bottom_up`).

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

import numpy as np

from chipstack.core.arrangement import Arrangement
from chipstack.core.errors import InputError
from chipstack.geometry.contacts import GROUND, ContactTable, find_contacts
from chipstack.meshing.resolution.bottom_up import resolve_bottom_up
from chipstack.meshing.resolution.global_route import resolve_globally
from chipstack.meshing.resolution.result import Resolution, UnresolvedError, unresolved_error
from chipstack.meshing.resolution.rigid import (
    LINE,
    convex_pieces,
    place_chip,
    separation_between,
)

__all__ = [
    "check_settings",
    "resolve_chips",
    "resolve_contacts",
    "separation_mm",
]

log = logging.getLogger(__name__)


def separation_mm(arrangement: Arrangement, i: int, j: int) -> float:
    """Separating-axis distance between chips ``i`` and ``j`` (mm; negative: they
    interpenetrate, by that depth)."""
    worlds = [
        place_chip(
            convex_pieces(arrangement.shapes[arrangement.shape_index[k]]),
            arrangement.rotations[k],
            arrangement.positions[k],
        )
        for k in (i, j)
    ]
    return separation_between(*worlds)


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
        raise unresolved_error(named, settings.get("gap_mm", 0.03)) from None
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
    settings = (gap_mm, snap_angle_deg, contact_gap_mm, touching_lines)
    resolved = resolve_globally(arrangement, contacts, *settings)
    if resolved is None:
        log.info("contact resolution: the global route did not clear every pair; bottom-up route")
        resolved = resolve_bottom_up(arrangement, contacts, *settings)
    info = {**resolved.info, **_lines_touching(resolved.arrangement, contacts)}
    return dataclasses.replace(resolved, seconds=time.perf_counter() - start, info=info)


def _lines_touching(resolved: Arrangement, contacts: ContactTable) -> dict[str, int]:
    """How many of the settled stack's line contacts between chips end touching (within
    a micrometre), measured on the resolved arrangement."""
    pairs = [
        (int(a), int(b))
        for a, b, k in zip(contacts.chip_a, contacts.chip_b, contacts.kind, strict=True)
        if k == LINE and b != GROUND
    ]
    touching = sum(1 for a, b in pairs if separation_mm(resolved, a, b) <= 1e-3)
    return {"line_contacts": len(pairs), "line_contacts_touching": touching}
