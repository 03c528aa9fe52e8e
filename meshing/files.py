"""Mesh files, registered by format name: gmsh 4 (.msh), VTK (.vtu + .pvd), Abaqus and
CalculiX (.inp), XDMF for FEniCS (.xdmf + .h5), and a PNG picture.

Every writer takes the path to write and a :class:`meshing.VolumeMesh`; the run directory
manager decides where the path is.
"""

from __future__ import annotations

import logging
from pathlib import Path

import meshio
import numpy as np

from chipstack.export.figure_kinds import FIGURES, FigureKind
from chipstack.meshing.boundaries import FACET_TAGS
from chipstack.meshing.formats import MESH_FORMATS
from chipstack.meshing.gmsh_session import GmshSession
from chipstack.meshing.interfaces import find_interfaces
from chipstack.meshing.mesh import VolumeMesh, region_name

__all__ = ["MESH_FORMATS", "write_mesh", "to_meshio", "MATERIALS", "facets", "FACET_TAGS"]

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

log = logging.getLogger(__name__)


def to_meshio(mesh: VolumeMesh):
    """The mesh as a ``meshio.Mesh`` with cell data region (the region id: chip k of the
    packing tables is k + 1, the pore space n_chips + 1; see ``VolumeMesh.region``),
    batch, layer, fibre_1, fibre_2, normal (the chip's material frame: its plies'
    in-plane directions and its normal, in the world frame; zeros in the pore space),
    quality (one value or vector per element), and for a voxel mesh voxel (i, j, k) of
    each hexahedron on the lattice its info's ``lattice`` states."""

    extra = {}
    if mesh.voxel is not None:
        extra["voxel"] = [np.asarray(mesh.voxel, dtype=np.int32)]
    return meshio.Mesh(
        np.asarray(mesh.points, dtype=float),
        [(mesh.cell_type, np.asarray(mesh.cells, dtype=np.int64))],
        cell_data={
            "region": [np.asarray(mesh.region, dtype=np.int32)],
            "batch": [np.asarray(mesh.batch, dtype=np.int32)],
            "layer": [np.asarray(mesh.layer, dtype=np.int32)],
            "fibre_1": [np.asarray(mesh.fibres[:, 0], dtype=float)],
            "fibre_2": [np.asarray(mesh.fibres[:, 1], dtype=float)],
            "normal": [np.asarray(mesh.normals, dtype=float)],
            "quality": [np.asarray(mesh.quality, dtype=float)],
            **extra,
        },
    )


def interface_surface(mesh: VolumeMesh):
    """The faces chips share as a ``meshio.Mesh`` (triangles or quads) with cell data
    interface (its tag), region_a and region_b (the two chips' region ids), or None when
    no chips touch."""

    found = find_interfaces(mesh)
    if not len(found.pairs):
        return None
    return meshio.Mesh(
        np.asarray(mesh.points, dtype=float),
        [(_MESHIO_FACET[found.faces.shape[1]], found.faces.astype(np.int64))],
        cell_data={
            "interface": [found.tags[found.pair].astype(np.int32)],
            "region_a": [found.pairs[found.pair, 0].astype(np.int32) + 1],
            "region_b": [found.pairs[found.pair, 1].astype(np.int32) + 1],
        },
    )


def write_vtu(path: Path, mesh: VolumeMesh) -> list[Path]:
    """VTK unstructured grid (binary, compressed) and a one-step .pvd beside it; the
    faces chips share as a surface mesh in ``<stem>_interfaces.vtu`` (cell data
    interface, region_a, region_b; see :func:`interface_surface`)."""

    path = Path(path)
    meshio.write(path, to_meshio(mesh), file_format="vtu", binary=True)
    written = [path]
    if (surface := interface_surface(mesh)) is not None:
        shared = path.with_name(f"{path.stem}_interfaces.vtu")
        meshio.write(shared, surface, file_format="vtu", binary=True)
        written.append(shared)
    pvd = path.with_suffix(".pvd")
    pvd.write_text(
        '<?xml version="1.0"?>\n'
        '<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">\n'
        f'  <Collection>\n    <DataSet timestep="0" part="0" file="{path.name}"/>\n'
        "  </Collection>\n</VTKFile>\n"
    )
    return [*written, pvd]


_GMSH_TYPE = {"tetra": 4, "hexahedron": 5}  # gmsh and VTK share these node orders
_GMSH_FACET = {3: 2, 4: 3}  # triangle, quadrangle
_MESHIO_FACET = {3: "triangle", 4: "quad"}


def facets(mesh: VolumeMesh) -> dict[str, np.ndarray]:
    """The faces of each platen and support surface the mesh has (``VolumeMesh.surfaces``:
    ``top``, ``bottom``, and the sides of a box or crop; tags in ``FACET_TAGS``), as node
    indices ordered so that the normal points out."""
    return {name: surface.nodes for name, surface in mesh.surfaces.items()}


def write_msh(path: Path, mesh: VolumeMesh) -> list[Path]:
    """gmsh 4.1 (binary): one discrete volume and physical group per region (its tag the
    region id, named ``chip_<id>`` or ``pore``); the platen and support surfaces as
    physical surfaces (tags and names in ``FACET_TAGS``: top, bottom, and the sides of a
    box or crop); the faces each pair of touching chips shares as a physical surface
    named interface_A_B (region ids; tags from ``INTERFACE_TAG_START``)."""

    path = Path(path)
    physical = mesh.region
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
            name = region_name(int(tag), mesh.n_chips)
            model.setPhysicalName(3, model.addPhysicalGroup(3, [int(tag)], int(tag)), name)
        for side, faces in facets(mesh).items():  # facet tags, as FEniCS reads them
            tag = FACET_TAGS[side]
            model.addDiscreteEntity(2, tag)
            model.mesh.addElementsByType(
                tag, _GMSH_FACET[faces.shape[1]], np.arange(first, first + len(faces)),
                (faces + 1).ravel(),
            )  # fmt: skip
            first += len(faces)
            model.setPhysicalName(2, model.addPhysicalGroup(2, [tag], tag), side)
        shared = find_interfaces(mesh)
        for k, (tag, part) in enumerate(zip(shared.tags.tolist(), shared.parts(), strict=True)):
            faces = shared.faces[part]
            model.addDiscreteEntity(2, tag)
            model.mesh.addElementsByType(
                tag,
                _GMSH_FACET[faces.shape[1]],
                np.arange(first, first + len(faces)),
                (faces + 1).ravel(),
            )
            first += len(faces)
            model.setPhysicalName(2, model.addPhysicalGroup(2, [tag], tag), shared.name(k))
        gmsh.option.setNumber("Mesh.Binary", 1)
        gmsh.write(str(path))
    return [path]


def write_xdmf(path: Path, mesh: VolumeMesh) -> list[Path]:
    """XDMF with its heavy data in HDF5 (.h5 beside it), as DOLFINx reads it: the grid
    ``mesh`` with the cell data of :func:`to_meshio` (``region`` among them); the platen
    and support surfaces (tags in ``FACET_TAGS``) and the faces each pair of touching
    chips shares (tags from ``INTERFACE_TAG_START``, as listed in the interface table)
    as the grid ``facets`` with its attribute ``facets`` in ``<stem>_facets.xdmf``.

    The HDF5 datasets are uncompressed: the HDF5 of DOLFINx's PyPI wheel has no deflate
    filter and cannot read gzip-compressed ones."""

    path = Path(path)
    _write_xdmf_grid(path, to_meshio(mesh), "mesh")
    written = [path, path.with_suffix(".h5")]
    tagged = [
        (faces, np.full(len(faces), FACET_TAGS[side], np.int32))
        for side, faces in facets(mesh).items()
    ]
    shared = find_interfaces(mesh)
    if len(shared.pairs):
        tagged.append((shared.faces, shared.tags[shared.pair].astype(np.int32)))
    if tagged:
        by_size: dict[int, list] = {}
        for faces, tag in tagged:
            by_size.setdefault(faces.shape[1], []).append((faces, tag))
        cells, tags = [], []
        for size, groups in sorted(by_size.items()):
            cells.append((_MESHIO_FACET[size], np.concatenate([f for f, _ in groups])))
            tags.append(np.concatenate([t for _, t in groups]))
        facet_path = path.with_name(f"{path.stem}_facets.xdmf")
        faces = meshio.Mesh(np.asarray(mesh.points, dtype=float), cells, cell_data={"facets": tags})
        _write_xdmf_grid(facet_path, faces, "facets")
        written += [facet_path, facet_path.with_suffix(".h5")]
    return written


def _write_xdmf_grid(path: Path, mesh, name: str) -> None:
    """meshio's XDMF, uncompressed, its one grid named ``name`` (meshio names every grid
    ``Grid``; DOLFINx finds a grid by its name)."""
    meshio.xdmf.write(path, mesh, data_format="HDF", compression=None)
    text = path.read_text()
    path.write_text(text.replace('<Grid Name="Grid"', f'<Grid Name="{name}"', 1))


_INP_ELEMENT = {"tetra": "C3D4", "hexahedron": "C3D8"}


def _write_ids(f, ids: np.ndarray) -> None:
    """Abaqus lists: at most 16 entries per line, 1-based."""
    ids = np.asarray(ids) + 1
    for start in range(0, len(ids), 16):
        f.write(", ".join(map(str, ids[start : start + 16])) + "\n")


def _write_rows(f, rows: np.ndarray, row_format: str, chunk: int = 65536) -> None:
    """``rows`` as text, ``row_format`` per row: the bytes ``np.savetxt`` writes, formatted
    a chunk of rows at a time rather than row by row (8.6 s for a 1.5 million element
    deck's nodes and elements with savetxt)."""
    for start in range(0, len(rows), chunk):
        part = rows[start : start + chunk]
        f.write((row_format * len(part)) % tuple(part.ravel().tolist()))


def write_inp(path: Path, mesh: VolumeMesh) -> list[Path]:
    """Abaqus / CalculiX input: nodes (one ``*NODE`` block, a periodic box's reference
    nodes included), elements, an element set per region (``CHIP_<id>``, four digits, and
    ``PORE``; ids as in every mesh file) and a material orientation per chip (local 1
    along its first fibre direction, 2 along the second), the platen and support surfaces
    as element-based ``*SURFACE``s (TOP, BOTTOM and, for a box or crop, XMIN ... YMAX)
    with node sets of the same names, LATERAL (the four side planes' nodes), each pair of
    touching chips' shared faces as two element-based surfaces IF_AAAA_BBBB_A and
    IF_AAAA_BBBB_B (region ids; the faces of chip A's and of chip B's elements: a tie,
    contact or cohesive pair), sections and materials (MPa, mm); for a periodic box, the
    reference nodes REF_X, REF_Y and the *EQUATION ties of opposite sides. Analysis steps
    are the user's."""
    path = Path(path)
    n = len(mesh.points)
    with open(path, "w") as f:
        f.write("** chipstack mesh: units mm, N, MPa\n*HEADING\nchip stack\n*NODE, NSET=NALL\n")
        rows = np.column_stack([np.arange(1, n + 1), mesh.points])
        if mesh.periodic is not None:
            # In the same block: meshio (and other readers) keep only the last *NODE block.
            rows = np.vstack([rows, np.column_stack([[n + 1, n + 2], _reference_points(mesh)])])
        _write_rows(f, rows, "%d, %.9g, %.9g, %.9g\n")
        f.write(f"*ELEMENT, TYPE={_INP_ELEMENT[mesh.cell_type]}, ELSET=EALL\n")
        cells = np.column_stack([np.arange(1, mesh.n_elements + 1), mesh.cells + 1])
        _write_rows(f, cells, ", ".join(["%d"] * cells.shape[1]) + "\n")
        region = mesh.region
        order = np.argsort(region, kind="stable")
        regions, starts = np.unique(region[order], return_index=True)
        groups = np.split(order, starts[1:])
        for tag, members in zip(regions.tolist(), groups, strict=True):
            f.write(f"*ELSET, ELSET={_inp_region(tag, mesh.n_chips)}\n")
            _write_ids(f, members)
        surfaces = mesh.surfaces
        node_sets = {**mesh.node_sets, **{k: s.node_ids for k, s in surfaces.items()}}
        for name, nodes in node_sets.items():
            f.write(f"*NSET, NSET={name.upper()}\n")
            _write_ids(f, nodes)
        for name, surface in surfaces.items():
            f.write(f"*SURFACE, NAME={name.upper()}, TYPE=ELEMENT\n")
            _write_rows(f, np.column_stack([surface.element + 1, surface.face + 1]), "%d, S%d\n")
        _write_interfaces(f, mesh)
        if mesh.periodic is not None:
            _write_periodic(f, mesh)
        c = MATERIALS["CHIP"]
        f.write("*MATERIAL, NAME=CHIP\n*ELASTIC, TYPE=ENGINEERING CONSTANTS\n")
        f.write(
            f"{c['E1']}, {c['E2']}, {c['E3']}, {c['nu12']}, {c['nu13']}, {c['nu23']}, "
            f"{c['G12']}, {c['G13']}\n{c['G23']}\n"
        )
        p = MATERIALS["PORE"]
        f.write(f"*MATERIAL, NAME=PORE\n*ELASTIC\n{p['E']}, {p['nu']}\n")
        for tag, members in zip(regions.tolist(), groups, strict=True):
            if tag == mesh.pore_region:
                f.write("*SOLID SECTION, ELSET=PORE, MATERIAL=PORE\n")
                continue
            a, b = mesh.fibres[members[0], 0], mesh.fibres[members[0], 1]
            if abs(a @ b) > 1 - 1e-6:  # one fibre direction: the in-plane normal to it
                b = np.cross(mesh.normals[members[0]], a)
            f.write(f"*ORIENTATION, NAME=OR_{tag:04d}, SYSTEM=RECTANGULAR\n")
            f.write(", ".join(f"{v:.9g}" for v in (*a, *b)) + "\n")
            f.write(
                f"*SOLID SECTION, ELSET=CHIP_{tag:04d}, MATERIAL=CHIP, ORIENTATION=OR_{tag:04d}\n"
            )
    return [path]


def _inp_region(region: int, n_chips: int) -> str:
    """A region's element set name in the .inp: ``CHIP_<id>`` (four digits) or ``PORE``."""
    return f"CHIP_{region:04d}" if region <= n_chips else "PORE"


def _write_interfaces(f, mesh: VolumeMesh) -> None:
    """Both sides of every interface as element-based surfaces (face label S1 ... S6),
    named by the two chips' region ids."""
    shared = find_interfaces(mesh)
    for (a, b), part in zip((shared.pairs + 1).tolist(), shared.parts(), strict=True):
        for side, elements, faces in (
            ("A", shared.element_a[part], shared.face_a[part]),
            ("B", shared.element_b[part], shared.face_b[part]),
        ):
            f.write(f"*SURFACE, NAME=IF_{a:04d}_{b:04d}_{side}, TYPE=ELEMENT\n")
            f.writelines(f"{e + 1}, S{s + 1}\n" for e, s in zip(elements, faces, strict=True))


def _reference_points(mesh: VolumeMesh) -> np.ndarray:
    """(2, 3) where the periodic box's reference nodes REF_X and REF_Y sit: one unit past
    the box's far corner along x and along y (their place is immaterial to the ties)."""
    corner = mesh.points.max(axis=0)
    return np.array([corner + (1.0, 0.0, 0.0), corner + (0.0, 1.0, 0.0)])


def _write_periodic(f, mesh: VolumeMesh) -> None:
    """Node sets of the reference nodes REF_X and REF_Y (written with the others: their
    displacement is the jump across the box along x and along y) and one *EQUATION per
    tied node and direction: u(dependent) - u(twin) - u(REF_X) [- u(REF_Y)] = 0; z is not
    tied on the top and bottom faces, which the platens press."""
    pairs = mesh.periodic
    n = len(mesh.points)
    f.write(f"*NSET, NSET=REF_X\n{n + 1}\n*NSET, NSET=REF_Y\n{n + 2}\n")
    f.write("*EQUATION\n")
    references = np.array([n + 1, n + 2])
    for dependent, twin, shifts, on_platen in zip(
        pairs.dependent + 1, pairs.independent + 1, pairs.shifts, pairs.on_platen, strict=True
    ):
        for dof in (1, 2) if on_platen else (1, 2, 3):
            terms = [(dependent, 1.0), (twin, -1.0)] + [(r, -1.0) for r in references[shifts]]
            f.write(f"{len(terms)}\n")
            f.write(", ".join(f"{node}, {dof}, {c:g}" for node, c in terms) + "\n")


def write_mesh(folder: Path, stem: str, mesh: VolumeMesh, formats: list[str]) -> list[Path]:
    """Write ``mesh`` as ``folder/stem.<format>`` for each format name; returns the files."""
    written = []
    for name in formats:
        written += MESH_FORMATS.get(name, key="--formats")(Path(folder) / f"{stem}.{name}", mesh)
    return written


def _mesh_view(folder: Path, picture) -> list[str]:
    """The mesh's outer surface coloured by chip (pores hidden), rendered off screen."""
    import pyvista

    from chipstack.export import render

    mesh = picture.mesh
    path = folder / f"{picture.stem}.png"
    grid = pyvista.from_meshio(to_meshio(mesh))
    grid = grid.extract_cells(np.flatnonzero(np.asarray(mesh.chip) >= 0))
    surface = grid.extract_surface(algorithm="dataset_surface")
    try:
        # Element edges show the mesh; on a million elements they only darken the picture.
        render.render_stack(path, surface, show_edges=surface.n_cells < 100_000)
    except RuntimeError as exc:
        log.warning("mesh picture not rendered: %s", exc)
        return []
    return [path.name]


FIGURES.register(
    "mesh_view",
    FigureKind(
        "mesh_view",
        "mesh",
        "stack_<kind>.png",
        "the mesh's outer surface coloured by chip, pores hidden (needs OpenGL)",
        _mesh_view,
    ),
)
