"""Mesh kinds, registered by name: what ``mesh.kind`` may ask for.

A mesh kind is one object: it builds its mesh of the settled stack, checks it, writes
its files and says in a line or two what it wrote. The mesh stage loops over the kinds a
scenario asks for and knows none of them by name; a new kind is a subclass of
:class:`MeshKind` and one ``MESH_KINDS.register`` call. Each kind also names the solve
models (:mod:`meshing.solve_models`) that can run on what it writes.

Heavy modules (numpy, gmsh, the meshers) are imported inside the methods: every
command-line start imports this registry.
"""

from __future__ import annotations

import json
import logging
import shutil
from dataclasses import dataclass, field, fields, make_dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from chipstack.core.errors import InputError, printable
from chipstack.core.registry import Registry
from chipstack.core.schema import KindChoice, Parameters
from chipstack.meshing.sections import ConformalKeys, ContactKeys, ImageKeys, VoxelKeys

if TYPE_CHECKING:
    from collections.abc import Callable

    import numpy as np

    from chipstack.core.arrangement import Arrangement
    from chipstack.core.schema import Scenario
    from chipstack.core.stages import StageInputs
    from chipstack.meshing.contact_model import ContactModel
    from chipstack.meshing.mesh import VolumeMesh

__all__ = [
    "Built",
    "MeshKind",
    "MESH_KINDS",
    "MESH_CHOICE",
    "COMBINED",
    "check_volume",
    "mesh_kinds",
]

log = logging.getLogger(__name__)

# Names of ``mesh.kind`` that stand for several kinds, built in this order.
COMBINED = {"both": ("voxel", "conformal")}


@dataclass
class Built:
    """What a kind built: its mesh (as a :class:`VolumeMesh`, for checks and files), files
    its mesher wrote itself (format -> scratch path), and what else it keeps for
    ``write`` (a contact resolution, a contact model)."""

    mesh: VolumeMesh
    native: dict[str, Path] = field(default_factory=dict)
    extra: dict[str, Any] = field(default_factory=dict)


class MeshKind:
    """One mesher of the settled stack (subclass and register in :data:`MESH_KINDS`)."""

    name: str = ""
    doc: str = ""
    # Its own keys in [mesh] (a core.schema.Parameters dataclass): read there when
    # mesh.kind names it, refused when it does not.
    parameters: type[Parameters] = Parameters
    crop_shift_mm: float = 0.0  # how far it may move a crop's sides (clear of chip corners)
    # Part of the mesh stage's cache key: raise it when the kind's algorithm gives another
    # mesh for the same keys, so that run directories made before remesh instead of
    # reusing the old mesh.
    version: int = 1
    solve_models: tuple[str, ...] = ()  # names in meshing.solve_models.SOLVE_MODELS
    # Errors of the mesher that mean "this stack cannot be meshed this way" (a one-line
    # message); with mesh.kind = "both" the other kind's mesh still stands.
    failures: tuple[type[Exception], ...] = ()

    def crop_margin_mm(self, spec) -> float:
        """How far inside a crop's sides a surface contact must lie for its two chips'
        meshes to be held to shared faces (a patch the crop cuts to a sliver may keep
        none): a millimetre, plus how far the kind moves the sides."""
        return 1.0 + self.crop_shift_mm

    def takes(self, key: str) -> bool:
        """Whether ``mesh.<key>`` is one of its own keys (``takes("crop")``: it crops)."""
        return any(f.name == key for f in fields(getattr(self, "parameters", Parameters)))

    def check_available(self) -> None:
        """Refuse, before any work, a kind whose mesher is not installed (``InputError``
        naming what installs it)."""

    def build(self, arrangement: Arrangement, scenario: Scenario, scratch: Path) -> Built:
        raise NotImplementedError

    def check(
        self,
        built: Built,
        arrangement: Arrangement,
        scenario: Scenario,
        surface_pairs: Callable[[], np.ndarray],
    ) -> dict[str, Any]:
        """The check report (``"valid"`` among its keys); raise when it is not valid."""
        raise NotImplementedError

    def write(self, folder: Path, built: Built, report: dict, inputs: StageInputs) -> dict:
        """The kind's files in ``folder``; returns its manifest entry."""
        return write_volume_mesh(folder, self.name, built, report, inputs)

    def report(self, summary: dict[str, Any]) -> list[str]:
        """Lines for the run's report, from the manifest entry."""
        return [
            f"{self.name} mesh: {summary['elements']:,} elements, {summary['nodes']:,} nodes, "
            f"quality min {summary['quality_min']:.3f}, largest chip volume error "
            f"{100 * summary['chip_volume_error_max']:.2f} %; in "
            f"{summary['info']['mesh_time_s']:.1f} s"
            + (
                f"; NOT VALID: {summary['chips_in_pieces_count']} chips in pieces"
                if summary.get("chips_in_pieces_count")
                else ""
            )
        ]


MESH_KINDS: Registry[MeshKind] = Registry("mesh kind", "chipstack.mesh_kinds")


def mesh_kinds(name: str, key: str = "mesh.kind") -> list[MeshKind]:
    """The kinds ``mesh.kind = name`` builds, in order; an unknown name is refused with
    the valid ones listed."""
    if name in COMBINED:
        return [MESH_KINDS.get(n) for n in COMBINED[name]]
    if name not in MESH_KINDS:
        valid = ", ".join([*MESH_KINDS.names(), *COMBINED])
        raise InputError(f"{key}: unknown mesh kind {printable(name)!r}; valid kinds: {valid}")
    return [MESH_KINDS.get(name)]


def write_volume_mesh(
    folder: Path, kind: str, built: Built, report: dict, inputs: StageInputs
) -> dict[str, Any]:
    """A volume mesh's files, picture and check report; returns its manifest entry."""
    from chipstack.meshing.files import write_mesh

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
        from chipstack.export.figure_kinds import MeshPicture, draw_figures

        files += draw_figures("mesh", folder, MeshPicture(stem, built.mesh))
    (folder / f"{stem}_checks.json").write_text(json.dumps(report, indent=2) + "\n")
    files.append(f"{stem}_checks.json")
    from chipstack.meshing.interfaces import find_interfaces, write_interface_table

    table = folder / f"{stem}_interfaces.csv"
    write_interface_table(table, find_interfaces(built.mesh), built.extra.get("contact_classes"))
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


def check_volume(mesh, arrangement, pairs, min_quality, tolerance, kind) -> dict[str, Any]:
    """The check report of a volume mesh of the stack (``meshing.checks.check_mesh``),
    raising when it is not valid: what a kind's ``check`` returns. ``pairs``: the chip
    pairs in surface contact, whose meshes must share faces; ``tolerance``: the largest
    accepted relative error of a chip's volume; ``kind``: the kind's name, for the log."""
    import logging

    from chipstack.meshing.checks import assert_valid, check_mesh, split_warning

    report = check_mesh(
        mesh,
        arrangement,
        pairs,
        min_quality,
        chip_tolerance=tolerance,
        region_mm=mesh.info.get("region_mm"),
    )
    assert_valid(report)
    if (warning := split_warning(report, kind)) is not None:
        logging.getLogger("chipstack.meshing.stage").warning("%s", warning)
    return report


class VoxelKind(MeshKind):
    name = "voxel"
    parameters = VoxelKeys

    doc = "hexahedra from the exact voxel image (always succeeds)"
    solve_models = ("volume",)

    def crop_margin_mm(self, spec) -> float:
        return 2 * spec.voxel_mm  # two voxels: a cut patch keeps a whole voxel face

    def build(self, arrangement, scenario, scratch):
        from chipstack.meshing.mesh import check_voxel_below_thinnest
        from chipstack.meshing.voxel import voxel_mesh

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

    def check(self, built, arrangement, scenario, surface_pairs):
        # Voxel centres alias on plates tilted at rational slopes: a chip can gain or lose
        # a fraction of a voxel layer through its thickness (measured: 2.6 % for a 2 mm
        # plate tilted 14 deg at 0.5 mm voxels). Allow a quarter of a layer.
        thinnest = min(s.thickness_mm for s in arrangement.shapes)
        tolerance = max(0.02, 0.25 * scenario.mesh.voxel_mm / thinnest)
        return check_volume(built.mesh, arrangement, surface_pairs(), 0.99, tolerance, self.name)


class ConformalKind(MeshKind):
    name = "conformal"
    parameters = ConformalKeys
    # 2: line contacts kept touching for a mesh of the chips alone; with the pore space,
    # the clearance mesh.pore_gap_mm. 3: crop sides off shallow faces and concave chips'
    # notches, grading toward corners near the box's planes, the sliver fallback keeping
    # holes empty. 4: the whole stack's box sides clear of the corners, HXT optimising
    # the elements under 0.2.
    version = 4
    solve_models = ("volume",)
    doc = "gmsh tetrahedra of the resolved arrangement, touching chips sharing faces"

    @property
    def crop_shift_mm(self) -> float:
        from chipstack.meshing.conformal import CROP_SHIFT_MM

        return CROP_SHIFT_MM

    @property
    def failures(self):
        from chipstack.meshing.conformal import MeshingError
        from chipstack.meshing.resolution import UnresolvedError

        return (MeshingError, UnresolvedError)

    def build(self, arrangement, scenario, scratch):
        from chipstack.meshing.conformal import MeshingError, chips_near, conformal_mesh
        from chipstack.meshing.resolution import (
            UnresolvedError,
            check_settings,
            resolve_chips,
            resolve_contacts,
        )

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
        mesh = type(mesh)(**{**mesh.__dict__, "info": info})
        return Built(mesh, {}, {"resolution": resolution})

    def check(self, built, arrangement, scenario, surface_pairs):
        import numpy as np

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
            self.name,
        )

    def report(self, summary):
        lines = super().report(summary)
        if (r := summary["info"].get("resolution")) is not None:
            lines.insert(
                1,
                f"  contact resolution: chips moved at most {r['max_translation_mm']:.3f} mm "
                f"and {r['max_rotation_deg']:.2f} deg; {r['snapped_chip_chip']} chip and "
                f"{r['snapped_conveyor']} conveyor surface contacts made coplanar, "
                f"{r['pairs_cleared']} near pairs cleared to {r['gap_mm']:g} mm, "
                f"{r['surface_contacts_cleared']} surface contacts cleared instead of snapped",
            )
        return lines


class ImageKind(MeshKind):
    name = "image"
    parameters = ImageKeys
    doc = (
        "CGAL Mesh_3 tetrahedra of the labelled voxel image (any chip shape; needs "
        "pygalmesh), touching chips sharing faces"
    )
    solve_models = ("volume",)

    @property
    def failures(self):
        from chipstack.meshing.conformal import MeshingError

        return (MeshingError,)

    def check_available(self) -> None:
        from chipstack.meshing.image import require_cgal

        require_cgal()

    def build(self, arrangement, scenario, scratch):
        from chipstack.meshing.image import image_mesh

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

    def check(self, built, arrangement, scenario, surface_pairs):
        # The chips' faces lie within half a voxel of the exact ones: a chip's volume is
        # held to 4 % (measured on the reference stack at 0.25 mm voxels: at most 1.1 %).
        # Without the sliver removal only inverted elements are refused (Mesh_3 leaves
        # slivers it cannot exude); with it every element is held to min_quality.
        spec = scenario.mesh
        floor = spec.min_quality if spec.image_improve else 0.0
        return check_volume(built.mesh, arrangement, surface_pairs(), floor, 0.04, self.name)


class ContactKind(MeshKind):
    name = "contact"
    parameters = ContactKeys
    doc = (
        "every chip meshed on its own, contact pairs and rigid platens: the model the "
        "solve stage runs"
    )
    solve_models = ("contact",)

    def build(self, arrangement, scenario, scratch):
        from chipstack.meshing.contact_model import contact_model

        spec = scenario.mesh
        model = contact_model(
            arrangement,
            spec.element_mm,
            spec.through_thickness,
            spec.contact_gap_mm,
            scenario.geometry.layer_mm,
        )
        return Built(contact_volume_mesh(model, arrangement), extra={"model": model})

    def check(self, built, arrangement, scenario, surface_pairs):
        return check_contact_model(built.extra["model"], built.mesh, arrangement)

    def write(self, folder, built, report, inputs):
        return write_contact(folder, built.extra["model"], built.mesh, report, inputs)

    def report(self, m):
        return [
            f"contact model: {m['chips']} chips, {m['elements']:,} {m['element']} "
            f"elements, {m['chip_pairs']} chip pairs, {m['floor_chips']} chips on the "
            f"conveyor; overlaps cleared by moving chips at most {m['max_move_mm']:.3f} mm"
        ]


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

    from chipstack.meshing.mesh import VolumeMesh, element_attributes

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


def write_contact(
    folder: Path, model: ContactModel, chips: VolumeMesh, report: dict, inputs: StageInputs
) -> dict[str, Any]:
    """The model's mesh part for CalculiX (the solve stage includes it in the compaction
    deck it writes from ``[solve]``), the model's arrays, a VTU of the chips and the
    check report; the manifest entry."""
    from chipstack.meshing.calculix_deck import write_contact_mesh
    from chipstack.meshing.conformal import MeshingError
    from chipstack.meshing.contact_model import save_contact_model
    from chipstack.meshing.files import write_mesh

    spec = inputs.scenario.mesh
    write_contact_mesh(folder / "stack_contact.inp", model, spec.element)
    save_contact_model(folder / "stack_contact_model.npz", model)
    files = ["stack_contact.inp", "stack_contact_model.npz"]
    files += [p.name for p in write_mesh(folder, "stack_contact", chips, ["vtu"])]
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
        "max_move_mm": round(model.info["max_move_mm"], 5),
        "info": model.info,
        "files": sorted(files),
    }


def pore_gap_mm(spec, arrangement: Arrangement) -> float:
    """The contact resolution's clearance with the pore space (``mesh.pore_gap_mm``, or
    its default: a tenth of the thinnest chip dimension, the largest the resolution
    takes), mm.

    A pore slab between two chips is as thin as this, and elements of ``size_mm`` across
    it are slivers unless it is about a tenth of their size or more (the reference
    stack's middle 50 x 50 mm at 1.5 mm, seed 0: 274 elements below quality 0.1 at
    0.05 mm; at 0.15 mm, seeds 0, 2, 3 and 8 each left one to six elements between 0.05
    and 0.1 where such slabs meet a side or the top; at 0.2 mm none)."""
    if spec.pore_gap_mm > 0:
        return float(spec.pore_gap_mm)
    return float(arrangement.thinnest_mm / 10)


def crop_region(scenario: Scenario) -> tuple[float, float, float, float] | None:
    """The crop of ``[mesh]`` as (x_min, x_max, y_min, y_max) mm, or None."""
    spec = scenario.mesh
    crop = getattr(spec, "crop", "none")  # a kind without the key meshes the whole stack
    if crop == "target":
        half = scenario.deposition.target_size_mm / 2
        return (-half, half, -half, half)
    if crop == "region":
        x0, x1, y0, y1 = spec.region_mm
        return (x0, x1, y0, y1)
    return None


for _kind in (VoxelKind(), ConformalKind(), ImageKind(), ContactKind()):
    MESH_KINDS.register(_kind.name, _kind)


@dataclass(frozen=True)
class VoxelKeysAndConformalKeys(ConformalKeys, VoxelKeys):
    """The keys of ``both``: the voxel mesh's and the conformal mesh's (a class of this
    module, so that a scenario holding it pickles)."""


_UNIONS: dict[tuple[type, ...], type[Parameters]] = {
    (VoxelKeys, ConformalKeys): VoxelKeysAndConformalKeys
}


def _parameters(kinds: list[MeshKind]) -> type[Parameters]:
    """The keys of ``mesh.kind``: its kind's, or every one of a combined name's kinds'."""
    own = tuple(dict.fromkeys(getattr(kind, "parameters", Parameters) for kind in kinds))
    if len(own) == 1:
        return own[0]
    if own not in _UNIONS:  # one class per combination: tables made twice compare equal
        name = "And".join(cls.__name__ for cls in own)
        union = make_dataclass(name, [], bases=own[::-1], frozen=True)
        union.__module__ = __name__
        globals()[name] = union  # found by name: a scenario with it pickles
        _UNIONS[own] = union
    return _UNIONS[own]


# How [mesh] chooses its kinds (a combined name several): the mesh stage declares it.
MESH_CHOICE = KindChoice(
    "mesh kind", lambda: [*MESH_KINDS.in_order(), *COMBINED], mesh_kinds, _parameters
)
