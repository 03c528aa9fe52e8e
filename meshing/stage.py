"""The mesh stage: the meshes the ``[mesh]`` table asks for, checked, in ``mesh/``."""

from __future__ import annotations

import logging
import tempfile
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from chipstack.core.errors import InputError, printable
from chipstack.core.schema import Scenario
from chipstack.core.stages import Stage, StageInputs, StageOptions, StageOutput
from chipstack.meshing.kinds import MESH_CHOICE, MESH_KINDS, Built, crop_region
from chipstack.meshing.sections import MeshSpec
from chipstack.packing.kinds import stack_kinds

# The meshers, checks and writers are imported where used: every command-line start
# registers this stage, and they bring numpy, scipy, manifold3d and gmsh (~1 s).
if TYPE_CHECKING:
    import numpy as np


__all__ = ["MeshStage", "STAGE", "check_formats"]

log = logging.getLogger(__name__)


@dataclass
class MeshedStack:
    """The checked meshes of one stack, by kind (:mod:`meshing.kinds`); a failed kind
    carries its error."""

    built: dict[str, Built] = field(default_factory=dict)
    reports: dict[str, dict[str, Any]] = field(default_factory=dict)
    errors: dict[str, str] = field(default_factory=dict)
    scratch: tempfile.TemporaryDirectory | None = None


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
        from chipstack.core.arrangement import stack_history
        from chipstack.geometry.contacts import find_contacts

        arrangement = stack_history(inputs.result("packing"))[-1]
        scenario = inputs.scenario
        kinds = scenario.mesh.chosen
        result = MeshedStack(scratch=tempfile.TemporaryDirectory(prefix="chipstack-mesh-"))
        found: list = []

        def contacts():
            if not found:
                g = scenario.geometry
                found.append(find_contacts(arrangement, g.contact_gap_mm, g.contact_extent_mm))
            return found[0]

        def surface_pairs() -> np.ndarray:
            return _surface_pairs(contacts(), scenario)

        report = inputs.options.progress
        for done, kind in enumerate(kinds):
            if report is not None:
                report(self.name, done, len(kinds), {"mesh": kind.name})
            try:
                built = kind.build(arrangement, scenario, Path(result.scratch.name))
            except kind.failures as exc:
                if len(kinds) == 1:
                    raise
                # Several were asked for: the others stand; the failure is reported.
                log.warning("%s", exc)
                result.errors[kind.name] = str(exc)
                continue
            result.reports[kind.name] = kind.check(built, arrangement, scenario, surface_pairs)
            built.extra["contact_classes"] = contact_classes(contacts())
            result.built[kind.name] = built
        if report is not None:
            report(self.name, len(kinds), len(kinds), {})
        return result

    def write(self, result: MeshedStack, folder: Path, inputs: StageInputs) -> StageOutput:
        try:
            summary = {kind: {"error": error} for kind, error in result.errors.items()}
            for kind in inputs.scenario.mesh.chosen:
                if kind.name in result.built:
                    built, report = result.built[kind.name], result.reports[kind.name]
                    summary[kind.name] = kind.write(folder, built, report, inputs)
        finally:
            if result.scratch is not None:
                result.scratch.cleanup()
        return StageOutput(summary)

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
    from chipstack.meshing.formats import MESH_FORMATS

    valid = ", ".join(MESH_FORMATS.names())
    if not formats:
        raise InputError(f"{key}: give at least one format ({valid})")
    for name in formats:
        if name not in MESH_FORMATS:
            raise InputError(
                f"{key}: unknown mesh format {printable(name)!r}; valid formats: {valid}"
            )


def contact_classes(table) -> dict[tuple[int, int], str]:
    """(lower chip, upper chip) -> the contact's class (point, line, surface) for every
    pair of chips in contact (``table``: ``geometry.contacts.find_contacts``)."""
    from chipstack.geometry.contacts import KINDS

    out = {}
    rows = zip(table.chip_a.tolist(), table.chip_b.tolist(), table.kind.tolist(), strict=True)
    for a, b, kind in rows:
        if a >= 0 and b >= 0:
            out[min(a, b), max(a, b)] = KINDS[kind]
    return out


def _surface_pairs(table, scenario: Scenario) -> np.ndarray:
    """(k, 2) the chip pairs in surface contact (``table``: the stack's contacts), whose
    meshes must share faces; a crop keeps those whose patch lies inside it, clear of its
    sides by each mesh kind's ``crop_margin_mm``."""
    import numpy as np

    from chipstack.geometry.contacts import KINDS

    checked = (table.chip_b >= 0) & (table.kind == KINDS.index("surface"))
    if (region := crop_region(scenario)) is not None:
        x0, x1, y0, y1 = region
        margin = max(kind.crop_margin_mm(scenario.mesh) for kind in scenario.mesh.chosen)
        x, y = table.centre_mm[:, 0], table.centre_mm[:, 1]
        checked &= (x > x0 + margin) & (x < x1 - margin)
        checked &= (y > y0 + margin) & (y < y1 - margin)
    return np.column_stack([table.chip_a, table.chip_b])[checked]
