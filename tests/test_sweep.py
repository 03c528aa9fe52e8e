"""``pipeline sweep``: ensembles at every point of a grid, the table and figures over
them, resuming, comparing points, and bad keys or values refused before anything runs."""

from __future__ import annotations

import csv
import dataclasses
import json

from conftest import run_cli
from test_conveyor import short_mat

from chipstack.pipeline.scenario_files import dumps_toml


def _short_mat_file(tmp_path):
    """Half the conveyor tests' short mat (80 chips, a mat about 67 mm long; a 20 mm panel
    and 10 mm weight cells in its 23 mm steady part): a sweep runs it eight times, and
    what it checks is the sweep, not the mat."""
    path = tmp_path / "short-mat.toml"
    mat = short_mat(deposition={"chips": 80, "target_size_mm": 20.0}, conveyor={"cell_mm": 10.0})
    path.write_text(dumps_toml(dataclasses.replace(mat, name="short-mat")))
    return path


def test_sweep_runs_every_point_and_tabulates_every_scalar(tmp_path):
    scenario = _short_mat_file(tmp_path)
    out = tmp_path / "sweep"
    args = ("sweep", str(scenario), "--vary", "conveyor.belt_speed_mm_s=40,60")
    args += ("--repeats", "2", "--workers", "2", "--out", str(out))
    first = run_cli(*args)
    assert first.returncode == 0, first.stderr
    record = json.loads((out / "sweep.json").read_text())
    assert [p["values"] for p in record["points"]] == [
        {"conveyor.belt_speed_mm_s": 40},
        {"conveyor.belt_speed_mm_s": 60},
    ]
    for point in record["points"]:
        weight = point["scalars"]["conveyor.areal_weight.mean_g_m2"]
        assert weight["n"] == 2 and weight["ci_low"] <= weight["mean"] <= weight["ci_high"]
        assert point["scalars"]["stack.volume_fraction"]["n"] == 2  # the panel's descriptors
        assert point["scalars"]["conveyor.chips.released"]["mean"] == 80
    # The same chips over a faster belt make a thinner, lighter mat.
    light, heavy = (p["scalars"]["conveyor.areal_weight.mean_g_m2"] for p in record["points"][::-1])
    assert light["mean"] < heavy["mean"]
    with open(out / "sweep.csv") as f:
        rows = list(csv.reader(f))
    assert len(rows) == 3 and "conveyor.areal_weight.cv mean" in rows[0]
    assert (out / "figures" / "sweep_conveyor.belt_speed_mm_s.png").stat().st_size > 50_000
    # Every point is an ensemble: compare two of them.
    compared = run_cli(
        "compare",
        str(out / "conveyor.belt_speed_mm_s=40"),
        str(out / "conveyor.belt_speed_mm_s=60"),
        "--out",
        str(tmp_path / "compare"),
        "--quiet",
    )
    assert compared.returncode == 0, compared.stderr
    # Run again: every run is reused, the table is the same.
    again = run_cli(*args)
    assert again.returncode == 0, again.stderr
    assert json.loads((out / "sweep.json").read_text())["points"] == record["points"]
    # --overwrite redoes the points: the same seeds give the same table, times aside.
    redone = run_cli(*args, "--overwrite")
    assert redone.returncode == 0, redone.stderr
    for old, new in zip(
        record["points"], json.loads((out / "sweep.json").read_text())["points"], strict=True
    ):
        physical = [name for name in old["scalars"] if ".time." not in name]
        assert {n: new["scalars"][n] for n in physical} == {n: old["scalars"][n] for n in physical}


def test_sweep_refuses_a_bad_key_or_value_before_running(tmp_path):
    scenario = _short_mat_file(tmp_path)
    for vary, expected in (
        ("conveyor.belt_sped_mm_s=1,2", "no such scenario key"),
        ("conveyor.belt_speed_mm_s=40,-5", "conveyor.belt_speed_mm_s: must be between"),
        ("conveyor.belt_speed_mm_s", "expected KEY=VALUE"),
        ("conveyor.belt_speed_mm_s=40,40.0", "are the same scenario"),
        ("name=a/b,c", "no '/'"),
    ):
        out = tmp_path / "bad"
        result = run_cli(
            "sweep", str(scenario), "--vary", vary, "--repeats", "2", "--out", str(out)
        )
        assert result.returncode == 2, result.stderr
        assert expected in result.stderr
        assert len(result.stderr.strip().splitlines()) == 1
        assert not out.exists()
