"""The mesh stage's work: the meshes a scenario asks for, each built, checked and written
by its kind's mesher.

:mod:`meshing.kinds` declares the kinds (their keys, what they can do), light enough for
every command-line start; each declaration names its mesher here (``mesher =
"chipstack.meshing.meshers:VOXEL_MESHER"``), imported when a stack is first meshed, so
this module imports the meshers and numerical libraries at the top.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from chipstack.core.arrangement import stack_history
from chipstack.core.stages import StageInputs, StageOutput
from chipstack.export.figure_kinds import MeshPicture, draw_figures
from chipstack.geometry.contacts import KINDS, find_contacts
from chipstack.meshing.boundaries import side_node_sets
from chipstack.meshing.calculix_deck import write_contact_mesh
from chipstack.meshing.checks import check_volume, surface_report
from chipstack.meshing.conformal import chips_near, conformal_mesh
from chipstack.meshing.contact_model import ContactModel, contact_model, save_contact_model
from chipstack.meshing.files import write_mesh
from chipstack.meshing.image import image_mesh
from chipstack.meshing.interfaces import find_interfaces, write_interface_table
from chipstack.meshing.kinds import Built, crop_region, pore_gap_mm
from chipstack.meshing.mesh import (
    MeshingError,
    VolumeMesh,
    check_voxel_below_thinnest,
    element_attributes,
)
from chipstack.meshing.resolution import (
    UnresolvedError,
    check_settings,
    resolve_chips,
    resolve_contacts,
)
from chipstack.meshing.voxel import voxel_mesh

if TYPE_CHECKING:
    from chipstack.core.arrangement import Arrangement
    from chipstack.core.schema import Scenario
    from chipstack.meshing.kinds import MeshKind

__all__ = [
    "mesh_stack",
    "write_meshes",
    "MeshedStack",
    "contact_classes",
    "surface_pairs",
    "Mesher",
    "VoxelMesher",
    "ConformalMesher",
    "ImageMesher",
    "ContactMesher",
    "write_volume_mesh",
    "DEFAULT_MESHER",
    "VOXEL_MESHER",
    "CONFORMAL_MESHER",
    "IMAGE_MESHER",
    "CONTACT_MESHER",
]

# The warnings keep the loggers they had before the work moved here from the stage and
# the kinds' declarations (a user's logging filters name them).
log = logging.getLogger(__name__)


@dataclass
class MeshedStack:
    """The checked meshes of one stack, by kind (:mod:`meshing.kinds`); a failed kind
    carries its error."""

    built: dict[str, Built] = field(default_factory=dict)
    reports: dict[str, dict[str, Any]] = field(default_factory=dict)
    errors: dict[str, str] = field(default_factory=dict)
    scratch: tempfile.TemporaryDirectory | None = None


def mesh_stack(inputs: StageInputs, stage: str) -> MeshedStack:
    """The meshes the scenario's ``[mesh]`` asks for, of the settled stack, each checked
    (``stage``: the name progress is reported under)."""
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

    def pairs() -> np.ndarray:
        return surface_pairs(contacts(), scenario)

    report = inputs.options.progress
    for done, kind in enumerate(kinds):
        if report is not None:
            report(stage, done, len(kinds), {"mesh": kind.name})
        try:
            built = kind.build(arrangement, scenario, Path(result.scratch.name))
        except kind.failures as exc:
            if len(kinds) == 1:
                raise
            # Several were asked for: the others stand; the failure is reported.
            log.warning("%s", exc)
            result.errors[kind.name] = str(exc)
            continue
        result.reports[kind.name] = kind.check(built, arrangement, scenario, pairs)
        built.extra["contact_classes"] = contact_classes(contacts())
        result.built[kind.name] = built
    if report is not None:
        report(stage, len(kinds), len(kinds), {})
    return result


def write_meshes(result: MeshedStack, folder: Path, inputs: StageInputs) -> StageOutput:
    """Each kind's files in ``folder`` (the scratch folder removed); the summary."""
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


def contact_classes(table) -> dict[tuple[int, int], str]:
    """(lower chip, upper chip) -> the contact's class (point, line, surface) for every
    pair of chips in contact (``table``: ``geometry.contacts.find_contacts``)."""
    out = {}
    rows = zip(table.chip_a.tolist(), table.chip_b.tolist(), table.kind.tolist(), strict=True)
    for a, b, kind in rows:
        if a >= 0 and b >= 0:
            out[min(a, b), max(a, b)] = KINDS[kind]
    return out


def surface_pairs(table, scenario: Scenario) -> np.ndarray:
    """(k, 2) the chip pairs in surface contact (``table``: the stack's contacts), whose
    meshes must share faces; a crop keeps those whose patch lies inside it, clear of its
    sides by each mesh kind's ``crop_margin_mm``."""

    checked = (table.chip_b >= 0) & (table.kind == KINDS.index("surface"))
    if (region := crop_region(scenario)) is not None:
        x0, x1, y0, y1 = region
        margin = max(kind.crop_margin_mm(scenario.mesh) for kind in scenario.mesh.chosen)
        x, y = table.centre_mm[:, 0], table.centre_mm[:, 1]
        checked &= (x > x0 + margin) & (x < x1 - margin)
        checked &= (y > y0 + margin) & (y < y1 - margin)
    return np.column_stack([table.chip_a, table.chip_b])[checked]


class Mesher:
    """What a mesh kind does (its declaration, :class:`meshing.kinds.MeshKind`, names
    a subclass by ``mesher``); every method is given the declaration as ``kind``."""

    # Errors that mean "this stack cannot be meshed this way" (a one-line message);
    # with mesh.kind = "both" the other kind's mesh still stands.
    failures: tuple[type[Exception], ...] = ()

    def build(self, kind: MeshKind, arrangement, scenario, scratch: Path):
        raise NotImplementedError

    def check(self, kind: MeshKind, built, arrangement, scenario, surface_pairs) -> dict:
        raise NotImplementedError

    def write(self, kind: MeshKind, folder: Path, built, report: dict, inputs) -> dict:
        return write_volume_mesh(folder, kind.name, built, report, inputs)


class VoxelMesher(Mesher):
    """The voxel mesh kind's work (:class:`meshing.kinds.VoxelKind`)."""

    def build(self, kind, arrangement, scenario, scratch):
        spec = scenario.mesh
        check_voxel_below_thinnest("mesh.voxel_mm", spec.voxel_mm, arrangement, 2)
        mesh = voxel_mesh(
            arrangement,
            spec.voxel_mm,
            spec.pore_space,
            scenario.geometry.layer_mm,
            crop_region(scenario),
            spec.periodic,
        )
        return Built(mesh)

    def check(self, kind, built, arrangement, scenario, surface_pairs):
        # Voxel centres alias on plates tilted at rational slopes: a chip can gain or lose
        # a fraction of a voxel layer through its thickness (measured: 2.6 % for a 2 mm
        # plate tilted 14 deg at 0.5 mm voxels). Allow a quarter of a layer.
        thinnest = min(s.thickness_mm for s in arrangement.shapes)
        tolerance = max(0.02, 0.25 * scenario.mesh.voxel_mm / thinnest)
        return check_volume(built.mesh, arrangement, surface_pairs(), 0.99, tolerance, kind.name)


class ConformalMesher(Mesher):
    """The conformal mesh kind's work (:class:`meshing.kinds.ConformalKind`)."""

    failures = (MeshingError, UnresolvedError)

    def build(self, kind, arrangement, scenario, scratch):
        spec, g = scenario.mesh, scenario.geometry
        # The .msh is written like every kind's (meshing.files): a physical volume per
        # chip and the pore space, the sides, and a physical surface per interface; the
        # gmsh session's own file knows no interfaces.
        region = crop_region(scenario)
        gap_key, gap = "mesh.gap_mm", spec.gap_mm
        if spec.pore_space != "none":
            gap_key, gap = "mesh.pore_gap_mm", pore_gap_mm(spec, arrangement)
        settings = dict(
            gap_mm=gap,
            snap_angle_deg=spec.snap_angle_deg,
            contact_gap_mm=g.contact_gap_mm,
            contact_extent_mm=g.contact_extent_mm,
        )
        # Before any work, naming the key the gap came from (the resolution checks again,
        # for callers of the library, with the default key).
        check_settings(gap, spec.snap_angle_deg, arrangement.thinnest_mm, gap_key)

        def resolve_and_mesh(touching_lines: bool):
            # The mesh-ready arrangement: the settled one is left as it is (descriptors
            # and the voxel mesh keep the physics' poses). A crop resolves only the chips
            # that can reach into it.
            if region is None:
                resolution = resolve_contacts(
                    arrangement, **settings, touching_lines=touching_lines
                )
            else:
                resolution = resolve_chips(
                    arrangement,
                    chips_near(arrangement, region),
                    **settings,
                    touching_lines=touching_lines,
                )
            mesh = conformal_mesh(
                resolution.arrangement,
                spec.size_mm,
                spec.pore_space,
                g.layer_mm,
                spec.min_quality,
                region_mm=region,
                pore_size_mm=spec.pore_size_mm,
            )
            return resolution, mesh

        # Without the pore space nothing is meshed between chips, so line contacts stay
        # touching (their class kept); with it they are cleared by the gap, which no pore
        # element could fill. Two chips laid within 0.2 um of each other can still make
        # the mesh fail (paper-rectangles, seed 0): then they are cleared as well.
        fell_back = None
        if spec.pore_space == "none":
            try:
                resolution, mesh = resolve_and_mesh(True)
            except (MeshingError, UnresolvedError) as exc:
                fell_back = str(exc)
                resolution, mesh = resolve_and_mesh(False)
                # Said once it worked: when it fails too, its error is the one line.
                log.warning(
                    "conformal mesh with line contacts touching failed (%s); they were "
                    "cleared by the gap instead",
                    exc,
                )
        else:
            resolution, mesh = resolve_and_mesh(False)
        info = dict(mesh.info)
        info["resolution"] = resolution.summary()
        if fell_back is not None:
            info["resolution"]["touching_lines_failed"] = fell_back
        info["mesh_time_s"] = round(info["mesh_time_s"] + resolution.seconds, 3)
        mesh = dataclasses.replace(mesh, info=info)
        return Built(mesh, {}, {"resolution": resolution})

    def check(self, kind, built, arrangement, scenario, surface_pairs):
        # Surface contacts the resolution could not make coplanar were cleared by the
        # gap (counted in its report); the others must share faces.
        resolution = built.extra["resolution"]
        cleared = {frozenset(p) for p in resolution.surface_cleared}
        pairs = np.array(
            [p for p in surface_pairs().tolist() if frozenset(p) not in cleared]
        ).reshape(-1, 2)
        return check_volume(
            built.mesh,
            resolution.arrangement,
            pairs,
            scenario.mesh.min_quality,
            0.02,
            kind.name,
        )


class ImageMesher(Mesher):
    """The image mesh kind's work (:class:`meshing.kinds.ImageKind`)."""

    failures = (MeshingError,)

    def build(self, kind, arrangement, scenario, scratch):
        spec = scenario.mesh
        mesh = image_mesh(
            arrangement,
            spec.image_voxel_mm,
            spec.size_mm,
            spec.pore_space,
            scenario.geometry.layer_mm,
            spec.image_optimise,
            seed=scenario.seed,
            region_mm=crop_region(scenario),
            improve=spec.image_improve,
        )
        return Built(mesh)

    def check(self, kind, built, arrangement, scenario, surface_pairs):
        # The chips' faces lie within half a voxel of the exact ones: a chip's volume is
        # held to 4 % (measured on the reference stack at 0.25 mm voxels: at most 1.1 %).
        # Without the sliver removal only inverted elements are refused (Mesh_3 leaves
        # slivers it cannot exude); with it every element is held to min_quality.
        spec = scenario.mesh
        floor = spec.min_quality if spec.image_improve else 0.0
        return check_volume(built.mesh, arrangement, surface_pairs(), floor, 0.04, kind.name)


class ContactMesher(Mesher):
    """The contact mesh kind's work (:class:`meshing.kinds.ContactKind`)."""

    def build(self, kind, arrangement, scenario, scratch):
        spec = scenario.mesh
        model = contact_model(
            arrangement,
            spec.element_mm,
            spec.through_thickness,
            spec.contact_gap_mm,
            scenario.geometry.layer_mm,
        )
        return Built(contact_volume_mesh(model, arrangement), extra={"model": model})

    def check(self, kind, built, arrangement, scenario, surface_pairs):
        return check_contact_model(built.extra["model"], built.mesh, arrangement)

    def write(self, kind, folder, built, report, inputs):
        stem = f"stack_{kind.name}"  # the contact press's model, or the loose press's
        return write_contact(folder, built.extra["model"], built.mesh, report, inputs, stem)


def write_volume_mesh(
    folder: Path, kind: str, built: Built, report: dict, inputs: StageInputs
) -> dict[str, Any]:
    """A volume mesh's files, picture and check report; returns its manifest entry."""
    stem = f"stack_{kind}"
    spec = inputs.scenario.mesh
    native = [f for f in built.native if f in spec.formats]
    formats = [f for f in spec.formats if f not in native]
    files = [p.name for p in write_mesh(folder, stem, built.mesh, formats)]
    for name in native:
        shutil.move(built.native[name], folder / f"{stem}.{name}")
        files.append(f"{stem}.{name}")
    if inputs.options.figures:
        # meshing.files (imported above) registers the mesh's figure.
        files += draw_figures("mesh", folder, MeshPicture(stem, built.mesh))
    report = {**report, "surfaces": surface_report(built.mesh)}
    (folder / f"{stem}_checks.json").write_text(json.dumps(report, indent=2) + "\n")
    files.append(f"{stem}_checks.json")
    table = folder / f"{stem}_interfaces.csv"
    # A crop holds some chips only: the contacts of chips it left out are not its own.
    present = set(np.unique(built.mesh.chip).tolist())
    contacts = {
        pair: kind
        for pair, kind in (built.extra.get("contact_classes") or {}).items()
        if pair[0] in present and pair[1] in present
    }
    write_interface_table(table, find_interfaces(built.mesh), contacts)
    files.append(table.name)
    mesh = built.mesh
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


def check_contact_model(
    model: ContactModel, mesh: VolumeMesh, arrangement: Arrangement
) -> dict[str, Any]:
    """Every element (``mesh``: the model's chips) has positive volume, every chip's
    meshed volume is its exact volume, and every chip has an outer surface."""
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
    n = len(model.cells)
    attributes = element_attributes(arrangement, model.chip, 2.0)
    # The chips' own nodes (the platens' come after them): the conveyor plane is the
    # bottom platen's face, and a chip resting on it may stand off by up to the gap.
    used = np.unique(model.cells)
    sides = side_node_sets(model.points[used])
    sides["bottom"] = used[model.points[used, 2] <= model.bottom.z_mm + max(model.gap_mm, 1e-6)]
    return VolumeMesh(
        points=model.points,
        cell_type="hexahedron",
        cells=model.cells,  # C3D8 and VTK_HEXAHEDRON share the node order
        chip=model.chip,
        quality=np.ones(n),
        node_sets={
            name: used[nodes] if name != "bottom" else nodes for name, nodes in sides.items()
        },
        n_chips=model.n_chips,
        kind="contact",
        info=dict(model.info),
        **attributes,
    )


def write_contact(
    folder: Path,
    model: ContactModel,
    chips: VolumeMesh,
    report: dict,
    inputs: StageInputs,
    stem: str = "stack_contact",
) -> dict[str, Any]:
    """The model's mesh part for CalculiX (the solve stage includes it in the compaction
    deck it writes from ``[solve]``), the model's arrays, a VTU of the chips and the
    check report; the manifest entry."""
    spec = inputs.scenario.mesh
    write_contact_mesh(folder / f"{stem}.inp", model, spec.element, chips.surfaces)
    save_contact_model(folder / f"{stem}_model.npz", model)
    files = [f"{stem}.inp", f"{stem}_model.npz"]
    # The .inp is the deck part above (chips and platens), the other formats the chips;
    # the .vtu always (the solve stage maps its result's nodes to chips through it).
    formats = ["vtu", *(name for name in spec.formats if name not in ("inp", "vtu"))]
    files += [p.name for p in write_mesh(folder, stem, chips, formats)]
    report = {**report, "surfaces": surface_report(chips)}
    (folder / f"{stem}_checks.json").write_text(json.dumps(report, indent=2) + "\n")
    files.append(f"{stem}_checks.json")
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
        "max_move_mm": round(model.info["max_move_mm"], 5),
        "info": model.info,
        "files": sorted(files),
    }


# The meshers the built-in kinds name (stateless: one each), and the one a kind that
# names none writes its volume mesh with.
DEFAULT_MESHER = Mesher()
VOXEL_MESHER = VoxelMesher()
CONFORMAL_MESHER = ConformalMesher()
IMAGE_MESHER = ImageMesher()
CONTACT_MESHER = ContactMesher()
