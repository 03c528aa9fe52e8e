"""Interpenetration volumes and projected overlap areas between chips."""

from __future__ import annotations

from chipstack.export.tables import fmt
from chipstack.geometry.descriptors.base import (
    Context,
    Descriptor,
    Table,
    scalar,
)
from chipstack.geometry.overlaps import Overlaps, find_overlaps


def _overlap_tables(o: Overlaps) -> dict[str, Table]:
    rows = (
        [int(i), int(j), fmt(a), fmt(v)]
        for (i, j), a, v in zip(o.pairs, o.projected_mm2, o.penetration_mm3, strict=True)
    )
    return {"overlaps.csv": (["chip_a", "chip_b", "projected_mm2", "penetration_mm3"], rows)}


def _overlaps(ctx: Context):
    result: Overlaps = find_overlaps(ctx.final)
    a = ctx.final
    volume = sum(a.shapes[i].volume_mm3 for i in a.shape_index) or 1.0
    n = max(a.n_chips, 1)
    scalars = {
        "projected_total_mm2": scalar(
            result.total_projected_mm2, "mm2", "sum over pairs of footprint overlap areas"
        ),
        "projected_per_chip_mm2": scalar(
            2 * result.total_projected_mm2 / n,
            "mm2",
            "mean over chips of their footprint overlap with all other chips",
        ),
        "overlapping_pairs": scalar(len(result.pairs), "", "pairs with overlapping footprints"),
        "penetration_total_mm3": scalar(
            result.total_penetration_mm3, "mm3", "sum over pairs of interpenetration volumes"
        ),
        "penetration_fraction": scalar(
            result.total_penetration_mm3 / volume, "", "interpenetration / total chip volume"
        ),
        "penetration_max_mm3": scalar(
            result.penetration_mm3.max(initial=0.0), "mm3", "largest interpenetration of a pair"
        ),
    }
    return result, {"scalars": scalars, "profiles": {}}


DESCRIPTOR = Descriptor(
    "overlaps",
    "interpenetration volumes and projected overlap areas between chips",
    tables=_overlap_tables,
    chip_columns=lambda o: {
        "projected_overlap_mm2": [fmt(v) for v in o.per_chip_projected_mm2],
        "penetration_mm3": [fmt(v) for v in o.per_chip_penetration_mm3],
    },
    order=40,
    compute=_overlaps,
)
