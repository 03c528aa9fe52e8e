"""The contract kit (issue 57): what every registered entry of every registry keeps, with
test ids generated from the registries themselves, so a new built-in or an installed
plugin's entry is tested without editing this file (``tests/test_plugins.py`` runs the
kit again with the test plugin installed and finds its entries among the ids).

Every entry has a generated row in the docs. Where a registry's entries run in a stage,
each runs end to end there on a small case, and what it writes is read back by the
library a user would read it with: every stack writer's files, every descriptor's section,
every mesh format (meshio), every mesh kind's mesh of a small stack; every effect changes
nothing at its neutral strength and something at its prior's middle.
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import meshio
import numpy as np
import pytest
import pyvista

from chipstack.pipeline.reference import GENERATED, _registries

REGISTRIES = {r.kind: r for layer in _registries().values() for r in layer}

# The generated docs table of each registry (pipeline/reference.py: GENERATED).
TABLE_OF = {
    "stage": "stages",
    "figure": "figures",
    "physics preset": "presets",
    "deposition site": "sites",
    "effect": "effects",
    "stack writer": "stack_writers",
    "scenario kind": "scenario_kinds",
    "shape": "shapes",
    "descriptor": "descriptors",
    "mesh format": "mesh_formats",
    "mesh kind": "mesh_kinds",
    "solve model": "solve_models",
    "experiment kind": "experiment_kinds",
    "quantity measure": "quantity_measures",
}


def entries(*kinds: str) -> list:
    """pytest params ``kind:name`` of every entry of the given registries (all if none)."""
    chosen = kinds or sorted(REGISTRIES)
    return [
        pytest.param(kind, name, id=f"{kind}:{name}")
        for kind in chosen
        for name in REGISTRIES[kind].in_order()
    ]


def names(kind: str) -> list:
    return [pytest.param(name, id=name) for name in REGISTRIES[kind].in_order()]


def test_every_registry_has_a_generated_docs_table_on_a_page():
    pages = "".join(p.read_text() for p in (Path(__file__).parent.parent / "docs").glob("*.md"))
    missing = sorted(set(REGISTRIES) - set(TABLE_OF))
    assert not missing, f"registries without a generated docs table: {missing}"
    for table in TABLE_OF.values():
        assert f"<!-- BEGIN generated:{table} -->" in pages, table


def _row(table: str, name: str) -> str | None:
    """The row of ``name`` in a generated table, if it has one row with a description."""
    rows = [line for line in table.splitlines() if line.startswith(f"| `{name}` |")]
    if len(rows) != 1:
        return None
    cells = [cell.strip() for cell in rows[0].strip().strip("|").split("|")]
    return rows[0] if len(cells) >= 2 and all(cells[1:]) else None


@pytest.mark.parametrize(("kind", "name"), entries())
def test_every_entry_has_a_row_in_its_generated_table(kind, name):
    row = _row(GENERATED[TABLE_OF[kind]](), name)
    assert row, f"{kind} {name!r}: no row of its own in the {TABLE_OF[kind]} table"


def test_the_kit_finds_a_missing_row_an_empty_one_and_a_nan():
    table = "| a | b |\n|---|---|\n| `box` | a box |\n| `bare` | |"
    assert _row(table, "box") and not _row(table, "star") and not _row(table, "bare")
    assert _finite({"a": [1.0, {"b": 2}]}) and not _finite({"a": [1.0, {"b": math.nan}]})


SMALL_MESHED = '[mesh]\nkind = "voxel"\nvoxel_mm = 1.0\n'


@pytest.fixture(scope="module")
def small_run(tmp_path_factory) -> Path:
    """The small stack through packing, geometry and the voxel mesh in every format."""
    from conftest import SMALL_SCENARIO, run_scenario

    return run_scenario(SMALL_SCENARIO + SMALL_MESHED, tmp_path_factory.mktemp("kit"), "mesh")


def _read_back(path: Path) -> None:
    """Read a written file with what a user reads it with; raises when it cannot."""
    suffix = path.suffix
    if suffix == ".csv":
        with path.open(newline="") as f:
            rows = list(csv.reader(f))
        assert rows and rows[0], path
    elif suffix == ".json":
        json.loads(path.read_text())
    elif suffix == ".npz":
        with np.load(path, allow_pickle=False) as arrays:
            assert arrays.files, path
    elif suffix in (".vtp", ".vtu", ".vti", ".pvd"):
        assert pyvista.read(path) is not None, path
    else:
        assert path.stat().st_size > 0, path


@pytest.mark.parametrize("name", names("stack writer"))
def test_every_stack_writer_writes_files_that_read_back(small_run, name):
    writer = REGISTRIES["stack writer"].get(name)
    for pattern in (p.strip() for p in writer.files.split(",")):
        found = sorted((small_run / "packing").glob(pattern.replace("NN", "*")))
        assert found, f"stack writer {name!r}: no {pattern} in packing/"
        for path in found:
            _read_back(path)


def _finite(value) -> bool:
    if isinstance(value, dict):
        return all(_finite(v) for v in value.values())
    if isinstance(value, list):
        return all(_finite(v) for v in value)
    if isinstance(value, float):
        return math.isfinite(value)
    return True


@pytest.mark.parametrize("name", names("descriptor"))
def test_every_descriptor_writes_its_section_of_finite_numbers(small_run, name):
    sections = json.loads((small_run / "geometry" / "descriptors.json").read_text())
    section = sections["descriptors"].get(name)
    assert section, f"descriptor {name!r}: no section in descriptors.json"
    assert _finite(section), f"descriptor {name!r}: a NaN or an infinity in its section"


@pytest.mark.parametrize("name", names("mesh format"))
def test_every_mesh_format_reads_back_with_meshio(small_run, name):
    checks = json.loads((small_run / "mesh" / "stack_voxel_checks.json").read_text())
    back = meshio.read(small_run / "mesh" / f"stack_voxel.{name}")
    volume_cells = sum(len(b.data) for b in back.cells if b.type in ("hexahedron", "tetra"))
    assert volume_cells == checks["elements"], name
    assert len(back.points) >= checks["nodes"], name


TINY = """
name = "tiny"
seed = 4
[chip]
length_mm = 20.0
width_mm = 20.0
thickness_mm = 2.0
[deposition]
chips = 3
batch_size = 3
target_size_mm = 40.0
release_height_mm = [30.0, 50.0]
[mesh]
kind = "{kind}"
voxel_mm = 1.0
"""


@pytest.mark.parametrize("name", names("mesh kind"))
def test_every_mesh_kind_meshes_a_small_stack_valid(tmp_path, name):
    """Each mesh kind through ``pipeline run --to mesh`` on three settled chips: its files
    written and its own check valid (the image kind needs CGAL, which CI installs)."""
    import os

    from conftest import run_scenario

    from chipstack.meshing.image import cgal_available

    if name == "image" and not (cgal_available() or os.environ.get("CHIPSTACK_REQUIRE_CGAL")):
        pytest.skip("the image mesh kind needs pygalmesh (make image)")
    out = run_scenario(TINY.format(kind=name), tmp_path, "mesh")
    summary = json.loads((out / "manifest.json").read_text())["stages"]["mesh"]["summary"]
    assert summary[name].get("valid", True), summary[name]
    written = [p for p in (out / "mesh").iterdir() if p.name.startswith(f"stack_{name}")]
    assert written, f"mesh kind {name!r} wrote no stack_{name}* file"


@pytest.mark.parametrize("name", names("effect"))
def test_every_effect_changes_nothing_at_its_neutral_strength(name):
    """At its neutral strength an effect leaves every drop (or every settled chip of a
    small stack) exactly as the baseline's; at its prior's middle it moves something."""
    from chipstack.diagnosis.reference_table import simulate_pool
    from chipstack.packing.drop import DropProtocol
    from chipstack.packing.effects import EFFECTS, contact_model
    from chipstack.packing.presets import PRESETS
    from chipstack.pipeline.scenario_files import load_scenario

    effect = EFFECTS.get(name)
    lo, hi = effect.prior
    if "drop" in effect.kinds:
        scenario = load_scenario("single-chip-drop")
        contact = contact_model(PRESETS.get(scenario.physics.preset), scenario.physics)

        def outcome(strengths):
            return simulate_pool(scenario, DropProtocol(height_mm=300.0), 3, strengths, 5)
    else:
        import tempfile

        from chipstack.packing import deposit

        with tempfile.TemporaryDirectory() as folder:
            path = Path(folder) / "tiny.toml"
            path.write_text(TINY.format(kind="voxel"))
            scenario = load_scenario(path)
        contact = contact_model(PRESETS.get(scenario.physics.preset), scenario.physics)

        def outcome(strengths):
            return deposit(scenario, effects=strengths).positions

    baseline = outcome({})
    assert np.array_equal(outcome({name: effect.neutral(contact)}), baseline)
    assert not np.array_equal(outcome({name: (lo + hi) / 2}), baseline)
