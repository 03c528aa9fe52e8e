"""Contact resolution (meshing/resolution/): analytic arrangements with known answers."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from chipstack.core.arrangement import Arrangement
from chipstack.core.errors import InputError
from chipstack.core.schema import ChipSpec
from chipstack.geometry.contacts import KINDS, find_contacts
from chipstack.meshing import check_mesh, conformal_mesh
from chipstack.meshing.resolution import (
    UnresolvedError,
    resolve_chips,
    resolve_contacts,
    separation_mm,
)
from chipstack.packing.shapes import box_shape

SQUARE = box_shape(ChipSpec())  # 20 x 20 x 2 mm


def arrange(poses) -> Arrangement:
    """poses: (centre, scipy Rotation or yaw in degrees)."""
    rotations = [
        r if isinstance(r, Rotation) else Rotation.from_euler("z", r, degrees=True)
        for _, r in poses
    ]
    n = len(poses)
    return Arrangement(
        (SQUARE,),
        np.zeros(n, int),
        np.array([p for p, _ in poses], dtype=float),
        np.array([r.as_quat() for r in rotations]),
        np.ones(n, int),
        80.0,
    )


def normal_of(a: Arrangement, chip: int, axis: int = 2) -> np.ndarray:
    return a.rotations[chip][:, axis]


def test_a_chip_tilted_on_another_is_laid_exactly_on_it():
    """The lower chip sinks 0.01 mm into the conveyor; the upper lies on it tilted by 0.3
    deg and 0.01 mm into it (a surface contact). Resolved: the lower lies exactly on the
    conveyor, the upper's bottom face exactly in the lower's top face, both snapped."""
    tilt = Rotation.from_euler("xz", (0.3, 10.0), degrees=True)
    a = arrange([((0.0, 0.0, 0.99), 0.0), ((3.0, 1.0, 2.99), tilt)])
    r = resolve_contacts(a)
    b = r.arrangement
    assert r.snapped == {"chip": 1, "conveyor": 1}
    assert b.bounds[0, 0, 2] == pytest.approx(0.0, abs=1e-12)
    assert np.abs(normal_of(b, 0) - normal_of(b, 1)).max() < 1e-12  # both flat, parallel
    assert b.bounds[1, 0, 2] == pytest.approx(2.0, abs=1e-12)  # on the lower's top face
    assert separation_mm(b, 0, 1) == pytest.approx(0.0, abs=1e-9)
    # The smallest motions: the tilt taken out about the centre of mass, and no more.
    assert r.rotation_deg[1] == pytest.approx(0.3, abs=1e-6)
    assert r.max_translation_mm < 0.05
    # Conformal: the two chips share their interface.
    mesh = conformal_mesh(b, size_mm=2.0)
    report = check_mesh(mesh, b, np.array([[0, 1]]), min_quality=0.1)
    assert report["valid"] and report["interfaces"]["sharing_faces"] == 1


def yaw_deg(a: Arrangement, chip: int) -> float:
    x = a.rotations[chip][:, 0]
    return float(np.degrees(np.arctan2(x[1], x[0])))


@pytest.mark.parametrize(("turned", "aligned"), [(2.0, True), (-4.5, True), (10.0, False)])
def test_chips_in_a_shared_plane_at_a_shallow_angle_are_aligned(turned, aligned):
    """Outlines crossing at a shallow angle in a shared plane cut the face into a thin
    wedge no sound tetrahedron fits: below the alignment angle (6 deg) the upper chip is
    turned about the plane's normal until the edges are parallel (the smaller turn, shared
    by both chips, mass-weighted); above it the yaw is left as it was."""
    a = arrange([((0.0, 0.0, 0.99), 0.0), ((6.0, 4.0, 2.99), turned)])
    r = resolve_contacts(a)
    b = r.arrangement
    assert r.info["route"] == "global"
    assert r.snapped == {"chip": 1, "conveyor": 1}
    relative = yaw_deg(b, 1) - yaw_deg(b, 0)
    if aligned:
        assert relative == pytest.approx(0.0, abs=1e-6)
        mesh = conformal_mesh(b, size_mm=2.0)
        report = check_mesh(mesh, b, np.array([[0, 1]]), min_quality=0.1)
        assert report["valid"] and report["interfaces"]["sharing_faces"] == 1
    else:
        assert relative == pytest.approx(turned, abs=1e-6)
    assert separation_mm(b, 0, 1) == pytest.approx(0.0, abs=1e-9)


def test_a_beam_crossing_a_square_at_a_shallow_angle_is_aligned_too():
    """Alignment is asked of the geometry, not of the shape's name: a beam of box section
    (40 x 6 x 2 mm) lying on a square at 1.7 deg is turned parallel like a square would
    be, and the pair meshes soundly (the beam's name had kept it out: a wedge of SICN
    0.065, mixed-shapes seed 3)."""
    from chipstack.packing.shapes import _slender

    beam = _slender("beam")(ChipSpec(shape="beam", length_mm=40.0, width_mm=6.0))
    a = Arrangement(
        (SQUARE, beam),
        np.array([0, 1]),
        np.array([[0.0, 0.0, 0.99], [2.0, 6.5, 2.99]]),
        np.array([Rotation.from_euler("z", yaw, degrees=True).as_quat() for yaw in (0.0, 1.7)]),
        np.ones(2, int),
        80.0,
    )
    r = resolve_contacts(a)
    b = r.arrangement
    assert r.snapped == {"chip": 1, "conveyor": 1}
    assert yaw_deg(b, 1) - yaw_deg(b, 0) == pytest.approx(0.0, abs=1e-6)
    mesh = conformal_mesh(b, size_mm=2.0)
    report = check_mesh(mesh, b, np.array([[0, 1]]), min_quality=0.1)
    assert report["valid"] and report["interfaces"]["sharing_faces"] == 1


def corners_in_frame_of(a: Arrangement, chip: int, other: int) -> np.ndarray:
    """The corners of ``chip`` (x, y) in the frame of ``other``."""
    world = SQUARE.vertices @ a.rotations[chip].T + a.positions[chip]
    return ((world - a.positions[other]) @ a.rotations[other])[:, :2]


def test_parallel_edges_a_hair_apart_in_a_shared_plane_are_made_flush():
    """Two aligned squares, one on the other, offset 0.05 mm across x: the edges at
    x = +-10 would cut both shared faces into strips 0.05 mm wide. Resolved: flush
    (collinear to rounding), the offset along y kept."""
    a = arrange([((0.0, 0.0, 0.99), 0.0), ((0.05, 6.0, 2.99), 0.0)])
    b = resolve_contacts(a).arrangement
    local = corners_in_frame_of(b, 1, 0)
    assert local[:, 0].min() == pytest.approx(-10.0, abs=1e-6)
    assert local[:, 0].max() == pytest.approx(10.0, abs=1e-6)
    assert local[:, 1].min() == pytest.approx(-4.0, abs=0.01)


def test_a_corner_a_hair_from_an_edge_in_a_shared_plane_is_moved_off_it():
    """The upper square, turned 20 deg, has a corner 0.05 mm inside the lower's edge
    x = -10: a neck 0.05 mm wide in the lower's top face. Resolved: the corner is 0.3 mm
    inside (the side it was on), and the pair meshes soundly."""
    a = arrange([((0.0, 0.0, 0.99), 0.0), ((2.867, -5.977, 2.99), 20.0)])
    assert corners_in_frame_of(a, 1, 0)[:, 0].min() == pytest.approx(-9.95, abs=1e-3)
    b = resolve_contacts(a).arrangement
    assert corners_in_frame_of(b, 1, 0)[:, 0].min() >= -9.7 - 1e-6
    mesh = conformal_mesh(b, size_mm=2.0)
    assert check_mesh(mesh, b, np.array([[0, 1]]), min_quality=0.1)["valid"]


def test_chips_that_nearly_touch_edge_on_are_cleared_by_the_gap():
    """Two flat chips side by side, 0.02 mm into each other at their edges (a line
    contact, not a surface): moved apart to the gap, by no more than it takes."""
    a = arrange([((-9.99, 0.0, 1.0), 0.0), ((9.99, 0.0, 1.0), 0.0)])
    assert separation_mm(a, 0, 1) == pytest.approx(-0.02)
    r = resolve_contacts(a, gap_mm=0.03)
    gap = separation_mm(r.arrangement, 0, 1)
    assert 0.03 <= gap <= 0.045  # cleared, still within the contact gap: still a contact
    assert r.cleared >= 1 and r.max_translation_mm < 0.06
    assert r.snapped == {"chip": 0, "conveyor": 2}


def test_a_line_contact_is_kept_touching_for_a_mesh_of_the_chips_alone():
    """The same two chips, resolved for a mesh without pore space: laid against each
    other (within the 0.2 um slack) instead of cleared, so they stay a line contact."""
    a = arrange([((-9.99, 0.0, 1.0), 0.0), ((9.99, 0.0, 1.0), 0.0)])
    r = resolve_contacts(a, gap_mm=0.03, touching_lines=True)
    assert 0.0 <= separation_mm(r.arrangement, 0, 1) <= 1e-3  # signed: an overlap is < 0
    assert r.max_translation_mm < 0.02
    assert r.summary()["line_contacts_touching"] == 1
    table = find_contacts(r.arrangement)
    pair = (table.chip_a == 0) & (table.chip_b == 1)
    assert [KINDS[k] for k in table.kind[pair]] == ["line"]


def test_an_overlap_no_small_motion_clears_is_named():
    """One chip 1.5 mm into another (the physics never leaves that): named, not dropped."""
    a = arrange([((0.0, 0.0, 1.0), 0.0), ((0.0, 0.0, 1.5), 30.0)])
    with pytest.raises(UnresolvedError, match=r"2 chips .* chips 0 \(1.530 mm short\), 1 "):
        resolve_contacts(a)


def test_resolving_some_chips_moves_only_them_and_names_chips_by_their_whole_index():
    """For a crop: chips 1 and 2 (0.02 mm into each other) are resolved alone, chip 0
    (0.02 mm into chip 1, but outside the crop) keeps its settled pose; what is reported
    and what cannot be cleared is named by the chips' indices in the whole stack."""
    a = arrange([((-19.98, 0.0, 1.0), 0.0), ((0.0, 0.0, 1.0), 0.0), ((19.98, 0.0, 1.0), 0.0)])
    r = resolve_chips(a, [1, 2], gap_mm=0.03)
    assert np.array_equal(r.arrangement.positions[0], a.positions[0])
    assert np.array_equal(r.arrangement.quaternions[0], a.quaternions[0])
    assert r.translation_mm[0] == 0 and r.rotation_deg[0] == 0
    assert separation_mm(r.arrangement, 1, 2) >= 0.03
    assert separation_mm(r.arrangement, 0, 1) < 0.03  # not asked for
    assert r.summary()["chips_resolved"] == 2
    stuck = arrange([((50.0, 0.0, 1.0), 0.0), ((0.0, 0.0, 1.0), 0.0), ((0.0, 0.0, 1.5), 30.0)])
    with pytest.raises(UnresolvedError, match=r"chips 1 \(1.530 mm short\), 2 ") as caught:
        resolve_chips(stuck, [1, 2])
    assert [c for c, _ in caught.value.unresolved] == [1, 2]


def test_the_settled_arrangement_is_left_as_it_was():
    a = arrange([((0.0, 0.0, 0.99), 0.0), ((3.0, 2.0, 2.98), 5.0)])

    def digest() -> str:
        return hashlib.sha256(a.positions.tobytes() + a.quaternions.tobytes()).hexdigest()

    before = digest()
    r = resolve_contacts(a)
    assert digest() == before
    assert r.arrangement is not a and not np.allclose(r.arrangement.positions, a.positions)


def test_a_chip_may_rise_one_gap_more_per_chip_thickness_it_sits_above_the_conveyor():
    """The global route's caps on each chip's motion: 1 mm and 6 degrees every way, and
    upwards one gap more per chip thickness between the chip and the conveyor (each
    contact cleared below a chip lifts it by a gap; with 1 mm for every chip the dense
    paper-rectangles stack could not be cleared)."""
    from chipstack.meshing.resolution import convex_pieces, place_chip
    from chipstack.meshing.resolution.relax_qp import _motion_caps

    a = arrange([((0.0, 0.0, 1.0), 0.0), ((0.0, 0.0, 11.0), 0.0), ((0.0, 0.0, 21.0), 30.0)])
    worlds = [place_chip(convex_pieces(SQUARE), a.rotations[k], a.positions[k]) for k in range(3)]
    up, down = (caps.reshape(3, 6) for caps in _motion_caps(worlds, 0.2, a.thinnest_mm))
    assert np.allclose(up[:, 2], [1.0, 2.0, 3.0])  # lowest corners at 0, 10 and 20 mm
    assert np.allclose(down[:, :3], 1.0) and np.allclose(up[:, :2], 1.0)
    assert np.allclose(up[:, 3:], np.radians(6.0)) and np.allclose(down[:, 3:], np.radians(6.0))


@pytest.mark.parametrize(
    ("gap", "angle", "message"),
    [
        (-0.01, 3.0, "mesh.gap_mm: must be positive"),
        (0.5, 3.0, "mesh.gap_mm: 0.5 mm is above a tenth of the thinnest chip dimension"),
        (0.03, -1.0, "mesh.snap_angle_deg: must be between 0 and 15"),
    ],
)
def test_settings_that_cannot_work_are_refused(gap, angle, message):
    a = arrange([((0.0, 0.0, 1.0), 0.0)])
    with pytest.raises(InputError, match=message):
        resolve_contacts(a, gap_mm=gap, snap_angle_deg=angle)


def test_a_gap_above_a_tenth_of_the_chip_is_one_line_from_the_cli(tmp_path, small_scenario):
    from conftest import assert_refused, run_cli, tree

    small_scenario.write_text(
        small_scenario.read_text() + '[mesh]\nkind = "conformal"\ngap_mm = 0.5\n'
    )
    before = tree(tmp_path)
    out = tmp_path / "run"
    result = run_cli("run", str(small_scenario), "--to", "mesh", "--out", str(out), "--quiet")
    named = "mesh.gap_mm: 0.5 mm is above a tenth of the thinnest chip dimension"
    assert_refused(result, named, tmp_path, before)
