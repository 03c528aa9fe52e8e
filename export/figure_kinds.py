"""The figures a run draws beside its descriptors' own, as a registry by name.

Each figure declares what it is drawn from (its ``subject``: the final stack of the
geometry stage, the drops, the conveyor's mat, the press's compaction), the files it
makes and what it shows; a stage draws every registered figure of the subjects it holds
(``draw_figures``) and never names one. Plugins add figures through the entry point
group ``chipstack.figures``. A descriptor's figures (Fig. 7, 9, 10 and their ensemble and
comparison versions) belong to the descriptor (``geometry.describe.Descriptor``).

The built-in figures are declared here by name and registered, with what draws them, by
:mod:`export.builtin_figures` when one is first asked for: listing them loads no
numerical library.
"""

from __future__ import annotations

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

# What a figure may be drawn from, and the folder of a run the stage that holds it puts
# its figures in.
SUBJECTS: dict[str, str] = {
    "stack": "the final arrangement of a stack or a mat's panel",
    "drops": "single-chip drops: their landing points and statistics",
    "mat": "a conveyor's mat: its areal weight and thickness along the belt",
    "mesh": "a volume mesh of the stack (``MeshPicture``)",
    "compaction": "the press's force against its travel",
    "loose_press": "a loose press's steps: pressure, contact area and voids",
}
SUBJECT_FOLDERS: dict[str, str] = {
    "stack": "geometry/figures/",
    "drops": "packing/figures/",
    "mat": "packing/figures/",
    "mesh": "mesh/",
    "compaction": "solve/",
    "loose_press": "solve/",
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
# The built-in figures, in the order they are drawn: declared by name, since what draws
# them brings matplotlib and pyvista (registered by that module when one is asked for).
FIGURES.declare(
    "chipstack.export.builtin_figures", "stack_view", "drop_scatter", "mat_profiles", "force_travel"
)


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
