"""The geometry stage from the command line: outputs read back, ensembles, bad input."""

from __future__ import annotations

import csv
import itertools
import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import pyvista
from conftest import SMALL_SCENARIO, run_cli

DESCRIPTOR_NAMES = {
    "contacts",
    "thickness",
    "layers",
    "overlaps",
    "orientation",
    "stack",
    "voxels",
    "coverage",
}


@pytest.fixture(scope="module")
def described(tmp_path_factory):
    root = tmp_path_factory.mktemp("geometry")
    scenario = root / "small.toml"
    scenario.write_text(SMALL_SCENARIO)
    out = root / "run"
    result = run_cli("run", str(scenario), "--to", "geometry", "--out", str(out), "--seed", "4")
    assert result.returncode == 0, result.stderr
    return out, result


def test_geometry_run_writes_every_descriptor_file(described):
    out, result = described
    names = {p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file()}
    for name in (
        "descriptors.json",
        "chips.csv",
        "contacts.csv",
        "contacts_by_batch.csv",
        "layers.csv",
        "neh_map.csv",
        "overlaps.csv",
        "coverage.csv",
        "voxels.vti",
        "figures/contact_types.png",
        "figures/neh_map.png",
        "figures/layer_filling.png",
        "figures/stack.png",
    ):
        assert f"geometry/{name}" in names
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["stages_completed"] == ["packing", "geometry"]
    assert "contacts per chip" in result.stdout


def test_descriptors_json_follows_its_schema(described):
    data = json.loads((described[0] / "geometry/descriptors.json").read_text())
    assert data["schema"] == "chipstack.descriptors/1"
    assert set(data["descriptors"]) == DESCRIPTOR_NAMES
    assert data["parameters"]["pixel_mm"] == 3.0
    for section in data["descriptors"].values():
        for entry in section["scalars"].values():
            assert {"value", "unit", "doc"} <= set(entry)
        for entry in section["profiles"].values():
            assert len(entry["index"]) == len(entry["values"])
            assert {"index_name", "unit", "doc"} <= set(entry)
    layers = data["descriptors"]["layers"]["profiles"]["chips"]["values"]
    assert sum(layers) == 24  # every chip in exactly one layer


def test_tables_agree_with_the_json(described):
    out = described[0]
    data = json.loads((out / "geometry/descriptors.json").read_text())["descriptors"]
    with open(out / "geometry/contacts_by_batch.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [int(r["batch"]) for r in rows] == [1, 2]
    point = data["contacts"]["profiles"]["point_per_chip_by_batch"]["values"]
    assert [float(r["point_per_chip"]) for r in rows] == pytest.approx(point, rel=1e-5)
    with open(out / "geometry/chips.csv", newline="") as f:
        chips = list(csv.DictReader(f))
    assert len(chips) == 24
    both_sides = sum(int(r["point_contacts"]) for r in chips) / 24
    expected = data["contacts"]["scalars"]["point_per_chip_both_sides"]["value"]
    assert both_sides == pytest.approx(expected)
    with open(out / "geometry/neh_map.csv", newline="") as f:
        neh = [(int(r["neh"]), int(r["on_target"])) for r in csv.DictReader(f)]
    mean = np.mean([n for n, on in neh if on])
    assert mean == pytest.approx(data["thickness"]["scalars"]["neh_mean"]["value"])


def test_voxel_image_opens_in_pyvista_with_every_chip(described):
    image = pyvista.read(described[0] / "geometry/voxels.vti")
    labels = np.asarray(image.cell_data["region"])
    assert set(np.unique(labels)) == set(range(1, 26))  # the 24 chips and void (the pore, 25)
    assert image.spacing == pytest.approx((1.0, 1.0, 1.0))
    data = json.loads((described[0] / "geometry/descriptors.json").read_text())
    assert data["descriptors"]["voxels"]["scalars"]["profile_max_difference"]["value"] < 0.05


def _packing_run(tmp_path: Path, small_scenario: Path) -> Path:
    out = tmp_path / "packed"
    result = run_cli("run", str(small_scenario), "--out", str(out), "--quiet")
    assert result.returncode == 0, result.stderr
    return out


def test_describe_adds_geometry_to_a_packing_run(tmp_path, small_scenario):
    out = _packing_run(tmp_path, small_scenario)
    result = run_cli("describe", str(out), "--descriptors", "contacts,layers", "--no-figures")
    assert result.returncode == 0, result.stderr
    data = json.loads((out / "geometry/descriptors.json").read_text())
    assert set(data["descriptors"]) == {"contacts", "layers"}
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["stages_completed"] == ["packing", "geometry"]
    again = run_cli("describe", str(out))
    assert again.returncode == 2 and "already described" in again.stderr
    assert not list(out.glob(".geometry*"))


def _one_line_error(result, *words: str) -> None:
    assert result.returncode == 2, result.stdout + result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert "Traceback" not in result.stderr
    for word in words:
        assert word in lines[0], lines[0]


def test_describe_a_directory_without_packing_result(tmp_path):
    empty = tmp_path / "nothing"
    empty.mkdir()
    _one_line_error(run_cli("describe", str(empty)), "nothing", "manifest.json")
    (empty / "manifest.json").write_text('{"stages_completed": []}')
    _one_line_error(run_cli("describe", str(empty)), "no packing result")
    assert sorted(p.name for p in empty.iterdir()) == ["manifest.json"]


@pytest.mark.parametrize(
    "corrupt, words",
    [
        (lambda t: t.replace("0.", "x.", 1), ["poses_after_batch_02.csv", "not a number"]),
        (lambda t: t.replace("chip,batch", "chip,bunch"), ["poses_after_batch_02.csv", "header"]),
        (lambda t: "\n".join(t.splitlines()[:1]), ["poses_after_batch_02.csv", "no chips"]),
        (lambda t: t.replace(",0.", ",nan", 1), ["poses_after_batch_02.csv"]),
        (lambda t: "", ["poses_after_batch_02.csv", "empty"]),
        (lambda t: re.sub(r"\n0,1,(box [^,]*),[^,]*,", r"\n0,1,\1,1e300,", t, count=1), ["beyond"]),
    ],
)
def test_describe_a_corrupted_poses_file(tmp_path, small_scenario, corrupt, words):
    out = _packing_run(tmp_path, small_scenario)
    poses = out / "packing/poses_after_batch_02.csv"
    poses.write_text(corrupt(poses.read_text()))
    before = sorted(p.relative_to(out).as_posix() for p in out.rglob("*"))
    _one_line_error(run_cli("describe", str(out)), *words)
    assert sorted(p.relative_to(out).as_posix() for p in out.rglob("*")) == before


def test_unknown_descriptor_name_is_refused_before_any_work(tmp_path, small_scenario):
    out = _packing_run(tmp_path, small_scenario)
    before = sorted(p.relative_to(out).as_posix() for p in out.rglob("*"))
    _one_line_error(
        run_cli("describe", str(out), "--descriptors", "contacts,porosity"),
        "porosity",
        "valid names: contacts",
    )
    assert sorted(p.relative_to(out).as_posix() for p in out.rglob("*")) == before
    fresh = tmp_path / "fresh"
    _one_line_error(
        run_cli(
            "run",
            str(small_scenario),
            "--to",
            "geometry",
            "--out",
            str(fresh),
            "--descriptors",
            "nope",
        ),
        "nope",
    )
    assert not fresh.exists()


def test_ensemble_and_comparison(tmp_path, small_scenario):
    a, b, cmp = tmp_path / "a", tmp_path / "b", tmp_path / "cmp"
    for out, seed in ((a, "1"), (b, "2")):
        result = run_cli(
            "run",
            str(small_scenario),
            "--to",
            "geometry",
            "--repeats",
            "3",
            "--seed",
            seed,
            "--out",
            str(out),
        )
        assert result.returncode == 0, result.stderr
    # The summary printed: each descriptor's own scalars with their intervals.
    printed = re.findall(r"^  (\w+\.\w+): ", result.stdout, re.MULTILINE)
    assert printed == [
        "contacts.point_per_chip",
        "contacts.line_per_chip",
        "contacts.surface_per_chip",
        "stack.height_max_mm",
        "stack.volume_fraction",
        "layers.highest_layer",
        "coverage.single_cover_fraction",
        "coverage.mean_cover",
    ]
    summary = json.loads((a / "ensemble.json").read_text())
    manifest = json.loads((a / "manifest.json").read_text())
    assert summary["repeats"] == 3 and len(set(manifest["seeds"])) == 3
    height = summary["descriptors"]["stack"]["scalars"]["height_max_mm"]
    assert height["n"] == 3 and height["ci_low"] <= height["mean"] <= height["ci_high"]
    assert height["mean"] == pytest.approx(np.mean(height["values"]))
    assert (a / "repeat_0/geometry/descriptors.json").is_file()
    assert (a / "figures/layer_filling.png").is_file()
    assert (a / "figures/contact_types.png").is_file()  # Fig. 7 with bands, the contacts' own
    result = run_cli("compare", str(a), str(b), "--out", str(cmp))
    assert result.returncode == 0, result.stderr
    assert "stack.height_max_mm" in result.stdout
    comparison = json.loads((cmp / "compare.json").read_text())
    entry = comparison["descriptors"]["stack"]["scalars"]["height_max_mm"]
    # 3 repeats against 3: the permutation test enumerates all C(6, 3) = 20 splits, so its
    # p-value is the share of splits whose |difference of means| reaches the observed one,
    # recomputed here from the two ensembles' values; the smallest it can be is 2 / 20
    # (the observed split and its mirror), so no descriptor of these ensembles can differ.
    values_a = height["values"]
    values_b = json.loads((b / "ensemble.json").read_text())["descriptors"]["stack"]["scalars"][
        "height_max_mm"
    ]["values"]
    pooled = np.array(values_a + values_b)
    observed = abs(np.mean(values_b) - np.mean(values_a))
    splits = [np.array(s) for s in itertools.combinations(range(6), 3)]
    reaching = sum(
        abs(np.delete(pooled, s).mean() - pooled[s].mean()) >= observed - 1e-9 for s in splits
    )
    assert entry["p_permutation"] == pytest.approx(reaching / 20, abs=1e-12), (values_a, values_b)
    assert entry["p_permutation"] >= 2 / 20 and entry["differs"] is False
    assert (cmp / "figures/layer_filling.png").is_file()
    # seeds depend on the ensemble seed and the index only: a 2-repeat ensemble is a prefix
    c = tmp_path / "c"
    result = run_cli(
        "run",
        str(small_scenario),
        "--to",
        "packing",
        "--repeats",
        "2",
        "--seed",
        "1",
        "--out",
        str(c),
        "--quiet",
    )
    assert result.returncode == 0, result.stderr
    assert json.loads((c / "manifest.json").read_text())["seeds"] == manifest["seeds"][:2]
    shutil.rmtree(c)


def test_compare_refuses_single_runs_and_missing_directories(tmp_path, described):
    _one_line_error(
        run_cli("compare", str(described[0]), str(described[0]), "--out", str(tmp_path / "x")),
        "single run",
    )
    _one_line_error(
        run_cli("compare", str(tmp_path / "no"), str(described[0]), "--out", str(tmp_path / "y")),
        "no such run directory",
    )
    assert not (tmp_path / "x").exists() and not (tmp_path / "y").exists()


@pytest.fixture(scope="module")
def two_repeat_ensemble(tmp_path_factory) -> Path:
    """A 2-repeat ensemble of the small scenario (stack and layers), made once: each
    damaged-ensemble case compares a copy with a damaged copy."""
    root = tmp_path_factory.mktemp("ensemble")
    scenario = root / "small.toml"
    scenario.write_text(SMALL_SCENARIO)
    out = root / "ensemble"
    result = run_cli(
        "run", str(scenario), "--to", "geometry", "--repeats", "2", "--out", str(out),
        "--quiet", "--descriptors", "stack,layers",
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    return out


@pytest.mark.parametrize(
    "damage, words",
    [
        (lambda d: d.update(repeats="3"), ["repeats"]),
        (
            lambda d: d["descriptors"]["stack"]["scalars"]["height_max_mm"]["values"].pop(),
            ["height_max_mm"],
        ),
        (
            lambda d: d["descriptors"]["layers"]["profiles"]["chips"]["values"][0].append(1),
            ["layers.chips"],
        ),
        (
            lambda d: d.update(parameters={**d["parameters"], "layer_mm": 4.0}),
            ["layer_mm 2.0 vs 4.0"],
        ),
        (lambda d: d.update(descriptors={}), ["share no descriptor"]),
    ],
)
def test_compare_refuses_damaged_or_mismatched_ensembles(
    tmp_path, two_repeat_ensemble, damage, words
):
    a, b = tmp_path / "a", tmp_path / "b"
    shutil.copytree(two_repeat_ensemble, a)
    shutil.copytree(a, b)
    data = json.loads((b / "ensemble.json").read_text())
    damage(data)
    (b / "ensemble.json").write_text(json.dumps(data))
    _one_line_error(run_cli("compare", str(a), str(b), "--out", str(tmp_path / "c")), *words)
    assert not (tmp_path / "c").exists()


def test_bad_repeats_are_refused(tmp_path, small_scenario):
    for value in ("1", "0", "-3", "100000"):
        _one_line_error(
            run_cli(
                "run",
                str(small_scenario),
                "--to",
                "geometry",
                "--repeats",
                value,
                "--out",
                str(tmp_path / "r"),
            ),
            "--repeats",
        )
    assert not (tmp_path / "r").exists()
