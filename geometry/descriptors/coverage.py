"""How many chips cover each part of the stack's footprint: the share of the area under
the stack covered by exactly 1, 2, 3, ... chips, from the same vertical rays as the NEH
map (over the whole footprint, the target's surroundings included, and with no cap on
the count). A panel pressed from the stack is thin where one chip lies alone."""

from __future__ import annotations

from typing import Any

import numpy as np

from chipstack.export.tables import fmt
from chipstack.geometry.descriptors.base import Context, Descriptor, Table, profile, scalar
from chipstack.geometry.rays import RayMaps


def _coverage_counts(maps: RayMaps) -> np.ndarray:
    """(k_max + 1,) pixels covered by exactly k chips, k = 0 ... the largest NEH."""
    return np.bincount(maps.neh.ravel(), minlength=2)


def _coverage_tables(maps: RayMaps) -> dict[str, Table]:
    counts = _coverage_counts(maps)
    pixel_area = maps.grid.pixel_mm**2
    footprint = max(int(counts[1:].sum()), 1)
    at_least = np.cumsum(counts[::-1])[::-1]
    header = ["chips", "pixels", "area_mm2", "fraction_of_footprint", "fraction_at_least"]
    rows = (
        [k, int(counts[k]), fmt(counts[k] * pixel_area), fmt(counts[k] / footprint)]
        + [fmt(at_least[k] / footprint)]
        for k in range(1, len(counts))
    )
    return {"coverage.csv": (header, rows)}


def _coverage(ctx: Context) -> tuple[RayMaps, dict[str, Any]]:
    maps = ctx.rays
    counts = _coverage_counts(maps)
    pixel_area = maps.grid.pixel_mm**2
    covered = int(counts[1:].sum())
    share = counts[1:] / max(covered, 1)
    k = np.arange(1, len(counts))
    scalars = {
        "footprint_mm2": scalar(
            covered * pixel_area, "mm2", "area under at least one chip (pixels of the NEH rays)"
        ),
        "single_cover_fraction": scalar(
            share[0] if covered else 0.0, "", "share of the footprint under exactly one chip"
        ),
        "mean_cover": scalar(
            float(k @ counts[1:]) / covered if covered else 0.0,
            "chips",
            "mean number of chips over a point of the footprint",
        ),
    }
    profiles = {
        "cover_fraction": profile(
            k.tolist(),
            share if covered else np.zeros(len(k)),
            "chips",
            "",
            "share of the footprint covered by exactly this many chips",
        ),
    }
    return maps, {"scalars": scalars, "profiles": profiles}


DESCRIPTOR = Descriptor(
    "coverage",
    "share of the stack's footprint covered by exactly 1, 2, 3, ... chips",
    compute=_coverage,
    tables=_coverage_tables,
    ensemble_scalars=("single_cover_fraction", "mean_cover"),
)
