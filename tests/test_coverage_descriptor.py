"""The coverage descriptor (geometry/descriptors/coverage.py) on arrangements whose
answer is known by hand: squares that overlap, a square turned in the plane, a tilted
chip whose projected outline has a closed-form area."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from chipstack.core.arrangement import Arrangement
from chipstack.core.schema import ChipSpec
from chipstack.geometry.describe import describe
from chipstack.geometry.descriptor_kinds import DESCRIPTORS
from chipstack.geometry.sections import GeometrySpec
from chipstack.packing.shapes import box_shape

SQUARE = box_shape(ChipSpec())  # 20 x 20 x 2 mm


def arrange(poses) -> Arrangement:
    """poses: (centre (3,) mm, rotation: a scipy Rotation or None for flat)."""
    positions = np.array([p for p, _ in poses], dtype=float).reshape(-1, 3)
    quats = np.array([(r or Rotation.identity()).as_quat() for _, r in poses]).reshape(-1, 4)
    n = len(poses)
    return Arrangement(
        (SQUARE,), np.zeros(n, dtype=int), positions, quats, np.ones(n, dtype=int), 150.0
    )


def coverage(arrangement: Arrangement, pixel_mm: float) -> dict:
    return describe([arrangement], GeometrySpec(pixel_mm=pixel_mm), ["coverage"]).sections[
        "coverage"
    ]


def test_coverage_counts_the_chips_over_each_part_of_the_footprint():
    """20 x 20 mm squares: A over x 0 to 20, B and C on it over x 10 to 30, D alone over
    x 60 to 80 (all y 0 to 20); 1 mm pixels on the squares' edges count exactly. By
    hand: covered by 1 chip 600 mm2 (A's free half, D), by 2 200 (B and C past A), by 3
    200, of a 1,000 mm2 footprint; the table says the same."""
    a = arrange(
        [((10, 10, 1), None), ((20, 10, 3), None), ((20, 10, 5), None), ((70, 10, 1), None)]
    )
    description = describe([a], GeometrySpec(pixel_mm=1.0), ["coverage"])
    section = description.sections["coverage"]
    s = section["scalars"]
    assert s["footprint_mm2"]["value"] == pytest.approx(1000.0)
    assert section["profiles"]["cover_fraction"]["index"] == [1, 2, 3]
    assert section["profiles"]["cover_fraction"]["values"] == pytest.approx([0.6, 0.2, 0.2])
    assert s["single_cover_fraction"]["value"] == pytest.approx(0.6)
    assert s["mean_cover"]["value"] == pytest.approx((600 + 2 * 200 + 3 * 200) / 1000)
    tables = DESCRIPTORS.get("coverage").tables(description.records["coverage"])
    header, rows = tables["coverage.csv"]
    rows = list(rows)
    assert header[:3] == ["chips", "pixels", "area_mm2"]
    assert [r[:2] for r in rows] == [[1, 600], [2, 200], [3, 200]]
    assert [float(r[4]) for r in rows] == pytest.approx([1.0, 0.4, 0.2])
    bare = coverage(arrange([]), 1.0)["scalars"]
    assert bare["footprint_mm2"]["value"] == 0.0 and bare["mean_cover"]["value"] == 0.0


def test_two_squares_overlapping_at_a_corner():
    """A over (0, 0) to (20, 20), B on it over (10, 10) to (30, 30): their union is
    400 + 400 - 100 = 700 mm2, 600 under one chip, the 10 x 10 mm corner under two; the
    1 mm pixels' edges fall on the squares' edges, so the counts are exact."""
    section = coverage(arrange([((10, 10, 1), None), ((20, 20, 3), None)]), 1.0)
    assert section["scalars"]["footprint_mm2"]["value"] == pytest.approx(700.0)
    assert section["profiles"]["cover_fraction"]["index"] == [1, 2]
    assert section["profiles"]["cover_fraction"]["values"] == pytest.approx([6 / 7, 1 / 7])
    assert section["scalars"]["mean_cover"]["value"] == pytest.approx(800 / 700)


def test_a_square_turned_in_the_plane_keeps_its_area():
    """A flat square turned 45 deg about z: its pixels' edges cross the outline, and at
    0.25 mm the counted area is 400 mm2 to within 1 % (the pixels cut by its 80 mm outline
    are 0.25 x 80 = 20 mm2, half of them counted on average)."""
    turned = Rotation.from_euler("z", 45, degrees=True)
    section = coverage(arrange([((0.3, -0.2, 1), turned)]), 0.25)
    assert section["scalars"]["footprint_mm2"]["value"] == pytest.approx(400.0, rel=0.01)
    assert section["profiles"]["cover_fraction"]["values"] == [1.0]


def test_a_tilted_chip_covers_its_projected_outline():
    """A 20 x 20 x 2 mm chip tilted 30 deg about x projects on the plane as a 20 mm by
    (20 cos 30 + 2 sin 30) mm rectangle, 366.4 mm2, all of it under one chip; a flat
    chip beside it that it does not reach adds its own 400 mm2."""
    tilted = Rotation.from_euler("x", 30, degrees=True)
    expected = 20 * (20 * math.cos(math.radians(30)) + 2 * math.sin(math.radians(30)))
    alone = coverage(arrange([((0, 0, 6), tilted)]), 0.25)["scalars"]
    assert alone["footprint_mm2"]["value"] == pytest.approx(expected, rel=0.01)
    both = coverage(arrange([((0, 0, 6), tilted), ((40, 0, 1), None)]), 0.25)["scalars"]
    assert both["footprint_mm2"]["value"] == pytest.approx(expected + 400.0, rel=0.01)
    assert both["single_cover_fraction"]["value"] == 1.0
