"""Plugins: a package outside the project (``tests/plugins``: its module and its
``.dist-info`` with the entry points, on the path of the runs below as an installed
package would be) adds a chip shape, a descriptor, a mesh kind, an effect, a scenario
kind with its own table and deposition site, a stack writer and a figure without touching
a file of the project; each works end to end, and its docs rows are generated."""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import meshio
import numpy as np
import pytest

PLUGINS = Path(__file__).resolve().parent / "plugins"

TRIANGLES = """
name = "triangles"
seed = 3
[chip]
shape = "triangle"
length_mm = 20.0
thickness_mm = 2.0
apex_angle_deg = 50.0
[deposition]
chips = 12
batch_size = 12
target_size_mm = 80.0
release_height_mm = [60.0, 120.0]
[mesh]
kind = "kuhn"
cube_mm = 1.0
"""

RING = """
name = "ring"
kind = "ring"
seed = 2
[chip]
length_mm = 10.0
width_mm = 10.0
thickness_mm = 2.0
[deposition]
chips = 12
batch_size = 4
target_size_mm = 80.0
release_height_mm = [40.0, 120.0]
[ring]
radius_mm = 8.0
centre_x_mm = 25.0
[mesh]
voxel_mm = 1.0
"""

WIND = """
kind = "drop"
name = "wind"
scenario = "single-chip-drop"
observations = "data.csv"
[measurement]
position_sd_mm = 0.0
angle_sd_deg = 0.0
[[condition]]
name = "high"
height_mm = 1000
"""


def run(args: list[str], cwd: Path, plugin: bool = True) -> subprocess.CompletedProcess:
    env = dict(os.environ)
    if plugin:
        env["PYTHONPATH"] = os.pathsep.join(p for p in (str(PLUGINS), env.get("PYTHONPATH")) if p)
    return subprocess.run(
        [sys.executable, *args], capture_output=True, text=True, cwd=cwd, env=env, timeout=600
    )


def test_a_plugin_shape_descriptor_mesh_kind_and_writer_run_through_their_stages(tmp_path):
    (tmp_path / "tri.toml").write_text(TRIANGLES)
    result = run(
        ["-m", "chipstack.pipeline", "run", "tri.toml", "--to", "mesh", "--out", "run"], tmp_path
    )
    assert result.returncode == 0, result.stderr
    assert "kuhn mesh:" in result.stdout
    # The plugin's stack writer: the centres after the last batch, as the poses file has them.
    centres = np.loadtxt(tmp_path / "run" / "packing" / "centres.xyz")
    with open(tmp_path / "run" / "packing" / "poses_after_batch_01.csv") as f:
        rows = list(csv.DictReader(f))
    poses = np.array([[float(r[k]) for k in ("x_mm", "y_mm", "z_mm")] for r in rows])
    assert centres.shape == (12, 3) and np.allclose(centres, poses, atol=1e-5)
    # The plugin's figure of the stack: drawn by the geometry stage and listed with its files.
    top_view = tmp_path / "run" / "geometry" / "figures" / "centres_top.png"
    assert top_view.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    manifest = json.loads((tmp_path / "run" / "manifest.json").read_text())
    assert "figures/centres_top.png" in manifest["stages"]["geometry"]["summary"]["files"]
    description = json.loads((tmp_path / "run" / "geometry" / "descriptors.json").read_text())
    heights = description["descriptors"]["centre_height"]
    # Triangles 2 mm thick lying on the conveyor and on each other: centres from 1 mm up.
    assert 0.99 < heights["mean_mm"] <= heights["max_mm"] < 10.0
    # Its per-chip column in chips.csv (the chips' heights, as the poses have them) and its
    # part of the stage's report line.
    with open(tmp_path / "run" / "geometry" / "chips.csv") as f:
        chip_rows = list(csv.DictReader(f))
    column = [float(r["centre_height_mm"]) for r in chip_rows]
    assert np.allclose(column, poses[:, 2], atol=1e-5)
    assert f"centres up to {heights['max_mm']:.1f} mm" in result.stdout
    # The plugin's mesher, with its own key: tetrahedra, six to each cube of 1 mm.
    mesh = meshio.read(tmp_path / "run" / "mesh" / "stack_kuhn.vtu")
    assert [block.type for block in mesh.cells] == ["tetra"]
    regions = np.unique(mesh.cell_data["region"][0])
    assert set(regions) == set(range(1, 13))  # chip k is region k + 1; no pore here
    checks = json.loads((tmp_path / "run" / "mesh" / "stack_kuhn_checks.json").read_text())
    assert checks["valid"] and checks["elements"] % 6 == 0
    # Each tetrahedron a sixth of a 1 mm cube: their volume sums to the cubes'.
    points, cells = mesh.points, mesh.cells[0].data
    edges = points[cells[:, 1:]] - points[cells[:, :1]]
    assert np.allclose(np.linalg.det(edges) / 6, 1 / 6, atol=1e-9)
    assert checks["chip_volume_error_max"] < 0.05
    # The shape's own key: base 20 mm, 50 deg at the apex, so 10 / tan(25 deg) = 21.4 mm
    # tall, 214.5 mm2 in area and 428.9 mm3 at 2 mm thick.
    scenario = (tmp_path / "run" / "scenario.toml").read_text()
    assert "apex_angle_deg = 50.0" in scenario and "width_mm" not in scenario
    shapes = json.loads((tmp_path / "run" / "packing" / "shapes.json").read_text())["shapes"]
    height = 10 / np.tan(np.radians(25))
    assert shapes[0]["volume_mm3"] == pytest.approx(2.0 * 20.0 * height / 2, rel=1e-9)


def test_without_the_plugin_its_names_are_refused_in_one_line(tmp_path):
    (tmp_path / "tri.toml").write_text(TRIANGLES)
    result = run(
        ["-m", "chipstack.pipeline", "run", "tri.toml", "--to", "mesh", "--out", "run"],
        tmp_path,
        False,
    )
    assert result.returncode == 2
    (line,) = result.stderr.strip().splitlines()
    assert "unknown shape 'triangle'; valid names:" in line
    assert not (tmp_path / "run").exists()


def test_a_plugin_scenario_kind_with_its_own_table_runs_through_the_stages(tmp_path):
    (tmp_path / "ring.toml").write_text(RING)
    result = run(
        ["-m", "chipstack.pipeline", "run", "ring.toml", "--to", "mesh", "--out", "run"], tmp_path
    )
    assert result.returncode == 0, result.stderr
    assert "[ring]\nradius_mm = 8.0" in (tmp_path / "run" / "scenario.toml").read_text()
    with open(tmp_path / "run" / "packing" / "poses_after_batch_03.csv") as f:
        rows = list(csv.DictReader(f))
    x = [float(r["x_mm"]) for r in rows]
    # Released over the disc 25 mm along x, not over the 80 mm square centred on 0.
    assert len(x) == 12 and np.median(x) > 12.0
    assert (tmp_path / "run" / "mesh" / "stack_voxel.vtu").exists()
    without = run(
        ["-m", "chipstack.pipeline", "run", "ring.toml", "--out", "run2"], tmp_path, False
    )
    assert without.returncode == 2
    assert "ring: unknown key in the top level" in without.stderr  # its table, then its kind


def test_a_plugin_effect_acts_on_simulated_drops(tmp_path):
    (tmp_path / "spec.toml").write_text(WIND)
    common = ["-m", "chipstack.pipeline", "synth", "spec.toml", "--drops", "12", "--seed", "1"]
    windy = run([*common, "--effect", "crosswind=1000", "-o", "a.csv", "--workers", "1"], tmp_path)
    assert windy.returncode == 0, windy.stderr
    still = run([*common, "-o", "b.csv", "--workers", "1"], tmp_path)
    assert still.returncode == 0, still.stderr

    def mean_x(name):
        return np.mean([float(r["x_mm"]) for r in csv.DictReader(open(tmp_path / name))])

    # A push of 1 m/s^2 along +x over a 1 m fall (0.45 s): at least 0.1 m downwind.
    assert mean_x("a.csv") - mean_x("b.csv") > 100.0


def test_plugin_rows_are_generated_in_the_docs_tables(tmp_path):
    code = (
        "from chipstack.pipeline.reference import GENERATED\n"
        "names = ('shapes', 'descriptors', 'mesh_kinds', 'effects', 'scenario_kinds',\n"
        "         'stack_writers', 'figures')\n"
        "for name in names:\n"
        "    print(GENERATED[name]())\n"
    )
    with_plugin = run(["-c", code], tmp_path)
    assert with_plugin.returncode == 0, with_plugin.stderr
    rows = ("| `triangle` | An isosceles triangle", "| `centre_height` |", "| `kuhn` |")
    rows += ("| `crosswind` |", "| `ring` | Batch deposition over a disc", "| `centres` |")
    rows += ("| `top_view` | `geometry/figures/centres_top.png`, from stack",)
    for row in rows:
        assert row in with_plugin.stdout, row
    without = run(["-c", code], tmp_path, plugin=False)
    assert "triangle" not in without.stdout and "crosswind" not in without.stdout
    assert "centres" not in without.stdout and "top_view" not in without.stdout


def test_a_broken_plugin_names_itself_every_time(tmp_path, monkeypatch):
    """A plugin that cannot be imported, or that takes a built-in's name, is one error
    naming it, on every call, not an unknown name on the second."""
    from chipstack.core.registry import Registry

    info = tmp_path / "broken-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: broken\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text("[chipstack.test_broken]\nwidget = no_such_module:X\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    registry = Registry("widget", "chipstack.test_broken")
    for _ in range(2):
        with pytest.raises(RuntimeError, match="widget plugin 'widget' .* failed to load"):
            registry.get("widget")
    (info / "entry_points.txt").write_text("[chipstack.test_clash]\nbuilt = json:dumps\n")
    clashing = Registry("widget", "chipstack.test_clash")
    clashing.register("built", object())
    with pytest.raises(RuntimeError, match="the name is already a widget"):
        clashing.names()


def test_the_contract_kit_lists_the_plugin_entries_and_they_pass_it(tmp_path):
    """The contract kit (tests/test_contracts.py) with the plugin installed: its ids list
    every entry the plugin adds, generated from the registries, and those entries keep
    every contract (a docs row; the stack writer's, descriptor's and mesh kind's runs;
    the effect neutral at its neutral strength)."""
    kit = str(Path(__file__).resolve().parent / "test_contracts.py")
    listed = run(["-m", "pytest", kit, "--collect-only", "-q", "-p", "no:cacheprovider"], tmp_path)
    assert listed.returncode == 0, listed.stdout[-2000:]
    added = {
        "shape": "triangle",
        "descriptor": "centre_height",
        "mesh kind": "kuhn",
        "effect": "crosswind",
        "scenario kind": "ring",
        "deposition site": "ring",
        "stack writer": "centres",
        "figure": "top_view",
    }
    for kind, name in added.items():
        assert f"[{kind}:{name}]" in listed.stdout, (kind, name)
    for test, name in (
        ("test_every_stack_writer_writes_files_that_read_back", "centres"),
        ("test_every_descriptor_writes_its_section_of_finite_numbers", "centre_height"),
        ("test_every_mesh_kind_meshes_a_small_stack_valid", "kuhn"),
        ("test_every_effect_changes_nothing_at_its_neutral_strength", "crosswind"),
    ):
        assert f"{test}[{name}]" in listed.stdout, (test, name)
    without = run(
        ["-m", "pytest", kit, "--collect-only", "-q", "-p", "no:cacheprovider"], tmp_path, False
    )
    assert "[shape:triangle]" not in without.stdout
    chosen = " or ".join(sorted(set(added.values())))
    result = run(["-m", "pytest", kit, "-q", "-p", "no:cacheprovider", "-k", chosen], tmp_path)
    assert result.returncode == 0, result.stdout[-3000:]
    assert "17 passed" in result.stdout, result.stdout[-500:]


@pytest.mark.slow
def test_pipeline_diagnose_finds_the_plugin_effect_withheld_from_the_model(tmp_path):
    """Drops synthesised with the plugin's crosswind (the model without it): ``pipeline
    diagnose`` with the amortised model choice among no effect, crosswind and friction,
    its reference table simulated with the plugin's effect, names crosswind and explains
    the gap with it; without the plugin the effect's name is refused in one line."""
    import sys

    sys.path.insert(0, str(Path(__file__).parent))
    from conftest import drop_spec

    spec = drop_spec(tmp_path, effects=("crosswind", "friction"), method="amortised")
    spec.write_text(
        spec.read_text().replace('method = "amortised"', 'method = "amortised"\ntable_pools = 8')
    )
    synth = ["-m", "chipstack.pipeline", "synth", "spec.toml", "--seed", "5", "--workers", "2"]
    made = run([*synth, "--effect", "crosswind=300", "-o", "data.csv"], tmp_path)
    assert made.returncode == 0, made.stderr
    diagnose = ["-m", "chipstack.pipeline", "diagnose", "spec.toml", "--workers", "2"]
    result = run([*diagnose, "--out", "out", "--tables", "tables"], tmp_path)
    assert result.returncode == 0, result.stderr
    report = json.loads((tmp_path / "out" / "diagnosis.json").read_text())
    choice = report["model_choice"]
    assert choice["design"]["confusion"]["models"] == ["no effect", "crosswind", "friction"]
    assert choice["best_effect"] == "crosswind", choice["probabilities"]
    assert report["verdict"]["kind"] in ("explained", "partly explained"), report["verdict"]
    low, high = choice["strengths"]["crosswind"]["strength_ci95"]
    assert low <= 300 <= high
    without = run([*diagnose, "--out", "out2"], tmp_path, plugin=False)
    assert without.returncode == 2
    (line,) = without.stderr.strip().splitlines()
    assert "crosswind" in line and "Traceback" not in without.stderr
