"""The loose press (issue 71) against known answers: a chip pressed flat, a chip bridging
two supports under a line load, an intersection check that is not the solver's own and
that reports the broken case, and the press through the command line with its files,
read back by meshio and pyvista, resumed after a stop."""

from __future__ import annotations

import csv
import json

import meshio
import numpy as np
import pytest
import pyvista
from conftest import run_cli

from chipstack.meshing.loose.ipc import IPCPress, PressSettings
from chipstack.meshing.loose.material import HOT_CHIP, isotropic
from chipstack.meshing.loose.verify import box_bodies, check_intersections, platens_over

GAP = 5e-4  # each platen starts half the barrier's distance away
SETTINGS = PressSettings(dhat_mm=1e-3, friction=0.0, pressure_scale_mpa=100.0)


def _press_flat(material, friction, strain_steps=4, step_mm=0.005):
    """A 10 x 10 x 2 mm chip pressed between the platens: its force and mean strain."""
    bodies = box_bodies([[0, 0, 1.0]], [[5, 5, 1.0]], material, (5, 5, 2))
    platens = platens_over(bodies, GAP)
    settings = PressSettings(dhat_mm=1e-3, friction=friction, pressure_scale_mpa=100.0)
    press = IPCPress(bodies, platens, settings)
    for k in range(1, strain_steps + 1):
        result = press.step(k * step_mm)
    uz = result.displacement[:, 2]
    top = bodies.points[:, 2] > 2.0 - 1e-9
    bottom = bodies.points[:, 2] < 1e-9
    strain = (uz[bottom].mean() - uz[top].mean()) / 2.0
    deformed = bodies.points + result.displacement
    check = check_intersections(
        deformed, bodies, platens.bottom_z, platens.top_z - result.travel_mm
    )
    return result.force_n, strain, check


def test_one_chip_pressed_flat_carries_e_a_strain():
    """Frictionless platens: uniaxial stress, force = E A delta / h within 2 %, for the
    cold isotropic chip and for the hot chip through its thickness (E3 = 10 MPa)."""
    for material, modulus in ((isotropic(3000.0, 0.35), 3000.0), (HOT_CHIP, 10.0)):
        step = 0.005 if modulus > 100 else 0.01
        force, strain, check = _press_flat(material, 0.0, step_mm=step)
        assert 0.009 < strain < 0.03
        assert force / (modulus * 100.0 * strain) == pytest.approx(1.0, abs=0.02)
        assert check.valid


def test_friction_on_the_platens_stiffens_a_chip_towards_the_confined_modulus():
    """Sticking platens hold the chip's faces from spreading: stiffer than the uniaxial
    E, softer than the fully confined E (1 - nu) / ((1 + nu) (1 - 2 nu)) = 1.605 E."""
    material = isotropic(3000.0, 0.35)
    free, strain_free, _ = _press_flat(material, 0.0)
    held, strain_held, _ = _press_flat(material, 0.3)
    ratio_free = free / (3000.0 * 100.0 * strain_free)
    ratio_held = held / (3000.0 * 100.0 * strain_held)
    assert ratio_free + 0.1 < ratio_held < 1.605


def test_a_chip_bridging_two_supports_bends_as_a_timoshenko_plate():
    """A 20 x 10 x 2 mm chip on two 0.25 mm support bars 16 mm apart, a bar on it at
    mid-span pressed by the platen (three-point bending; nu = 0, so that the plate in
    cylindrical bending is the beam): mid-span deflection F L^3 / (48 E I) + F L / (4 k G
    A) within 10 % (measured 0.95 to 0.99: the supports' friction holds the beam's lower
    face a little)."""
    e, span, width, h = 3000.0, 16.0, 10.0, 2.0
    bar = 0.25
    centres = [
        [-span / 2, 0, 1.0],
        [span / 2, 0, 1.0],
        [0, 0, 2 + 2 * GAP + h / 2],
        [0, 0, 2 + 4 * GAP + h + 0.5],
    ]
    halves = [[bar / 2, width / 2, 1.0]] * 2 + [[10, width / 2, h / 2], [bar / 2, width / 2, 0.5]]
    divisions = [(1, 5, 2), (1, 5, 2), (40, 5, 2), (1, 5, 2)]
    bodies = box_bodies(centres, halves, isotropic(e, 0.0), divisions)
    platens = platens_over(bodies, GAP)
    settings = PressSettings(dhat_mm=1e-3, friction=0.3, pressure_scale_mpa=100.0)
    press = IPCPress(bodies, platens, settings)
    beam_bottom = (bodies.node_chip == 2) & np.isclose(bodies.points[:, 2], 2 + 2 * GAP)
    middle = beam_bottom & np.isclose(bodies.points[:, 0], 0.0)
    over_supports = beam_bottom & (np.abs(np.abs(bodies.points[:, 0]) - span / 2) < bar)
    inertia, area, shear = width * h**3 / 12, width * h, e / 2
    compliance = span**3 / (48 * e * inertia) + span / (4 * (5 / 6) * shear * area)
    for k in range(1, 5):
        result = press.step(0.02 * k)
        uz = result.displacement[:, 2]
        deflection = uz[over_supports].mean() - uz[middle].mean()
        assert result.force_n > 1.0
        assert deflection / (compliance * result.force_n) == pytest.approx(1.0, abs=0.10)
    check = check_intersections(
        bodies.points + result.displacement, bodies, platens.bottom_z, platens.top_z - 0.08
    )
    assert check.valid and check.pairs_checked == 3
    assert 0 < check.min_gap_mm < 1e-3


def test_the_intersection_check_reports_a_chip_pushed_into_another():
    """Two chips 0.001 mm apart pass; the upper pushed 0.05 mm into the lower, or the
    lower through the conveyor, fail with the volume or depth."""
    bodies = box_bodies([[0, 0, 1.0], [3, 0, 3.001]], [[5, 5, 1.0]] * 2, HOT_CHIP, (5, 5, 2))
    apart = check_intersections(bodies.points, bodies, -0.01, 10.0)
    assert apart.valid and apart.min_gap_mm == pytest.approx(0.001, rel=1e-3)
    pushed = bodies.points.copy()
    pushed[bodies.node_chip == 1, 2] -= 0.051
    check = check_intersections(pushed, bodies, -0.01, 10.0)
    assert not check.valid
    [(a, b, volume)] = check.overlapping
    assert (a, b) == (0, 1) and volume == pytest.approx(7 * 10 * 0.05, rel=1e-3)
    sunk = bodies.points.copy()
    sunk[bodies.node_chip == 0, 2] -= 0.2
    check = check_intersections(sunk, bodies, -0.01, 10.0)
    assert check.through_platens == ((0, pytest.approx(0.19)),)


def test_the_start_is_refused_when_chips_overlap():
    bodies = box_bodies([[0, 0, 1.0], [3, 0, 2.9]], [[5, 5, 1.0]] * 2, HOT_CHIP, (5, 5, 2))
    with pytest.raises(RuntimeError, match="starting stack intersects"):
        IPCPress(bodies, platens_over(bodies, GAP), SETTINGS)


THREE_CHIPS = """
name = "three"
seed = 3
[chip]
length_mm = 10.0
width_mm = 10.0
thickness_mm = 1.0
[deposition]
chips = 3
batch_size = 3
target_size_mm = 20.0
release_height_mm = [10.0, 20.0]
[mesh]
kind = "loose"
formats = ["vtu", "msh"]
[solve]
press_fraction = 0.3
increments = 6
target_pressure_mpa = 0.0
"""


def test_loose_press_from_the_command_line_stops_resumes_and_writes_its_files(tmp_path):
    scenario = tmp_path / "three.toml"
    scenario.write_text(THREE_CHIPS)
    out = tmp_path / "run"
    stopped = run_cli(
        "run", str(scenario), "--to", "solve", "--out", str(out), "--set", "solve.time_limit_s=1"
    )
    assert stopped.returncode == 2
    line = stopped.stderr.strip().splitlines()[-1]  # after the progress bars
    assert line.startswith("pipeline: error: loose press: ")
    assert "stopped at the time limit (solve.time_limit_s = 1 s) after" in line
    assert "run the same command again" in line and "are kept in" in line
    assert not out.exists()
    result = run_cli("run", str(scenario), "--to", "solve", "--out", str(out))
    assert result.returncode == 0, result.stderr
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["stages_reused"] == ["packing", "geometry", "mesh"]
    assert manifest["solve"]["resumed_after_batch"] >= 1  # it went on from its checkpoint
    solve = out / "solve"
    with open(solve / "force_displacement.csv") as f:
        rows = list(csv.DictReader(f))
    travel = np.array([float(r["travel_mm"]) for r in rows])
    force = np.array([float(r["platen_force_n"]) for r in rows])
    gaps = np.array([float(r["min_distance_mm"]) for r in rows])
    summary = json.loads((solve / "press_summary.json").read_text())
    height = summary["model"]["stack_height_mm"]
    assert len(rows) >= 6 and travel[-1] == pytest.approx(0.3 * height, rel=1e-4)
    assert np.all(np.diff(travel) > 0)
    assert force[-1] > 1.0 and np.all(gaps > 0)
    assert np.all(np.diff(force) > -1e-3 * force.max())  # monotone within the tolerance
    with open(solve / "contact_areas.csv") as f:
        pairs = list(csv.DictReader(f))
    touching = {(int(p["chip_a"]), int(p["chip_b"])) for p in pairs}
    assert touching & {(0, 1), (0, 2), (1, 2)}  # two chips in contact
    assert any(b == -1 for _, b in touching)  # and a chip on the conveyor (id -1)
    assert any(b == -2 for _, b in touching)  # and the press plate (id -2) on a chip
    series = pyvista.get_reader(str(solve / "press.pvd"))
    assert len(series.time_values) == len(rows)
    pressed = meshio.read(solve / "pressed.msh")
    deck = meshio.read(solve / "pressed.inp")
    assert len(pressed.points) == len(deck.points) == summary["model"]["nodes"]
    assert pressed.points[:, 2].max() <= summary["model"]["stack_height_mm"] * 0.7 + 1e-3 + (
        pressed.points[:, 2].min()
    )
