"""The exact penetration check against arrangements with known answers."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from chipstack.core.overlap import box_penetration_depth, floor_penetration_mm, penetrating_pairs

HALF = np.array([10.0, 10.0, 1.0])
I3 = np.eye(3)


def depth(centre_b, rotation_b=I3):
    return box_penetration_depth(
        np.zeros(3), I3, HALF, np.asarray(centre_b, float), rotation_b, HALF
    )[0]


def test_face_on_face_overlap_is_the_vertical_overlap():
    assert depth([3.0, -4.0, 1.7]) == pytest.approx(0.3)


def test_separated_and_touching_boxes_have_no_penetration():
    assert depth([0.0, 0.0, 2.5]) == 0.0
    assert depth([0.0, 0.0, 2.0]) == pytest.approx(0.0, abs=1e-12)
    assert depth([25.0, 0.0, 0.0]) == 0.0


def test_corner_of_a_rotated_chip_pushed_into_an_edge():
    # B turned 45 degrees about z: its corner reaches sqrt(2) * 10 from its centre.
    rotation = Rotation.from_euler("z", 45, degrees=True).as_matrix()
    centre = [10.0 + 10.0 * np.sqrt(2) - 0.5, 0.0, 0.0]
    assert depth(centre, rotation) == pytest.approx(0.5)


def test_edge_on_edge_cross_axis_gives_the_depth():
    # A tilted 45 deg about x has a ridge along x at its top; B tilted 45 deg about y has a
    # ridge along y at its bottom. The ridges cross with 0.2 mm of vertical overlap; the
    # separating direction is x cross y = z, an edge-edge axis.
    a = Rotation.from_euler("x", 45, degrees=True).as_matrix()
    b = Rotation.from_euler("y", 45, degrees=True).as_matrix()
    ridge = (10 + 1) / np.sqrt(2)  # height of the ridge above the centre
    centre = np.array([0.0, 0.0, 2 * ridge - 0.2])
    assert box_penetration_depth(np.zeros(3), a, HALF, centre, b, HALF)[0] == pytest.approx(0.2)


def test_pairs_are_found_and_reported_once():
    positions = np.array([[0, 0, 1.0], [5, 0, 2.9], [100, 0, 1.0]])
    quaternions = np.tile([0, 0, 0, 1.0], (3, 1))
    pairs, depths = penetrating_pairs(positions, quaternions, HALF)
    assert pairs.tolist() == [[0, 1]]
    assert depths[0] == pytest.approx(0.1)


def test_floor_penetration_of_flat_and_tilted_chips():
    quaternions = np.array([[0, 0, 0, 1.0], Rotation.from_euler("x", 90, degrees=True).as_quat()])
    positions = np.array([[0, 0, 0.9], [0, 0, 9.0]])
    vertices = np.array([[sx, sy, sz] for sx in (-10, 10) for sy in (-10, 10) for sz in (-1, 1)])
    assert floor_penetration_mm(positions, quaternions, vertices) == pytest.approx([0.1, 1.0])


def test_inputs_are_not_modified():
    positions = np.array([[0, 0, 1.0], [5, 0, 2.9]])
    quaternions = np.tile([0, 0, 0, 1.0], (2, 1))
    before = positions.copy(), quaternions.copy()
    penetrating_pairs(positions, quaternions, HALF)
    assert np.array_equal(positions, before[0]) and np.array_equal(quaternions, before[1])
