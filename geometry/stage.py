"""The geometry stage: the descriptors of a settled stack, written to ``geometry/``.

Every command-line start registers this stage and checks what it reads (its tables, its
key, the descriptors asked for): the stage is declared here without the descriptors,
which bring numpy, scipy and manifold3d (~1 s). Each step names the function that does
it (``"module:function"``, imported when the stage first works)."""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from chipstack.core.lazy import named
from chipstack.core.schema import Scenario
from chipstack.core.stages import Stage, StageInputs, StageOptions, StageOutput
from chipstack.geometry.sections import GeometrySpec
from chipstack.packing.kinds import stack_kinds

if TYPE_CHECKING:
    from chipstack.geometry.describe import Description

__all__ = ["GeometryStage", "STAGE"]


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
        named("chipstack.geometry.describe:check_names")(options.descriptors)

    def key_extra(self, scenario: Scenario, options: StageOptions) -> dict[str, Any]:
        return {
            "descriptors": list(options.descriptors) if options.descriptors else None,
            "figures": options.figures,
        }

    def compute(self, inputs: StageInputs) -> Description:
        return named("chipstack.geometry.describe:describe_stack")(inputs, self.name)

    def write(self, result: Description, folder: Path, inputs: StageInputs) -> StageOutput:
        return named("chipstack.geometry.files:write_description_files")(result, folder, inputs)

    def load(self, folder: Path, scenario: Scenario) -> dict[str, Any]:
        """The written ``descriptors.json`` (downstream stages read numbers, not arrays)."""
        return json.loads((folder / "descriptors.json").read_text())

    def report(self, summary: Mapping[str, Any], folder: Path) -> list[str]:
        return named("chipstack.geometry.files:report_lines")(summary, folder)

    def summarize_repeats(self, folders, seeds) -> dict[str, Any]:
        """Mean and 95 % confidence interval of every descriptor over the repeats."""
        return named("chipstack.geometry.ensemble:summarize_repeats")(folders, seeds)

    def write_repeats(self, summary: dict[str, Any], path) -> None:
        named("chipstack.geometry.ensemble:write_repeats")(summary, path)


STAGE = GeometryStage()
