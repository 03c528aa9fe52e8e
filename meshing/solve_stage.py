"""The solve stage: CalculiX runs the compaction of the contact model, or of a cropped voxel
volume between whole-face platens; the results come back as VTU for ParaView, the platen
force against the press as CSV and a figure."""

from __future__ import annotations

import csv
import logging
import shutil
import tempfile
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from chipstack.core.schema import Scenario
from chipstack.core.stages import Stage, StageInputs, StageOutput
from chipstack.meshing.sections import SolveSpec
from chipstack.meshing.solve_models import SOLVE_CHOICE, solve_model
from chipstack.packing.kinds import stack_kinds

# The solver's driver, readers and writers are imported where used: every command-line
# start registers this stage, and they bring numpy and scipy.
if TYPE_CHECKING:
    import numpy as np

__all__ = ["SolveStage", "STAGE", "Compaction"]

log = logging.getLogger(__name__)

JOB = "compaction"


@dataclass
class Compaction:
    """A solved compaction: the solver's folder (scratch), the press against the force,
    and the solver's wall time."""

    scratch: Path
    press_mm: np.ndarray  # (k,) top platen displacement down, at each increment
    force_n: np.ndarray  # (k,) force on the top platen (reaction, pressing down: positive)
    bottom_force_n: np.ndarray  # (k,) reaction at the conveyor
    wall_time_s: float


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
        from chipstack.meshing.calculix import ccx_path

        ccx_path()

    def compute(self, inputs: StageInputs) -> Compaction:
        from chipstack.meshing.calculix import SolverError, read_node_prints, run_ccx

        mesh = inputs.result("mesh")
        scratch = Path(tempfile.mkdtemp(prefix="chipstack-solve-"))
        model = solve_model(inputs.scenario)
        prepared = model.prepare(mesh.folder, scratch, JOB, inputs.scenario)
        report = inputs.options.progress

        def progress(step_time: float) -> None:
            if report is not None:
                report(self.name, round(100 * step_time), 100, {})

        try:
            solve = inputs.scenario.solve
            run = run_ccx(scratch, JOB, solve.threads, solve.time_limit_s, progress)
        except SolverError as exc:
            raise SolverError(f"{exc}; the deck and its log are kept in {scratch}") from None
        prints = read_node_prints(scratch / f"{JOB}.dat")
        moved, force, bottom_force = model.forces(prints, prepared)
        return Compaction(
            scratch=scratch,
            press_mm=moved,
            force_n=force,
            bottom_force_n=bottom_force,
            wall_time_s=run.wall_time_s,
        )

    def write(self, result: Compaction, folder: Path, inputs: StageInputs) -> StageOutput:
        try:
            files = _write_results(result, folder, inputs.options.figures)
        finally:
            shutil.rmtree(result.scratch, ignore_errors=True)
        summary = {
            "increments": len(result.force_n),
            "press_mm": round(float(result.press_mm[-1]), 6),
            "force_n": round(float(result.force_n[-1]), 3),
            "conveyor_force_n": round(float(result.bottom_force_n[-1]), 3),
            "solver_wall_time_s": round(result.wall_time_s, 2),
            "files": sorted(files),
        }
        summary.update(solve_model(inputs.scenario).summary(folder / f"{JOB}.vtu", inputs))
        return StageOutput(summary)

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


def _write_results(result: Compaction, folder: Path, figures: bool) -> list[str]:
    """The deck, the solver's log and .dat, the last increment as VTU, and the force
    against the press as CSV (and a figure)."""
    from chipstack.meshing.calculix import frd_to_vtu

    files = []
    for suffix in (".inp", ".dat", ".log"):
        shutil.copy(result.scratch / f"{JOB}{suffix}", folder / f"{JOB}{suffix}")
        files.append(f"{JOB}{suffix}")
    # What the deck includes (the mesh's part), so that the solve folder runs as is.
    for include in sorted(result.scratch.glob("*.inp")):
        if include.stem != JOB:
            shutil.copy(include, folder / include.name)
            files.append(include.name)
    written = frd_to_vtu(result.scratch / f"{JOB}.frd")
    vtus = sorted(p for p in written if p.suffix == ".vtu")
    if vtus:  # the final state; one file per increment would be hundreds of MB
        shutil.copy(vtus[-1], folder / f"{JOB}.vtu")
        files.append(f"{JOB}.vtu")
    with open(folder / "force_displacement.csv", "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["press_mm", "platen_force_n", "conveyor_force_n"])
        for row in zip(result.press_mm, result.force_n, result.bottom_force_n, strict=True):
            writer.writerow([f"{v:.9g}" for v in row])
    files.append("force_displacement.csv")
    if figures:
        from chipstack.export.figure_kinds import draw_figures

        files += draw_figures("compaction", folder, result)
    return files
