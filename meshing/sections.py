"""The scenario tables of the meshing package: ``[mesh]`` (the mesh stage) and ``[solve]``
(the solve stage) (see :mod:`packing.sections`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

from chipstack.core.errors import InputError
from chipstack.core.keys import between, key, one_of, region
from chipstack.core.schema import KindKeys, Parameters, Section

__all__ = [
    "ConformalKeys",
    "ContactKeys",
    "ContactPressKeys",
    "CropKeys",
    "ImageKeys",
    "MeshSpec",
    "SolveSpec",
    "TetrahedraKeys",
    "VoxelKeys",
]


@dataclass(frozen=True)
class CropKeys(Parameters):
    """The keys of the kinds that mesh the stack with or without its pore space, whole or
    cropped (voxel, conformal, image)."""

    pore_space: str = key(
        "none",
        "",
        "`box`: also mesh the pore space in the box over the chips from the conveyor to "
        "the top; `none`: chips only",
        one_of("none", "box"),
    )
    crop: str = key(
        "none",
        "",
        "`target` crops the mesh to the deposition target, `region` to `region_mm`; "
        "`none`: the whole stack",
        one_of("none", "target", "region"),
    )
    region_mm: tuple[float, ...] = key(
        (),
        "mm",
        "[x_min, x_max, y_min, y_max] of the crop with crop = 'region'",
        region,
    )

    def check(self, key: str) -> None:
        if self.crop == "region" and not self.region_mm:
            raise InputError(
                f"{key}.region_mm: give [x_min, x_max, y_min, y_max] with {key}.crop = 'region'"
            )
        if self.region_mm and self.crop != "region":
            raise InputError(
                f"{key}.region_mm: read only with {key}.crop = 'region' (it is {self.crop!r})"
            )


@dataclass(frozen=True)
class VoxelKeys(CropKeys):
    """The voxel mesh's keys."""

    voxel_mm: float = key(0.5, "mm", "voxel of the hexahedral mesh", between(0.05, 100.0))
    periodic: bool = key(
        False,
        "",
        "cropped with pore_space = 'box': tie each node of the xmax and ymax sides to its "
        "twin on the opposite side (*EQUATION in the .inp, reference nodes REF_X and REF_Y "
        "carry the jumps): a representative volume",
    )

    def check(self, key: str) -> None:
        super().check(key)
        if self.periodic and (self.crop == "none" or self.pore_space != "box"):
            raise InputError(
                f"{key}.periodic: needs a crop ({key}.crop) and {key}.pore_space = 'box', so "
                "that opposite sides are full faces whose nodes match"
            )


@dataclass(frozen=True)
class TetrahedraKeys(CropKeys):
    """The keys the tetrahedral meshes (conformal, image) share."""

    size_mm: float = key(1.5, "mm", "largest element edge", between(0.05, 100.0))
    min_quality: float = key(
        0.1,
        "",
        "smallest accepted element quality (SICN; the image mesh's with image_improve)",
        between(0, 1),
    )


@dataclass(frozen=True)
class ConformalKeys(TetrahedraKeys):
    """The conformal mesh's keys."""

    gap_mm: float = key(
        0.03,
        "mm",
        "contact resolution leaves chips that are not in surface contact at least this far "
        "apart (at most a tenth of the thinnest chip dimension)",
        between(1e-4, 10.0),
    )
    pore_gap_mm: float = key(
        0.0,
        "mm",
        "with the pore space: the clearance of the contact resolution in place of gap_mm, "
        "wide enough for pore elements between chips, about a tenth of size_mm or more "
        "(0: a tenth of the thinnest chip dimension, the largest allowed)",
        between(0.0, 10.0),
    )
    pore_size_mm: float = key(
        0.0,
        "mm",
        "with the pore space: largest element edge of the pore space away from the chips, "
        "graded from size_mm at their faces (0: four times size_mm; size_mm: no grading)",
        between(0.0, 100.0),
    )
    snap_angle_deg: float = key(
        3.0,
        "deg",
        "surface contacts whose faces are within this angle are made exactly coplanar and touching",
        between(0.0, 15.0),
    )


@dataclass(frozen=True)
class ImageKeys(TetrahedraKeys):
    """The image mesh's keys."""

    image_voxel_mm: float = key(
        0.0,
        "mm",
        "voxel of the labelled image CGAL meshes (0: an eighth of the thinnest chip "
        "dimension; below that dimension)",
        between(0.0, 100.0),
    )
    image_optimise: bool = key(
        False,
        "",
        "perturb and exude slivers after the refinement (about five times the time, the "
        "worst SICN ~0.04 instead of ~0.001; CGAL's optimisers do not give the same mesh "
        "twice, so the run is no longer reproducible)",
    )
    image_improve: bool = key(
        True,
        "",
        "remove the slivers Mesh_3 leaves (gmsh's optimiser, then nodes on interfaces and "
        "box sides moved within them; regions, shared faces and volumes kept, the same mesh "
        "every run), and hold every element to min_quality",
    )


@dataclass(frozen=True)
class ContactKeys(Parameters):
    """The contact model's keys."""

    element_mm: float = key(
        0.0,
        "mm",
        "in-plane element size (0: a tenth of the chip's shortest side, at most 2 mm)",
        between(0.0, 100.0),
    )
    through_thickness: int = key(2, "", "elements through a chip's thickness", between(1, 16))
    element: str = key(
        "C3D8I",
        "",
        "CalculiX element (`C3D8I` incompatible modes for bending with few elements, "
        "`C3D8`, or `C3D20R`)",
        one_of("C3D8I", "C3D8", "C3D20R"),
    )
    contact_gap_mm: float = key(
        0.3, "mm", "chips closer than this get a contact pair", between(1e-4, 10.0)
    )


@dataclass(frozen=True, init=False)
class MeshSpec(Section, KindKeys):
    """How the meshing stage meshes the stack (see docs/meshing.md): the mesh kind, its
    own keys (``mesh.params``, read as ``mesh.voxel_mm``) and the files to write."""

    table: ClassVar[str] = "mesh"
    selector: ClassVar[str] = "kind"

    kind: str = key(
        "voxel",
        "",
        "mesh kind, from the mesh-kind registry (see Meshes): `voxel` (hexahedra, always "
        "succeeds), `conformal` (gmsh tetrahedra), `image` (CGAL tetrahedra of the "
        "labelled image), `both`, or `contact` (every chip meshed on its own, contact "
        "pairs and rigid platens: the model the solve stage runs)",
    )
    formats: tuple[str, ...] = key(
        ("msh", "vtu", "inp", "xdmf"), "", "files to write (the CLI's --formats overrides)"
    )
    # The kind's own keys (its ``parameters``), filled in from the kind's table.
    params: Parameters = field(default=None, metadata={"doc": "the mesh kind's own keys"})


@dataclass(frozen=True)
class ContactPressKeys(Parameters):
    """The contact press's own keys (the contact model's chips, pairs and springs)."""

    friction: float = key(
        0.3, "", "Coulomb friction between chips and on the platens", between(0, 2)
    )
    contact_stiffness_mpa_mm: float = key(
        1e4,
        "MPa/mm",
        "penalty stiffness of the linear pressure-overclosure contact law",
        between(1.0, 1e8),
    )
    spring_n_mm: float = key(
        1e-3,
        "N/mm",
        "weak springs to ground, 3 per corner of each chip's mid-plane, that make a chip "
        "held only by contact non-singular (their force is at most 12 x this x the press "
        "per chip)",
        between(0.0, 1e3),
    )


@dataclass(frozen=True, init=False)
class SolveSpec(Section, KindKeys):
    """The compaction the solve stage runs (see docs/solve.md): the press, and the keys of
    the solve model that presses the mesh ``[mesh]`` asks for (the model follows from the
    mesh kind; it is not a key of the file)."""

    table: ClassVar[str] = "solve"
    selector: ClassVar[str] = "model"

    model: str = key(
        "contact",
        "",
        "the solve model, set by [mesh]: `contact` for the contact model, `volume` for a "
        "box with its pore space, `none` when nothing presses the mesh",
    )
    press_fraction: float = key(
        0.05,
        "",
        "the top platen moves down this fraction of the stack's height",
        between(1e-4, 0.95),
    )
    increments: int = key(
        20, "", "the press is applied in at least this many increments", between(1, 10000)
    )
    time_limit_s: float = key(
        7200.0,
        "s",
        "stop the solver after this wall time (of one run: the loose press resumes from its "
        "last step when run again)",
        between(1.0, 1e6),
        execution=True,
    )
    threads: int = key(0, "", "solver threads (0: one per core)", between(0, 256))
    # The solve model's own keys (its ``parameters``).
    params: Parameters = field(default=None, metadata={"doc": "the solve model's own keys"})
