"""Layer filling by centre of mass (the paper's Fig. 10), with the solid and covered
fractions of each layer."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from chipstack.export.tables import fmt
from chipstack.geometry.descriptors.base import (
    Context,
    Descriptor,
    Table,
    bands,
    figure_module,
    profile,
    scalar,
)
from chipstack.geometry.layers import LayerFilling, layer_filling


def _layer_tables(f: LayerFilling) -> dict[str, Table]:
    h = f.layer_mm
    header = ["layer", "z_low_mm", "z_high_mm", "chips", "chips_over_target", "full_layer"]
    header += ["solid_fraction", "porosity", "covered_fraction"]
    rows = (
        [
            k,
            fmt(k * h),
            fmt((k + 1) * h),
            int(f.chips[k]),
            int(f.chips_over_target[k]),
            fmt(f.full_layer),
            fmt(f.solid_fraction[k]),
            fmt(1 - f.solid_fraction[k]),
            fmt(f.covered_fraction[k]),
        ]
        for k in range(len(f.chips))
    )
    return {"layers.csv": (header, rows)}


def _layer_figures(filling: LayerFilling, section: dict[str, Any], folder: Path) -> list[str]:
    figures = figure_module()
    layers = np.arange(len(filling.chips))
    figures.plot_layer_filling(
        folder / "layer_filling.png", layers, filling.chips, filling.full_layer
    )
    figures.plot_profile(
        folder / "porosity_profile.png",
        filling.layer_mm * (layers + 0.5),
        1.0 - filling.solid_fraction,
        "porosity over the target (per layer)",
        "Porosity through the thickness",
    )
    return ["layer_filling.png", "porosity_profile.png"]


def _layer_ensemble_figures(summary: dict[str, Any], folder: Path) -> list[str]:
    """Fig. 10 with 95 % confidence bands over the repeats."""
    figures = figure_module()
    chips = summary["profiles"]["chips"]
    mean, low, high = bands(chips)
    full = summary["scalars"]["full_layer"]["mean"]
    figures.plot_layer_filling(
        folder / "layer_filling.png", np.array(chips["index"]), mean, full, low, high
    )
    return ["layer_filling.png"]


def _layer_comparison_figures(
    labels: tuple[str, str], summaries: tuple[dict[str, Any], dict[str, Any]], folder: Path
) -> list[str]:
    """Fig. 12: the two ensembles' layer filling side by side."""
    figures = figure_module()
    series = []
    longest: list[Any] = []
    for label, summary in zip(labels, summaries, strict=True):
        chips = summary["profiles"]["chips"]
        mean, low, high = bands(chips)
        series.append((label, mean, low, high))
        longest = max(longest, chips["index"], key=len)
    full = summaries[0]["scalars"]["full_layer"]["mean"]
    figures.plot_layer_comparison(folder / "layer_filling.png", np.array(longest), series, full)
    return ["layer_filling.png"]


def _layers(ctx: Context):
    filling: LayerFilling = layer_filling(ctx.final, ctx.union, ctx.spec.layer_mm)
    index = list(range(len(filling.chips)))
    nonempty = np.flatnonzero(filling.chips)
    scalars = {
        "full_layer": scalar(filling.full_layer, "chips", "chips per full layer"),
        "highest_layer": scalar(
            nonempty.max() if len(nonempty) else -1, "", "highest layer holding a centre"
        ),
        "nonempty_layers": scalar(len(nonempty), "", "layers holding at least one centre"),
    }
    h = filling.layer_mm
    profiles = {
        "chips": profile(index, filling.chips, "layer", "chips", f"chips per {h:g} mm layer"),
        "chips_cumulative": profile(
            index,
            np.cumsum(filling.chips),
            "layer",
            "chips",
            "chips whose centre lies in this layer or below (filling up to the layer's top)",
            pad="last",
        ),
        "chips_over_target": profile(
            index,
            filling.chips_over_target,
            "layer",
            "chips",
            "chips per layer, counting chips whose centre lies over the target",
        ),
        "solid_fraction": profile(
            index,
            filling.solid_fraction,
            "layer",
            "",
            "solid volume / layer volume over the target (porosity = 1 - this)",
        ),
        "covered_fraction": profile(
            index,
            filling.covered_fraction,
            "layer",
            "",
            "area of the target under the layer's solid / target area",
        ),
    }
    return filling, {"scalars": scalars, "profiles": profiles}


DESCRIPTOR = Descriptor(
    "layers",
    "layer filling by centre of mass, solid and covered fractions per layer",
    tables=_layer_tables,
    figures=_layer_figures,
    ensemble_figures=_layer_ensemble_figures,
    comparison_figures=_layer_comparison_figures,
    ensemble_scalars=("highest_layer",),
    headline=lambda section: f"highest layer {int(section['scalars']['highest_layer']['value'])}",
    order=50,
    compute=_layers,
)
