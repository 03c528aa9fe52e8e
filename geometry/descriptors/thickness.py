"""Local stack thickness: the number of chips a vertical ray crosses (NEH map), over the
target and in rings around its centre."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from chipstack.export.tables import fmt
from chipstack.geometry.descriptors.base import (
    Context,
    Descriptor,
    Table,
    figure_module,
    profile,
    scalar,
)
from chipstack.geometry.rays import RayMaps

RING_EDGES_MM = (0.0, 25.0, 50.0, 75.0, np.inf)  # the last ring: the target's corners


def _thickness_tables(maps: RayMaps) -> dict[str, Table]:
    grid = maps.grid
    rows = (
        [
            fmt(grid.x[i]),
            fmt(grid.y[j]),
            int(grid.on_target[i, j]),
            int(maps.neh[i, j]),
            fmt(maps.top_mm[i, j]),
            fmt(maps.solid_mm[i, j]),
        ]
        for i in range(grid.nx)
        for j in range(grid.ny)
    )
    return {"neh_map.csv": (["x_mm", "y_mm", "on_target", "neh", "top_mm", "solid_mm"], rows)}


def _thickness_figures(maps: RayMaps, section: dict[str, Any], folder: Path) -> list[str]:
    figures = figure_module()
    grid = maps.grid
    figures.plot_neh_map(
        folder / "neh_map.png",
        grid.x0 + grid.pixel_mm * np.arange(grid.nx + 1),
        grid.y0 + grid.pixel_mm * np.arange(grid.ny + 1),
        maps.neh,
        grid.target_size_mm,
    )
    return ["neh_map.png"]


def _thickness(ctx: Context):
    maps = ctx.rays
    on = maps.grid.on_target
    neh = maps.neh[on]
    radius = np.hypot(maps.grid.x[:, None], maps.grid.y[None, :])
    ring_means = []
    labels = []
    for lo, hi in zip(RING_EDGES_MM[:-1], RING_EDGES_MM[1:], strict=True):
        ring = (radius >= lo) & (radius < hi) & on
        ring_means.append(maps.neh[ring].mean() if ring.any() else np.nan)
        labels.append(f"{lo:g}-{hi:g}" if np.isfinite(hi) else f">{lo:g}")
    histogram = np.bincount(np.minimum(neh, 8), minlength=9) / max(len(neh), 1)
    scalars = {
        "neh_mean": scalar(neh.mean(), "chips", "mean NEH over the target's pixels"),
        "neh_max": scalar(maps.neh.max(initial=0), "chips", "largest NEH anywhere"),
        "pixel_mm": scalar(maps.grid.pixel_mm, "mm", "pixel side"),
    }
    profiles = {
        "neh_by_ring": profile(
            labels,
            ring_means,
            "distance from the target centre (mm)",
            "chips",
            "mean NEH of the target's pixels in rings around its centre",
        ),
        "neh_histogram": profile(
            [str(k) if k < 8 else "8+" for k in range(9)],
            histogram,
            "NEH",
            "",
            "fraction of the target's pixels with each NEH (8 and more together)",
        ),
    }
    return maps, {"scalars": scalars, "profiles": profiles}


DESCRIPTOR = Descriptor(
    "thickness",
    "local stack thickness: chips crossed by vertical rays (NEH map)",
    tables=_thickness_tables,
    figures=_thickness_figures,
    compute=_thickness,
)
