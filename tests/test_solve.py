"""The contact model and the solve stage: geometry of the model, overlap clearing, and
CalculiX compactions with known answers (one chip, a flat layup), end to end."""

from __future__ import annotations

import csv
import json
import os

import meshio
import numpy as np
import pytest
import pyvista
from conftest import SMALL_SCENARIO, run_cli
from parts import needs

from chipstack.core.arrangement import Arrangement
from chipstack.core.schema import ChipSpec
from chipstack.meshing.calculix import read_node_prints, run_ccx
from chipstack.meshing.calculix_deck import write_contact_deck
from chipstack.meshing.contact_model import chip_block, clear_overlaps, contact_model, separation
from chipstack.meshing.sections import SolveSpec
from chipstack.packing.shapes import make_shape

E3, AREA, THICKNESS = 8000.0, 400.0, 2.0  # MPa, mm2, mm: the chip across its thickness


def flat_stack(heights: list[float]) -> Arrangement:
    """20 x 20 x 2 mm chips lying flat, centred on (0, 0), centres at ``heights``."""
    shape = make_shape(ChipSpec())
    n = len(heights)
    positions = np.column_stack([np.zeros(n), np.zeros(n), heights])
    quaternions = np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))
    return Arrangement((shape,), np.zeros(n, int), positions, quaternions, np.ones(n, int), 150.0)


def test_a_chip_block_has_its_outer_faces_and_positive_volumes():
    points, cells, surface, anchors = chip_block(np.array([10.0, 10.0, 1.0]), (4, 3, 2))
    assert len(points) == 5 * 4 * 3 and len(cells) == 24
    # faces on the outside: 2 x (4 x 3) top and bottom, 2 x (4 x 2) + 2 x (3 x 2) sides
    assert len(surface) == 24 + 16 + 12
    corners = points[cells]
    a, b, d, e = corners[:, 0], corners[:, 1], corners[:, 3], corners[:, 4]
    volumes = np.einsum("ij,ij->i", np.cross(b - a, d - a), e - a)
    assert volumes == pytest.approx(np.full(24, 5.0 * (20 / 3) * 1.0))
    assert np.allclose(points[anchors][:, 2], 0.0)  # the mid-plane corners


def test_separation_finds_the_overlap_and_which_box_is_on_top():
    a = flat_stack([1.0, 2.96])
    corners = [np.array([[x, y, z] for x in (-10, 10) for y in (-10, 10) for z in (-1, 1)], float)]
    lower = corners[0] + a.positions[0]
    upper = corners[0] + a.positions[1]
    axes = np.eye(3)
    depth, direction, first_on_top = separation(upper, lower, axes, axes)
    assert depth == pytest.approx(0.04) and np.allclose(direction, [0, 0, 1]) and first_on_top
    assert separation(upper + [0, 0, 0.1], lower, axes, axes)[0] == 0.0


def test_clearing_leaves_no_overlap_and_moves_chips_only_as_far_as_needed():
    a = flat_stack([0.99, 2.95, 4.9])  # into the floor by 0.01, then 0.04 and 0.05 deep
    shifts = clear_overlaps(a, clearance_mm=1e-3)
    z = a.positions[:, 2] + shifts[:, 2]
    assert z[0] - 1 >= 1e-3 - 1e-12 and np.diff(z).min() >= 2 + 1e-3 - 1e-12
    assert np.abs(shifts[:, :2]).max() == 0.0
    # each rises by its own overlap plus the clearance, and by what the chip below rose
    assert shifts[:, 2] == pytest.approx([0.011, 0.052, 0.103], abs=1e-9)


def test_the_contact_model_has_pairs_platens_and_refuses_a_coarse_element():
    model = contact_model(flat_stack([1.0, 3.0]), element_mm=2.0, through_thickness=2)
    assert model.n_chips == 2 and model.n_elements == 2 * 10 * 10 * 2
    assert model.pairs.tolist() == [[0, 1]] and model.floor_chips.tolist() == [0]
    assert model.bottom.z_mm <= model.points[: model.cells.max() + 1, 2].min() + 1e-9
    assert model.height_mm == pytest.approx(4.0, abs=0.01)
    from chipstack.core.errors import InputError

    with pytest.raises(InputError, match="mesh.element_mm"):
        contact_model(flat_stack([1.0]), element_mm=15.0)


def _compress(tmp_path, heights, press_fraction):
    model = contact_model(flat_stack(heights), element_mm=2.0, through_thickness=2)
    solve = SolveSpec(
        press_fraction=press_fraction, friction=0.0, contact_stiffness_mpa_mm=1e6, increments=2
    )
    write_contact_deck(tmp_path / "job.inp", model, solve, "C3D8I")
    run_ccx(tmp_path, "job", threads=1)
    prints = read_node_prints(tmp_path / "job.dat")
    return model, -prints["REF_TOP"]["forces"][-1, 2], -prints["REF_TOP"]["displacements"][-1, 2]


@needs("ccx")
@pytest.mark.parametrize("chips", [1, 3])
def test_a_flat_layup_pressed_between_platens_gives_the_elastic_force(tmp_path, chips):
    """Chips stacked face on face, frictionless platens: uniaxial stress through the
    thickness, F = E3 A press / (n t), in series with the penalty springs of the n + 1
    interfaces (1e6 MPa/mm: 0.5 % of the compliance)."""
    heights = [1.0 + 2.0 * k for k in range(chips)]
    model, force, press = _compress(tmp_path, heights, 0.01)
    assert press == pytest.approx(0.01 * model.height_mm, rel=1e-6)
    chip_compliance = chips * THICKNESS / (E3 * AREA)
    gaps = model.height_mm - chips * THICKNESS  # the clearances left by the clearing
    predicted = (press - gaps) / (chip_compliance + (chips + 1) / (1e6 * AREA))
    assert force == pytest.approx(predicted, rel=0.01)
    assert force == pytest.approx(E3 * AREA * (press - gaps) / (chips * THICKNESS), rel=0.05)


ONE_CHIP = """
name = "one"
[deposition]
chips = 1
batch_size = 1
target_size_mm = 40.0
release_height_mm = [30.0, 40.0]
[mesh]
kind = "contact"
[solve]
press_fraction = 0.01
friction = 0.0
contact_stiffness_mpa_mm = 1e6
increments = 4
"""


@needs("ccx")
def test_solve_end_to_end_writes_results_paraview_reads(tmp_path):
    scenario = tmp_path / "one.toml"
    scenario.write_text(ONE_CHIP)
    out = tmp_path / "run"
    result = run_cli("run", str(scenario), "--to", "solve", "--out", str(out))
    assert result.returncode == 0, result.stderr
    assert "compaction:" in result.stdout and "contact pressure on 1 chips" in result.stdout
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["stages_completed"] == ["packing", "geometry", "mesh", "solve"]
    rows = list(csv.DictReader(open(out / "solve" / "force_displacement.csv")))
    forces = [float(r["platen_force_n"]) for r in rows]
    assert len(forces) == 4 and all(np.diff(forces) > 0)
    assert float(rows[-1]["conveyor_force_n"]) == pytest.approx(forces[-1], rel=1e-6)
    # The compaction's figure (a registered figure of the press's result), listed.
    assert (out / "solve" / "force_displacement.png").stat().st_size > 10_000
    assert "force_displacement.png" in manifest["stages"]["solve"]["summary"]["files"]
    solved = pyvista.read(out / "solve" / "compaction.vtu")
    assert {"U", "S", "CONTACT"} <= set(solved.point_data.keys())
    top = solved.points[:, 2] > solved.points[:, 2].max() - 1e-3
    press = float(rows[-1]["press_mm"])
    # the .frd read back: the chip's top face moved down by the press, less the
    # penalty's share of the compliance
    assert -solved.point_data["U"][top, 2].mean() == pytest.approx(press, rel=0.02)
    deck = meshio.read(out / "mesh" / "stack_contact.vtu")
    assert len(deck.cells[0].data) == 200
    # The chip's platen surfaces, named as on every mesh: the whole 20 x 20 mm chip
    # under the platen and on the conveyor, in the check report, the .msh and the deck.
    surfaces = json.loads((out / "mesh" / "stack_contact_checks.json").read_text())["surfaces"]
    assert surfaces["top"]["projected_area_mm2"] == pytest.approx(AREA, rel=1e-6)
    assert surfaces["bottom"]["projected_area_mm2"] == pytest.approx(AREA, rel=1e-6)
    msh = meshio.read(out / "mesh" / "stack_contact.msh")
    assert {"top": 2, "bottom": 1} == {k: int(v[0]) for k, v in msh.field_data.items() if v[1] == 2}
    part = (out / "mesh" / "stack_contact.inp").read_text()
    assert "*SURFACE, NAME=TOP, TYPE=ELEMENT\n" in part and "ELSET=CHIP_0001\n" in part
    pressure = np.asarray(meshio.read(out / "solve" / "compaction.vtu").point_data["CONTACT"])[:, 3]
    assert pressure.max() == pytest.approx(forces[-1] / AREA, rel=0.05)


@needs("ccx")
def test_a_new_press_reuses_the_mesh_and_solves_again(tmp_path):
    """The compaction deck is the solve model's: a changed ``[solve]`` runs the solve
    stage again on the mesh already written (packing, geometry and mesh reused), and the
    new press is the one solved. (The mesh stage wrote the whole deck before, so a new
    press remeshed.)"""
    scenario = tmp_path / "one.toml"
    scenario.write_text(ONE_CHIP)
    out = tmp_path / "run"
    assert run_cli("run", str(scenario), "--to", "solve", "--out", str(out)).returncode == 0
    mesh_before = (out / "mesh" / "stack_contact.inp").read_bytes()
    first = list(csv.DictReader(open(out / "solve" / "force_displacement.csv")))
    scenario.write_text(ONE_CHIP.replace("press_fraction = 0.01", "press_fraction = 0.02"))
    result = run_cli("run", str(scenario), "--to", "solve", "--out", str(out))
    assert result.returncode == 0, result.stderr
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["stages_reused"] == ["packing", "geometry", "mesh"]
    assert (out / "mesh" / "stack_contact.inp").read_bytes() == mesh_before
    assert "*STEP" not in mesh_before.decode()  # the mesh part holds no step
    second = list(csv.DictReader(open(out / "solve" / "force_displacement.csv")))
    assert float(second[-1]["press_mm"]) == pytest.approx(2 * float(first[-1]["press_mm"]))
    assert "*INCLUDE, INPUT=stack_contact.inp" in (out / "solve" / "compaction.inp").read_text()


def test_a_contact_model_round_trips_through_its_archive(tmp_path):
    from chipstack.meshing.contact_model import load_contact_model, save_contact_model

    model = contact_model(flat_stack([1.0, 3.0]), element_mm=2.0, through_thickness=2)
    back = load_contact_model(save_contact_model(tmp_path / "model.npz", model))
    for name in ("points", "cells", "chip", "pairs", "floor_chips", "fibres", "normals"):
        assert np.array_equal(getattr(back, name), getattr(model, name)), name
    assert len(back.surfaces) == len(model.surfaces)
    assert all(np.array_equal(a, b) for a, b in zip(back.surfaces, model.surfaces, strict=True))
    for a, b in ((back.bottom, model.bottom), (back.top, model.top)):
        assert np.array_equal(a.cells, b.cells)
        assert (a.name, a.face, a.reference_node, a.rotation_node, a.z_mm) == (
            b.name,
            b.face,
            b.reference_node,
            b.rotation_node,
            b.z_mm,
        )
    assert (back.height_mm, back.gap_mm, back.info) == (model.height_mm, model.gap_mm, model.info)


def test_solve_refuses_a_model_it_cannot_run(tmp_path):
    scenario = tmp_path / "one.toml"
    # A voxel mesh without its pore space: nothing presses it, so [solve] holds the press's
    # keys only (the contact press's friction and stiffness would be refused by name).
    voxel = ONE_CHIP.replace('kind = "contact"', 'kind = "voxel"')
    scenario.write_text(voxel.replace("friction = 0.0\ncontact_stiffness_mpa_mm = 1e6\n", ""))
    result = run_cli("run", str(scenario), "--to", "solve", "--out", str(tmp_path / "run"))
    assert result.returncode == 2
    assert result.stderr.strip().splitlines() == [
        "pipeline: error: --to solve: needs the contact model (mesh.kind = 'contact'), a "
        "box-shaped volume (mesh.kind = 'voxel', 'image' or 'conformal', "
        "mesh.pore_space = 'box') or the loose stack (mesh.kind = 'loose'); mesh.kind is "
        "'voxel', mesh.pore_space 'none'"
    ]
    assert not (tmp_path / "run").exists()


CROPPED_VOLUME = (
    SMALL_SCENARIO
    + """
[mesh]
voxel_mm = 1.0
pore_space = "box"
crop = "region"
region_mm = [-20.0, 20.0, -20.0, 20.0]
periodic = true
formats = ["inp", "vtu"]
[solve]
press_fraction = 0.01
"""
)


@needs("ccx")
def test_solve_a_cropped_periodic_volume_of_a_physics_stack(tmp_path):
    """A settled stack cropped to 40 x 40 mm with its pore space, periodic sides confined,
    pressed by 1 % of its height between whole-face platens: the force goes through the
    volume to the conveyor, and the result reads back with the press face moved."""
    scenario = tmp_path / "volume.toml"
    scenario.write_text(CROPPED_VOLUME)
    out = tmp_path / "run"
    result = run_cli("run", str(scenario), "--to", "solve", "--out", str(out))
    assert result.returncode == 0, result.stderr
    assert "compaction:" in result.stdout and "contact pressure" not in result.stdout
    checks = json.loads((out / "mesh" / "stack_voxel_checks.json").read_text())
    height = checks["bounds_mm"][1][2] - checks["bounds_mm"][0][2]
    rows = list(csv.DictReader(open(out / "solve" / "force_displacement.csv")))
    press, force = float(rows[-1]["press_mm"]), float(rows[-1]["platen_force_n"])
    assert press == pytest.approx(0.01 * height)
    # The press face's force reaches the conveyor; to the tolerance of CalculiX's
    # iterative solver (measured: 1.5e-4 relative), not to round-off as a direct solve.
    assert force > 0 and float(rows[-1]["conveyor_force_n"]) == pytest.approx(force, rel=1e-3)
    # The effective confined modulus lies between two rigorous bounds computed from this
    # mesh's own elements (_confined_modulus_bounds): Voigt's (a uniform strain is an
    # admissible field), the volume mean of each element's C_zzzz in its chip's frame,
    # above; homogeneous PA6 below, as the chip is stiffer than PA6 in every direction.
    # Measured: 4008 MPa in [3210, 4762], a band a factor 1.48 wide (chips 26 % of the
    # volume); the old band, PA6 to the chip's stiffest direction, was a factor 7.8 wide.
    # Beyond the bounds by CalculiX's iterative tolerance (measured 1.5e-4) at most.
    (x0, y0, z0), (x1, y1, z1) = checks["bounds_mm"]
    modulus = force / ((x1 - x0) * (y1 - y0)) / (press / (z1 - z0))
    lower, upper = _confined_modulus_bounds(pyvista.read(out / "mesh" / "stack_voxel.vtu"))
    assert lower * (1 - 1e-3) < modulus < upper * (1 + 1e-3), (lower, modulus, upper)
    solved = pyvista.read(out / "solve" / "compaction.vtu")
    assert {"U", "S"} <= set(solved.point_data.keys())
    top = solved.points[:, 2] > solved.points[:, 2].max() - 1e-6
    assert np.allclose(solved.point_data["U"][top, 2], -press)
    bottom = solved.points[:, 2] < solved.points[:, 2].min() + 1e-6
    assert np.allclose(solved.point_data["U"][bottom, 2], 0.0)
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["stages_completed"][-1] == "solve"


def _mandel(c: np.ndarray) -> np.ndarray:
    """A 6 x 6 Voigt stiffness (tensor shear terms) in Mandel form, whose eigenvalues are
    the stiffness tensor's."""
    w = np.array([1, 1, 1, np.sqrt(2), np.sqrt(2), np.sqrt(2)])
    return c * np.outer(w, w)


def _confined_modulus_bounds(grid) -> tuple[float, float]:
    """Rigorous bounds (MPa) on the effective C_zzzz of a mesh of chips (their material
    frames in the cell data ``fibre_1``, ``fibre_2``, ``normal``) and PA6 pore space under
    a uniform z strain with the sides confined. Upper: Voigt, the volume mean of each
    element's C_zzzz (the uniform strain is an admissible field). Lower: PA6's confined
    modulus, since the chip's stiffness exceeds PA6's in every direction (asserted) and
    the strain energy grows with the stiffness."""
    from chipstack.meshing.files import MATERIALS

    c, pa6 = MATERIALS["CHIP"], MATERIALS["PORE"]
    compliance = np.zeros((6, 6))
    compliance[:3, :3] = [
        [1 / c["E1"], -c["nu12"] / c["E1"], -c["nu13"] / c["E1"]],
        [-c["nu12"] / c["E1"], 1 / c["E2"], -c["nu23"] / c["E2"]],
        [-c["nu13"] / c["E1"], -c["nu23"] / c["E2"], 1 / c["E3"]],
    ]
    compliance[3:, 3:] = np.diag([1 / c["G23"], 1 / c["G13"], 1 / c["G12"]])
    chip = np.linalg.inv(compliance)
    e, nu = pa6["E"], pa6["nu"]
    lam, mu = e * nu / ((1 + nu) * (1 - 2 * nu)), e / (2 * (1 + nu))
    pore = np.zeros((6, 6))
    pore[:3, :3] = lam
    pore += np.diag([2 * mu] * 3 + [mu] * 3)
    assert np.linalg.eigvalsh(_mandel(chip) - _mandel(pore)).min() > 0
    # World z in each element's material frame: the z components of its three axes.
    n1, n2, n3 = (np.asarray(grid.cell_data[k])[:, 2] for k in ("fibre_1", "fibre_2", "normal"))
    c_zzzz = (
        chip[0, 0] * n1**4
        + chip[1, 1] * n2**4
        + chip[2, 2] * n3**4
        + 2 * (chip[0, 1] + 2 * chip[5, 5]) * (n1 * n2) ** 2
        + 2 * (chip[0, 2] + 2 * chip[4, 4]) * (n1 * n3) ** 2
        + 2 * (chip[1, 2] + 2 * chip[3, 3]) * (n2 * n3) ** 2
    )
    solid = np.linalg.norm(grid.cell_data["normal"], axis=1) > 0  # the pore has no frame
    c_zzzz = np.where(solid, c_zzzz, pore[2, 2])
    volume = grid.compute_cell_sizes(length=False, area=False, volume=True).cell_data["Volume"]
    return float(pore[2, 2]), float(np.sum(volume * c_zzzz) / np.sum(volume))


def test_solve_without_calculix_is_one_line(tmp_path):
    scenario = tmp_path / "one.toml"
    scenario.write_text(ONE_CHIP)
    env_path = os.environ["PATH"]
    try:
        os.environ["PATH"] = str(tmp_path)  # no ccx here; python is called by full path
        result = run_cli("run", str(scenario), "--to", "solve", "--out", str(tmp_path / "run"))
    finally:
        os.environ["PATH"] = env_path
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "CalculiX (ccx) is not on the PATH" in lines[0]
    assert not (tmp_path / "run").exists()
