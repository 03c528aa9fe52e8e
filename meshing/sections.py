"""The scenario tables of the meshing package: ``[mesh]`` (the mesh stage) and ``[solve]``
(the solve stage) (see :mod:`packing.sections`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from chipstack.core.schema import Section, between, key, one_of, region

__all__ = ["MeshSpec", "SolveSpec"]


@dataclass(frozen=True)
class MeshSpec(Section):
    """How the meshing stage meshes the stack (see README: Meshes)."""

    table: ClassVar[str] = "mesh"

    kind: str = key(
        "voxel",
        "",
        "mesh kind, from the mesh-kind registry (see Meshes): `voxel` (hexahedra, always "
        "succeeds), `conformal` (gmsh tetrahedra), `image` (CGAL tetrahedra of the "
        "labelled image), `both`, or `contact` (every chip meshed on its own, contact "
        "pairs and rigid platens: the model the solve stage runs)",
    )
    voxel_mm: float = key(0.5, "mm", "voxel of the hexahedral mesh", between(0.05, 100.0))
    size_mm: float = key(
        1.5, "mm", "largest element edge of the conformal mesh", between(0.05, 100.0)
    )
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
        "voxel and image meshes: `target` crops them to the deposition target, `region` to "
        "`region_mm`; "
        "`none`: the whole stack",
        one_of("none", "target", "region"),
    )
    region_mm: tuple[float, ...] = key(
        (),
        "mm",
        "[x_min, x_max, y_min, y_max] of the crop with crop = 'region'",
        region,
    )
    periodic: bool = key(
        False,
        "",
        "voxel mesh cropped with pore_space = 'box': tie each node of the xmax and ymax "
        "sides to its twin on the opposite side (*EQUATION in the .inp, reference nodes "
        "REF_X and REF_Y carry the jumps): a representative volume",
    )
    min_quality: float = key(
        0.1,
        "",
        "smallest accepted element quality (SICN) of the conformal mesh, and of the image "
        "mesh with image_improve",
        between(0, 1),
    )
    image_voxel_mm: float = key(
        0.0,
        "mm",
        "image mesh: voxel of the labelled image CGAL meshes (0: an eighth of the thinnest "
        "chip dimension; below that dimension)",
        between(0.0, 100.0),
    )
    image_optimise: bool = key(
        False,
        "",
        "image mesh: perturb and exude slivers after the refinement (about five times the "
        "time, the worst SICN ~0.04 instead of ~0.001; CGAL's optimisers do not give the "
        "same mesh twice, so the run is no longer reproducible)",
    )
    image_improve: bool = key(
        True,
        "",
        "image mesh: remove the slivers Mesh_3 leaves (gmsh's optimiser, then nodes on "
        "interfaces and box sides moved within them; regions, shared faces and volumes "
        "kept, the same mesh every run), and hold every element to min_quality",
    )
    gap_mm: float = key(
        0.03,
        "mm",
        "conformal mesh: contact resolution leaves chips that are not in surface contact at "
        "least this far apart (at most a tenth of the thinnest chip dimension)",
        between(1e-4, 10.0),
    )
    pore_gap_mm: float = key(
        0.0,
        "mm",
        "conformal mesh with the pore space: the clearance of the contact resolution in "
        "place of gap_mm, wide enough for pore elements between chips, about a tenth of "
        "size_mm or more (0: a tenth of the thinnest chip dimension, the largest allowed)",
        between(0.0, 10.0),
    )
    pore_size_mm: float = key(
        0.0,
        "mm",
        "conformal mesh with the pore space: largest element edge of the pore space away "
        "from the chips, graded from size_mm at their faces (0: four times size_mm; "
        "size_mm: no grading)",
        between(0.0, 100.0),
    )
    snap_angle_deg: float = key(
        3.0,
        "deg",
        "conformal mesh: surface contacts whose faces are within this angle are made exactly "
        "coplanar and touching",
        between(0.0, 15.0),
    )
    formats: tuple[str, ...] = key(
        ("msh", "vtu", "inp", "xdmf"), "", "files to write (the CLI's --formats overrides)"
    )
    element_mm: float = key(
        0.0,
        "mm",
        "contact model: in-plane element size (0: a tenth of the chip's shortest side, at "
        "most 2 mm)",
        between(0.0, 100.0),
    )
    through_thickness: int = key(
        2, "", "contact model: elements through a chip's thickness", between(1, 16)
    )
    element: str = key(
        "C3D8I",
        "",
        "contact model: CalculiX element (`C3D8I` incompatible modes for bending with few "
        "elements, `C3D8`, or `C3D20R`)",
        one_of("C3D8I", "C3D8", "C3D20R"),
    )
    contact_gap_mm: float = key(
        0.3,
        "mm",
        "contact model: chips closer than this get a contact pair",
        between(1e-4, 10.0),
    )


@dataclass(frozen=True)
class SolveSpec(Section):
    """The compaction the solve stage runs on the contact model (see docs/solve.md)."""

    table: ClassVar[str] = "solve"

    press_fraction: float = key(
        0.05,
        "",
        "the top platen moves down this fraction of the stack's height",
        between(1e-4, 0.5),
    )
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
    increments: int = key(
        20, "", "the press is applied in at least this many increments", between(1, 10000)
    )
    time_limit_s: float = key(
        7200.0, "s", "stop the solver after this wall time", between(1.0, 1e6)
    )
    threads: int = key(0, "", "solver threads (0: one per core)", between(0, 256))
