"""The geometry stage: the descriptors of a settled stack, written to ``geometry/``."""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from chipstack.core.schema import Scenario
from chipstack.core.stages import Stage, StageInputs, StageOptions, StageOutput
from chipstack.geometry.sections import GeometrySpec
from chipstack.packing.kinds import stack_kinds

# The descriptors and their writers are imported where used: every command-line start
# registers this stage, and they bring numpy, scipy and manifold3d (~1 s).
if TYPE_CHECKING:
    from chipstack.geometry.describe import Description

__all__ = ["GeometryStage", "STAGE", "write_geometry"]


class GeometryStage(Stage):
    """Every registered descriptor (or the ones asked for) of the stack after each batch."""

    name = "geometry"
    progress_label = "describing"
    upstream = ("packing",)
    sections = ("geometry",)
    owned_sections = (GeometrySpec,)
    kinds = property(lambda self: stack_kinds())  # the kinds whose stack goes on
    repeat_statistics = True

    def check_options(self, options: StageOptions) -> None:
        from chipstack.geometry.describe import check_names

        check_names(options.descriptors)

    def key_extra(self, scenario: Scenario, options: StageOptions) -> dict[str, Any]:
        return {
            "descriptors": list(options.descriptors) if options.descriptors else None,
            "figures": options.figures,
        }

    def compute(self, inputs: StageInputs) -> Description:
        from chipstack.core.arrangement import stack_history
        from chipstack.geometry.describe import describe

        history = stack_history(inputs.result("packing"))
        report = inputs.options.progress
        if report is not None:
            report(self.name, 0, 1, {})
        description = describe(history, inputs.scenario.geometry, inputs.options.descriptors)
        if report is not None:
            report(self.name, 1, 1, {})
        return description

    def write(self, result: Description, folder: Path, inputs: StageInputs) -> StageOutput:
        from chipstack.core.arrangement import stack_history

        history = stack_history(inputs.result("packing"))
        summary = write_geometry(folder, result, history, inputs.scenario, inputs.options.figures)
        return StageOutput(summary)

    def load(self, folder: Path, scenario: Scenario) -> dict[str, Any]:
        """The written ``descriptors.json`` (downstream stages read numbers, not arrays)."""
        return json.loads((folder / "descriptors.json").read_text())

    def report(self, summary: Mapping[str, Any], folder: Path) -> list[str]:
        from chipstack.geometry.describe import DESCRIPTORS, in_output_order

        d = json.loads((folder / "descriptors.json").read_text())["descriptors"]
        known = in_output_order(d)
        parts = [DESCRIPTORS.get(n).headline(d[n]) for n in known]
        seconds = summary["descriptor_time_s"]
        return [f"descriptors in {seconds:.2f} s: " + "; ".join(p for p in parts if p)]

    def summarize_repeats(self, folders, seeds) -> dict[str, Any]:
        """Mean and 95 % confidence interval of every descriptor over the repeats."""
        from chipstack.geometry.ensemble import summarize_runs  # scipy.stats: 0.7 s to import

        sections = [json.loads((f / "descriptors.json").read_text()) for f in folders]
        summary = summarize_runs(sections, list(seeds))
        summary["runs"] = [f.parent.name for f in folders]
        return summary

    def write_repeats(self, summary: dict[str, Any], path) -> None:
        from chipstack.geometry.run_figures import ensemble_figures  # matplotlib only when drawing

        path("ensemble.json").write_text(json.dumps(summary, indent=2) + "\n")
        ensemble_figures(path("figures/x").parent, summary)


STAGE = GeometryStage()


def write_geometry(
    folder: Path, description: Description, history, scenario: Scenario, figures: bool
) -> dict[str, Any]:
    """Write a computed description's files into ``folder``; returns the manifest entry."""
    from chipstack.geometry.files import write_description

    extra = {"scenario": scenario.name, "seed": scenario.seed, "chips": history[-1].n_chips}
    files = write_description(folder, description, history[-1], extra)
    if figures:
        from chipstack.geometry.run_figures import (
            single_run_figures,  # matplotlib only when drawing
        )

        files += single_run_figures(folder / "figures", description, history[-1])
    return {
        "descriptors": list(description.records),
        "files": sorted(files),
        "descriptor_time_s": round(sum(description.timings_s.values()), 4),
        "descriptor_times_s": {k: round(v, 4) for k, v in description.timings_s.items()},
    }
