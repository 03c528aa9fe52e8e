"""Solve models, registered by name: what the solve stage can press, and how.

A solve model takes the files one mesh kind wrote (:mod:`meshing.kinds`, whose
``solve_models`` name it) and presses them. The CalculiX models (``contact``,
``volume``) write the compaction deck in the solver's folder and read the platen forces
back from the solver's node prints; the loose press (``loose``,
:mod:`meshing.loose.model`) runs its own Incremental Potential Contact solver. The solve
stage picks the first model of the scenario's mesh kinds that accepts the scenario and
knows none by name; a new model is a subclass of :class:`SolveModel` and one
``SOLVE_MODELS.register`` call.
"""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace
from typing import TYPE_CHECKING, Any

from chipstack.core.errors import InputError
from chipstack.core.lazy import named
from chipstack.core.registry import Registry
from chipstack.core.schema import KindChoice, Parameters
from chipstack.meshing.sections import ContactPressKeys

if TYPE_CHECKING:
    import numpy as np

    from chipstack.core.schema import Scenario
    from chipstack.core.stages import StageInputs, StageOutput

__all__ = ["SolveModel", "SOLVE_MODELS", "SOLVE_CHOICE", "pressing_model", "solve_model"]


class SolveModel:
    """One way of pressing a meshed stack (subclass and register in :data:`SOLVE_MODELS`)."""

    name: str = ""
    needs: str = ""  # what it needs, for the message when nothing accepts a scenario
    solver: str = "CalculiX"  # what presses, for the stage's report
    # Its own keys in [solve] (a core.schema.Parameters dataclass), beside the press's.
    parameters: type[Parameters] = Parameters

    def accepts(self, scenario: Scenario) -> bool:
        """Whether this model can press what ``[mesh]`` asks for."""
        raise NotImplementedError

    def check(self, scenario: Scenario) -> None:
        """Refuse, in one line, a scenario it accepts but cannot run (before any work)."""

    def check_run(self, scenario: Scenario) -> None:
        """Refuse, in one line, to start when its solver is missing (CalculiX's ``ccx``)."""
        named("chipstack.meshing.calculix:ccx_path")()

    def compute(self, inputs: StageInputs, stage: str) -> Any:
        """Press the mesh stage's files (CalculiX on the deck :meth:`prepare` writes);
        ``stage``: the name progress is reported under."""
        return named("chipstack.meshing.compaction:compact")(inputs, stage)

    def write(self, result: Any, folder: Path, inputs: StageInputs) -> StageOutput:
        """The press's files in ``folder`` and the stage's summary."""
        return named("chipstack.meshing.compaction:write_compaction")(result, folder, inputs)

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
    each = [SOLVE_MODELS.get(n).needs for n in SOLVE_MODELS.in_order()]
    needs = each[0] if len(each) == 1 else f"{', '.join(each[:-1])} or {each[-1]}"
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
        deck = named("chipstack.meshing.compaction:prepare_contact_deck")
        return deck(mesh_folder, scratch, job, scenario)

    def forces(self, prints, prepared):
        top, bottom = prints["REF_TOP"], prints["REF_BOTTOM"]  # the platens' reference nodes
        return -top["displacements"][:, 2], -top["forces"][:, 2], bottom["forces"][:, 2]

    def summary(self, vtu, inputs):
        return named("chipstack.meshing.compaction:contact_summary")(vtu, inputs)


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
        deck = named("chipstack.meshing.compaction:prepare_volume_deck")
        return deck(self.stem(scenario), mesh_folder, scratch, job, scenario)

    def forces(self, prints, press):
        # The faces' forces summed; the press ramps with the step time.
        top, bottom = prints["TOP"], prints["BOTTOM"]
        return press * top["time"], -top["forces"][:, 2], bottom["forces"][:, 2]


for _model in (ContactPress(), VolumePress()):
    SOLVE_MODELS.register(_model.name, _model)
SOLVE_MODELS.register_named("loose", "chipstack.meshing.loose.model:LOOSE_PRESS")
