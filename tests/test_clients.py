"""A run's mesh files as the clients users run read them: gmsh, meshio and pyvista (in the
project's environment), DOLFINx (``.venv-dolfinx``, ``make dolfinx``), ParaView's
``pvpython`` (under ``xvfb-run``) and CalculiX, on a small stack (chips only) and on the
reference crop (the paper's stack cropped to 30 x 30 mm with its pore space). Each checks
what ``docs/run-directory.md`` says of the files: one region id per chip and for the pore
in every format, the surfaces ``top``, ``bottom`` (and the crop's sides) by name and tag,
every node and cell. DOLFINx and CalculiX press the crop alike and their platen forces
agree; every built-in scenario that meshes gives each region the same elements in the
.msh, .vtu and .xdmf.

The client scripts are in ``tests/clients/`` (they print JSON); the crop and the small
stack are built once for the module.
"""

from __future__ import annotations

import csv
import json
from importlib import resources
from pathlib import Path

import gmsh
import meshio
import numpy as np
import pytest
import pyvista
from clients import solvers
from parts import needs

from chipstack.meshing.boundaries import FACET_TAGS

BOX_SURFACES = ("bottom", "top", "xmin", "xmax", "ymin", "ymax")


class Stack:
    """A run directory's voxel mesh files and what its own records say of them."""

    def __init__(self, name: str, run: Path) -> None:
        self.name, self.run = name, run
        self.mesh = run / "mesh"
        self.stem = self.mesh / "stack_voxel"
        self.checks = json.loads((self.mesh / "stack_voxel_checks.json").read_text())
        manifest = json.loads((run / "manifest.json").read_text())
        self.chips = int(manifest["packing"]["chips"])
        self.batches = len(manifest["packing"]["batches"])
        self.pore = self.chips + 1  # the pore's region id
        self.surfaces = {name: s["faces"] for name, s in self.checks["surfaces"].items()}
        grid = meshio.read(f"{self.stem}.vtu")
        self.regions = _region_counts(grid.cells, grid.cell_data["region"])

    def path(self, suffix: str) -> Path:
        return Path(f"{self.stem}{suffix}")


def _region_counts(blocks, data) -> dict[int, int]:
    """Region id -> cells, over the volume blocks of a meshio mesh."""
    values = np.concatenate(
        [np.asarray(d).ravel() for c, d in zip(blocks, data, strict=True) if c.dim == 3]
    )
    ids, counts = np.unique(values, return_counts=True)
    return dict(zip(ids.tolist(), counts.tolist(), strict=True))


@pytest.fixture(scope="module")
def crop(tmp_path_factory) -> Stack:
    """The reference crop (``solvers.CROP_SCENARIO`` with ``CROP_OVERRIDES``)."""
    out = tmp_path_factory.mktemp("clients") / "crop"
    run = solvers.build(solvers.CROP_SCENARIO, solvers.CROP_OVERRIDES, out, ["stack"])
    return Stack("crop", run)


@pytest.fixture(scope="module")
def small(tmp_path_factory) -> Stack:
    """The small stack (``solvers.SMALL_SCENARIO`` with ``SMALL_OVERRIDES``), with the
    geometry's voxel image (``voxels.vti``, on the mesh's 1 mm lattice)."""
    out = tmp_path_factory.mktemp("clients") / "small"
    run = solvers.build(solvers.SMALL_SCENARIO, solvers.SMALL_OVERRIDES, out, ["voxels"])
    return Stack("small", run)


@pytest.fixture(params=["small", "crop"])
def stack(request) -> Stack:
    return request.getfixturevalue(request.param)


def test_the_stacks_are_what_the_tests_claim(small, crop):
    """The crop is a full 30 x 30 mm box of hexahedra with every side; the small stack is
    chips only, top and bottom."""
    assert crop.chips == 270 and small.chips == 24
    assert crop.checks["bounds_mm"][0][:2] == [-15.0, -15.0]
    assert crop.checks["bounds_mm"][1][:2] == [15.0, 15.0]
    height = crop.checks["bounds_mm"][1][2] - crop.checks["bounds_mm"][0][2]
    assert crop.checks["elements"] == 30 * 30 * height  # 1 mm voxels, the pore filled
    assert set(crop.surfaces) == set(BOX_SURFACES) and set(small.surfaces) == {"top", "bottom"}
    assert crop.pore in crop.regions and small.pore not in small.regions
    assert sorted(small.regions) == list(range(1, 25))


def test_gmsh_names_every_region_and_surface(stack):
    """gmsh's Python API lists a physical volume per region, tag = region id, named
    ``chip_<id>`` (``pore`` for the pore space), and the surfaces by their names and
    facet tags, each with the faces the check report counts."""
    gmsh.initialize(["", "-noenv"], readConfigFiles=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.open(str(stack.path(".msh")))
        groups = {}
        for dim, tag in gmsh.model.getPhysicalGroups():
            name = gmsh.model.getPhysicalName(dim, tag)
            elements = 0
            for entity in gmsh.model.getEntitiesForPhysicalGroup(dim, tag):
                _, tags, _ = gmsh.model.mesh.getElements(dim, entity)
                elements += sum(len(t) for t in tags)
            groups[dim, tag] = (name, elements)
    finally:
        gmsh.finalize()
    volumes = {tag: value for (dim, tag), value in groups.items() if dim == 3}
    expected = {
        k: ("pore" if k == stack.pore else f"chip_{k}", n) for k, n in stack.regions.items()
    }
    assert volumes == expected
    surfaces = {name: (tag, n) for (dim, tag), (name, n) in groups.items() if dim == 2}
    for name, faces in stack.surfaces.items():
        assert surfaces[name] == (FACET_TAGS[name], faces)
    interfaces = {n for n in surfaces if n.startswith("interface_")}
    assert set(surfaces) == set(stack.surfaces) | interfaces and interfaces


def test_meshio_reads_every_node_cell_set_and_tag(stack):
    """meshio reads the .inp whole (every node, every hexahedron, the chip and pore
    element sets by region id, the node sets TOP and BOTTOM on their planes), the .msh's
    tags and names, the .xdmf's ``region`` and the facet file's ``facets``."""
    nodes, elements = stack.checks["nodes"], stack.checks["elements"]
    deck = meshio.read(stack.path(".inp"))
    assert len(deck.points) == nodes
    assert [(c.type, len(c.data)) for c in deck.cells] == [("hexahedron", elements)]
    sets = {name: sum(len(i) for i in ids) for name, ids in deck.cell_sets.items()}
    expected = {
        ("PORE" if k == stack.pore else f"CHIP_{k:04d}"): n for k, n in stack.regions.items()
    }
    assert {k: v for k, v in sets.items() if k.startswith(("CHIP_", "PORE"))} == expected
    z = deck.points[:, 2]
    assert np.all(z[deck.point_sets["BOTTOM"]] == z.min())
    if stack.name == "crop":  # the box's top plane; the small stack's top is its envelope
        assert np.all(z[deck.point_sets["TOP"]] == z.max())
        assert len(deck.point_sets["TOP"]) == 31 * 31
    assert len(deck.point_sets["TOP"]) == stack.checks["surfaces"]["top"]["nodes"]

    msh = meshio.read(stack.path(".msh"))
    assert len(msh.points) == nodes
    assert _region_counts(msh.cells, msh.cell_data["gmsh:physical"]) == stack.regions
    for name in stack.surfaces:
        assert msh.field_data[name].tolist() == [FACET_TAGS[name], 2]
    assert msh.field_data["chip_1" if stack.name == "small" else "pore"][1] == 3

    xdmf = meshio.read(stack.path(".xdmf"))
    assert len(xdmf.points) == nodes
    assert _region_counts(xdmf.cells, xdmf.cell_data["region"]) == stack.regions
    facets = meshio.read(stack.path("_facets.xdmf"))
    tags, counts = np.unique(np.concatenate(facets.cell_data["facets"]), return_counts=True)
    found = dict(zip(tags.tolist(), counts.tolist(), strict=True))
    assert {FACET_TAGS[n]: found[FACET_TAGS[n]] for n in stack.surfaces} == {
        FACET_TAGS[n]: f for n, f in stack.surfaces.items()
    }
    with open(stack.path("_interfaces.csv")) as file:
        # the pairs sharing faces (the table also lists contacts that share none, tag -1)
        interface_tags = {int(r["tag"]) for r in csv.DictReader(file) if int(r["faces"]) > 0}
    assert set(found) == {FACET_TAGS[n] for n in stack.surfaces} | interface_tags


def test_pyvista_reads_the_vtu_the_pvd_and_the_voxel_image_on_one_lattice(small):
    """pyvista reads ``region`` from the .vtu and its .pvd, and each hexahedron lies in
    the voxel of ``voxels.vti`` that holds the same region id (one lattice, 1 mm)."""
    grid = pyvista.read(small.path(".vtu"))
    assert grid.n_cells == small.checks["elements"]
    series = pyvista.read(small.path(".pvd"))
    assert np.array_equal(series[0].cell_data["region"], grid.cell_data["region"])
    image = pyvista.read(small.run / "geometry" / "voxels.vti")
    found = image.find_containing_cell(grid.cell_centers().points)
    assert not np.any(found == -1)  # pyvista's -1: a centre outside the image
    assert np.array_equal(image.cell_data["region"][found], grid.cell_data["region"])
    # the image's other voxels are void: the pore's id
    void = np.setdiff1d(np.arange(image.n_cells), found)
    assert np.all(image.cell_data["region"][void] == small.pore)


@needs("dolfinx")
def test_dolfinx_reads_the_msh_and_the_xdmf_alike(stack):
    """DOLFINx reads the .msh (``read_from_msh``: cell tags = region ids, facet tags =
    the surfaces' tags, gmsh's names) and the .xdmf (grid ``mesh``, tags ``region``; the
    facet file's grid ``facets``, attribute ``facets``) to the same mesh and tags."""
    found, _ = solvers.dolfinx("dolfinx_open.py", stack.stem)
    regions = {str(k): n for k, n in stack.regions.items()}
    surfaces = {str(FACET_TAGS[name]): n for name, n in stack.surfaces.items()}
    for kind in ("msh", "xdmf"):
        read = found[kind]
        assert (read["cells"], read["nodes"], read["cell_type"]) == (
            stack.checks["elements"],
            stack.checks["nodes"],
            "hexahedron",
        ), kind
        assert read["regions"] == regions, kind
        assert {k: v for k, v in read["facets"].items() if k in surfaces} == surfaces, kind
    assert found["msh"]["facets"] == found["xdmf"]["facets"]
    names = found["names"]
    assert {names[f"2/{FACET_TAGS[n]}"] for n in stack.surfaces} == set(stack.surfaces)
    for region in stack.regions:
        assert names[f"3/{region}"] == ("pore" if region == stack.pore else f"chip_{region}")


@needs("paraview")
def test_paraview_opens_every_file(stack):
    """``pvpython`` (under ``xvfb-run``) opens the .vtu, .pvd, .xdmf, the facet file and
    the packing's ``stack.pvd`` (a time step per batch), and for the small stack the
    voxel image: each with every cell, ``region`` holding the region ids."""
    files = [stack.path(s) for s in (".vtu", ".pvd", ".xdmf", "_facets.xdmf")]
    files.append(stack.run / "packing" / "stack.pvd")
    if stack.name == "small":
        files.append(stack.run / "geometry" / "voxels.vti")
    found, _ = solvers.paraview(*files)
    found = {Path(k).name if "packing" not in k else "packing.pvd": v for k, v in found.items()}
    ids = sorted(stack.regions)
    for name in ("stack_voxel.vtu", "stack_voxel.pvd", "stack_voxel.xdmf"):
        read = found[name]
        assert (read["cells"], read["points"]) == (
            stack.checks["elements"],
            stack.checks["nodes"],
        ), name
        assert {"region", "batch", "layer", "fibre_1", "fibre_2"} <= set(read["cell_arrays"])
        assert read["ranges"]["region"] == [ids[0], ids[-1]], name
    assert found["stack_voxel.pvd"]["time_steps"] == 1
    facets = found["stack_voxel_facets.xdmf"]
    assert facets["cell_arrays"] == ["facets"] and facets["ranges"]["facets"][0] == 1
    packing = found["packing.pvd"]
    assert packing["time_steps"] == stack.batches
    assert {"region", "batch"} <= set(packing["cell_arrays"])
    assert packing["ranges"]["region"] == [1, stack.chips]  # every chip after the last batch
    if stack.name == "small":
        image = found["voxels.vti"]
        assert image["ranges"]["region"] == [1, stack.pore]


@pytest.fixture(scope="module")
def calculix_isotropic(crop, tmp_path_factory) -> dict:
    """CalculiX's press of the crop, every region isotropic (``solvers.isotropic_deck``,
    the iterative Cholesky solver the solve stage uses)."""
    folder = tmp_path_factory.mktemp("calculix")
    press = solvers.PRESS_FRACTION * _height(crop)
    deck = solvers.isotropic_deck(
        crop.path(".inp"), folder / "press.inp", press, "ITERATIVE CHOLESKY"
    )
    return solvers.calculix(deck)


def _height(stack: Stack) -> float:
    return stack.checks["bounds_mm"][1][2] - stack.checks["bounds_mm"][0][2]


@needs("ccx")
def test_calculix_runs_the_crop_deck_as_written(crop, calculix_isotropic, tmp_path):
    """The deck with its own materials (orthotropic chips in their orientations, the pore's
    PA6) and the same press: CalculiX finishes, the platens' forces balance, and the
    force exceeds the all-PA6 press's (every chip's stiffness exceeds PA6's: the
    difference of the stiffness matrices is positive definite, so the energy, and the
    force at a prescribed press, can only rise)."""
    text = crop.path(".inp").read_text()
    assert "*ELEMENT, TYPE=C3D8," in text and "*ORIENTATION" in text
    press = solvers.PRESS_FRACTION * _height(crop)
    deck = tmp_path / "written.inp"
    deck.write_text(text + "\n".join(solvers.press_step(press, "ITERATIVE CHOLESKY")) + "\n")
    written = solvers.calculix(deck)
    top, bottom = written["forces"]["TOP"][2], written["forces"]["BOTTOM"][2]
    # to the tolerance of CalculiX's iterative solver (measured: 1.1e-3 apart; SPOOLES's
    # direct solve gives the top's force to 3e-5, the same)
    assert top < 0 and bottom == pytest.approx(-top, rel=5e-3)
    assert -top > -calculix_isotropic["forces"]["TOP"][2] * 1.05


@needs("dolfinx", "ccx")
def test_dolfinx_and_calculix_press_the_crop_alike(crop, calculix_isotropic):
    """DOLFINx and CalculiX press the same crop (the .msh and the .inp of one mesh) with
    one isotropic material (E 2000 MPa, nu 0.35), the bottom fixed, the top moved down by
    1 % of the height (x, y held), the sides free, on the same element (linear hexahedra,
    2 x 2 x 2 Gauss points: CalculiX's C3D8, DOLFINx's Q1 at quadrature degree 2): the
    platen forces agree within 0.5 %."""
    assert "*ELEMENT, TYPE=C3D8," in crop.path(".inp").read_text()  # not C3D8R or C3D8I
    press = solvers.PRESS_FRACTION * _height(crop)
    found, _ = solvers.dolfinx(
        "dolfinx_press.py", crop.path(".msh"), solvers.YOUNG_MPA, solvers.POISSON, press
    )
    assert found["cells"] == crop.checks["elements"] and found["cell_type"] == "hexahedron"
    assert found["facets"] == {"bottom": 30 * 30, "top": 30 * 30}
    assert found["dofs"] == 3 * crop.checks["nodes"]
    calculix = calculix_isotropic["forces"]["TOP"][2]
    assert found["force_n"] < 0 and found["bottom_force_n"] == pytest.approx(-found["force_n"])
    assert found["force_n"] == pytest.approx(calculix, rel=0.005)
    # Between the hand values of a free uniaxial column (E) and a confined one (the
    # confined modulus): the platens hold x and y, the sides are free.
    area, strain = 30.0 * 30.0, solvers.PRESS_FRACTION
    e, nu = solvers.YOUNG_MPA, solvers.POISSON
    confined = e * (1 - nu) / ((1 + nu) * (1 - 2 * nu))
    assert e * area * strain < -found["force_n"] < confined * area * strain


# Every built-in scenario that meshes, made small: the overrides (the small stack and the
# crop are the module's fixtures).
SCENARIOS = {
    "paper-squares": "small",
    "paper-volume": "crop",
    "paper-whole-stack": {  # conformal tetrahedra with the pore space
        "deposition.chips": 12,
        "deposition.batch_size": 6,
        "deposition.target_size_mm": 60.0,
    },
    "conveyor-line": {  # a short mat (tests/test_conveyor.py's), a 40 mm panel
        "deposition.chips": 160,
        "deposition.target_size_mm": 40.0,
        "conveyor.belt_speed_mm_s": 40.0,
        "conveyor.cell_mm": 30.0,
        "conveyor.run_in_mm": 0.0,
    },
    "loose-press": {  # every chip its own body of bricks, no pore space
        "deposition.chips": 6,
        "deposition.batch_size": 6,
    },
}


def test_the_meshing_scenarios_are_all_listed():
    """SCENARIOS lists every built-in scenario with a ``[mesh]`` table."""
    folder = resources.files("chipstack.pipeline.scenarios")
    meshing = {
        p.name.removesuffix(".toml")
        for p in folder.iterdir()
        if p.name.endswith(".toml") and "\n[mesh]" in p.read_text()
    }
    assert meshing == set(SCENARIOS)


@pytest.mark.parametrize("scenario", sorted(SCENARIOS))
def test_every_format_gives_each_region_the_same_elements(scenario, request, tmp_path):
    """The per-region element counts meshio reads from the .msh (physical tags), the .vtu
    and the .xdmf (``region``) are one mapping, region ids within 1 to n + 1."""
    case = SCENARIOS[scenario]
    if isinstance(case, str):
        mesh = request.getfixturevalue(case).mesh
    else:
        mesh = solvers.build(scenario, case, tmp_path / "run", ["stack"]) / "mesh"
    (stem,) = {p.name.removesuffix("_checks.json") for p in mesh.glob("*_checks.json")}
    msh = meshio.read(mesh / f"{stem}.msh")
    counts = {"msh": _region_counts(msh.cells, msh.cell_data["gmsh:physical"])}
    for name in ("vtu", "xdmf"):
        back = meshio.read(mesh / f"{stem}.{name}")
        counts[name] = _region_counts(back.cells, back.cell_data["region"])
    assert counts["msh"] == counts["vtu"] == counts["xdmf"]
    manifest = json.loads((mesh.parent / "manifest.json").read_text())
    chips = int(manifest["packing"]["chips"])
    assert set(counts["msh"]) <= set(range(1, chips + 2)) and len(counts["msh"]) > 1
    checks = json.loads((mesh / f"{stem}_checks.json").read_text())
    assert sum(counts["msh"].values()) == checks["elements"]
