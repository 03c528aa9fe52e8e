"""CalculiX references for small loose stacks of box chips (issue 71, point 3): the same
mesh as the loose press (:func:`meshing.loose.verify.box_bodies`) solved by CalculiX,
once with its own contact pairs and once bonded.

- :func:`calculix_press`: every chip its own body of C3D8I bricks (the element the loose
  press's bricks are), penalty surface-to-surface ``*CONTACT PAIR`` between every two
  chips that face each other across a horizontal gap and between each chip and the
  platen it faces, Coulomb friction, the two platens rigid bodies (``*RIGID BODY`` of one
  C3D8 block each), the press plate driven down by the travel in equal increments.
- :func:`calculix_bonded`: the same chips tied (``*TIE``) wherever the contact press
  would declare a pair, the faces on the platens held (conveyor: all three directions;
  press plate: x and y, z moved by the travel): the stack with every gap closed and
  every interface bonded, linear, one increment.

Units: mm, N, MPa. The same nodes as the loose press, so the same starting gaps; the
loose press keeps its contacts a fraction of the barrier distance apart and CalculiX's
penalty lets them overlap by pressure / stiffness, so forces are compared at equal
*compression* (:func:`compression_mm`): the mean downward displacement of the chips'
faces on the press plate less that of their faces on the conveyor, which leaves out
what each solver does at the two platens.

CalculiX needs every chip held against its rigid modes before the contacts carry it:
weak springs to ground (``SPRING1``, ``spring_n_mm`` per node and direction, a force
below 1e-4 of the platen's in the cases of ``tests/test_loose_press_reference.py``).
Measured limit: on the three-chip bridge of that test CalculiX 2.20 (friction 0.3)
stops with "too many cutbacks" as its last gap closes (a travel of 0.0225 mm); it
converges to 0.02 mm. Side faces are not paired: in box stacks whose neighbours are a
millimetre apart they do not meet.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

import numpy as np

from chipstack.meshing.calculix import read_node_prints, run_ccx
from chipstack.meshing.contact_model import FACE_NODES
from chipstack.meshing.loose.ipc import Platens, PressBodies
from chipstack.meshing.loose.material import ChipMaterial

__all__ = [
    "ContactSettings",
    "StackFaces",
    "ReferencePress",
    "stack_faces",
    "compression_mm",
    "write_contact_deck",
    "write_bonded_deck",
    "calculix_press",
    "calculix_bonded",
]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ContactSettings:
    """CalculiX's contact and increments.

    Attributes
    ----------
    friction : float
        Coulomb coefficient on every pair (0: frictionless, no ``*FRICTION``).
    penalty_mpa_mm : float
        Slope of the linear pressure-overclosure law, MPa/mm: 1e6 lets a 20 MPa contact
        overlap by 2e-5 mm.
    tension_mpa : float
        CalculiX's tension at large clearance (the law's second value, MPa).
    stick_slope_mpa_mm : float
        Tangential stiffness of a sticking contact, MPa/mm.
    spring_n_mm : float
        Weak springs to ground at every chip node in x, y and z, N/mm.
    increments : int
        Equal increments of the travel.
    reach_mm : float
        Two faces closer than this (mm) across a horizontal gap are a contact pair.
    """

    friction: float = 0.3
    penalty_mpa_mm: float = 1e6
    tension_mpa: float = 1e-3
    stick_slope_mpa_mm: float = 1e5
    spring_n_mm: float = 1e-3
    increments: int = 16
    reach_mm: float = 0.1


@dataclass(frozen=True)
class StackFaces:
    """The horizontal outer faces of a box stack and what they face.

    Attributes
    ----------
    bottom, top : list of (k, 2) int arrays
        Per chip, (cell, face index 0..5 of ``FACE_NODES``) of its downward and upward
        outer faces.
    pairs : list of (lower, upper)
        Chips whose top and bottom faces face each other within the reach.
    on_conveyor, under_plate : list of int
        Chips whose bottom is within reach of the conveyor; chips whose top is within
        reach of the press plate after the travel.
    bottom_nodes, top_nodes : list of int arrays
        Per chip, the node ids (0-based) of its bottom and top faces.
    """

    bottom: list
    top: list
    pairs: list
    on_conveyor: list
    under_plate: list
    bottom_nodes: list
    top_nodes: list


def _outer_faces(cells: np.ndarray) -> np.ndarray:
    """(k, 2) rows of (cell, face index) of the faces only one cell has."""
    quads = np.concatenate([cells[:, list(face)] for face in FACE_NODES])
    keys = np.sort(quads, axis=1)
    _, first, counts = np.unique(keys, axis=0, return_index=True, return_counts=True)
    outer = np.sort(first[counts == 1])
    return np.column_stack([outer % len(cells), outer // len(cells)])


def _normals(points: np.ndarray, cells: np.ndarray, faces: np.ndarray) -> np.ndarray:
    quad = points[
        cells[faces[:, 0]][np.arange(len(faces))[:, None], np.array(FACE_NODES)[faces[:, 1]]]
    ]
    # FACE_NODES run clockwise seen from outside the brick.
    n = np.cross(quad[:, 3] - quad[:, 1], quad[:, 2] - quad[:, 0])
    return n / np.linalg.norm(n, axis=1)[:, None]


def stack_faces(
    bodies: PressBodies, platens: Platens, travel_mm: float, reach_mm: float = 0.1
) -> StackFaces:
    """The contact pairs of a stack of box chips (see :class:`StackFaces`).

    Parameters
    ----------
    bodies : PressBodies
        The chips (nodes mm, C3D8-ordered bricks).
    platens : Platens
        The conveyor and the press plate (mm).
    travel_mm : float
        How far the press plate moves down, mm: chips it reaches are paired with it.
    reach_mm : float
        Faces closer than this (mm) are paired.
    """
    points, cells = bodies.points, bodies.cells
    faces = _outer_faces(cells)
    normal_z = _normals(points, cells, faces)[:, 2]
    owner = bodies.chip[faces[:, 0]]
    n_chips = int(bodies.chip.max()) + 1
    bottom = [faces[(owner == k) & (normal_z < -0.99)] for k in range(n_chips)]
    top = [faces[(owner == k) & (normal_z > 0.99)] for k in range(n_chips)]
    lo = np.array(
        [points[cells[bodies.chip == k]].reshape(-1, 3).min(axis=0) for k in range(n_chips)]
    )
    hi = np.array(
        [points[cells[bodies.chip == k]].reshape(-1, 3).max(axis=0) for k in range(n_chips)]
    )
    pairs = []
    for a in range(n_chips):
        for b in range(n_chips):
            overlap = np.minimum(hi[a, :2], hi[b, :2]) - np.maximum(lo[a, :2], lo[b, :2])
            gap = lo[b, 2] - hi[a, 2]
            if a != b and np.all(overlap > 0) and -1e-9 <= gap <= reach_mm:
                pairs.append((a, b))
    on_conveyor = [k for k in range(n_chips) if lo[k, 2] - platens.bottom_z <= reach_mm]
    under_plate = [k for k in range(n_chips) if platens.top_z - travel_mm - hi[k, 2] <= reach_mm]
    return StackFaces(
        bottom,
        top,
        pairs,
        on_conveyor,
        under_plate,
        [np.unique(_nodes_of(cells, f)) for f in bottom],
        [np.unique(_nodes_of(cells, f)) for f in top],
    )


def _nodes_of(cells: np.ndarray, faces: np.ndarray) -> np.ndarray:
    return cells[faces[:, 0][:, None], np.array(FACE_NODES)[faces[:, 1]]].ravel()


def platen_nodes(faces: StackFaces) -> tuple[np.ndarray, np.ndarray]:
    """(conveyor-side, plate-side) node ids (0-based): the bottom faces of the chips on
    the conveyor and the top faces of the chips under the press plate."""
    bottom = np.unique(np.concatenate([faces.bottom_nodes[k] for k in faces.on_conveyor]))
    top = np.unique(np.concatenate([faces.top_nodes[k] for k in faces.under_plate]))
    return bottom, top


def compression_mm(faces: StackFaces, displacement: np.ndarray) -> float:
    """The stack's compression, mm: the mean downward displacement of the plate-side
    nodes less that of the conveyor-side nodes (:func:`platen_nodes`).

    Parameters
    ----------
    faces : StackFaces
        The stack's faces.
    displacement : (n, 3) array, mm
        The chips' nodal displacements.
    """
    bottom, top = platen_nodes(faces)
    return float(displacement[bottom, 2].mean() - displacement[top, 2].mean())


@dataclass(frozen=True)
class ReferencePress:
    """A CalculiX press, increment by increment.

    Attributes
    ----------
    travel_mm : (k,) array
        The press plate's travel, mm.
    force_n : (k,) array
        The press plate's force, N (pressing: positive).
    conveyor_force_n : (k,) array
        The conveyor's force, N (pressing: positive).
    compression_mm : (k,) array
        The stack's compression (:func:`compression_mm`), mm.
    wall_time_s : float
        CalculiX's wall time, s.
    """

    travel_mm: np.ndarray
    force_n: np.ndarray
    conveyor_force_n: np.ndarray
    compression_mm: np.ndarray
    wall_time_s: float

    def force_at(self, compression: float) -> float:
        """The force (N) at a ``compression`` (mm), interpolated between increments;
        ValueError outside the increments' range."""
        c = np.concatenate([[0.0], self.compression_mm])
        f = np.concatenate([[0.0], self.force_n])
        if not c[0] <= compression <= c[-1] or np.any(np.diff(c) <= 0):
            raise ValueError(
                f"compression {compression:.6g} mm outside CalculiX's increments "
                f"({c[0]:.6g} to {c[-1]:.6g} mm, increasing: {bool(np.all(np.diff(c) > 0))})"
            )
        return float(np.interp(compression, c, f))


def _lines(f: TextIO, rows, per_line: int = 16) -> None:
    for row in rows:
        row = list(row)
        for start in range(0, len(row), per_line):
            f.write(", ".join(str(v) for v in row[start : start + per_line]) + "\n")


def _material(f: TextIO, material: ChipMaterial) -> None:
    """The chip's law in the world frame (box chips' ply frame is the world's)."""
    m = material
    f.write("*MATERIAL, NAME=CHIP\n*ELASTIC, TYPE=ENGINEERING CONSTANTS\n")
    values = (
        m.in_plane_mpa,
        m.in_plane_mpa,
        m.through_thickness_mpa,
        m.in_plane_poisson,
        m.transverse_poisson,
        m.transverse_poisson,
        m.in_plane_shear_mpa,
        m.transverse_shear_mpa,
    )
    f.write(", ".join(f"{v:.9g}" for v in values) + f"\n{m.transverse_shear_mpa:.9g}\n")


def _chips(f: TextIO, bodies: PressBodies, material: ChipMaterial) -> None:
    f.write("*NODE, NSET=NALL\n")
    for i, (x, y, z) in enumerate(bodies.points, start=1):
        f.write(f"{i}, {x:.12g}, {y:.12g}, {z:.12g}\n")
    for k in range(int(bodies.chip.max()) + 1):
        mine = np.flatnonzero(bodies.chip == k)
        f.write(f"*ELEMENT, TYPE=C3D8I, ELSET=CHIP_{k + 1}\n")
        _lines(f, ([e + 1, *(bodies.cells[e] + 1)] for e in mine))
    f.write("*ELSET, ELSET=CHIPS\n")
    _lines(f, [[f"CHIP_{k + 1}" for k in range(int(bodies.chip.max()) + 1)]], per_line=8)
    _material(f, material)
    f.write("*SOLID SECTION, ELSET=CHIPS, MATERIAL=CHIP\n")


def _surface(f: TextIO, name: str, faces: np.ndarray) -> None:
    f.write(f"*SURFACE, NAME={name}, TYPE=ELEMENT\n")
    _lines(f, ([c + 1, f"S{face + 1}"] for c, face in faces))


def _nset(f: TextIO, name: str, nodes: np.ndarray) -> None:
    f.write(f"*NSET, NSET={name}\n")
    _lines(f, [(np.asarray(nodes) + 1).tolist()])


def _facing(bodies: PressBodies, faces: np.ndarray, other: int, margin: float) -> np.ndarray:
    """The faces whose centre lies over (or under) chip ``other``'s footprint."""
    pts = bodies.points[bodies.cells[bodies.chip == other]].reshape(-1, 3)
    lo, hi = pts.min(axis=0)[:2] - margin, pts.max(axis=0)[:2] + margin
    centre = bodies.points[_nodes_of(bodies.cells, faces).reshape(len(faces), 4)].mean(axis=1)
    inside = np.all((centre[:, :2] > lo) & (centre[:, :2] < hi), axis=1)
    return faces[inside]


def write_contact_deck(
    folder: Path,
    bodies: PressBodies,
    platens: Platens,
    material: ChipMaterial,
    travel_mm: float,
    settings: ContactSettings = ContactSettings(),
    job: str = "press",
) -> StackFaces:
    """Write ``folder/job.inp``: the loose stack pressed in CalculiX with contact pairs.

    Parameters
    ----------
    folder : Path
        Where the deck is written (existing).
    bodies : PressBodies
        The chips (:func:`meshing.loose.verify.box_bodies`), nodes in mm.
    platens : Platens
        The conveyor and the press plate (mm).
    material : ChipMaterial
        The chips' material (MPa), in the world frame.
    travel_mm : float
        The press plate's travel, mm, in ``settings.increments`` equal increments.
    settings : ContactSettings
        Contact, friction, springs and increments.
    job : str
        The deck's name.

    Returns
    -------
    StackFaces
        The faces and pairs the deck declares.
    """
    s = settings
    faces = stack_faces(bodies, platens, travel_mm, s.reach_mm)
    n_nodes, n_cells = bodies.n_nodes, len(bodies.cells)
    path = Path(folder) / f"{job}.inp"
    with open(path, "w") as f:
        f.write("** chipstack: a loose box stack pressed with CalculiX contact pairs\n")
        _chips(f, bodies, material)
        # The platens: one rigid C3D8 block each, 1 mm thick, over the platens' rectangle.
        x0, x1, y0, y1 = platens.xy
        corners = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])
        f.write("*NODE\n")
        node = n_nodes
        blocks = {}
        for name, z_low, z_high in (
            ("CONVEYOR", platens.bottom_z - 1.0, platens.bottom_z),
            ("PLATE", platens.top_z, platens.top_z + 1.0),
        ):
            ids = []
            for z in (z_low, z_high):
                for x, y in corners:
                    node += 1
                    ids.append(node)
                    f.write(f"{node}, {x:.12g}, {y:.12g}, {z:.12g}\n")
            node += 1
            f.write(f"{node}, 0, 0, {z_high:.12g}\n")
            node += 1
            f.write(f"{node}, 0, 0, {z_high:.12g}\n")
            blocks[name] = (ids, node - 1, node)
        element = n_cells
        for name, (ids, ref, rot) in blocks.items():
            element += 1
            f.write(f"*ELEMENT, TYPE=C3D8, ELSET=P_{name}\n{element}, ")
            f.write(", ".join(str(i) for i in ids) + "\n")
            blocks[name] = (element, ref, rot)
        f.write("*MATERIAL, NAME=STEEL\n*ELASTIC\n210000., 0.3\n")
        for name, (_cell, ref, rot) in blocks.items():
            f.write(f"*SOLID SECTION, ELSET=P_{name}, MATERIAL=STEEL\n")
            f.write(f"*RIGID BODY, ELSET=P_{name}, REF NODE={ref}, ROT NODE={rot}\n")
            f.write(f"*NSET, NSET=REF_{name}\n{ref}\n*NSET, NSET=ROT_{name}\n{rot}\n")
        f.write(f"*SURFACE, NAME=S_CONVEYOR, TYPE=ELEMENT\n{blocks['CONVEYOR'][0]}, S2\n")
        f.write(f"*SURFACE, NAME=S_PLATE, TYPE=ELEMENT\n{blocks['PLATE'][0]}, S1\n")
        # Weak springs to ground: every chip node in x, y and z.
        if s.spring_n_mm > 0:
            for dof in (1, 2, 3):
                f.write(f"*ELEMENT, TYPE=SPRING1, ELSET=SPRINGS_{dof}\n")
                _lines(f, ([element + 1 + i, i + 1] for i in range(n_nodes)))
                element += n_nodes
                f.write(f"*SPRING, ELSET=SPRINGS_{dof}\n{dof}\n{s.spring_n_mm:.9g}\n")
        pairs = []
        for a, b in faces.pairs:
            slave = _facing(bodies, faces.bottom[b], a, 1.0)
            master = _facing(bodies, faces.top[a], b, 1.0)
            _surface(f, f"S_{b + 1}_ON_{a + 1}", slave)
            _surface(f, f"S_{a + 1}_UNDER_{b + 1}", master)
            pairs.append((f"S_{b + 1}_ON_{a + 1}", f"S_{a + 1}_UNDER_{b + 1}"))
        for k in faces.on_conveyor:
            _surface(f, f"S_{k + 1}_BOTTOM", faces.bottom[k])
            pairs.append((f"S_{k + 1}_BOTTOM", "S_CONVEYOR"))
        for k in faces.under_plate:
            _surface(f, f"S_{k + 1}_TOP", faces.top[k])
            pairs.append((f"S_{k + 1}_TOP", "S_PLATE"))
        bottom, top = platen_nodes(faces)
        _nset(f, "ON_CONVEYOR", bottom)
        _nset(f, "UNDER_PLATE", top)
        f.write("*SURFACE INTERACTION, NAME=SI\n*SURFACE BEHAVIOR, PRESSURE-OVERCLOSURE=LINEAR\n")
        f.write(f"{s.penalty_mpa_mm:.9g}, {s.tension_mpa:.9g}\n")
        if s.friction > 0:
            f.write(f"*FRICTION\n{s.friction:.9g}, {s.stick_slope_mpa_mm:.9g}\n")
        for slave, master in pairs:
            f.write("*CONTACT PAIR, INTERACTION=SI, TYPE=SURFACE TO SURFACE\n")
            f.write(f"{slave}, {master}\n")
        dt = 1.0 / s.increments
        f.write("*STEP, INC=10000\n*STATIC\n")
        f.write(f"{dt:.9g}, 1., {dt * 1e-4:.9g}, {dt:.9g}\n")
        # The residual test against a fixed 1 N (the project's press deck's choice): the
        # average force is nothing while the chips float on their springs.
        f.write("*CONTROLS, PARAMETERS=FIELD\n0.005, 0.01, 0., 1.\n")
        f.write("*CONTROLS, PARAMETERS=TIME INCREMENTATION\n8, 16, 9, 50, 10, 4, 0, 5\n")
        f.write("*BOUNDARY\nREF_CONVEYOR, 1, 3, 0.\nROT_CONVEYOR, 1, 3, 0.\n")
        f.write(f"REF_PLATE, 1, 2, 0.\nREF_PLATE, 3, 3, {-travel_mm:.12g}\nROT_PLATE, 1, 3, 0.\n")
        f.write("*NODE PRINT, NSET=REF_PLATE\nU, RF\n*NODE PRINT, NSET=REF_CONVEYOR\nRF\n")
        f.write("*NODE PRINT, NSET=ON_CONVEYOR\nU\n*NODE PRINT, NSET=UNDER_PLATE\nU\n")
        f.write("*END STEP\n")
    log.info("loose reference: %s, %d contact pairs", path, len(pairs))
    return faces


def calculix_press(
    folder: Path,
    bodies: PressBodies,
    platens: Platens,
    material: ChipMaterial,
    travel_mm: float,
    settings: ContactSettings = ContactSettings(),
    time_limit_s: float = 600.0,
) -> ReferencePress:
    """The stack pressed by ``travel_mm`` (mm) in CalculiX with contact pairs
    (:func:`write_contact_deck`): force (N), travel and compression (mm) at every
    increment. Raises ``SolverError`` (CalculiX's message) when it does not finish."""
    faces = write_contact_deck(folder, bodies, platens, material, travel_mm, settings)
    run = run_ccx(Path(folder), "press", threads=1, time_limit_s=time_limit_s)
    prints = read_node_prints(Path(folder) / "press.dat")
    bottom, top = platen_nodes(faces)
    plate, conveyor = prints["REF_PLATE"], prints["REF_CONVEYOR"]
    compression = prints["ON_CONVEYOR"]["displacements"][:, 2] / len(bottom) - prints[
        "UNDER_PLATE"
    ]["displacements"][:, 2] / len(top)
    return ReferencePress(
        travel_mm=-plate["displacements"][:, 2],
        force_n=-plate["forces"][:, 2],
        conveyor_force_n=conveyor["forces"][:, 2],
        compression_mm=compression,
        wall_time_s=run.wall_time_s,
    )


def write_bonded_deck(
    folder: Path,
    bodies: PressBodies,
    platens: Platens,
    material: ChipMaterial,
    travel_mm: float,
    reach_mm: float = 0.1,
    job: str = "bonded",
) -> StackFaces:
    """Write ``folder/job.inp``: the stack bonded (see the module docstring), its faces
    on the press plate moved down by ``travel_mm`` (mm) in one linear increment.

    Parameters are those of :func:`write_contact_deck`; ``reach_mm`` (mm) decides which
    faces are tied, as it decides the contact pairs there. Every gap within reach is
    tied as it is (``ADJUST=NO``).
    """
    faces = stack_faces(bodies, platens, travel_mm, reach_mm)
    path = Path(folder) / f"{job}.inp"
    with open(path, "w") as f:
        f.write("** chipstack: a box stack bonded (tied interfaces, held faces)\n")
        _chips(f, bodies, material)
        for a, b in faces.pairs:
            slave = _facing(bodies, faces.bottom[b], a, 1.0)
            master = _facing(bodies, faces.top[a], b, 1.0)
            _surface(f, f"S_{b + 1}_ON_{a + 1}", slave)
            _surface(f, f"S_{a + 1}_UNDER_{b + 1}", master)
            f.write(f"*TIE, NAME=T{a + 1}_{b + 1}, POSITION TOLERANCE={reach_mm:.9g}, ADJUST=NO\n")
            f.write(f"S_{b + 1}_ON_{a + 1}, S_{a + 1}_UNDER_{b + 1}\n")
        bottom, top = platen_nodes(faces)
        _nset(f, "ON_CONVEYOR", bottom)
        _nset(f, "UNDER_PLATE", top)
        f.write("*STEP\n*STATIC\n*BOUNDARY\nON_CONVEYOR, 1, 3, 0.\n")
        f.write(f"UNDER_PLATE, 1, 2, 0.\nUNDER_PLATE, 3, 3, {-travel_mm:.12g}\n")
        f.write("*NODE PRINT, NSET=UNDER_PLATE\nRF\n*END STEP\n")
    return faces


def calculix_bonded(
    folder: Path,
    bodies: PressBodies,
    platens: Platens,
    material: ChipMaterial,
    travel_mm: float = 0.01,
    reach_mm: float = 0.1,
) -> float:
    """The bonded stack's stiffness, N/mm: its press plate's force over the travel
    (:func:`write_bonded_deck`, linear, so independent of ``travel_mm``)."""
    write_bonded_deck(folder, bodies, platens, material, travel_mm, reach_mm)
    run_ccx(Path(folder), "bonded", threads=1)
    prints = read_node_prints(Path(folder) / "bonded.dat")
    return float(-prints["UNDER_PLATE"]["forces"][-1, 2] / travel_mm)
