"""The CalculiX input deck of a contact model: chips, surfaces, contact pairs, rigid
platens, materials and a displacement-controlled compaction step (units: mm, N, MPa,
tonne, s)."""

from __future__ import annotations

from collections.abc import Iterable
from functools import cache, partial
from pathlib import Path
from typing import TextIO

import numpy as np

from chipstack.meshing.boundaries import Surface
from chipstack.meshing.contact_model import (
    ContactModel,
    Platen,
    chip_box,
    faces_near_box,
    faces_within,
)
from chipstack.meshing.files import MATERIALS
from chipstack.meshing.sections import SolveSpec

__all__ = [
    "write_contact_deck",
    "write_contact_mesh",
    "write_contact_compaction",
    "write_volume_compaction",
    "COMPACTION_DOC",
    "SPRING_ELSETS",
]

SPRING_ELSETS = ("SPRINGS_X", "SPRINGS_Y", "SPRINGS_Z")
PLATEN_MATERIAL = "*MATERIAL, NAME=PLATEN\n*ELASTIC\n210000., 0.3\n*DENSITY\n7.85e-9\n"
COMPACTION_DOC = (
    "bottom platen fixed, top platen pressed down by press_fraction x the stack height in "
    "a static step with penalty surface-to-surface contact and Coulomb friction"
)


def _lines(f: TextIO, rows: Iterable[Iterable], per_line: int = 16) -> None:
    """Data lines of at most ``per_line`` values (CalculiX reads at most 16 per line)."""
    for row in rows:
        row = list(row)
        for start in range(0, len(row), per_line):
            f.write(", ".join(str(v) for v in row[start : start + per_line]) + "\n")


def write_contact_mesh(
    path: Path, model: ContactModel, element: str, surfaces: dict[str, Surface] | None = None
) -> Path:
    """The model's mesh part (what the mesh stage writes, whatever the press): nodes,
    chip and platen elements (chip k's element set ``CHIP_<k + 1>``, the region id of
    every mesh file), materials, orientations and sections, the rigid platens and their
    faces, and the chips' platen and support ``surfaces`` (``VolumeMesh.surfaces`` of the
    chips: TOP, BOTTOM) as element-based surfaces with node sets of the same names.
    :func:`write_contact_compaction` writes the rest, from ``[solve]``."""
    with open(path, "w") as f:
        f.write("** chipstack contact model: every chip on its own and two rigid platens\n")
        f.write(f"** {model.n_chips} chips, {model.n_elements} chip elements ({element}), ")
        f.write(f"{len(model.pairs)} chip pairs, {len(model.floor_chips)} chips on the conveyor\n")
        _nodes(f, model)
        _elements(f, model, element)
        _materials(f, model)
        _platen_surfaces(f, model)
        for name, surface in (surfaces or {}).items():
            f.write(f"*NSET, NSET={name.upper()}\n")
            _lines(f, [(surface.node_ids + 1).tolist()])
            f.write(f"*SURFACE, NAME={name.upper()}, TYPE=ELEMENT\n")
            _lines(
                f,
                ([e + 1, f"S{s + 1}"] for e, s in zip(surface.element, surface.face, strict=True)),
            )
    return Path(path)


def write_contact_compaction(
    path: Path, mesh_file: str, model: ContactModel, solve: SolveSpec
) -> Path:
    """The compaction deck (what the solve stage writes): the mesh part included from
    ``mesh_file``, then the weak springs, the contact surfaces and pairs, and the
    displacement-controlled step of ``solve``."""
    with open(path, "w") as f:
        f.write("** chipstack compaction of a contact model\n")
        f.write(f"*INCLUDE, INPUT={mesh_file}\n")
        _springs(f, model, solve.spring_n_mm)
        pairs, surfaces = contact_surfaces(model, solve)
        _surfaces(f, surfaces)
        _contacts(f, pairs, solve)
        _step(f, model, solve)
    return Path(path)


def write_contact_deck(path: Path, model: ContactModel, solve: SolveSpec, element: str) -> Path:
    """The whole deck at ``path``, its mesh part beside it (``<stem>_model.inp``):
    both parts at once, as the mesh and solve stages write them one after the other."""
    path = Path(path)
    mesh = path.with_name(f"{path.stem}_model.inp")
    write_contact_mesh(mesh, model, element)
    return write_contact_compaction(path, mesh.name, model, solve)


def _nodes(f: TextIO, model: ContactModel) -> None:
    f.write("*NODE, NSET=NALL\n")
    ids = np.arange(1, len(model.points) + 1)
    for i, (x, y, z) in zip(ids, model.points, strict=True):
        f.write(f"{i}, {x:.9g}, {y:.9g}, {z:.9g}\n")
    for platen in (model.bottom, model.top):
        f.write(f"*NSET, NSET=REF_{platen.name}\n{platen.reference_node + 1}\n")
        f.write(f"*NSET, NSET=ROT_{platen.name}\n{platen.rotation_node + 1}\n")


def _elements(f: TextIO, model: ContactModel, element: str) -> None:
    for chip in range(model.n_chips):
        mine = np.flatnonzero(model.chip == chip)
        f.write(f"*ELEMENT, TYPE={element}, ELSET=CHIP_{chip + 1:04d}\n")
        _lines(f, ([e + 1, *(model.cells[e] + 1)] for e in mine))
    first = len(model.cells) + 1
    for platen in (model.bottom, model.top):
        f.write(f"*ELEMENT, TYPE=C3D8, ELSET=PLATEN_{platen.name}\n")
        _lines(f, ([first + k, *(c + 1)] for k, c in enumerate(platen.cells)))
        first += len(platen.cells)
    f.write("*ELSET, ELSET=CHIPS\n")
    _lines(f, [[f"CHIP_{chip + 1:04d}" for chip in range(model.n_chips)]], per_line=8)


def _springs(f: TextIO, model: ContactModel, stiffness: float) -> None:
    """Weak springs to ground at each chip's mid-plane corners, one element per dof."""
    if stiffness <= 0:
        return
    first = len(model.cells) + len(model.bottom.cells) + len(model.top.cells) + 1
    nodes = model.anchors.ravel() + 1
    for dof, elset in enumerate(SPRING_ELSETS, start=1):
        f.write(f"*ELEMENT, TYPE=SPRING1, ELSET={elset}\n")
        _lines(f, ([first + k, node] for k, node in enumerate(nodes)))
        first += len(nodes)
        f.write(f"*SPRING, ELSET={elset}\n{dof}\n{stiffness:.9e}\n")


def _materials(f: TextIO, model: ContactModel) -> None:
    c = MATERIALS["CHIP"]
    f.write("*MATERIAL, NAME=CHIP\n*ELASTIC, TYPE=ENGINEERING CONSTANTS\n")
    f.write(
        f"{c['E1']}, {c['E2']}, {c['E3']}, {c['nu12']}, {c['nu13']}, {c['nu23']}, "
        f"{c['G12']}, {c['G13']}\n{c['G23']}\n*DENSITY\n1.7e-9\n"
    )
    f.write(PLATEN_MATERIAL)
    for k in range(model.n_chips):
        a, b = model.fibres[k]
        if abs(a @ b) > 1 - 1e-6:  # one fibre direction: the in-plane normal to it
            normal = np.cross(model.normals[k], a)
            b = normal / np.linalg.norm(normal)
        tag = k + 1  # the region id of the mesh files
        f.write(f"*ORIENTATION, NAME=OR_{tag:04d}, SYSTEM=RECTANGULAR\n")
        f.write(", ".join(f"{v:.9g}" for v in (*a, *b)) + "\n")
        f.write(f"*SOLID SECTION, ELSET=CHIP_{tag:04d}, MATERIAL=CHIP, ORIENTATION=OR_{tag:04d}\n")
    for platen in (model.bottom, model.top):
        f.write(f"*SOLID SECTION, ELSET=PLATEN_{platen.name}, MATERIAL=PLATEN\n")
        f.write(
            f"*RIGID BODY, ELSET=PLATEN_{platen.name}, REF NODE={platen.reference_node + 1}, "
            f"ROT NODE={platen.rotation_node + 1}\n"
        )


def _platen_faces(platen: Platen, first_element: int) -> list[list]:
    return [[first_element + k, f"S{platen.face}"] for k in range(len(platen.cells))]


def contact_surfaces(model: ContactModel, solve: SolveSpec) -> list[tuple[str, str, list]]:
    """The contact pairs of the deck as (slave, master, [(surface name, faces)...]).

    Each side of a pair is only the part of the chip's surface that can reach the other
    side (within the gap tolerance or the press): CalculiX matches every
    slave face with every master face of a pair at each increment, and whole chip surfaces
    made that matching most of the run time. Chips get a pair with the conveyor when they
    are within reach of it, and with the press plate when it can reach them."""
    reach = max(model.gap_mm, press_mm(model, solve))
    pairs, surfaces = [], []
    box = cache(partial(chip_box, model))  # a chip is in several pairs
    for a, b in model.pairs:
        near_a = faces_near_box(model, a, box(b), reach)
        near_b = faces_near_box(model, b, box(a), reach)
        if len(near_a) and len(near_b):
            names = (f"S_{a + 1:04d}_{b + 1:04d}", f"S_{b + 1:04d}_{a + 1:04d}")
            surfaces += [(names[0], near_a), (names[1], near_b)]
            pairs.append(names)
    for platen, low, high in (
        (model.bottom, -np.inf, model.bottom.z_mm + reach),
        (model.top, model.top.z_mm - press_mm(model, solve) - reach, np.inf),
    ):
        for chip in range(model.n_chips):
            near = faces_within(model, chip, low, high)
            if len(near):
                name = f"S_{chip + 1:04d}_{platen.name}"
                surfaces.append((name, near))
                pairs.append((name, f"S_{platen.name}"))
    return pairs, surfaces


def _surfaces(f: TextIO, surfaces: list) -> None:
    for name, faces in surfaces:
        f.write(f"*SURFACE, NAME={name}, TYPE=ELEMENT\n")
        _lines(f, ([e + 1, f"S{face}"] for e, face in faces))


def _platen_surfaces(f: TextIO, model: ContactModel) -> None:
    first = len(model.cells) + 1
    for platen in (model.bottom, model.top):
        f.write(f"*SURFACE, NAME=S_{platen.name}, TYPE=ELEMENT\n")
        _lines(f, _platen_faces(platen, first))
        first += len(platen.cells)


def _contacts(f: TextIO, pairs: list, solve: SolveSpec) -> None:
    """Penalty contact: linear pressure-overclosure, Coulomb friction. The chip is the
    slave against a platen; of two chips, the lower-numbered one."""
    stiffness = solve.contact_stiffness_mpa_mm
    f.write("*SURFACE INTERACTION, NAME=SI\n*SURFACE BEHAVIOR, PRESSURE-OVERCLOSURE=LINEAR\n")
    f.write(f"{stiffness:.9g}, 1e-3\n")
    if solve.friction > 0:
        f.write(f"*FRICTION\n{solve.friction:.9g}, {stiffness:.9g}\n")
    for slave, master in pairs:
        f.write("*CONTACT PAIR, INTERACTION=SI, TYPE=SURFACE TO SURFACE\n")
        f.write(f"{slave}, {master}\n")


def press_mm(model: ContactModel, solve: SolveSpec) -> float:
    """How far the top platen moves down (mm)."""
    return solve.press_fraction * model.height_mm


def _step(f: TextIO, model: ContactModel, solve: SolveSpec) -> None:
    first = 1.0 / solve.increments
    f.write(f"** compaction: {COMPACTION_DOC}\n")
    f.write("*STEP, INC=100000\n*STATIC\n")
    f.write(f"{first:.9g}, 1., {first * 1e-4:.9g}, {first:.9g}\n")
    # Chips held by weak springs carry almost no force before they touch: CalculiX's
    # residual test, relative to the average force, could then never pass. A fixed
    # reference force of 1 N makes it absolute (0.005 N), and contact needs more
    # iterations than the defaults allow.
    f.write("*CONTROLS, PARAMETERS=FIELD\n0.005, 0.01, 0., 1.\n")
    f.write("*CONTROLS, PARAMETERS=TIME INCREMENTATION\n8, 16, 9, 50, 10, 4, 0, 5\n")
    f.write("*BOUNDARY\nREF_BOTTOM, 1, 3, 0.\nROT_BOTTOM, 1, 3, 0.\n")
    f.write(f"REF_TOP, 1, 2, 0.\nREF_TOP, 3, 3, {-press_mm(model, solve):.9g}\n")
    f.write("ROT_TOP, 1, 3, 0.\n")
    f.write("*NODE PRINT, NSET=REF_TOP\nU, RF\n*NODE PRINT, NSET=REF_BOTTOM\nRF\n")
    if solve.spring_n_mm > 0:
        f.write("*EL PRINT, ELSET=SPRINGS_Z, TOTALS=ONLY\nELSE\n")
    f.write("*NODE FILE\nU, RF\n*EL FILE\nS\n*CONTACT FILE\nCDIS, CSTR\n*END STEP\n")


def write_volume_compaction(
    path: Path, mesh_file: str, height_mm: float, solve: SolveSpec, periodic: bool
) -> float:
    """The compaction deck of a cropped voxel volume (``mesh_file``, included as is):
    frictionless whole-face platens, the conveyor (``BOTTOM``) held in z, the press plate
    (``TOP``) moved down by ``press_fraction`` x ``height_mm`` in ``increments`` equal
    increments. Periodic sides keep their jumps at zero (``REF_X``, ``REF_Y``: a laterally
    confined volume, as inside a wide mat) and ``ANCHOR`` stops the box sliding; without
    ties, one bottom corner is held in x and y and the bottom plane in z, the sides free.
    Returns the press (mm)."""
    press = solve.press_fraction * height_mm
    first = 1.0 / solve.increments
    with open(path, "w") as f:
        f.write(f"** chipstack: compaction of a cropped voxel volume ({COMPACTION_DOC_VOLUME})\n")
        f.write(f"*INCLUDE, INPUT={mesh_file}\n")
        # A volume of solid hexahedra is what CalculiX's preconditioned conjugate gradients
        # suit: on a 50 x 50 mm crop of the reference stack (57,500 hexahedra) 17 s and
        # 0.3 GB, against 327 s and 5.4 GB with the direct solver (SPOOLES), same force.
        f.write(f"*STEP\n*STATIC, DIRECT, SOLVER=ITERATIVE CHOLESKY\n{first:.9g}, 1.\n")
        f.write("*BOUNDARY\n")
        f.write(f"BOTTOM, 3, 3, 0.\nTOP, 3, 3, {-press:.9g}\n")
        if periodic:
            f.write("ANCHOR, 1, 2, 0.\nREF_X, 1, 3, 0.\nREF_Y, 1, 3, 0.\n")
        else:  # no ties: hold the bottom face in x and y too (a conveyor the stack grips)
            f.write("BOTTOM, 1, 2, 0.\n")
        f.write("*NODE PRINT, NSET=TOP\nRF\n*NODE PRINT, NSET=BOTTOM\nRF\n")
        f.write("*NODE FILE\nU, RF\n*EL FILE\nS\n*END STEP\n")
    return press


COMPACTION_DOC_VOLUME = (
    "conveyor face held in z, press face moved down by press_fraction x the volume's "
    "height, periodic sides confined (zero jumps)"
)
