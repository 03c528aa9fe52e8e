"""The mesh stage: the meshes the ``[mesh]`` table asks for, checked, in ``mesh/``."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from chipstack.core.errors import InputError, printable
from chipstack.core.lazy import named
from chipstack.core.schema import Scenario
from chipstack.core.stages import Stage, StageInputs, StageOptions, StageOutput
from chipstack.meshing.formats import MESH_FORMATS
from chipstack.meshing.kinds import MESH_CHOICE, MESH_KINDS
from chipstack.meshing.sections import MeshSpec
from chipstack.packing.kinds import stack_kinds

# The meshers, checks and writers (meshing.meshers) are named, imported when a stack is
# first meshed: every command-line start registers this stage, and they bring numpy,
# scipy, manifold3d and gmsh (~1 s).
if TYPE_CHECKING:
    from chipstack.meshing.meshers import MeshedStack


__all__ = ["MeshStage", "STAGE", "check_formats"]


class MeshStage(Stage):
    """Voxel hexahedra, conformal or image (CGAL) tetrahedra of the final stack, with checks."""

    name = "mesh"
    progress_label = "meshing"
    upstream = ("packing",)
    # Not [solve]: the compaction deck is the solve model's (a press changed is not a
    # new mesh).
    sections = ("geometry", "mesh")
    owned_sections = (MeshSpec,)
    kind_choices = {"mesh": MESH_CHOICE}  # [mesh]: the mesh kind's own keys
    kinds = property(lambda self: stack_kinds())  # the kinds whose stack goes on
    in_ensembles = False

    def check(self, scenario: Scenario) -> None:
        spec = scenario.mesh
        check_formats(spec.formats, "mesh.formats")
        # A combined kind takes the keys of each of its kinds; the periodic ties need
        # every one of them to take them.
        if getattr(spec, "periodic", False) and not all(k.takes("periodic") for k in spec.chosen):
            able = [n for n in MESH_KINDS.names() if MESH_KINDS.get(n).takes("periodic")]
            raise InputError(
                f"mesh.periodic: the {', '.join(able)} mesh only (mesh.kind is {spec.kind!r}: "
                "its opposite sides do not match node for node)"
            )

    def check_run(self, scenario: Scenario) -> None:
        """A mesher that is not installed (the image kind's pygalmesh) is refused before
        the packing stage starts, not after it."""
        for kind in scenario.mesh.chosen:
            kind.check_available()

    def key_extra(self, scenario: Scenario, options: StageOptions) -> dict[str, Any]:
        versions = {kind.name: kind.version for kind in scenario.mesh.chosen}
        return {"figures": options.figures, "algorithms": versions}

    def compute(self, inputs: StageInputs) -> MeshedStack:
        return named("chipstack.meshing.meshers:mesh_stack")(inputs, self.name)

    def write(self, result: MeshedStack, folder: Path, inputs: StageInputs) -> StageOutput:
        return named("chipstack.meshing.meshers:write_meshes")(result, folder, inputs)

    def load(self, folder: Path, scenario: Scenario) -> MeshFiles:
        """The mesh files written, by kind (downstream stages read the files)."""
        files = {
            kind: sorted(p.name for p in folder.glob(f"stack_{kind}.*"))
            for kind in (k.name for k in scenario.mesh.chosen)
        }
        return MeshFiles(folder, files)

    def report(self, summary: Mapping[str, Any], folder: Path) -> list[str]:
        lines = []
        for kind, m in summary.items():
            if "error" in m:
                lines.append(f"{kind} mesh: not written (see the warning above)")
                continue
            lines += MESH_KINDS.get(kind).report(m)
        return lines


STAGE = MeshStage()


@dataclass(frozen=True)
class MeshFiles:
    """Where a mesh stage wrote its files, and their names by mesh kind."""

    folder: Path
    files: dict[str, list[str]]


def check_formats(formats: tuple[str, ...], key: str) -> None:
    """Refuse an empty list or an unknown mesh format, listing the valid ones."""
    valid = ", ".join(MESH_FORMATS.names())
    if not formats:
        raise InputError(f"{key}: give at least one format ({valid})")
    for name in formats:
        if name not in MESH_FORMATS:
            raise InputError(
                f"{key}: unknown mesh format {printable(name)!r}; valid formats: {valid}"
            )
