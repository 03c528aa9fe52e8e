"""The solve stage: CalculiX runs the compaction of the contact model, or of a cropped voxel
volume between whole-face platens; the results come back as VTU for ParaView, the platen
force against the press as CSV and a figure."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from chipstack.core.lazy import named
from chipstack.core.schema import Scenario
from chipstack.core.stages import Stage, StageInputs, StageOutput
from chipstack.meshing.sections import SolveSpec
from chipstack.meshing.solve_models import SOLVE_CHOICE, solve_model
from chipstack.packing.kinds import stack_kinds

# The solver's driver, readers and writers (meshing.compaction) are named, imported when
# a stack is first pressed: every command-line start registers this stage, and they
# bring numpy and meshio.
if TYPE_CHECKING:
    from chipstack.meshing.compaction import Compaction

__all__ = ["SolveStage", "STAGE"]


class SolveStage(Stage):
    """CalculiX on the contact model or a cropped voxel volume: the press of ``[solve]``,
    forces and fields."""

    name = "solve"
    progress_label = "solving (% of the press)"
    progress_unit = "%"
    upstream = ("mesh",)
    sections = ("solve",)
    owned_sections = (SolveSpec,)
    kind_choices = {"solve": SOLVE_CHOICE}  # [solve]: the pressing model's own keys
    kinds = property(lambda self: stack_kinds())  # the kinds whose stack goes on
    in_ensembles = False

    def check_run(self, scenario: Scenario) -> None:
        solve_model(scenario).check(scenario)
        named("chipstack.meshing.calculix:ccx_path")()  # refused when ccx is not installed

    def compute(self, inputs: StageInputs) -> Compaction:
        return named("chipstack.meshing.compaction:compact")(inputs, self.name)

    def write(self, result: Compaction, folder: Path, inputs: StageInputs) -> StageOutput:
        return named("chipstack.meshing.compaction:write_compaction")(result, folder, inputs)

    def load(self, folder: Path, scenario: Scenario) -> Path:
        return folder

    def report(self, summary: Mapping[str, Any], folder: Path) -> list[str]:
        contact = (
            f"; contact pressure on {summary['chips_in_contact']} chips"
            if "chips_in_contact" in summary
            else ""
        )
        return [
            f"compaction: {summary['press_mm']:.3f} mm press, platen force "
            f"{summary['force_n']:,.1f} N over {summary['increments']} increments{contact}; "
            f"CalculiX {summary['solver_wall_time_s']:.1f} s"
        ]


STAGE = SolveStage()
