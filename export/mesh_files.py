"""Mesh files, registered by format name: gmsh 4 (.msh), VTK (.vtu + .pvd), Abaqus and
CalculiX (.inp), XDMF for FEniCS (.xdmf + .h5), and a PNG picture.

Every writer takes the path to write and a :class:`meshing.VolumeMesh`; the run directory
manager decides where the path is.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from core.registry import Registry
from meshing.mesh import PORE, VolumeMesh

__all__ = ["MESH_FORMATS", "write_mesh", "to_meshio", "MATERIALS"]

# Linear-elastic placeholders for a first consolidation model (MPa): the chip is PA6 with
# 60 wt % balanced glass twill (packing paper 2.2: 18 GPa tensile in warp and weft); the
# through-thickness and shear values are typical of woven glass/PA6 laminates. The pore
# space is given solid PA6 (a matrix-rich zone once consolidated).
MATERIALS = {
    "CHIP": {
        "E1": 18000.0,
        "E2": 18000.0,
        "E3": 8000.0,
        "nu12": 0.12,
        "nu13": 0.35,
        "nu23": 0.35,
        "G12": 3000.0,
        "G13": 2500.0,
        "G23": 2500.0,
    },
    "PORE": {"E": 2000.0, "nu": 0.35},
}

MESH_FORMATS: Registry[Callable[[Path, VolumeMesh], list[Path]]] = Registry("mesh format")


def _format(name: str):
    def wrap(function):
        MESH_FORMATS.register(name, function)
        return function

    return wrap


def to_meshio(mesh: VolumeMesh):
    """The mesh as a ``meshio.Mesh`` with cell data chip, batch, layer, fibre_1, fibre_2,
    quality (one value or vector per element)."""
    import meshio

    return meshio.Mesh(
        np.asarray(mesh.points, dtype=float),
        [(mesh.cell_type, np.asarray(mesh.cells, dtype=np.int64))],
        cell_data={
            "chip": [np.asarray(mesh.chip, dtype=np.int32)],
            "batch": [np.asarray(mesh.batch, dtype=np.int32)],
            "layer": [np.asarray(mesh.layer, dtype=np.int32)],
            "fibre_1": [np.asarray(mesh.fibres[:, 0], dtype=float)],
            "fibre_2": [np.asarray(mesh.fibres[:, 1], dtype=float)],
            "quality": [np.asarray(mesh.quality, dtype=float)],
        },
    )


@_format("vtu")
def write_vtu(path: Path, mesh: VolumeMesh) -> list[Path]:
    """VTK unstructured grid (binary, compressed) and a one-step .pvd beside it."""
    import meshio

    path = Path(path)
    meshio.write(path, to_meshio(mesh), file_format="vtu", binary=True)
    pvd = path.with_suffix(".pvd")
    pvd.write_text(
        '<?xml version="1.0"?>\n'
        '<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">\n'
        f'  <Collection>\n    <DataSet timestep="0" part="0" file="{path.name}"/>\n'
        "  </Collection>\n</VTKFile>\n"
    )
    return [path, pvd]


_GMSH_TYPE = {"tetra": 4, "hexahedron": 5}  # gmsh and VTK share these node orders


@_format("msh")
def write_msh(path: Path, mesh: VolumeMesh) -> list[Path]:
    """gmsh 4.1 (binary): one discrete volume and physical group per chip (tag k + 1,
    named chip_K) and one for the pores (tag n + 1, named pore)."""
    from meshing.conformal import GmshSession

    path = Path(path)
    physical = np.where(mesh.chip >= 0, mesh.chip + 1, mesh.n_chips + 1).astype(np.int64)
    order = np.argsort(physical, kind="stable")
    tags, starts = np.unique(physical[order], return_index=True)
    blocks = np.split(order, starts[1:])
    with GmshSession() as gmsh:
        model = gmsh.model
        for tag in tags:
            model.addDiscreteEntity(3, int(tag))
        # Every node lives on the first volume; elements of the others refer to them.
        model.mesh.addNodes(
            3, int(tags[0]), np.arange(1, len(mesh.points) + 1), mesh.points.ravel()
        )
        first = 1
        for tag, block in zip(tags, blocks, strict=True):
            model.mesh.addElementsByType(
                int(tag),
                _GMSH_TYPE[mesh.cell_type],
                np.arange(first, first + len(block)),
                (mesh.cells[block] + 1).ravel(),
            )
            first += len(block)
            name = f"chip_{tag - 1}" if tag <= mesh.n_chips else "pore"
            model.setPhysicalName(3, model.addPhysicalGroup(3, [int(tag)], int(tag)), name)
        gmsh.option.setNumber("Mesh.Binary", 1)
        gmsh.write(str(path))
    return [path]


@_format("xdmf")
def write_xdmf(path: Path, mesh: VolumeMesh) -> list[Path]:
    """XDMF with its heavy data in HDF5 (.h5 beside it), as FEniCS reads it."""
    import meshio

    path = Path(path)
    meshio.write(path, to_meshio(mesh), file_format="xdmf")
    return [path, path.with_suffix(".h5")]


_INP_ELEMENT = {"tetra": "C3D4", "hexahedron": "C3D8"}


def _write_ids(f, ids: np.ndarray) -> None:
    """Abaqus lists: at most 16 entries per line, 1-based."""
    ids = np.asarray(ids) + 1
    for start in range(0, len(ids), 16):
        f.write(", ".join(map(str, ids[start : start + 16])) + "\n")


@_format("inp")
def write_inp(path: Path, mesh: VolumeMesh) -> list[Path]:
    """Abaqus / CalculiX input: nodes, elements, an element set and a material orientation
    per chip (local 1 along its first fibre direction, 2 along the second), node sets
    for the platens (BOTTOM, TOP) and the sides (LATERAL), sections and materials (MPa,
    mm). Analysis steps are the user's."""
    path = Path(path)
    with open(path, "w") as f:
        f.write("** chipstack mesh: units mm, N, MPa\n*HEADING\nchip stack\n*NODE, NSET=NALL\n")
        rows = np.column_stack([np.arange(1, len(mesh.points) + 1), mesh.points])
        np.savetxt(f, rows, fmt=["%d", "%.9g", "%.9g", "%.9g"], delimiter=", ")
        f.write(f"*ELEMENT, TYPE={_INP_ELEMENT[mesh.cell_type]}, ELSET=EALL\n")
        cells = np.column_stack([np.arange(1, mesh.n_elements + 1), mesh.cells + 1])
        np.savetxt(f, cells, fmt="%d", delimiter=", ")
        order = np.argsort(mesh.chip, kind="stable")
        chips, starts = np.unique(mesh.chip[order], return_index=True)
        groups = np.split(order, starts[1:])
        for chip, members in zip(chips, groups, strict=True):
            name = "PORE" if chip == PORE else f"CHIP_{chip:04d}"
            f.write(f"*ELSET, ELSET={name}\n")
            _write_ids(f, members)
        for name, nodes in mesh.node_sets.items():
            f.write(f"*NSET, NSET={name.upper()}\n")
            _write_ids(f, nodes)
        chip_material = MATERIALS["CHIP"]
        c = chip_material
        f.write("*MATERIAL, NAME=CHIP\n*ELASTIC, TYPE=ENGINEERING CONSTANTS\n")
        f.write(
            f"{c['E1']}, {c['E2']}, {c['E3']}, {c['nu12']}, {c['nu13']}, {c['nu23']}, "
            f"{c['G12']}, {c['G13']}\n{c['G23']}\n"
        )
        p = MATERIALS["PORE"]
        f.write(f"*MATERIAL, NAME=PORE\n*ELASTIC\n{p['E']}, {p['nu']}\n")
        for chip, members in zip(chips, groups, strict=True):
            if chip == PORE:
                f.write("*SOLID SECTION, ELSET=PORE, MATERIAL=PORE\n")
                continue
            a, b = mesh.fibres[members[0], 0], mesh.fibres[members[0], 1]
            if abs(a @ b) > 1 - 1e-6:  # one fibre direction: the in-plane normal to it
                b = np.cross(mesh.normals[members[0]], a)
            f.write(f"*ORIENTATION, NAME=OR_{chip:04d}, SYSTEM=RECTANGULAR\n")
            f.write(", ".join(f"{v:.9g}" for v in (*a, *b)) + "\n")
            f.write(
                f"*SOLID SECTION, ELSET=CHIP_{chip:04d}, MATERIAL=CHIP, ORIENTATION=OR_{chip:04d}\n"
            )
    return [path]


def write_mesh(folder: Path, stem: str, mesh: VolumeMesh, formats: list[str]) -> list[Path]:
    """Write ``mesh`` as ``folder/stem.<format>`` for each format name; returns the files."""
    written = []
    for name in formats:
        written += MESH_FORMATS.get(name, key="--formats")(Path(folder) / f"{stem}.{name}", mesh)
    return written
