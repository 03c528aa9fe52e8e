"""How many chips cover each part of the stack's footprint.

The chips' outlines are projected on the conveyor plane (z = 0) by the vertical rays of
the NEH map (:func:`geometry.rays.ray_maps`): a ray at the centre of every pixel of a
square grid over the target and every chip counts the chips it passes through, exactly
where each chip's (possibly tilted) footprint is. The footprint is the area under at
least one chip, the target's surroundings included; the cover fraction of k chips is the
share of the footprint under exactly k of them, k = 1 ... the largest count (no cap), so
the fractions sum to 1. Areas are in mm2, the pixel's side in mm set by the geometry
section (``pixel_mm``); a pixel counts whole where its centre is covered. A panel pressed
from the stack is thin where one chip lies alone.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from chipstack.export.tables import fmt
from chipstack.geometry.descriptors.base import Context, Descriptor, Table, profile, scalar
from chipstack.geometry.rays import RayMaps


def _coverage_counts(maps: RayMaps) -> np.ndarray:
    """Pixels of the ray grid covered by exactly k chips.

    Parameters
    ----------
    maps : RayMaps
        The vertical rays of the stack (``maps.neh``: (nx, ny) int, chips per pixel).

    Returns
    -------
    (k_max + 1,) int
        Pixels under exactly k chips, k = 0 ... the largest NEH (at least 2 entries).
    """
    return np.bincount(maps.neh.ravel(), minlength=2)


def _coverage_tables(maps: RayMaps) -> dict[str, Table]:
    """The table ``coverage.csv``: one row per cover k = 1 ... the largest.

    Parameters
    ----------
    maps : RayMaps
        The vertical rays of the stack, as :func:`_coverage` returned them.

    Returns
    -------
    dict of str to (header, rows)
        ``{"coverage.csv": (header, rows)}``; columns ``chips`` (k), ``pixels``,
        ``area_mm2`` (mm2), ``fraction_of_footprint`` (under exactly k chips) and
        ``fraction_at_least`` (under k chips or more), fractions of the footprint.
    """
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
    """The coverage section of a stack's description.

    Parameters
    ----------
    ctx : Context
        The stack's shared intermediate results (its ray maps: ``ctx.rays``).

    Returns
    -------
    RayMaps
        The record the tables are written from.
    dict
        ``scalars``: ``footprint_mm2`` (mm2, the area under at least one chip),
        ``single_cover_fraction`` (share of the footprint under exactly one chip) and
        ``mean_cover`` (chips, the mean count over the footprint); ``profiles``:
        ``cover_fraction`` (index k = 1 ... the largest count, the share of the footprint
        under exactly k chips). A stack with no chip has a footprint of 0 and every
        fraction 0.
    """
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
