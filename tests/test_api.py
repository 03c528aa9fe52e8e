"""The Python API (``chipstack``): a real run of a small scenario read back as arrays,
DataFrames and meshes; the same results as the command line; docstring examples run."""

from __future__ import annotations

import doctest
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import run_cli

import chipstack
import chipstack.api
from chipstack.core.errors import InputError

ROOT = Path(__file__).resolve().parent.parent
SMALL = {
    "deposition.chips": 24,
    "deposition.batch_size": 12,
    "deposition.target_size_mm": 80.0,
    "mesh.voxel_mm": 1.0,
    "mesh.formats": ["vtu", "msh"],
}


@pytest.fixture(scope="module")
def small_run(tmp_path_factory) -> chipstack.Run:
    out = tmp_path_factory.mktemp("api") / "run"
    return chipstack.run("paper-squares", to="mesh", out=out, seed=3, overrides=SMALL)


def test_a_run_reads_back_as_arrays_tables_and_meshes(small_run):
    import meshio
    import pandas as pd
    import pyvista as pv

    run = small_run
    assert run.stages == ["packing", "geometry", "mesh"]
    assert run.scenario.seed == 3 and run.scenario.deposition.chips == 24
    assert run.positions.shape == (24, 3) and run.quaternions.shape == (24, 4)
    np.testing.assert_allclose(np.linalg.norm(run.quaternions, axis=1), 1.0, atol=1e-6)
    # The poses table is the same stack as the arrays (CSV: 6 decimals).
    assert isinstance(run.poses, pd.DataFrame)
    np.testing.assert_allclose(run.poses[["x_mm", "y_mm", "z_mm"]], run.positions, atol=1e-5)
    assert run.positions[:, 2].min() > 0  # every chip rests on the conveyor or on chips
    # Per-chip and per-contact tables, and the descriptors as numbers.
    assert list(run.chips["chip"]) == list(range(24))
    assert set(run.contacts["kind"]) <= {"point", "line", "surface"}
    assert (run.contacts["chip_b"] == -1).any()  # the conveyor is in the contact table
    assert 0 < run.descriptors["stack.volume_fraction"] < 1
    table = run.descriptor_table
    row = table[(table.descriptor == "stack") & (table.name == "height_max_mm")]
    assert row.unit.item() == "mm"
    assert row.value.item() == pytest.approx(run.descriptors["stack.height_max_mm"])
    # The mesh, as meshio and as pyvista, every chip in it.
    mesh = run.mesh()
    assert isinstance(mesh, meshio.Mesh)
    chips = np.concatenate(mesh.cell_data["region"])
    assert set(np.unique(chips)) == set(range(1, 25))  # region id: the chips table's chip + 1
    grid = run.mesh_grid()
    assert isinstance(grid, pv.UnstructuredGrid) and grid.n_cells == len(chips)
    stack = run.stack_grid()
    assert set(np.unique(stack.cell_data["region"])) == set(range(1, 25))
    assert stack.bounds[5] == pytest.approx(run.descriptors["stack.height_max_mm"], abs=0.01)
    assert run.stack_grid(batch=1).n_cells < stack.n_cells
    assert any(p.name == "stack_voxel.msh" for p in run.files("mesh"))


def test_the_api_and_the_command_line_give_the_same_run(small_run, tmp_path):
    """Same scenario and seed: the same stack and descriptors through both doors; a run
    written by the command line opens in the API."""
    scenario = tmp_path / "small.toml"
    scenario.write_text((small_run.path / "scenario.toml").read_text())
    out = tmp_path / "cli"
    result = run_cli("run", str(scenario), "--to", "geometry", "--out", str(out), "--quiet")
    assert result.returncode == 0, result.stderr
    for name in ("packing/poses_after_batch_02.csv", "geometry/chips.csv"):
        assert (out / name).read_bytes() == (small_run.path / name).read_bytes(), name
    opened = chipstack.open_run(out)
    assert opened.descriptors == small_run.descriptors
    np.testing.assert_array_equal(opened.positions, small_run.positions)
    with pytest.raises(InputError, match=r"has no mesh result \(run it with to='mesh'\)"):
        opened.mesh()


def test_running_again_reuses_the_finished_stages(small_run):
    again = chipstack.run("paper-squares", to="mesh", out=small_run.path, seed=3, overrides=SMALL)
    assert again.manifest["stages_reused"] == ["packing", "geometry", "mesh"]
    assert again.descriptors == small_run.descriptors


def test_bad_input_is_one_error_naming_the_key(tmp_path):
    overrides = {"deposition.chipz": 3}
    with pytest.raises(InputError, match=r"^deposition.chipz: no such scenario key"):
        chipstack.run("paper-squares", out=tmp_path / "x", overrides=overrides)
    assert overrides == {"deposition.chipz": 3}  # the caller's mapping is not changed
    with pytest.raises(InputError, match=r"^deposition.chips: expected an integer"):
        chipstack.load_scenario(None, {"deposition.chips": "many"})
    with pytest.raises(InputError, match=r"^seed: must be a whole number"):
        chipstack.load_scenario("paper-squares", seed=-1)
    with pytest.raises(InputError, match=r"unknown stage"):
        chipstack.run("paper-squares", to="press", out=tmp_path / "y")
    assert not (tmp_path / "x").exists() and not (tmp_path / "y").exists()


def test_docstring_examples_run(monkeypatch, tmp_path):
    monkeypatch.chdir(tmp_path)
    for module in (chipstack, chipstack.api):
        result = doctest.testmod(module, optionflags=doctest.ELLIPSIS)
        assert result.attempted > 3, module.__name__
        assert result.failed == 0, module.__name__


def test_nothing_generic_is_importable_outside_the_clone(tmp_path):
    """The project installs one import name, ``chipstack``: its packages are
    ``chipstack.core``, ``chipstack.pipeline``... and none of their folders' generic names
    (``core``, ``pipeline``...) can be imported from outside the clone."""
    generic = ("core", "pipeline", "packing", "geometry", "meshing", "export", "diagnosis")
    probe = (
        "import importlib.util, chipstack.core.errors, chipstack.pipeline.cli\n"
        f"print(*[n for n in {generic!r} if importlib.util.find_spec(n) is not None])"
    )
    result = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, cwd=tmp_path
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.split() == []
    for name in generic:
        result = subprocess.run(
            [sys.executable, "-c", f"import {name}"], capture_output=True, text=True, cwd=tmp_path
        )
        assert f"ModuleNotFoundError: No module named '{name}'" in result.stderr


def test_a_module_of_the_users_named_like_ours_shadows_nothing(tmp_path):
    """``core`` and ``pipeline`` are generic names: a user's ``core.py`` or ``pipeline.py``
    beside their script is theirs, and chipstack still finds its own packages."""
    (tmp_path / "core.py").write_text("VALUE = 1\n")
    (tmp_path / "pipeline.py").write_text("VALUE = 2\n")
    probe = (
        "import chipstack, chipstack.core.errors as errors\n"
        "core, pipeline = __import__('core'), __import__('pipeline')\n"
        "print(core.VALUE, pipeline.VALUE, errors.__name__, "
        "chipstack.load_scenario('paper-squares').name)"
    )
    result = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, cwd=tmp_path
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.split() == ["1", "2", "chipstack.core.errors", "paper-squares"]


def _blocks(text: str, language: str) -> list[str]:
    return re.findall(rf"```{language}\n(.*?)```", text, re.DOTALL)


def test_the_tutorial_runs(tmp_path):
    """docs/python.md's code blocks, in order, in one interpreter: deposit, describe,
    mesh and plot."""
    code = "\n".join(_blocks((ROOT / "docs" / "python.md").read_text(), "python"))
    assert "chipstack.run(" in code and "screenshot" in code
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path, timeout=600
    )
    assert result.returncode == 0, result.stderr
    assert "['packing', 'geometry', 'mesh']" in result.stdout
    for name in ("stack.png", "layers.png", "stack.vtk"):
        assert (tmp_path / name).stat().st_size > 1000, name


@pytest.mark.slow
def test_the_readme_example_prints_what_the_readme_says(tmp_path):
    """The README's Python example, copied into a fresh interpreter, prints the lines the
    README shows (a 270-chip run to its mesh)."""
    readme = (ROOT / "README.md").read_text()
    section = readme.split("## Use from Python", 1)[1]
    code = _blocks(section, "python")[0]
    expected = _blocks(section, "text")[0]
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path, timeout=600
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout == expected
