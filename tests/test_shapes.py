"""Chip shapes: exact outlines and partitions, files, mixes, and bad shapes refused."""

from __future__ import annotations

import math
import tomllib

import manifold3d as m3
import numpy as np
import pytest
import trimesh
from conftest import run_cli

from chipstack.core.schema import ChipSpec
from chipstack.packing import InputError, deposit, scenario_from_dict
from chipstack.packing.polygons import (
    check_simple,
    convex_partition,
    is_convex,
    signed_area,
    star_polygon,
)
from chipstack.packing.release import draw_shapes
from chipstack.packing.shapes import SHAPES, make_shape, shape_from_record, shape_record
from chipstack.pipeline.scenario_files import dumps_toml


def _pieces_volume(shape) -> float:
    return sum(m3.Manifold.hull_points(p).volume() for p in shape.convex_pieces)


def test_registry_lists_every_shape_and_refuses_unknown_names():
    assert set(SHAPES.names()) == {
        "box",
        "polygon",
        "star",
        "random_polygon",
        "beam",
        "fibre",
        "file",
    }
    with pytest.raises(InputError, match="valid names: beam, box, fibre, file, polygon"):
        scenario_from_dict({"chip": {"shape": "blob"}})


def test_star_partition_is_exact_and_convex():
    outline = star_polygon(5, 15.0, 7.5)
    pieces = convex_partition(outline)
    assert len(pieces) > 1 and all(is_convex(p) for p in pieces)
    assert sum(signed_area(p) for p in pieces) == pytest.approx(signed_area(outline), rel=1e-12)
    # Analytic area of a star: 2 n (1/2) R r sin(pi / n).
    assert signed_area(outline) == pytest.approx(5 * 15.0 * 7.5 * math.sin(math.pi / 5))
    shape = make_shape(ChipSpec(shape="star", sides=5, length_mm=30.0, thickness_mm=2.0))
    assert shape.volume_mm3 == pytest.approx(2 * signed_area(outline))
    assert _pieces_volume(shape) == pytest.approx(shape.volume_mm3, rel=1e-9)


@pytest.mark.parametrize(
    ("spec", "volume"),
    [
        (ChipSpec(), 800.0),
        (ChipSpec(shape="polygon", sides=6, length_mm=30.0), 1.5 * math.sqrt(3) * 15**2 * 2),
        (ChipSpec(shape="beam", length_mm=40.0, width_mm=5.0), 400.0),
        (
            ChipSpec(shape="fibre", section="cylinder", length_mm=25.0, thickness_mm=1.0),
            math.pi * 0.25 * 25,
        ),
    ],
)
def test_analytic_volumes_and_centred_frames(spec, volume):
    shape = make_shape(spec)
    assert shape.volume_mm3 == pytest.approx(volume, rel=1e-9)
    # The polygon standing for a round fibre keeps the circle's area exactly.
    assert _pieces_volume(shape) == pytest.approx(volume, rel=1e-9)
    solid = m3.Manifold.batch_boolean(
        [m3.Manifold.hull_points(p) for p in shape.convex_pieces], m3.OpType.Add
    )
    # centred on the centre of mass
    assert np.allclose(np.mean(shape.vertices, axis=0), 0.0, atol=1e-9) or spec.shape == "star"
    assert solid.volume() == pytest.approx(volume, rel=1e-9)


@pytest.mark.parametrize(
    ("spec", "order", "cuboid"),
    [
        (ChipSpec(), 4, True),
        (ChipSpec(width_mm=10.0), 2, True),
        (ChipSpec(shape="polygon", sides=6), 6, False),
        (ChipSpec(shape="polygon", sides=4), 4, False),
        (ChipSpec(shape="star", sides=5), 5, False),
        (ChipSpec(shape="random_polygon", sides=7), 1, False),
        (ChipSpec(shape="polygon", sides=16), 16, False),
        (ChipSpec(shape="star", sides=13), 13, False),
        (ChipSpec(shape="beam", length_mm=40.0, width_mm=6.0), 2, True),
        (ChipSpec(shape="fibre", section="cylinder", length_mm=25.0, thickness_mm=1.0), 2, False),
    ],
)
def test_what_a_shape_can_do_is_read_from_its_geometry(spec, order, cuboid):
    """Turn symmetry about the chip's normal (a landed chip's yaw is defined modulo
    360 deg over it) and whether it is one box along its axes, from the corners, not the
    builder's name: a hexagon was given 4 and a star 2 by name."""
    shape = make_shape(spec, np.random.default_rng(3))
    assert shape.plan_symmetry == order
    assert shape.is_cuboid is cuboid


def test_random_polygons_are_seeded_simple_and_on_principal_axes():
    spec = ChipSpec(shape="random_polygon", sides=9, length_mm=30.0, convex=False)
    a = make_shape(spec, np.random.default_rng(7))
    b = make_shape(spec, np.random.default_rng(7))
    c = make_shape(spec, np.random.default_rng(8))
    assert np.array_equal(a.vertices, b.vertices)
    assert not np.array_equal(a.vertices, c.vertices)
    outline = a.vertices[: len(a.vertices) // 2, :2]
    check_simple(outline, "outline")  # raises if it crossed itself
    assert _pieces_volume(a) == pytest.approx(a.volume_mm3, rel=1e-9)
    # principal axes: the product of inertia of the outline vanishes, long axis along x
    x, y = outline.T
    xn, yn = np.roll(x, -1), np.roll(y, -1)
    cross = x * yn - xn * y
    ixy = ((x * yn + 2 * x * y + 2 * xn * yn + xn * y) * cross).sum() / 24
    assert abs(ixy) < 1e-6 * a.volume_mm3 * 30
    assert a.inertia_mm2[0] <= a.inertia_mm2[1] <= a.inertia_mm2[2]


def test_fibre_directions_turn_with_the_principal_axes():
    # A rectangle given along y with fibres along its length: on principal axes its long
    # side becomes local x, and so do its fibres.
    from chipstack.packing.shapes import prism_shape

    outline = np.array([[-2.0, -10.0], [2.0, -10.0], [2.0, 10.0], [-2.0, 10.0]])
    outline = outline @ np.array([[math.cos(0.3), math.sin(0.3)], [-math.sin(0.3), math.cos(0.3)]])
    angle = math.degrees(math.atan2(math.cos(0.3), -math.sin(0.3)))  # the long side
    shape = prism_shape("r", "box", outline, 1.0, ChipSpec(fibre_directions_deg=(angle,)))
    assert abs(shape.fibre_directions[0, 0]) == pytest.approx(1.0, abs=1e-9)
    assert shape.half_extents[0] == pytest.approx(10.0)


@pytest.mark.parametrize(
    ("outline", "message"),
    [
        ([[0, 0], [10, 10], [10, 0], [0, 5]], "intersects itself"),
        ([[0, 0], [1, 0]], "at least 3 corners"),
        ([[0, 0], [1, 1], [2, 2]], "no area"),
        ([[0, 0], [0, 0], [1, 0], [0, 1]], "coincide"),
        ([[0, 0], [1, float("nan")], [0, 1]], "NaN"),
    ],
)
def test_bad_outlines_are_refused(outline, message):
    with pytest.raises(InputError, match=message):
        check_simple(outline, "outline")


def test_shape_records_round_trip_exactly():
    for spec in (
        ChipSpec(shape="star"),
        ChipSpec(shape="fibre", section="cylinder", thickness_mm=1.0, length_mm=10.0),
    ):
        shape = make_shape(spec)
        again = shape_from_record(shape_record(shape), "test")
        for name in ("vertices", "fibre_directions", "inertia_mm2", "half_extents"):
            assert np.array_equal(getattr(shape, name), getattr(again, name))
        assert again.faces == shape.faces and again.collision == shape.collision


def _write_mesh(path, mesh):
    mesh.export(path)
    return path


def test_geometry_file_chip_convex_and_units(tmp_path):
    box = trimesh.creation.box(extents=(2.0, 1.0, 0.2))  # in cm
    path = _write_mesh(tmp_path / "chip.stl", box)
    shape = make_shape(ChipSpec(shape="file", file=str(path), units="cm"))
    assert shape.volume_mm3 == pytest.approx(20 * 10 * 2, rel=1e-6)  # STL holds float32
    assert len(shape.convex_pieces) == 1
    # principal axes: length along x, thickness along z
    assert np.allclose(shape.half_extents, [10.0, 5.0, 1.0], atol=1e-5)


def test_non_convex_geometry_file_is_decomposed(tmp_path):
    star = make_shape(ChipSpec(shape="star", sides=5, length_mm=30.0))
    solid = m3.Manifold.batch_boolean(
        [m3.Manifold.hull_points(p) for p in star.convex_pieces], m3.OpType.Add
    ).to_mesh()
    prism = trimesh.Trimesh(np.asarray(solid.vert_properties)[:, :3], np.asarray(solid.tri_verts))
    path = _write_mesh(tmp_path / "star.obj", prism)
    shape = make_shape(ChipSpec(shape="file", file=str(path)))
    assert len(shape.convex_pieces) > 1
    # a flat chip is split exactly through its outline
    assert _pieces_volume(shape) == pytest.approx(star.volume_mm3, rel=1e-6)


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda p: p.write_text(""), "empty"),
        (
            lambda p: _write_mesh(
                p,
                trimesh.Trimesh(trimesh.creation.box().vertices, trimesh.creation.box().faces[:-2]),
            ),
            "watertight",
        ),
        (lambda p: p.write_text("solid x\nendsolid x\n"), "no surface|unreadable|empty"),
    ],
)
def test_bad_geometry_files_are_one_line_errors(tmp_path, make, message):
    path = tmp_path / "bad.stl"
    make(path)
    with pytest.raises(InputError, match=message) as info:
        make_shape(ChipSpec(shape="file", file=str(path)))
    assert "\n" not in str(info.value) and "bad.stl" in str(info.value)


def test_mix_by_weights_and_size_distribution():
    scenario = scenario_from_dict(
        {
            "mix": [
                {"shape": "box", "weight": 3.0},
                {
                    "shape": "star",
                    "length_mm": 30.0,
                    "weight": 1.0,
                    "size_distribution": "uniform",
                    "size_spread": 0.2,
                },
                {"shape": "beam", "length_mm": 40.0, "width_mm": 5.0, "weight": 0.0},
            ]
        }
    )
    shapes = draw_shapes(scenario, 4000, np.random.default_rng(1))
    kinds = np.array([s.kind for s in shapes])
    assert (kinds == "beam").sum() == 0
    assert (kinds == "box").mean() == pytest.approx(0.75, abs=0.03)
    stars = [s for s in shapes if s.kind == "star"]
    sizes = np.array([2 * s.circumradius_mm for s in stars])
    across = np.array([2 * np.linalg.norm(s.vertices[:, :2], axis=1).max() for s in stars])
    assert across.min() >= 30 * 0.8 - 1e-6 and across.max() <= 30 * 1.2 + 1e-6
    assert sizes.std() > 1.0
    # the resolved scenario writes [[mix]] tables that load back equal
    assert scenario_from_dict(tomllib.loads(dumps_toml(scenario))) == scenario


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ({"mix": [{"shape": "box", "weight": 0.0}]}, "mix: the weights sum to 0"),
        ({"mix": [{"shape": "box", "weight": -1.0}]}, r"mix\[0\].weight"),
        (
            {"chip": {"shape": "box", "length_mm": 200.0, "width_mm": 200.0}},
            "larger than the target",
        ),
        ({"chip": {"shape": "box"}, "mix": [{"shape": "box"}]}, "not both"),
        ({"chip": {"shape": "file"}}, "chip.file: give the geometry file"),
        ({"chip": {"shape": "star", "sides": 2}}, "chip.sides"),
        ({"chip": {"shape": "random_polygon", "convex": "yes"}}, "chip.convex: expected true"),
        ({"mix": []}, "at least one"),
        (
            {
                "kind": "container",
                "chip": {"shape": "fibre", "length_mm": 60.0, "width_mm": 1.0, "thickness_mm": 1.0},
            },
            "longer than the container",
        ),
    ],
)
def test_bad_shape_settings_name_the_key(data, message):
    with pytest.raises(InputError, match=message):
        scenario_from_dict(data)


def test_bad_geometry_file_from_the_cli(tmp_path):
    (tmp_path / "hole.stl").write_text("")
    scenario = tmp_path / "s.toml"
    scenario.write_text('[chip]\nshape = "file"\nfile = "hole.stl"\n')
    result = run_cli("run", str(scenario), "--out", str(tmp_path / "out"))
    assert result.returncode == 2
    assert result.stderr.count("\n") == 1 and "hole.stl" in result.stderr
    assert not (tmp_path / "out").exists()


def test_mixed_shapes_pack_describe_and_mesh(tmp_path):
    """Stars, beams, random polygons and round fibres go through physics, geometry and the
    voxel mesh: chips rest on the floor, not in it, and the mesh keeps every volume."""
    scenario = tmp_path / "mixed.toml"
    scenario.write_text(
        """
name = "mixed-small"
seed = 2
[[mix]]
shape = "star"
length_mm = 24.0
[[mix]]
shape = "random_polygon"
convex = false
sides = 7
length_mm = 22.0
[[mix]]
shape = "beam"
length_mm = 30.0
width_mm = 4.0
thickness_mm = 2.0
[deposition]
chips = 18
batch_size = 9
target_size_mm = 80.0
release_height_mm = [40.0, 80.0]
[mesh]
voxel_mm = 0.5
formats = ["vtu"]
"""
    )
    out = tmp_path / "run"
    result = run_cli("run", str(scenario), "--to", "mesh", "--out", str(out), "--quiet")
    assert result.returncode == 0, result.stderr
    import json

    manifest = json.loads((out / "manifest.json").read_text())
    last = manifest["packing"]["batches"][-1]
    assert last["max_floor_penetration_mm"] < 0.1
    assert last["max_chip_penetration_mm"] < 0.2
    assert manifest["packing"]["all_settled"]
    assert manifest["mesh"]["voxel"]["total_volume_error"] < 0.01
    shapes = json.loads((out / "packing" / "shapes.json").read_text())["shapes"]
    assert {s["kind"] for s in shapes} == {"star", "random_polygon", "beam"}
    # `describe` reads the saved shapes back (random outlines cannot be rebuilt otherwise)
    again = run_cli("describe", str(out), "--overwrite", "--quiet", "--no-figures")
    assert again.returncode == 0, again.stderr


def test_cylinder_rod_comes_to_rest_on_the_floor():
    """A round rod must settle (without rolling resistance Bullet makes it roll for ever)."""
    scenario = scenario_from_dict(
        {
            "kind": "drop",
            "chip": {
                "shape": "fibre",
                "section": "cylinder",
                "length_mm": 20.0,
                "thickness_mm": 2.0,
            },
            "drop": {"drops": 3, "height_mm": 60.0, "tilt_deg": 20.0},
        }
    )
    from chipstack.packing.drop import drop_chips

    result = drop_chips(scenario)
    assert result.settled.all()
    assert np.allclose(result.positions[:, 2], 1.0, atol=0.05)  # lying on its side


def test_deposit_of_a_single_box_shape_is_unchanged_by_the_registry():
    scenario = scenario_from_dict(
        {
            "seed": 5,
            "deposition": {
                "chips": 6,
                "batch_size": 6,
                "target_size_mm": 60.0,
                "release_height_mm": [40.0, 60.0],
            },
        }
    )
    stack = deposit(scenario)
    assert len(stack.shapes) == 1 and stack.shapes[0].name == "box 20x20x2"


def test_effects_that_reshape_a_chip_ask_its_geometry_not_its_name():
    """Edge rounding and warp take any flat convex prism, whatever its kind is called (a
    triangle under a new name, a convex random polygon, a box-section beam) and refuse a
    star and a round fibre by what they are; a slender chip's fibres lie along its axis
    and a plate's are woven, by what each builder declares."""
    from chipstack.packing.effects import shaped
    from chipstack.packing.shapes import prism_shape

    side = 20.0
    outline = side / np.sqrt(3) * np.array([[0.0, 1.0], [-0.866, -0.5], [0.866, -0.5]])
    triangle = prism_shape("t", "a_new_name", outline, 2.0, ChipSpec())
    convex = make_shape(
        ChipSpec(shape="random_polygon", sides=7, convex=True), np.random.default_rng(1)
    )
    beam = make_shape(ChipSpec(shape="beam", section="box", length_mm=30, width_mm=4))
    for shape in (triangle, convex, beam):
        rounded = shaped(shape, {"edge_rounding": 0.4})
        assert rounded.volume_mm3 < shape.volume_mm3
        assert len(shaped(shape, {"warp": 1.5}).convex_pieces) > 1
    star = make_shape(ChipSpec(shape="star", sides=5))
    fibre = make_shape(ChipSpec(shape="fibre", section="cylinder", length_mm=10, thickness_mm=1))
    for shape in (star, fibre):
        with pytest.raises(InputError, match="supports flat convex chips"):
            shaped(shape, {"edge_rounding": 0.4})
    assert len(beam.fibre_directions) == 1 and len(fibre.fibre_directions) == 1
    assert len(triangle.fibre_directions) == 2


def test_a_chip_too_large_for_its_target_names_the_key_that_sets_its_size(tmp_path):
    """A box is sized by its length; a chip read from a file by its file."""
    from conftest import write_box_obj

    path = write_box_obj(tmp_path / "plate.obj", 100.0, 2.0)
    small = {"target_size_mm": 50.0, "release_height_mm": [100.0, 200.0]}
    with pytest.raises(InputError, match=r"^chip\.file: the chip \(141\.4 mm across\)"):
        scenario_from_dict({"chip": {"shape": "file", "file": str(path)}, "deposition": small})
    with pytest.raises(InputError, match=r"^chip\.length_mm: the chip \(94\.3 mm across\)"):
        scenario_from_dict({"chip": {"length_mm": 80.0, "width_mm": 50.0}, "deposition": small})
