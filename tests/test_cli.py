"""The command line end to end: outputs read back by the libraries users use, bad input."""

import csv
import json
import xml.etree.ElementTree as ET

import numpy as np
import pytest
import pyvista
from conftest import run_cli

from chipstack.pipeline.scenario_files import dumps_toml, load_scenario


@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("run")
    scenario = root / "small.toml"
    from conftest import SMALL_SCENARIO

    scenario.write_text(SMALL_SCENARIO)
    out = root / "out"
    result = run_cli("run", str(scenario), "--to", "packing", "--out", str(out), "--seed", "7")
    assert result.returncode == 0, result.stderr
    return out, result


def test_run_directory_holds_every_output(small_run):
    out, _ = small_run
    names = {p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file()}
    for batch in ("01", "02"):
        for stem in ("poses", "contacts", "stack"):
            ext = "vtp" if stem == "stack" else "csv"
            assert f"packing/{stem}_after_batch_{batch}.{ext}" in names
    assert {"scenario.toml", "manifest.json", "packing/stack.pvd"} <= names
    assert not list(out.parent.glob(".out*"))  # no build, state or lock left beside it


def test_manifest_records_versions_seed_times_and_warnings(small_run):
    manifest = json.loads((small_run[0] / "manifest.json").read_text())
    assert manifest["seed"] == 7
    assert manifest["versions"]["pybullet"] != "not installed"
    assert manifest["wall_time_s"]["packing"] > 0
    assert manifest["warnings"] == []
    assert [b["chips"] for b in manifest["packing"]["batches"]] == [12, 24]


def test_resolved_scenario_loads_back_to_the_same_scenario(small_run):
    out = small_run[0]
    resolved = load_scenario(out / "scenario.toml")
    assert resolved == load_scenario(out.parent / "small.toml").with_seed(7)
    assert dumps_toml(resolved) == (out / "scenario.toml").read_text()


def test_poses_csv_matches_the_vtk_series(small_run):
    out, _ = small_run
    with open(out / "packing/poses_after_batch_02.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 24
    assert rows[0].keys() >= {
        "chip",
        "batch",
        "shape",
        "x_mm",
        "y_mm",
        "z_mm",
        "qx",
        "qy",
        "qz",
        "qw",
    }
    quaternions = np.array([[float(r[k]) for k in ("qx", "qy", "qz", "qw")] for r in rows])
    assert np.allclose(np.linalg.norm(quaternions, axis=1), 1.0, atol=1e-6)
    centres = np.array([[float(r[k]) for k in ("x_mm", "y_mm", "z_mm")] for r in rows])

    pvd = ET.parse(out / "packing/stack.pvd").getroot()
    files = [d.get("file") for d in pvd.iter("DataSet")]
    assert files == ["stack_after_batch_01.vtp", "stack_after_batch_02.vtp"]
    mesh = pyvista.read(out / "packing" / files[-1])
    assert mesh.n_cells == 24 * 6
    region, batch = mesh.cell_data["region"], mesh.cell_data["batch"]
    assert sorted(set(region.tolist())) == list(range(1, 25))  # chip k is region k + 1
    assert set(batch.tolist()) == {1, 2}
    # The mean of a chip's cell centres is its centre: the file and the CSV agree.
    cell_centres = mesh.cell_centers().points
    for chip in (0, 23):
        assert np.allclose(cell_centres[region == chip + 1].mean(axis=0), centres[chip], atol=1e-3)


def test_contacts_csv_has_pairs_points_normals_distances(small_run):
    with open(small_run[0] / "packing/contacts_after_batch_02.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert rows, "a settled stack has contacts"
    assert any(r["chip_b"] == "-1" for r in rows)  # the ground
    normals = np.array([[float(r[k]) for k in ("nx", "ny", "nz")] for r in rows])
    assert np.allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-6)
    assert max(float(r["distance_mm"]) for r in rows) <= 0.05 + 1e-9


def test_progress_bar_is_shown_and_quiet_silences_it(small_scenario, tmp_path):
    loud = run_cli("run", str(small_scenario), "--out", str(tmp_path / "a"))
    quiet = run_cli("run", str(small_scenario), "--out", str(tmp_path / "b"), "--quiet")
    assert loud.returncode == quiet.returncode == 0
    assert "depositing" in loud.stderr and "2/2" in loud.stderr
    assert "written to" in loud.stdout
    assert quiet.stderr == "" and quiet.stdout == ""


def test_errors_stay_one_line_without_quiet(small_scenario, tmp_path):
    # The progress bar must not be drawn before the run directory has been checked.
    (tmp_path / "busy").mkdir()
    (tmp_path / "busy" / "keep.txt").write_text("x")
    result = run_cli("run", str(small_scenario), "--out", str(tmp_path / "busy"))
    assert result.returncode == 2
    assert len(result.stderr.strip().splitlines()) == 1, result.stderr


def test_an_unsettled_batch_is_shown_to_the_user(small_scenario, tmp_path):
    text = small_scenario.read_text() + "[settling]\nmax_time_s = 0.1\n"
    small_scenario.write_text(text)
    result = run_cli("run", str(small_scenario), "--out", str(tmp_path / "w"), "--quiet")
    assert result.returncode == 0
    assert "warning: batch 1 did not settle" in result.stderr
    manifest = json.loads((tmp_path / "w/manifest.json").read_text())
    assert manifest["warnings"] and not manifest["packing"]["all_settled"]


def test_unknown_stage_and_occupied_output_are_refused(small_scenario, tmp_path):
    result = run_cli(
        "run", str(small_scenario), "--to", "consolidate", "--out", str(tmp_path / "m")
    )
    assert result.returncode == 2 and "--to consolidate" in result.stderr
    assert "valid stages: packing, geometry, mesh" in result.stderr
    assert not (tmp_path / "m").exists()
    (tmp_path / "busy").mkdir()
    (tmp_path / "busy" / "keep.txt").write_text("x")
    result = run_cli("run", str(small_scenario), "--out", str(tmp_path / "busy"))
    assert result.returncode == 2 and "not an earlier run (no manifest.json)" in result.stderr
    assert (tmp_path / "busy" / "keep.txt").exists()


def test_missing_scenario_file_and_bad_flags(tmp_path):
    result = run_cli("run", str(tmp_path / "nope.toml"), "--out", str(tmp_path / "o"))
    assert result.returncode == 2 and "nope.toml" in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1
    result = run_cli("run", str(tmp_path), "--out", str(tmp_path / "o"))
    assert result.returncode == 2 and "is a directory" in result.stderr
    result = run_cli("run", "--seed", "abc", "--out", str(tmp_path / "o"))
    assert result.returncode == 2 and "--seed" in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1
    result = run_cli("run", "--to", "mesh\nmore", "--out", str(tmp_path / "o"))
    assert result.returncode == 2 and len(result.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("out", [".", ".."])
def test_the_current_directory_and_its_parents_are_never_replaced(small_scenario, tmp_path, out):
    work = tmp_path / "work"
    work.mkdir()
    (work / "keep.txt").write_text("precious")
    result = run_cli("run", str(small_scenario), "--out", out, "--overwrite", cwd=work)
    assert result.returncode == 2 and len(result.stderr.strip().splitlines()) == 1
    assert (work / "keep.txt").read_text() == "precious"
    assert sorted(p.name for p in work.iterdir()) == ["keep.txt"]


def test_overwrite_replaces_only_an_earlier_run(small_scenario, tmp_path):
    notes = tmp_path / "notes"
    notes.mkdir()
    (notes / "thesis.tex").write_text("x")
    result = run_cli("run", str(small_scenario), "--out", str(notes), "--overwrite")
    assert result.returncode == 2 and "manifest.json" in result.stderr
    assert (notes / "thesis.tex").exists()
    link = tmp_path / "link"
    link.symlink_to(notes)
    result = run_cli("run", str(small_scenario), "--out", str(link), "--overwrite")
    assert result.returncode == 2 and "symbolic link" in result.stderr
    assert not list(tmp_path.glob(".*partial*"))


def test_builtin_scenarios_are_the_papers():
    squares, rectangles = load_scenario(None), load_scenario("paper-rectangles")
    for s in (squares, rectangles):
        d = s.deposition
        assert (d.chips, d.batch_size, d.target_size_mm, d.release_height_mm) == (
            270,
            54,
            150.0,
            (100.0, 200.0),
        )
    assert (squares.chip.length_mm, squares.chip.width_mm) == (20.0, 20.0)
    assert (rectangles.chip.length_mm, rectangles.chip.width_mm) == (40.0, 10.0)
    volume = [
        s.chip.length_mm * s.chip.width_mm * s.chip.thickness_mm for s in (squares, rectangles)
    ]
    assert volume[0] == volume[1]


def test_the_whole_stack_model_is_the_reference_stack_with_its_pore_space():
    """``paper-whole-stack`` (the README's whole-stack solve) packs the very stack of
    ``paper-squares`` and meshes it conformally with its pore space, in every format."""
    squares, whole = load_scenario(None), load_scenario("paper-whole-stack")
    for table in ("chip", "deposition", "physics", "settling"):
        assert getattr(whole, table) == getattr(squares, table), table
    assert (whole.kind, whole.seed) == (squares.kind, squares.seed)
    assert (whole.mesh.kind, whole.mesh.pore_space) == ("conformal", "box")
    assert set(whole.mesh.formats) == {"msh", "vtu", "inp", "xdmf"}
