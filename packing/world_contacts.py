"""Which chips of a :class:`packing.world.ChipWorld` touch or come near which, read from
the engine in millimetres."""

from __future__ import annotations

import numpy as np

from chipstack.core.stack import ContactRecord
from chipstack.packing.bullet import pybullet
from chipstack.packing.world_bodies import RETIRED, ChipBodies
from chipstack.packing.world_engine import MM_PER_UNIT, EngineSession

__all__ = ["GROUND", "ContactRecord", "ContactQueries"]

GROUND = -1  # chip index used for the floor in contact records


class ContactQueries:
    """Neighbours, solver contacts and closest points of chips."""

    def __init__(self, session: EngineSession, chips: ChipBodies) -> None:
        self._session = session
        self._chips = chips

    def chips_near(self, chip: int, margin_mm: float) -> list[int]:
        """Chips whose bounding boxes come within ``margin_mm`` of this chip's."""
        c = self._session.client
        lo, hi = pybullet.getAABB(self._chips.body_ids[chip], physicsClientId=c)
        m = margin_mm / MM_PER_UNIT
        found = pybullet.getOverlappingObjects(
            [lo[0] - m, lo[1] - m, lo[2] - m],
            [hi[0] + m, hi[1] + m, hi[2] + m],
            physicsClientId=c,
        )
        index = self._chips.index_of
        return sorted(index[b] for b, _ in (found or ()) if b in index and index[b] != chip)

    def within(self, chip: int, others: list[int], distance_mm: float) -> list[int]:
        """The chips of ``others`` whose surface comes within ``distance_mm`` of ``chip``'s."""
        c, reach = self._session.client, distance_mm / MM_PER_UNIT
        body, bodies = self._chips.body_ids[chip], self._chips.body_ids
        return [
            other
            for other in others
            if pybullet.getClosestPoints(body, bodies[other], reach, physicsClientId=c)
        ]

    def contact_points(self, chip: int) -> list[tuple[int, float]]:
        """Current solver contacts of one chip: (other chip index or GROUND, distance mm)."""
        c = self._session.client
        points = pybullet.getContactPoints(bodyA=self._chips.body_ids[chip], physicsClientId=c)
        return [(self._chips.chip_of(p[2], GROUND), p[8] * MM_PER_UNIT) for p in points]

    def closest_points(self, distance_mm: float, floor: int) -> ContactRecord:
        """All chip-chip and chip-floor closest points within ``distance_mm``.

        Computed from the geometry on demand (not the solver's cached manifolds, which do
        not exist between frozen chips).
        """
        c = self._session.client
        reach = distance_mm / MM_PER_UNIT
        bodies = self._chips.body_ids
        rows = []
        for a, body in enumerate(bodies):
            if body == RETIRED:  # out of the engine: no contacts read
                continue
            for b in self.chips_near(a, distance_mm):
                if b <= a:
                    continue
                rows += [
                    (a, b, pt)
                    for pt in pybullet.getClosestPoints(body, bodies[b], reach, physicsClientId=c)
                ]
            rows += [
                (a, GROUND, pt)
                for pt in pybullet.getClosestPoints(body, floor, reach, physicsClientId=c)
            ]
        return _record(rows)


def _record(rows: list[tuple[int, int, tuple]]) -> ContactRecord:
    """The record of (chip a, chip b, PyBullet closest point) rows."""
    if not rows:
        empty3 = np.empty((0, 3))
        return ContactRecord(
            np.empty(0, int), np.empty(0, int), empty3, empty3, empty3, np.empty(0)
        )
    return ContactRecord(
        chip_a=np.array([r[0] for r in rows], dtype=int),
        chip_b=np.array([r[1] for r in rows], dtype=int),
        point_a=np.array([r[2][5] for r in rows]) * MM_PER_UNIT,
        point_b=np.array([r[2][6] for r in rows]) * MM_PER_UNIT,
        normal=np.array([r[2][7] for r in rows]),
        distance=np.array([r[2][8] for r in rows]) * MM_PER_UNIT,
    )
