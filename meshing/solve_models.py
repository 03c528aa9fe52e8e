"""Solve models, registered by name: what the solve stage can press in CalculiX.

A solve model takes the files one mesh kind wrote (:mod:`meshing.kinds`, whose
``solve_models`` name it), writes the compaction deck in the solver's folder, and reads
the platen forces back from the solver's node prints. The solve stage picks the first
model of the scenario's mesh kinds that accepts the scenario and knows none by name; a
new model is a subclass of :class:`SolveModel` and one ``SOLVE_MODELS.register`` call.
"""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path
from types import SimpleNamespace
from typing import TYPE_CHECKING, Any

from chipstack.core.errors import InputError
from chipstack.core.registry import Registry
from chipstack.core.schema import KindChoice, Parameters
from chipstack.meshing.sections import ContactPressKeys

if TYPE_CHECKING:
    import numpy as np

    from chipstack.core.schema import Scenario
    from chipstack.core.stages import StageInputs

__all__ = ["SolveModel", "SOLVE_MODELS", "SOLVE_CHOICE", "pressing_model", "solve_model"]

log = logging.getLogger(__name__)


class SolveModel:
    """One way of pressing a meshed stack (subclass and register in :data:`SOLVE_MODELS`)."""

    name: str = ""
    needs: str = ""  # what it needs, for the message when nothing accepts a scenario
    # Its own keys in [solve] (a core.schema.Parameters dataclass), beside the press's.
    parameters: type[Parameters] = Parameters

    def accepts(self, scenario: Scenario) -> bool:
        """Whether this model can press what ``[mesh]`` asks for."""
        raise NotImplementedError

    def check(self, scenario: Scenario) -> None:
        """Refuse, in one line, a scenario it accepts but cannot run (before any work)."""

    def prepare(self, mesh_folder: Path, scratch: Path, job: str, scenario: Scenario):
        """Write ``job.inp`` (and what it includes) in ``scratch``; returns what
        :meth:`forces` needs."""
        raise NotImplementedError

    def forces(self, prints: dict, prepared) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(press mm, top platen force N, conveyor force N) at each increment."""
        raise NotImplementedError

    def summary(self, vtu: Path, inputs: StageInputs) -> dict[str, Any]:
        """What the stage's summary adds for this model."""
        return {}


SOLVE_MODELS: Registry[SolveModel] = Registry("solve model", "chipstack.solve_models")


NO_SOLVE = "none"  # [solve]'s model when nothing presses the mesh


def pressing_model(tables) -> str:
    """The name of the model that presses the mesh ``tables["mesh"]`` asks for: the first
    of its kinds' models that accepts it, else :data:`NO_SOLVE`."""
    mesh = tables.get("mesh")
    if mesh is None:
        return NO_SOLVE
    for kind in mesh.chosen:
        for name in kind.solve_models:
            if SOLVE_MODELS.get(name).accepts(SimpleNamespace(mesh=mesh)):
                return name
    return NO_SOLVE


def _resolve(name: str, key: str) -> SolveModel | None:
    return None if name == NO_SOLVE else SOLVE_MODELS.get(name, key=key)


# How [solve] gets its model's keys: the model follows from [mesh] (the solve stage
# declares it).
SOLVE_CHOICE = KindChoice(
    "solve model",
    lambda: [*SOLVE_MODELS.in_order(), NO_SOLVE],
    _resolve,
    lambda model: Parameters if model is None else getattr(model, "parameters", Parameters),
    follows=pressing_model,
)


def solve_model(scenario: Scenario) -> SolveModel:
    """The model that presses the scenario's mesh (``solve.chosen``, resolved when the
    scenario was made); refused in one line when none can."""
    if scenario.solve.chosen is not None:
        return scenario.solve.chosen
    needs = " or ".join(SOLVE_MODELS.get(n).needs for n in SOLVE_MODELS.in_order())
    raise InputError(
        f"--to solve: needs {needs}; mesh.kind is {scenario.mesh.kind!r}, "
        f"mesh.pore_space {getattr(scenario.mesh, 'pore_space', 'none')!r}"
    )


class ContactPress(SolveModel):
    """The contact model's own deck: chips, contact pairs and rigid platens."""

    name = "contact"
    needs = "the contact model (mesh.kind = 'contact')"
    parameters = ContactPressKeys

    def accepts(self, scenario):
        return any(self.name in kind.solve_models for kind in scenario.mesh.chosen)

    def prepare(self, mesh_folder, scratch, job, scenario):
        from chipstack.meshing.calculix_deck import write_contact_compaction
        from chipstack.meshing.contact_model import load_contact_model

        shutil.copy(mesh_folder / "stack_contact.inp", scratch / "stack_contact.inp")
        model = load_contact_model(mesh_folder / "stack_contact_model.npz")
        write_contact_compaction(scratch / f"{job}.inp", "stack_contact.inp", model, scenario.solve)
        return None

    def forces(self, prints, prepared):
        top, bottom = prints["REF_TOP"], prints["REF_BOTTOM"]  # the platens' reference nodes
        return -top["displacements"][:, 2], -top["forces"][:, 2], bottom["forces"][:, 2]

    def summary(self, vtu, inputs):
        return contact_summary(vtu, inputs)


class VolumePress(SolveModel):
    """A box-shaped volume (voxel, image or conformal mesh), pore space and all, between
    whole-face platens: a crop of the stack, or the whole stack in the box over its
    footprint."""

    name = "volume"
    needs = (
        "a box-shaped volume (mesh.kind = 'voxel', 'image' or 'conformal', mesh.pore_space = 'box')"
    )

    @staticmethod
    def stem(scenario) -> str:
        """The files of the first of the scenario's mesh kinds that this model presses."""
        kind = next(k for k in scenario.mesh.chosen if "volume" in k.solve_models)
        return f"stack_{kind.name}"

    def accepts(self, scenario):
        spec = scenario.mesh
        pressable = any(self.name in kind.solve_models for kind in spec.chosen)
        return pressable and getattr(spec, "pore_space", "none") == "box"

    def check(self, scenario):
        if "inp" not in scenario.mesh.formats:
            raise InputError(
                "--to solve: the volume is solved from its .inp; add inp to mesh.formats"
            )

    def prepare(self, mesh_folder, scratch, job, scenario):
        from chipstack.meshing.calculix_deck import write_volume_compaction

        stem = self.stem(scenario)
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

    def forces(self, prints, press):
        # The faces' forces summed; the press ramps with the step time.
        top, bottom = prints["TOP"], prints["BOTTOM"]
        return press * top["time"], -top["forces"][:, 2], bottom["forces"][:, 2]


def contact_summary(vtu: Path, inputs: StageInputs) -> dict[str, Any]:
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
    owner = chip_of_node(inputs, solved.points)
    touched = np.unique(owner[(pressure > 0) & (owner >= 0)])
    return {
        "chips_in_contact": int(len(touched)),
        "contact_pressure_max_mpa": round(float(pressure.max(initial=0.0)), 4),
    }


def chip_of_node(inputs: StageInputs, points: np.ndarray) -> np.ndarray:
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


for _model in (ContactPress(), VolumePress()):
    SOLVE_MODELS.register(_model.name, _model)
