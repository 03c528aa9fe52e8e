"""What contact resolution returns, and the error it raises."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from chipstack.core.arrangement import Arrangement
from chipstack.core.errors import ChipstackError

__all__ = ["Resolution", "UnresolvedError", "unresolved_error"]


class UnresolvedError(ChipstackError):
    """Some chips cannot be resolved by small motions (the message names them).

    unresolved: (chip, how far short of the gap, mm) of each."""

    def __init__(self, message: str, unresolved: tuple[tuple[int, float], ...] = ()) -> None:
        super().__init__(message)
        self.unresolved = unresolved


def unresolved_error(unresolved, gap_mm: float) -> UnresolvedError:
    names = ", ".join(f"{c} ({-w:.3f} mm short)" for c, w in unresolved[:12])
    return UnresolvedError(
        f"contact resolution: {len(unresolved)} chips cannot be cleared by {gap_mm:g} mm "
        f"with small motions: chips {names}; use the voxel mesh (mesh.kind = 'voxel')",
        tuple(unresolved),
    )


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
