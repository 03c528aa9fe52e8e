"""The solve stage: the scenario's solve model presses the mesh stage's model. CalculiX
runs the compaction of the contact model, or of a cropped volume between whole-face
platens; the loose press (Incremental Potential Contact) presses separate chips. The
results come back as VTU for ParaView, the platen force against the press as CSV and a
figure."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

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
    checkpointed = True  # the loose press saves every accepted step (CalculiX runs whole)

    def check_run(self, scenario: Scenario) -> None:
        model = solve_model(scenario)
        model.check(scenario)
        model.check_run(scenario)  # refused when its solver is not installed

    def compute(self, inputs: StageInputs) -> Compaction:
        return solve_model(inputs.scenario).compute(inputs, self.name)

    def write(self, result: Compaction, folder: Path, inputs: StageInputs) -> StageOutput:
        return solve_model(inputs.scenario).write(result, folder, inputs)

    def load(self, folder: Path, scenario: Scenario) -> Path:
        return folder

    def report(self, summary: Mapping[str, Any], folder: Path) -> list[str]:
        contact = (
            f"; contact pressure on {summary['chips_in_contact']} chips"
            if "chips_in_contact" in summary
            else ""
        )
        pressure = (
            f" ({summary['nominal_pressure_mpa']:.3g} MPa nominal; voids "
            f"{100 * summary['void_fraction_start']:.1f} % to "
            f"{100 * summary['void_fraction']:.1f} %)"
            if "nominal_pressure_mpa" in summary
            else ""
        )
        return [
            f"compaction: {summary['press_mm']:.3f} mm press, platen force "
            f"{summary['force_n']:,.1f} N{pressure} over {summary['increments']} "
            f"increments{contact}; {summary.get('solver', 'CalculiX')} "
            f"{summary['solver_wall_time_s']:.1f} s"
        ]


STAGE = SolveStage()
