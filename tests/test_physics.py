"""Real PyBullet runs: free fall, rest, tunnelling, reproducibility, settling warnings."""

import math

import numpy as np
import pytest

from chipstack.core.overlap import floor_penetration_mm, penetrating_pairs
from chipstack.core.schema import ChipSpec
from chipstack.packing import PRESETS, ChipWorld, deposit, make_shape, scenario_from_dict
from chipstack.packing.sections import PhysicsSpec
from chipstack.packing.world import GROUND

G = 9810.0  # mm/s^2


@pytest.mark.parametrize("preset", ["default", "paper"])
def test_flat_chip_hits_the_floor_at_the_free_fall_time(preset):
    """Released flat, bottom face 200 mm up: first contact at sqrt(2 h / g) within 2 %."""
    shape = make_shape(ChipSpec())
    height = 200.0
    with ChipWorld(PRESETS.get(preset), PhysicsSpec()) as world:
        chip = world.add_chip(shape, np.array([0, 0, height + 1.0]), np.array([0, 0, 0, 1.0]))
        while not any(other == GROUND and d <= 0.0 for other, d in world.contact_points(chip)):
            world.step()
            assert world.time_s < 1.0, "the chip never reached the floor"
        expected = math.sqrt(2 * height / G)
    assert world.time_s == pytest.approx(expected, rel=0.02)


def test_chip_comes_to_rest_on_the_floor_at_its_half_thickness():
    shape = make_shape(ChipSpec())
    with ChipWorld(PRESETS.get("default"), PhysicsSpec()) as world:
        chip = world.add_chip(shape, np.array([0, 0, 30.0]), np.array([0, 0, 0, 1.0]))
        world.step(1000)
        positions, _ = world.poses()
        assert world.max_point_speed_mm_s(chip) < 1.0
    assert positions[0, 2] == pytest.approx(1.0, abs=0.02)


def small(seed=3, **sections):
    data = {
        "name": "small",
        "seed": seed,
        "deposition": {
            "chips": 24,
            "batch_size": 12,
            "target_size_mm": 80.0,
            "release_height_mm": [60.0, 120.0],
        },
    }
    for key, table in sections.items():
        data.setdefault(key, {}).update(table)
    return scenario_from_dict(data)


def test_same_seed_gives_identical_poses_and_another_seed_does_not():
    first, again, other = deposit(small(3)), deposit(small(3)), deposit(small(4))
    assert np.array_equal(first.positions, again.positions)
    assert np.array_equal(first.quaternions, again.quaternions)
    assert not np.allclose(first.positions, other.positions)


def test_chips_off_the_target_are_kept_and_counted():
    stack = deposit(small(5, deposition={"target_size_mm": 30.0, "release_area_mm": 120.0}))
    assert stack.n_chips == 24 and len(stack.positions) == 24
    outside = int((~stack.inside_target()).sum())
    assert outside >= 12  # most centres were released outside a 30 mm target
    assert stack.batches[-1].outside_target == outside


def test_a_batch_that_cannot_settle_in_time_is_a_warning_not_silence():
    stack = deposit(small(3, settling={"max_time_s": 0.1}))
    assert not stack.batches[0].settled
    assert stack.warnings and "did not settle" in stack.warnings[0]


@pytest.mark.slow
def test_reference_stack_has_no_tunnelling_and_settles():
    """The full 270-chip paper stack: nothing deeper than 0.1 mm in the floor or a chip."""
    scenario = scenario_from_dict({"seed": 11})
    stack = deposit(scenario)
    shape = stack.shapes[0]
    assert stack.n_chips == 270 and len(stack.batches) == 5
    assert all(b.settled for b in stack.batches), stack.warnings
    _, depth = penetrating_pairs(stack.positions, stack.quaternions, shape.half_extents)
    floor = floor_penetration_mm(stack.positions, stack.quaternions, shape.vertices)
    assert depth.max(initial=0) <= 0.1
    assert floor.max() <= 0.1
    # Tunnelling would leave a chip below the floor or inside another: neither happened,
    # and every chip rests on something (it appears in a recorded contact).
    contacts = stack.batches[-1].contacts
    touching = set(contacts.chip_a.tolist()) | set(contacts.chip_b[contacts.chip_b >= 0].tolist())
    assert touching == set(range(270))
    assert stack.positions[:, 2].min() > 0.9
    assert np.isfinite(stack.positions).all()
    assert stack.positions[:, 2].max() < 40.0


def test_chips_deep_under_the_surface_are_buried_and_the_rest_are_not():
    """A column of 12 rods (reach 10 mm, length 20 mm), one every 5 mm of height, and a
    lone rod on the floor 100 mm away: with a depth of 2 lengths (40 mm) the rods whose top
    is more than 40 mm under the column's top (65 mm: tops below 25 mm, centres 0 to 10 mm)
    are buried; the lone rod, with nothing over it, is not; a depth deeper than the column
    buries nothing."""
    from chipstack.packing.settling import buried_under

    column = np.array([[0.0, 0.0, 5.0 * k] for k in range(12)])
    lone = np.array([[100.0, 0.0, 0.0]])
    positions = np.vstack([column, lone])
    reach = np.full(13, 10.0)
    buried = buried_under(positions, reach, 2.0)
    assert buried.tolist() == [True] * 3 + [False] * 10
    assert not buried_under(positions, reach, 10.0).any()
    # The column is the surface over the cells next to its own too (25 mm away).
    beside = np.vstack([column, [[25.0, 0.0, 0.0]]])
    assert buried_under(beside, np.full(13, 10.0), 2.0)[-1]


def test_a_release_spin_acts_in_a_stack_and_strength_zero_changes_nothing():
    """The release hook is called in deposition as in a drop (it was declared for stacks
    but never called, so the stack study counted a planted effect that did nothing): a
    spin of 20 rad/s changes where the chips come to rest; strength 0 leaves the stack
    exactly as without the effect."""
    scenario = scenario_from_dict(
        {"seed": 3, "deposition": {"chips": 24, "batch_size": 12, "target_size_mm": 80.0}}
    )
    plain = deposit(scenario)
    spun = deposit(scenario, effects={"release_perturbation": 20.0})
    zero = deposit(scenario, effects={"release_perturbation": 0.0})
    assert np.array_equal(zero.positions, plain.positions)
    assert np.abs(spun.positions - plain.positions).max() > 1.0  # mm
