"""The figures a run draws beside its descriptors' own, as a registry by name.

Each figure declares what it is drawn from (its ``subject``: the final stack of the
geometry stage, the drops, the conveyor's mat, the press's compaction), the files it
makes and what it shows; a stage draws every registered figure of the subjects it holds
(``draw_figures``) and never names one. Plugins add figures through the entry point
group ``chipstack.figures``. A descriptor's figures (Fig. 7, 9, 10 and their ensemble and
comparison versions) belong to the descriptor (``geometry.describe.Descriptor``).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from chipstack.core.registry import Registry

__all__ = [
    "FIGURES",
    "SUBJECTS",
    "SUBJECT_FOLDERS",
    "DropScatter",
    "FigureKind",
    "MeshPicture",
    "draw_figures",
]

log = logging.getLogger(__name__)

# What a figure may be drawn from, and the folder of a run the stage that holds it puts
# its figures in.
SUBJECTS: dict[str, str] = {
    "stack": "the final arrangement of a stack or a mat's panel",
    "drops": "single-chip drops: their landing points and statistics",
    "mat": "a conveyor's mat: its areal weight and thickness along the belt",
    "mesh": "a volume mesh of the stack (``MeshPicture``)",
    "compaction": "the press's force against its travel",
}
SUBJECT_FOLDERS: dict[str, str] = {
    "stack": "geometry/figures/",
    "drops": "packing/figures/",
    "mat": "packing/figures/",
    "mesh": "mesh/",
    "compaction": "solve/",
}


@dataclass(frozen=True)
class FigureKind:
    """One figure: what it is drawn from, the files it makes (as the docs show them),
    what it shows, and ``draw(folder, subject) -> names written in folder`` (an empty
    list when the subject has nothing to show)."""

    name: str
    subject: str
    files: str
    doc: str
    draw: Callable[[Path, Any], list[str]]

    def __post_init__(self) -> None:
        if self.subject not in SUBJECTS:
            raise ValueError(
                f"figure {self.name!r}: unknown subject {self.subject!r}; valid subjects: "
                + ", ".join(SUBJECTS)
            )


@dataclass(frozen=True)
class DropScatter:
    """The subject ``drops``: landing points (n, 2) in mm, their statistics
    (``packing.scatter.drop_statistics``) and the release yaw (deg)."""

    xy: Any
    statistics: Mapping[str, Any]
    yaw_deg: float


@dataclass(frozen=True)
class MeshPicture:
    """The subject ``mesh``: a volume mesh (``meshing.mesh.VolumeMesh``) and the stem its
    files are written under (``stack_voxel``, ...)."""

    stem: str
    mesh: Any


FIGURES: Registry[FigureKind] = Registry("figure", "chipstack.figures")


def draw_figures(subject: str, folder: Path, data: Any) -> list[str]:
    """Every registered figure of ``subject`` drawn from ``data`` into ``folder``; returns
    the names written, in registry order. ``folder`` is made for the figures and left
    out again when none draws anything (a mat without a steady part has no figure)."""
    if subject not in SUBJECTS:
        valid = ", ".join(SUBJECTS)
        raise ValueError(f"unknown figure subject {subject!r}; valid subjects: {valid}")
    kinds = [FIGURES.get(n) for n in FIGURES.in_order()]
    kinds = [k for k in kinds if k.subject == subject]
    if not kinds:
        return []
    made = not folder.exists()
    folder.mkdir(parents=True, exist_ok=True)
    written: list[str] = []
    for kind in kinds:
        written += kind.draw(folder, data)
    if made and not written and not any(folder.iterdir()):
        folder.rmdir()
    return written


def _stack_view(folder: Path, arrangement) -> list[str]:
    from chipstack.export import figures, stack_polydata  # pyvista only when drawing

    a = arrangement
    mesh = stack_polydata(a.shapes, a.shape_index, a.positions, a.quaternions, a.batch)
    try:
        figures.render_stack(folder / "stack.png", mesh)
    except RuntimeError as exc:  # no OpenGL on this machine: the other outputs still count
        log.warning("3-D view not rendered: %s", exc)
        return []
    return ["stack.png"]


def _drop_scatter(folder: Path, drops: DropScatter) -> list[str]:
    from chipstack.export.figures import plot_drops  # matplotlib only when drawing

    plot_drops(folder / "fig15_drops.png", drops.xy, drops.statistics, drops.yaw_deg)
    return ["fig15_drops.png"]


def _mat_profiles(folder: Path, record: Mapping[str, Any]) -> list[str]:
    if not (record["areal_weight"] and record["thickness"]):
        return []  # no steady part of the mat to draw
    from chipstack.export.figures import plot_mat

    plot_mat(folder / "mat.png", record)
    return ["mat.png"]


def _force_travel(folder: Path, compaction) -> list[str]:
    from chipstack.export.figures import plot_force_displacement

    plot_force_displacement(
        folder / "force_displacement.png", compaction.press_mm, compaction.force_n
    )
    return ["force_displacement.png"]


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
):
    FIGURES.register(_figure.name, _figure)
