"""The built-in figures of :mod:`export.figure_kinds`, with what draws them (matplotlib
and pyvista, through :mod:`export.render` and :mod:`export.process_figures`). The
registry declares their names and imports this module when a figure is first asked
for, so that listing the figures loads no numerical library."""

from __future__ import annotations

import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from chipstack.export import process_figures, render
from chipstack.export.figure_kinds import FIGURES, DropScatter, FigureKind
from chipstack.export.vtk import stack_polydata

# The registry's logger, as before the built-in figures moved here.
log = logging.getLogger(__name__)


def _stack_view(folder: Path, arrangement) -> list[str]:
    a = arrangement
    mesh = stack_polydata(a.shapes, a.shape_index, a.positions, a.quaternions, a.batch)
    try:
        render.render_stack(folder / "stack.png", mesh)
    except RuntimeError as exc:  # no OpenGL on this machine: the other outputs still count
        log.warning("3-D view not rendered: %s", exc)
        return []
    return ["stack.png"]


def _drop_scatter(folder: Path, drops: DropScatter) -> list[str]:
    process_figures.plot_drops(
        folder / "fig15_drops.png", drops.xy, drops.statistics, drops.yaw_deg
    )
    return ["fig15_drops.png"]


def _mat_profiles(folder: Path, record: Mapping[str, Any]) -> list[str]:
    if not (record["areal_weight"] and record["thickness"]):
        return []  # no steady part of the mat to draw
    process_figures.plot_mat(folder / "mat.png", record)
    return ["mat.png"]


def _force_travel(folder: Path, compaction) -> list[str]:
    process_figures.plot_force_displacement(
        folder / "force_displacement.png", compaction.press_mm, compaction.force_n
    )
    return ["force_displacement.png"]


def _loose_press(folder: Path, press) -> list[str]:
    history = press.history  # columns: meshing.loose.press.HISTORY
    process_figures.plot_loose_press(
        folder / "loose_press.png", history[:, 0], history[:, 3], history[:, 4], history[:, 5]
    )
    return ["loose_press.png"]


for _figure in (
    FigureKind(
        "stack_view",
        "stack",
        "stack.png",
        "Fig. 6: the chips in 3-D, coloured by batch (needs OpenGL; without, skipped with a "
        "warning)",
        _stack_view,
    ),
    FigureKind(
        "drop_scatter",
        "drops",
        "fig15_drops.png",
        "Fig. 15: where the chips landed, with the paper's statistics",
        _drop_scatter,
    ),
    FigureKind(
        "mat_profiles",
        "mat",
        "mat.png",
        "the mat's areal weight and thickness along the belt (when it has a steady part)",
        _mat_profiles,
    ),
    FigureKind(
        "force_travel",
        "compaction",
        "force_displacement.png",
        "the platen's force against the press's travel",
        _force_travel,
    ),
    FigureKind(
        "loose_press",
        "loose_press",
        "loose_press.png",
        "the loose press's nominal pressure, contact area and voids against its travel",
        _loose_press,
    ),
):
    FIGURES.register(_figure.name, _figure)
