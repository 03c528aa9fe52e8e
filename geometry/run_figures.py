"""Which figures a run, an ensemble and a comparison get: every descriptor's own and every
registered figure of the stack (``export.figure_kinds``); drawing is in
``export.figures``."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from chipstack.export.figure_kinds import draw_figures
from chipstack.geometry.descriptor_kinds import DESCRIPTORS

__all__ = ["single_run_figures", "ensemble_figures", "comparison_figures"]


def single_run_figures(folder: Path, description, arrangement) -> list[str]:
    """The figures of each descriptor computed (Fig. 7, 9, 10), then the stack's own
    (Fig. 6, the 3-D view); names relative to the geometry folder."""
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    for name, record in description.records.items():
        drawn = DESCRIPTORS.get(name).figures(record, description.sections[name], folder)
        written += [f"figures/{file}" for file in drawn]
    written += [f"figures/{file}" for file in draw_figures("stack", folder, arrangement)]
    return written


def ensemble_figures(folder: Path, summary: dict[str, Any]) -> list[str]:
    """Each summarised descriptor's figures with 95 % confidence bands over the repeats
    (Fig. 7 and 10)."""
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    for name, section in summary["descriptors"].items():
        if name in DESCRIPTORS:
            drawn = DESCRIPTORS.get(name).ensemble_figures(section, folder)
            written += [f"figures/{file}" for file in drawn]
    return written


def comparison_figures(
    folder: Path, labels: tuple[str, str], ensembles: tuple[dict[str, Any], dict[str, Any]]
) -> list[str]:
    """Each descriptor both ensembles summarise, side by side (Fig. 12: layer filling)."""
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    first, second = (e["descriptors"] for e in ensembles)
    for name in first:
        if name in second and name in DESCRIPTORS:
            drawn = DESCRIPTORS.get(name).comparison_figures(
                labels, (first[name], second[name]), folder
            )
            written += [f"figures/{file}" for file in drawn]
    return written
