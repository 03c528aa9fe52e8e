"""The solve stage's work: CalculiX presses the mesh stage's model (the deck written by
the scenario's solve model, :mod:`meshing.solve_models`), and its forces and fields come
back as files.

:mod:`meshing.solve_stage` and :mod:`meshing.solve_models` declare the stage and the
models, light for every command-line start; they name what is here, imported when a
stack is first pressed, so this module imports the solver's driver, readers and writers
at its top.
"""

from __future__ import annotations

import csv
import json
import logging
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import meshio
import numpy as np

from chipstack.core.stages import StageInputs, StageOutput
from chipstack.export.figure_kinds import draw_figures
from chipstack.meshing.calculix import SolverError, frd_to_vtu, read_node_prints, run_ccx
from chipstack.meshing.calculix_deck import write_contact_compaction, write_volume_compaction
from chipstack.meshing.contact_model import load_contact_model
from chipstack.meshing.solve_models import solve_model

if TYPE_CHECKING:
    from chipstack.core.schema import Scenario

__all__ = [
    "JOB",
    "Compaction",
    "compact",
    "write_compaction",
    "prepare_contact_deck",
    "prepare_volume_deck",
    "contact_summary",
    "chip_of_node",
]

# The logger of the solve models, whose summary this is (a user's filters name it).
log = logging.getLogger(__name__)

JOB = "compaction"  # the deck's job name: compaction.inp, .dat, .frd, .vtu


@dataclass
class Compaction:
    """A solved compaction: the solver's folder (scratch), the press against the force,
    and the solver's wall time."""

    scratch: Path
    press_mm: np.ndarray  # (k,) top platen displacement down, at each increment
    force_n: np.ndarray  # (k,) force on the top platen (reaction, pressing down: positive)
    bottom_force_n: np.ndarray  # (k,) reaction at the conveyor
    wall_time_s: float


def compact(inputs: StageInputs, stage: str) -> Compaction:
    """The compaction the scenario's ``[solve]`` asks for, run by CalculiX on the mesh
    stage's files (``stage``: the name progress is reported under)."""
    mesh = inputs.result("mesh")
    scratch = Path(tempfile.mkdtemp(prefix="chipstack-solve-"))
    model = solve_model(inputs.scenario)
    prepared = model.prepare(mesh.folder, scratch, JOB, inputs.scenario)
    report = inputs.options.progress

    def progress(step_time: float) -> None:
        if report is not None:
            report(stage, round(100 * step_time), 100, {})

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


def write_compaction(result: Compaction, folder: Path, inputs: StageInputs) -> StageOutput:
    """The solve stage's files in ``folder`` (the scratch folder removed) and its summary."""
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


def _write_results(result: Compaction, folder: Path, figures: bool) -> list[str]:
    """The deck, the solver's log and .dat, the last increment as VTU, and the force
    against the press as CSV (and a figure)."""
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
        files += draw_figures("compaction", folder, result)
    return files


def prepare_contact_deck(mesh_folder: Path, scratch: Path, job: str, scenario: Scenario):
    """The contact press's deck ``job.inp`` in ``scratch``, including the contact
    model's mesh part (:class:`meshing.solve_models.ContactPress`)."""
    shutil.copy(mesh_folder / "stack_contact.inp", scratch / "stack_contact.inp")
    model = load_contact_model(mesh_folder / "stack_contact_model.npz")
    write_contact_compaction(scratch / f"{job}.inp", "stack_contact.inp", model, scenario.solve)
    return None


def prepare_volume_deck(
    stem: str, mesh_folder: Path, scratch: Path, job: str, scenario: Scenario
) -> float:
    """The volume press's deck ``job.inp`` in ``scratch``, including the volume mesh
    ``stem.inp`` (:class:`meshing.solve_models.VolumePress`); returns the press, mm."""
    shutil.copy(mesh_folder / f"{stem}.inp", scratch / f"{stem}.inp")
    checks = json.loads((mesh_folder / f"{stem}_checks.json").read_text())
    low, high = checks["bounds_mm"]
    return write_volume_compaction(
        scratch / f"{job}.inp",
        f"{stem}.inp",
        high[2] - low[2],
        scenario.solve,
        getattr(scenario.mesh, "periodic", False),
    )


def contact_summary(vtu: Path, inputs: StageInputs) -> dict[str, Any]:
    """How many chips carry contact pressure at the end of the press, and the largest
    pressure (MPa). CalculiX writes the contact state at slave nodes, which are chip
    nodes: COPEN, CSLIP1, CSLIP2, CPRESS, CSHEAR1, CSHEAR2."""
    if not vtu.is_file():
        return {"chips_in_contact": 0, "contact_pressure_max_mpa": 0.0}
    solved = meshio.read(vtu)
    contact = solved.point_data.get("CONTACT")
    if contact is None or np.ndim(contact) != 2 or contact.shape[1] < 4:
        return {"chips_in_contact": 0, "contact_pressure_max_mpa": 0.0}
    pressure = np.asarray(contact)[:, 3]
    owner = chip_of_node(inputs, solved.points)
    touched = np.unique(owner[(pressure > 0) & (owner >= 0)])
    return {
        "chips_in_contact": int(len(touched)),
        "contact_pressure_max_mpa": round(float(pressure.max(initial=0.0)), 4),
    }


def chip_of_node(inputs: StageInputs, points: np.ndarray) -> np.ndarray:
    """(N,) the chip of every node of the solved mesh (-1: platens). The converter keeps
    the deck's node order, chips first; the coordinates are checked to be sure."""
    model = meshio.read(inputs.result("mesh").folder / "stack_contact.vtu")
    cells = model.cells[0].data
    chip = np.asarray(model.cell_data["region"][0]) - 1  # region id: chip index + 1
    n = int(cells.max()) + 1  # the chips' nodes come first in the deck
    owner = np.full(len(points), -1)
    if len(points) < n or not np.allclose(points[:n], model.points[:n], rtol=1e-4, atol=1e-3):
        log.warning("solve: the result's nodes are not the model's; no contact count")
        return owner
    owner[cells.ravel()] = np.repeat(chip, cells.shape[1])
    return owner
