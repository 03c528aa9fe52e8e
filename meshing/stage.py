"""The mesh stage: the meshes the ``[mesh]`` table asks for, checked, in ``mesh/``."""

from __future__ import annotations

import json
import logging
import shutil
import tempfile
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from core.errors import InputError, printable
from core.schema import Scenario
from core.stages import Stage, StageInputs, StageOptions, StageOutput

# The meshers, checks and writers are imported where used: every command-line start
# registers this stage, and they bring numpy, scipy, manifold3d and gmsh (~1 s).
if TYPE_CHECKING:
    from geometry.arrangement import Arrangement
    from meshing.contact_model import ContactModel
    from meshing.mesh import VolumeMesh

__all__ = ["MeshStage", "STAGE", "MESH_KINDS", "check_formats"]

log = logging.getLogger(__name__)

MESH_KINDS = {
    "voxel": ("voxel",),
    "conformal": ("conformal",),
    "both": ("voxel", "conformal"),
    "contact": ("contact",),
}
NATIVE_FORMATS = {"conformal": ("msh",)}  # written by the mesher itself, physical groups and all


@dataclass
class MeshedStack:
    """The checked meshes of one stack, by kind; a failed kind carries its error."""

    meshes: dict[str, VolumeMesh] = field(default_factory=dict)
    reports: dict[str, dict[str, Any]] = field(default_factory=dict)
    errors: dict[str, str] = field(default_factory=dict)
    native: dict[str, Path] = field(default_factory=dict)  # files the mesher wrote (scratch)
    scratch: tempfile.TemporaryDirectory | None = None
    contact: ContactModel | None = None  # the contact model, when asked for
    resolution: Any = None  # the conformal mesh's contact resolution (geometry.resolve)


class MeshStage(Stage):
    """Voxel hexahedra and/or conformal tetrahedra of the final stack, with checks."""

    name = "mesh"
    progress_label = "meshing"
    upstream = ("packing",)
    sections = ("geometry", "mesh", "solve")  # the contact model's deck holds the step
    in_ensembles = False

    def check(self, scenario: Scenario) -> None:
        spec = scenario.mesh
        check_formats(spec.formats, "mesh.formats")
        if spec.crop == "region" and not spec.region_mm:
            raise InputError(
                "mesh.region_mm: give [x_min, x_max, y_min, y_max] with mesh.crop = 'region'"
            )
        if spec.region_mm and spec.crop != "region":
            raise InputError(
                f"mesh.region_mm: read only with mesh.crop = 'region' (it is {spec.crop!r})"
            )
        if spec.crop != "none" and spec.kind != "voxel":
            raise InputError(f"mesh.crop: the voxel mesh only so far (mesh.kind is {spec.kind!r})")
        if spec.periodic and (spec.crop == "none" or spec.pore_space != "box"):
            raise InputError(
                "mesh.periodic: needs a crop (mesh.crop) and mesh.pore_space = 'box', so "
                "that opposite sides are full faces whose nodes match"
            )

    def key_extra(self, scenario: Scenario, options: StageOptions) -> dict[str, Any]:
        return {"figures": options.figures}

    def compute(self, inputs: StageInputs) -> MeshedStack:
        import numpy as np

        from geometry.arrangement import stack_history
        from geometry.contacts import KINDS, find_contacts
        from geometry.resolve import UnresolvedError
        from meshing.checks import assert_valid, check_mesh, split_warning
        from meshing.conformal import MeshingError
        from meshing.contact_model import contact_model

        arrangement = stack_history(inputs.result("packing"))[-1]
        spec, g = inputs.scenario.mesh, inputs.scenario.geometry
        if spec.kind == "contact":
            if inputs.options.progress is not None:
                inputs.options.progress(self.name, 0, 1, {"mesh": "contact"})
            model = contact_model(
                arrangement,
                spec.element_mm,
                spec.through_thickness,
                spec.contact_gap_mm,
                g.layer_mm,
            )
            mesh = contact_volume_mesh(model, arrangement)
            return MeshedStack(
                meshes={"contact": mesh},
                reports={"contact": check_contact_model(model, mesh, arrangement)},
                contact=model,
            )
        table = find_contacts(arrangement, g.contact_gap_mm, g.contact_extent_mm)
        chips = table.chip_b >= 0
        checked = chips & (table.kind == KINDS.index("surface"))
        if (region := crop_region(inputs.scenario)) is not None:
            # A crop keeps the contacts whose patch lies inside it, two voxels clear of
            # its sides (a patch the crop cuts to a sliver may keep no whole voxel face).
            x0, x1, y0, y1 = region
            margin = 2 * spec.voxel_mm
            x, y = table.centre_mm[:, 0], table.centre_mm[:, 1]
            checked &= (x > x0 + margin) & (x < x1 - margin)
            checked &= (y > y0 + margin) & (y < y1 - margin)
        surface_pairs = np.column_stack([table.chip_a, table.chip_b])[checked]
        result = MeshedStack(scratch=tempfile.TemporaryDirectory(prefix="chipstack-mesh-"))
        kinds = MESH_KINDS[spec.kind]
        report = inputs.options.progress
        for done, kind in enumerate(kinds):
            if report is not None:
                report(self.name, done, len(kinds), {"mesh": kind})
            try:
                mesh = self._mesh(kind, arrangement, inputs.scenario, result)
            except (MeshingError, UnresolvedError) as exc:
                if len(kinds) == 1:
                    raise
                # Both were asked for: the voxel mesh stands; the failure is reported.
                log.warning("%s", exc)
                result.errors[kind] = str(exc)
                continue
            meshed, pairs = arrangement, surface_pairs
            if result.resolution is not None and kind == "conformal":
                # Surface contacts the resolution could not make coplanar were cleared by
                # the gap (counted in its report); the others must share faces.
                meshed = result.resolution.arrangement
                cleared = {frozenset(p) for p in result.resolution.surface_cleared}
                pairs = np.array(
                    [p for p in surface_pairs.tolist() if frozenset(p) not in cleared]
                ).reshape(-1, 2)
            checks = check_mesh(
                mesh,
                meshed,
                pairs,
                spec.min_quality if kind == "conformal" else 0.99,
                chip_tolerance=_volume_tolerance(kind, arrangement, spec.voxel_mm),
                region_mm=mesh.info.get("region_mm"),
            )
            assert_valid(checks)
            if (warning := split_warning(checks, kind)) is not None:
                log.warning("%s", warning)
            result.meshes[kind], result.reports[kind] = mesh, checks
        if report is not None:
            report(self.name, len(kinds), len(kinds), {})
        return result

    @staticmethod
    def _mesh(kind: str, arrangement: Arrangement, scenario: Scenario, result: MeshedStack):
        from meshing.conformal import conformal_mesh
        from meshing.voxel import voxel_mesh

        spec, layer_mm = scenario.mesh, scenario.geometry.layer_mm
        if kind == "voxel":
            _check_voxel_size(spec.voxel_mm, arrangement)
            region = crop_region(scenario)
            return voxel_mesh(
                arrangement, spec.voxel_mm, spec.pore_space, layer_mm, region, spec.periodic
            )
        from geometry.resolve import resolve_contacts

        msh = None
        if "msh" in spec.formats:
            msh = result.native[kind] = Path(result.scratch.name) / f"stack_{kind}.msh"
        g = scenario.geometry
        # The mesh-ready arrangement: the settled one is left as it is (descriptors and
        # the voxel mesh keep the physics' poses).
        resolution = resolve_contacts(
            arrangement,
            spec.gap_mm,
            spec.snap_angle_deg,
            contact_gap_mm=g.contact_gap_mm,
            contact_extent_mm=g.contact_extent_mm,
        )
        result.resolution = resolution
        mesh = conformal_mesh(
            resolution.arrangement,
            spec.size_mm,
            spec.pore_space,
            layer_mm,
            spec.min_quality,
            msh_path=msh,
        )
        info = dict(mesh.info)
        info["resolution"] = resolution.summary()
        info["mesh_time_s"] = round(info["mesh_time_s"] + resolution.seconds, 3)
        return type(mesh)(**{**mesh.__dict__, "info": info})

    def write(self, result: MeshedStack, folder: Path, inputs: StageInputs) -> StageOutput:
        if result.contact is not None:
            return StageOutput({"contact": _write_contact(folder, result, inputs)})
        try:
            summary = {kind: {"error": error} for kind, error in result.errors.items()}
            for kind, mesh in result.meshes.items():
                summary[kind] = _write_kind(folder, kind, mesh, result, inputs)
        finally:
            if result.scratch is not None:
                result.scratch.cleanup()
        return StageOutput(summary)

    def load(self, folder: Path, scenario: Scenario) -> MeshFiles:
        """The mesh files written, by kind (downstream stages read the files)."""
        files = {
            kind: sorted(p.name for p in folder.glob(f"stack_{kind}.*"))
            for kind in MESH_KINDS[scenario.mesh.kind]
        }
        return MeshFiles(folder, files)

    def report(self, summary: Mapping[str, Any], folder: Path) -> list[str]:
        lines = []
        for kind, m in summary.items():
            if kind == "contact":
                lines.append(
                    f"contact model: {m['chips']} chips, {m['elements']:,} {m['element']} "
                    f"elements, {m['chip_pairs']} chip pairs, {m['floor_chips']} chips on the "
                    f"conveyor; overlaps cleared by moving chips at most {m['max_move_mm']:.3f} mm"
                )
                continue
            if "error" in m:
                lines.append(f"{kind} mesh: not written (see the warning above)")
                continue
            lines.append(
                f"{kind} mesh: {m['elements']:,} elements, {m['nodes']:,} nodes, quality min "
                f"{m['quality_min']:.3f}, largest chip volume error "
                f"{100 * m['chip_volume_error_max']:.2f} %; in {m['info']['mesh_time_s']:.1f} s"
            )
            if (r := m["info"].get("resolution")) is not None:
                lines.append(
                    f"  contact resolution: chips moved at most {r['max_translation_mm']:.3f} mm "
                    f"and {r['max_rotation_deg']:.2f} deg; {r['snapped_chip_chip']} chip and "
                    f"{r['snapped_conveyor']} conveyor surface contacts made coplanar, "
                    f"{r['pairs_cleared']} near pairs cleared to {r['gap_mm']:g} mm, "
                    f"{r['surface_contacts_cleared']} surface contacts cleared instead of snapped"
                )
            if m.get("chips_in_pieces_count"):
                lines[-1] += f"; NOT VALID: {m['chips_in_pieces_count']} chips in pieces"
        return lines


STAGE = MeshStage()


@dataclass(frozen=True)
class MeshFiles:
    """Where a mesh stage wrote its files, and their names by mesh kind."""

    folder: Path
    files: dict[str, list[str]]


def check_contact_model(
    model: ContactModel, mesh: VolumeMesh, arrangement: Arrangement
) -> dict[str, Any]:
    """Every element (``mesh``: the model's chips) has positive volume, every chip's
    meshed volume is its exact volume, and every chip has an outer surface."""
    import numpy as np

    volumes = mesh.element_volumes()
    exact = np.array([s.volume_mm3 for s in arrangement.shapes])[arrangement.shape_index]
    meshed = np.bincount(model.chip, weights=volumes, minlength=model.n_chips)
    error = np.abs(meshed - exact) / exact
    faces = np.array([len(f) for f in model.surfaces])
    report = {
        "elements": int(model.n_elements),
        "nodes": int(len(model.points)),
        "volume_min_mm3": float(volumes.min()),
        "chip_volume_error_max": float(error.max()),
        "surface_faces_min": int(faces.min()),
        "max_move_mm": model.info["max_move_mm"],
        "chips_moved_apart": model.info["chips_moved_apart"],
    }
    problems = []
    if volumes.min() <= 0:
        problems.append(f"{int((volumes <= 0).sum())} elements with non-positive volume")
    if error.max() > 1e-6:
        problems.append(
            f"chip {int(error.argmax())} meshed volume off by {100 * error.max():.3g} %"
        )
    report["valid"] = not problems
    report["problems"] = problems
    return report


def contact_volume_mesh(model: ContactModel, arrangement: Arrangement) -> VolumeMesh:
    """The chips of a contact model as a :class:`VolumeMesh` (for checks and files)."""
    import numpy as np

    from meshing.mesh import VolumeMesh, element_attributes

    n = len(model.cells)
    attributes = element_attributes(arrangement, model.chip, 2.0)
    return VolumeMesh(
        points=model.points,
        cell_type="hexahedron",
        cells=model.cells,  # C3D8 and VTK_HEXAHEDRON share the node order
        chip=model.chip,
        quality=np.ones(n),
        node_sets={},
        n_chips=model.n_chips,
        kind="contact",
        info=dict(model.info),
        **attributes,
    )


def _write_contact(folder: Path, result: MeshedStack, inputs: StageInputs) -> dict[str, Any]:
    """The CalculiX deck, a VTU of the chips and the check report; the manifest entry."""
    from export.calculix import press_mm, write_contact_deck
    from export.mesh_files import write_mesh
    from meshing.conformal import MeshingError

    model = result.contact
    spec = inputs.scenario.mesh
    write_contact_deck(folder / "stack_contact.inp", model, inputs.scenario.solve, spec.element)
    files = ["stack_contact.inp"]
    chips = result.meshes["contact"]  # built and checked in compute
    files += [p.name for p in write_mesh(folder, "stack_contact", chips, ["vtu"])]
    report = result.reports["contact"]
    (folder / "stack_contact_checks.json").write_text(json.dumps(report, indent=2) + "\n")
    files.append("stack_contact_checks.json")
    if not report["valid"]:
        raise MeshingError(f"contact model: {'; '.join(report['problems'])}")
    return {
        "chips": model.n_chips,
        "elements": model.n_elements,
        "element": spec.element,
        "nodes": len(model.points),
        "chip_pairs": len(model.pairs),
        "floor_chips": len(model.floor_chips),
        "height_mm": round(model.height_mm, 4),
        "press_mm": round(press_mm(model, inputs.scenario.solve), 4),
        "max_move_mm": round(model.info["max_move_mm"], 5),
        "info": model.info,
        "files": sorted(files),
    }


def crop_region(scenario: Scenario) -> tuple[float, float, float, float] | None:
    """The crop of ``[mesh]`` as (x_min, x_max, y_min, y_max) mm, or None."""
    spec = scenario.mesh
    if spec.crop == "target":
        half = scenario.deposition.target_size_mm / 2
        return (-half, half, -half, half)
    if spec.crop == "region":
        x0, x1, y0, y1 = spec.region_mm
        return (x0, x1, y0, y1)
    return None


def _check_voxel_size(voxel_mm: float, arrangement: Arrangement) -> None:
    """A voxel as thick as a chip samples it once through its thickness: tilted chips
    fall apart into pieces joined at edges (half the reference stack at 2 mm)."""
    thinnest = min(2 * float(min(s.half_extents)) for s in arrangement.shapes)
    if voxel_mm >= thinnest:
        raise InputError(
            f"mesh.voxel_mm: {voxel_mm:g} mm is not below the thinnest chip dimension "
            f"({thinnest:g} mm); use at most {thinnest / 2:g} mm (2 voxels through a chip)"
        )


def check_formats(formats: tuple[str, ...], key: str) -> None:
    """Refuse an empty list or an unknown mesh format, listing the valid ones."""
    from export.mesh_files import MESH_FORMATS  # numpy: when a scenario is checked

    valid = ", ".join(MESH_FORMATS.names())
    if not formats:
        raise InputError(f"{key}: give at least one format ({valid})")
    for name in formats:
        if name not in MESH_FORMATS:
            raise InputError(
                f"{key}: unknown mesh format {printable(name)!r}; valid formats: {valid}"
            )


def _volume_tolerance(kind: str, arrangement: Arrangement, voxel_mm: float) -> float:
    """How far a chip's meshed volume may stray from its exact solid (fraction)."""
    if kind != "voxel":
        return 0.02
    # Voxel centres alias on plates tilted at rational slopes: a chip can gain or lose a
    # fraction of a voxel layer through its thickness (measured: 2.6 % for a 2 mm plate
    # tilted 14 deg at 0.5 mm voxels). Allow a quarter of a layer.
    thinnest = min(s.thickness_mm for s in arrangement.shapes)
    return max(0.02, 0.25 * voxel_mm / thinnest)


def _write_kind(folder: Path, kind: str, mesh: VolumeMesh, result: MeshedStack, inputs) -> dict:
    """One mesh's files, picture and check report; returns its manifest entry."""
    from export.mesh_files import write_mesh

    stem = f"stack_{kind}"
    spec = inputs.scenario.mesh
    native = [f for f in NATIVE_FORMATS.get(kind, ()) if f in spec.formats]
    formats = [f for f in spec.formats if f not in native]
    files = [p.name for p in write_mesh(folder, stem, mesh, formats)]
    for name in native:
        shutil.move(result.native[kind], folder / f"{stem}.{name}")
        files.append(f"{stem}.{name}")
    if inputs.options.figures:
        from export.run_figures import mesh_figure  # pyvista only when drawing

        files += mesh_figure(folder / f"{stem}.png", mesh)
    report = result.reports[kind]
    (folder / f"{stem}_checks.json").write_text(json.dumps(report, indent=2) + "\n")
    files.append(f"{stem}_checks.json")
    return {
        "elements": mesh.n_elements,
        "nodes": len(mesh.points),
        "quality_min": round(report["quality_min"], 4),
        "quality_p1": round(report["quality_p1"], 4),
        "chip_volume_error_max": report["chip_volume_error_max"],
        "total_volume_error": report["total_volume_error"],
        "chips_in_pieces_count": report["chips_in_pieces_count"],
        "valid": report["valid"],
        "info": mesh.info,
        "files": sorted(files),
    }
