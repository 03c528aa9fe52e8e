"""Mesh kinds, registered by name: what ``mesh.kind`` may ask for.

A mesh kind is one object: it builds its mesh of the settled stack, checks it, writes
its files and says in a line or two what it wrote. The mesh stage loops over the kinds a
scenario asks for and knows none of them by name; a new kind is a subclass of
:class:`MeshKind` and one ``MESH_KINDS.register`` call. Each kind also names the solve
models (:mod:`meshing.solve_models`) that can run on what it writes.

This module holds the declarations only (names, keys, what each kind can do): every
command-line start imports this registry. Each built-in kind names its mesher
(:mod:`meshing.meshers`, which imports numpy, scipy and the meshers at its top; gmsh
when a session opens), imported when a stack is first meshed.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, make_dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from chipstack.core.errors import InputError, printable
from chipstack.core.lazy import named
from chipstack.core.registry import Registry
from chipstack.core.schema import KindChoice, Parameters
from chipstack.meshing.sections import ConformalKeys, ContactKeys, ImageKeys, VoxelKeys

if TYPE_CHECKING:
    from collections.abc import Callable

    import numpy as np

    from chipstack.core.arrangement import Arrangement
    from chipstack.core.schema import Scenario
    from chipstack.core.stages import StageInputs
    from chipstack.meshing.mesh import VolumeMesh
    from chipstack.meshing.meshers import Mesher

__all__ = [
    "Built",
    "MeshKind",
    "MESH_KINDS",
    "MESH_CHOICE",
    "COMBINED",
    "CROP_SHIFT_MM",
    "mesh_kinds",
    "crop_region",
    "pore_gap_mm",
]

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
    # The "module:attribute" of its mesher (a meshing.meshers.Mesher), imported when a
    # stack is first meshed; a kind may instead override build, check and write itself.
    mesher: str = ""

    @property
    def work(self) -> Mesher:
        """Its mesher (a kind that names none writes with the default one)."""
        return named(self.mesher or "chipstack.meshing.meshers:DEFAULT_MESHER")

    # Errors of the mesher that mean "this stack cannot be meshed this way" (a one-line
    # message); with mesh.kind = "both" the other kind's mesh still stands. A kind with a
    # mesher reads them from it (meshing.meshers), when a stack is meshed.
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
        naming what installs it); checked on every run that meshes, so it must not import
        the mesher."""

    def build(self, arrangement: Arrangement, scenario: Scenario, scratch: Path) -> Built:
        """Its mesh of the settled ``arrangement`` (scratch: a folder for its files)."""
        return self.work.build(self, arrangement, scenario, scratch)

    def check(
        self,
        built: Built,
        arrangement: Arrangement,
        scenario: Scenario,
        surface_pairs: Callable[[], np.ndarray],
    ) -> dict[str, Any]:
        """The check report (``"valid"`` among its keys); raise when it is not valid."""
        return self.work.check(self, built, arrangement, scenario, surface_pairs)

    def write(self, folder: Path, built: Built, report: dict, inputs: StageInputs) -> dict:
        """The kind's files in ``folder``; returns its manifest entry (by default the
        volume mesh's files, picture, check report and interface table)."""
        return self.work.write(self, folder, built, report, inputs)

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


# How far a side of a conformal mesh's crop may move to clear the chips' corners, mm.
CROP_SHIFT_MM = 1.0


class VoxelKind(MeshKind):
    name = "voxel"
    parameters = VoxelKeys
    mesher = "chipstack.meshing.meshers:VOXEL_MESHER"
    doc = "hexahedra from the exact voxel image (always succeeds)"
    solve_models = ("volume",)

    def crop_margin_mm(self, spec) -> float:
        return 2 * spec.voxel_mm  # two voxels: a cut patch keeps a whole voxel face


class ConformalKind(MeshKind):
    name = "conformal"
    parameters = ConformalKeys
    mesher = "chipstack.meshing.meshers:CONFORMAL_MESHER"
    # 2: line contacts kept touching for a mesh of the chips alone; with the pore space,
    # the clearance mesh.pore_gap_mm. 3: crop sides off shallow faces and concave chips'
    # notches, grading toward corners near the box's planes, the sliver fallback keeping
    # holes empty. 4: the whole stack's box sides clear of the corners, HXT optimising
    # the elements under 0.2.
    version = 4
    solve_models = ("volume",)
    doc = "gmsh tetrahedra of the resolved arrangement, touching chips sharing faces"
    crop_shift_mm = CROP_SHIFT_MM

    @property
    def failures(self):
        return self.work.failures

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
    mesher = "chipstack.meshing.meshers:IMAGE_MESHER"
    doc = (
        "CGAL Mesh_3 tetrahedra of the labelled voxel image (any chip shape; needs "
        "pygalmesh), touching chips sharing faces"
    )
    solve_models = ("volume",)

    @property
    def failures(self):
        return self.work.failures

    def check_available(self) -> None:
        named("chipstack.meshing.image:require_cgal")()


class ContactKind(MeshKind):
    name = "contact"
    parameters = ContactKeys
    mesher = "chipstack.meshing.meshers:CONTACT_MESHER"
    doc = (
        "every chip meshed on its own, contact pairs and rigid platens: the model the "
        "solve stage runs"
    )
    solve_models = ("contact",)

    def report(self, m):
        return [
            f"contact model: {m['chips']} chips, {m['elements']:,} {m['element']} "
            f"elements, {m['chip_pairs']} chip pairs, {m['floor_chips']} chips on the "
            f"conveyor; overlaps cleared by moving chips at most {m['max_move_mm']:.3f} mm"
        ]


class LooseKind(ContactKind):
    """The contact model's chips (every chip its own block of bricks, overlaps cleared)
    for the loose press, which needs no contact pairs: its files are ``stack_loose.*``."""

    name = "loose"
    doc = (
        "every chip its own deformable body (the contact model's bricks) for the loose "
        "press: frictional contact by Incremental Potential Contact, no pairs to declare"
    )
    solve_models = ("loose",)

    def report(self, m):
        return [
            f"loose stack: {m['chips']} chips, {m['elements']:,} bricks, {m['nodes']:,} "
            f"nodes; overlaps cleared by moving chips at most {m['max_move_mm']:.3f} mm"
        ]


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


for _kind in (VoxelKind(), ConformalKind(), ImageKind(), ContactKind(), LooseKind()):
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
