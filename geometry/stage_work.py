"""What the geometry stage (:mod:`geometry.stage`) does once it runs: describe the stack,
write the description's files and figures, summarize its written descriptors for the
command line, and take an ensemble's statistics over its repeats.

Every command-line start registers the stage, so it is declared without the
descriptors: they bring numpy, scipy and manifold3d (~1 s), imported with this module
when the stage first works."""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from chipstack.core.arrangement import stack_history
from chipstack.core.schema import Scenario
from chipstack.core.stages import StageInputs, StageOutput
from chipstack.geometry.describe import Description, check_names, describe, in_output_order
from chipstack.geometry.descriptor_kinds import DESCRIPTORS
from chipstack.geometry.files import write_description
from chipstack.geometry.run_figures import ensemble_figures, single_run_figures

__all__ = [
    "check_names",
    "describe_stack",
    "report_lines",
    "summarize_repeats",
    "write_description_files",
    "write_geometry",
    "write_repeats",
]


def describe_stack(inputs: StageInputs, stage_name: str) -> Description:
    """The description of the packing's stack after each batch, reported as one step."""
    history = stack_history(inputs.result("packing"))
    report = inputs.options.progress
    if report is not None:
        report(stage_name, 0, 1, {})
    description = describe(history, inputs.scenario.geometry, inputs.options.descriptors)
    if report is not None:
        report(stage_name, 1, 1, {})
    return description


def write_description_files(result: Description, folder: Path, inputs: StageInputs) -> StageOutput:
    """A computed description's files in ``folder`` and its manifest entry."""
    history = stack_history(inputs.result("packing"))
    summary = write_geometry(folder, result, history, inputs.scenario, inputs.options.figures)
    return StageOutput(summary)


def report_lines(summary: Mapping[str, Any], folder: Path) -> list[str]:
    """The command line's summary of the written ``descriptors.json``: each descriptor's
    headline."""
    d = json.loads((folder / "descriptors.json").read_text())["descriptors"]
    known = in_output_order(d)
    parts = [DESCRIPTORS.get(n).headline(d[n]) for n in known]
    seconds = summary["descriptor_time_s"]
    return [f"descriptors in {seconds:.2f} s: " + "; ".join(p for p in parts if p)]


def summarize_repeats(folders: Sequence[Path], seeds: Sequence[int]) -> dict[str, Any]:
    """Mean and 95 % confidence interval of every descriptor over the repeats."""
    from chipstack.geometry.ensemble import summarize_runs  # scipy.stats: 0.7 s to import

    sections = [json.loads((f / "descriptors.json").read_text()) for f in folders]
    summary = summarize_runs(sections, list(seeds))
    summary["runs"] = [f.parent.name for f in folders]
    return summary


def write_repeats(summary: dict[str, Any], path) -> None:
    """The ensemble's statistics (``ensemble.json``) and their figures."""
    path("ensemble.json").write_text(json.dumps(summary, indent=2) + "\n")
    ensemble_figures(path("figures/x").parent, summary)


def write_geometry(
    folder: Path, description: Description, history, scenario: Scenario, figures: bool
) -> dict[str, Any]:
    """Write a computed description's files into ``folder``; returns the manifest entry."""
    extra = {"scenario": scenario.name, "seed": scenario.seed, "chips": history[-1].n_chips}
    files = write_description(folder, description, history[-1], extra)
    if figures:
        files += single_run_figures(folder / "figures", description, history[-1])
    return {
        "descriptors": list(description.records),
        "files": sorted(files),
        "descriptor_time_s": round(sum(description.timings_s.values()), 4),
        "descriptor_times_s": {k: round(v, 4) for k, v in description.timings_s.items()},
    }
