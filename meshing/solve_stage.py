"""The solve stage: CalculiX runs the compaction of the contact model, or of a cropped voxel
volume between whole-face platens; the results come back as VTU for ParaView, the platen
force against the press as CSV and a figure."""

from __future__ import annotations

import csv
import json
import logging
import shutil
import tempfile
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from core.errors import InputError
from core.schema import Scenario
from core.stages import Stage, StageInputs, StageOutput

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
    in_ensembles = False

    def check_run(self, scenario: Scenario) -> None:
        spec = scenario.mesh
        volume = spec.kind == "voxel" and spec.crop != "none" and spec.pore_space == "box"
        if spec.kind != "contact" and not volume:
            raise InputError(
                "--to solve: needs the contact model (mesh.kind = 'contact') or a cropped "
                "voxel volume (mesh.kind = 'voxel', mesh.crop, mesh.pore_space = 'box'); "
                f"mesh.kind is {spec.kind!r}"
            )
        if volume and "inp" not in spec.formats:
            raise InputError(
                "--to solve: the voxel volume is solved from its .inp; add inp to mesh.formats"
            )
        from meshing.calculix import ccx_path

        ccx_path()

    def compute(self, inputs: StageInputs) -> Compaction:
        from export.calculix import write_volume_compaction
        from meshing.calculix import SolverError, read_node_prints, run_ccx

        mesh = inputs.result("mesh")
        scratch = Path(tempfile.mkdtemp(prefix="chipstack-solve-"))
        solve = inputs.scenario.solve
        if inputs.scenario.mesh.kind == "contact":
            shutil.copy(mesh.folder / "stack_contact.inp", scratch / f"{JOB}.inp")
            press = None
        else:
            shutil.copy(mesh.folder / "stack_voxel.inp", scratch / "stack_voxel.inp")
            checks = json.loads((mesh.folder / "stack_voxel_checks.json").read_text())
            low, high = checks["bounds_mm"]
            press = write_volume_compaction(
                scratch / f"{JOB}.inp", "stack_voxel.inp", high[2] - low[2], solve,
                inputs.scenario.mesh.periodic,
            )  # fmt: skip
        report = inputs.options.progress

        def progress(step_time: float) -> None:
            if report is not None:
                report(self.name, round(100 * step_time), 100, {})

        try:
            run = run_ccx(scratch, JOB, solve.threads, solve.time_limit_s, progress)
        except SolverError as exc:
            raise SolverError(f"{exc}; the deck and its log are kept in {scratch}") from None
        prints = read_node_prints(scratch / f"{JOB}.dat")
        if press is None:  # the contact model: its platens' reference nodes
            top, bottom = prints["REF_TOP"], prints["REF_BOTTOM"]
            moved = -top["displacements"][:, 2]
        else:  # a volume: the faces' forces summed; the press ramps with the step time
            top, bottom = prints["TOP"], prints["BOTTOM"]
            moved = press * top["time"]
        return Compaction(
            scratch=scratch,
            press_mm=moved,
            force_n=-top["forces"][:, 2],
            bottom_force_n=bottom["forces"][:, 2],
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
        if inputs.scenario.mesh.kind == "contact":
            summary.update(_contact_summary(folder / f"{JOB}.vtu", inputs))
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
    from meshing.calculix import frd_to_vtu

    files = []
    for suffix in (".inp", ".dat", ".log"):
        shutil.copy(result.scratch / f"{JOB}{suffix}", folder / f"{JOB}{suffix}")
        files.append(f"{JOB}{suffix}")
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
        from export.figures import plot_force_displacement  # matplotlib only when drawing

        plot_force_displacement(folder / "force_displacement.png", result.press_mm, result.force_n)
        files.append("force_displacement.png")
    return files


def _contact_summary(vtu: Path, inputs: StageInputs) -> dict[str, Any]:
    """How many chips carry contact pressure at the end of the press, and the largest
    pressure (MPa). CalculiX writes the contact state at slave nodes, which are chip
    nodes: COPEN, CSLIP1, CSLIP2, CPRESS, CSHEAR1, CSHEAR2."""
    import meshio
    import numpy as np

    if not vtu.is_file():
        return {"chips_in_contact": 0, "contact_pressure_max_mpa": 0.0}
    solved = meshio.read(vtu)
    contact = solved.point_data.get("CONTACT")
    if contact is None or np.ndim(contact) != 2 or contact.shape[1] < 4:
        return {"chips_in_contact": 0, "contact_pressure_max_mpa": 0.0}
    pressure = np.asarray(contact)[:, 3]
    owner = _chip_of_node(inputs, solved.points)
    touched = np.unique(owner[(pressure > 0) & (owner >= 0)])
    return {
        "chips_in_contact": int(len(touched)),
        "contact_pressure_max_mpa": round(float(pressure.max(initial=0.0)), 4),
    }


def _chip_of_node(inputs: StageInputs, points: np.ndarray) -> np.ndarray:
    """(N,) the chip of every node of the solved mesh (-1: platens). The converter keeps
    the deck's node order, chips first; the coordinates are checked to be sure."""
    import meshio
    import numpy as np

    model = meshio.read(inputs.result("mesh").folder / "stack_contact.vtu")
    cells = model.cells[0].data
    chip = np.asarray(model.cell_data["chip"][0])
    n = int(cells.max()) + 1  # the chips' nodes come first in the deck
    owner = np.full(len(points), -1)
    if len(points) < n or not np.allclose(points[:n], model.points[:n], rtol=1e-4, atol=1e-3):
        log.warning("solve: the result's nodes are not the model's; no contact count")
        return owner
    owner[cells.ravel()] = np.repeat(chip, cells.shape[1])
    return owner
