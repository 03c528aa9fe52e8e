"""Which figures a run, an ensemble and a comparison get (drawing is in export.figures)."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from geometry.contacts import KINDS
from geometry.describe import DESCRIPTORS

log = logging.getLogger(__name__)

__all__ = ["single_run_figures", "ensemble_figures", "comparison_figures"]


def single_run_figures(folder: Path, description, arrangement) -> list[str]:
    """Fig. 6 (3-D view), 7 (contact types vs NBD), 9 (NEH map), 10 (layer filling)."""
    from export import figures, stack_polydata

    folder.mkdir(parents=True, exist_ok=True)
    written = []
    for name, record in description.records.items():
        drawn = DESCRIPTORS.get(name).figures(record, description.sections[name], folder)
        written += [f"figures/{file}" for file in drawn]
    a = arrangement
    mesh = stack_polydata(a.shapes, a.shape_index, a.positions, a.quaternions, a.batch)
    try:
        figures.render_stack(folder / "stack.png", mesh)
        written.append("figures/stack.png")
    except RuntimeError as exc:  # no OpenGL on this machine: the other outputs still count
        log.warning("3-D view not rendered: %s", exc)
    return written


def _bands(profile: dict[str, Any]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    def array(key: str) -> np.ndarray:
        return np.array([np.nan if v is None else v for v in profile[key]], dtype=float)

    mean = array("mean")
    low, high = array("ci_low"), array("ci_high")
    return mean, np.where(np.isnan(low), mean, low), np.where(np.isnan(high), mean, high)


def ensemble_figures(folder: Path, summary: dict[str, Any]) -> list[str]:
    """Fig. 7 and Fig. 10 with 95 % confidence bands over the repeats."""
    from export import figures

    folder.mkdir(parents=True, exist_ok=True)
    written = []
    d = summary["descriptors"]
    if "contacts" in d:
        profiles = d["contacts"]["profiles"]
        batches = np.array(profiles["point_per_chip_by_batch"]["index"])
        mean, low, high = {}, {}, {}
        for kind in KINDS:
            mean[kind], low[kind], high[kind] = _bands(profiles[f"{kind}_per_chip_by_batch"])
        figures.plot_contact_types(folder / "contact_types.png", batches, mean, low, high)
        written.append("figures/contact_types.png")
    if "layers" in d:
        chips = d["layers"]["profiles"]["chips"]
        mean, low, high = _bands(chips)
        full = d["layers"]["scalars"]["full_layer"]["mean"]
        figures.plot_layer_filling(
            folder / "layer_filling.png", np.array(chips["index"]), mean, full, low, high
        )
        written.append("figures/layer_filling.png")
    return written


def comparison_figures(
    folder: Path, labels: tuple[str, str], ensembles: tuple[dict[str, Any], dict[str, Any]]
) -> list[str]:
    """Fig. 12: the two ensembles' layer filling side by side."""
    from export import figures

    folder.mkdir(parents=True, exist_ok=True)
    if not all("layers" in e["descriptors"] for e in ensembles):
        return []
    series = []
    longest: list[Any] = []
    for label, ensemble in zip(labels, ensembles, strict=True):
        chips = ensemble["descriptors"]["layers"]["profiles"]["chips"]
        mean, low, high = _bands(chips)
        series.append((label, mean, low, high))
        longest = max(longest, chips["index"], key=len)
    full = ensembles[0]["descriptors"]["layers"]["scalars"]["full_layer"]["mean"]
    figures.plot_layer_comparison(folder / "layer_filling.png", np.array(longest), series, full)
    return ["figures/layer_filling.png"]
