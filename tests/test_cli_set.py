"""``pipeline run --set KEY=VALUE`` and ``pipeline scenarios``: keys changed on the command
line, typed and checked by the scenario's schema, recorded and cached like the file's."""

import json
import logging
from pathlib import Path

import pytest
from conftest import SMALL_SCENARIO, assert_refused, run_cli, tree

from chipstack.core.errors import InputError
from chipstack.pipeline.scenario_files import load_scenario, parse_setting

ROOT = Path(__file__).resolve().parent.parent
BUILTINS = ROOT / "pipeline" / "scenarios"

# Four chips in two batches: a packing run of a second or so.
TINY = ("--set", "deposition.chips=4", "--set", "deposition.batch_size=2")


@pytest.fixture
def small(tmp_path: Path) -> Path:
    path = tmp_path / "small.toml"
    path.write_text(SMALL_SCENARIO)
    return path


def _run(scenario: Path | str, out: Path, *args: str):
    return run_cli("run", str(scenario), "--to", "packing", "--out", str(out), "--quiet", *args)


@pytest.mark.parametrize(
    "text, key, value",
    [
        ("deposition.chips=24", "deposition.chips", 24),
        ("settling.speed_mm_s=7.5", "settling.speed_mm_s", 7.5),
        ('mesh.formats=["vtu", "msh"]', "mesh.formats", ["vtu", "msh"]),
        ("mesh.kind=conformal", "mesh.kind", "conformal"),  # not TOML: bare text
        ('name="2024"', "name", "2024"),  # quoted: text, not a number
        ("mesh.periodic=true", "mesh.periodic", True),
        (" name = a b ", "name", "a b"),
        ("physics.preset=", "physics.preset", ""),
        ("name=1\nseed = 5", "name", "1\nseed = 5"),  # two TOML keys are not one value
    ],
)
def test_a_setting_is_a_dotted_key_and_a_toml_value(text, key, value):
    parsed = parse_setting(text)
    assert parsed == (key, value)
    assert type(parsed[1]) is type(value)


@pytest.mark.parametrize("text", ["deposition.chips", "deposition..chips=1", "=3", "a b=1"])
def test_a_setting_that_is_not_key_equals_value_is_refused(text):
    with pytest.raises(InputError, match=r"^--set "):
        parse_setting(text)


def test_settings_of_every_type_reach_the_run_and_its_manifest(small, tmp_path):
    out = tmp_path / "run"
    result = _run(
        small,
        out,
        *TINY,
        "--set",
        "settling.speed_mm_s=7.5",
        "--set",
        "deposition.release_height_mm=[50, 90]",
        "--set",
        'mesh.formats=["vtu","msh"]',
        "--set",
        "mesh.kind=conformal",
        "--set",
        "name=tiny",
    )
    assert result.returncode == 0, result.stderr
    resolved = load_scenario(out / "scenario.toml")
    assert (resolved.deposition.chips, resolved.deposition.batch_size) == (4, 2)
    assert resolved.settling.speed_mm_s == 7.5
    assert resolved.deposition.release_height_mm == (50.0, 90.0)
    assert resolved.mesh.formats == ("vtu", "msh")
    assert resolved.mesh.kind == "conformal"
    assert resolved.name == "tiny"
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["set"] == {
        "deposition.chips": 4,
        "deposition.batch_size": 2,
        "settling.speed_mm_s": 7.5,
        "deposition.release_height_mm": [50, 90],
        "mesh.formats": ["vtu", "msh"],
        "mesh.kind": "conformal",
        "name": "tiny",
    }
    assert [b["chips"] for b in manifest["packing"]["batches"]] == [2, 4]
    # The run is reproducible from its manifest: the same file and settings, the same scenario.
    again = load_scenario(small, manifest["set"])
    assert again.with_seed(manifest["seed"]) == resolved


def test_an_ensemble_records_the_settings_in_every_manifest(small, tmp_path):
    out = tmp_path / "ensemble"
    result = _run(small, out, *TINY, "--repeats", "2", "--workers", "1")
    assert result.returncode == 0, result.stderr
    expected = {"deposition.chips": 4, "deposition.batch_size": 2}
    assert json.loads((out / "manifest.json").read_text())["set"] == expected
    for repeat in ("repeat_0", "repeat_1"):
        manifest = json.loads((out / repeat / "manifest.json").read_text())
        assert manifest["set"] == expected
        assert [b["chips"] for b in manifest["packing"]["batches"]] == [2, 4]


def test_a_run_without_settings_records_none(small, tmp_path):
    out = tmp_path / "plain"
    result = _run(small, out, "--seed", "1")
    assert result.returncode == 0, result.stderr
    assert json.loads((out / "manifest.json").read_text())["set"] == {}


def test_switching_the_mesh_kind_drops_the_old_kinds_keys(caplog):
    """paper-volume's voxel crop (voxel_mm, periodic: voxel keys) meshed conformally
    instead: the voxel keys go, the keys both kinds take are kept."""
    base = load_scenario("paper-volume")
    assert (base.mesh.kind, base.mesh.voxel_mm, base.mesh.periodic) == ("voxel", 1.0, True)
    with caplog.at_level(logging.INFO, logger="chipstack.core.scenario_edits"):
        conformal = load_scenario("paper-volume", {"mesh.kind": "conformal", "mesh.size_mm": 2.0})
    mesh = conformal.mesh
    assert (mesh.kind, mesh.size_mm) == ("conformal", 2.0)
    assert (mesh.pore_space, mesh.crop, mesh.region_mm) == ("box", "region", (-25, 25, -25, 25))
    assert mesh.formats == base.mesh.formats
    assert not hasattr(mesh, "voxel_mm") and not hasattr(mesh, "periodic")
    dropped = [r.getMessage() for r in caplog.records if "dropped" in r.getMessage()]
    assert dropped == [
        "dropped mesh.voxel_mm, mesh.periodic: the kinds now chosen do not take them"
    ]
    # The rest of the scenario is the file's.
    for table in ("chip", "deposition", "physics", "settling"):
        assert getattr(conformal, table) == getattr(base, table), table


def test_a_kind_switch_still_refuses_keys_of_neither_kind_and_named_old_keys():
    with pytest.raises(InputError, match=r"^--set mesh\.bogus_mm: unknown key in \[mesh\]"):
        load_scenario("paper-volume", {"mesh.kind": "conformal", "mesh.bogus_mm": 1.0})
    # A key of the old kind that the user sets is not dropped: it is refused, naming it.
    with pytest.raises(InputError, match=r"^--set mesh\.voxel_mm: a key of mesh kind 'voxel'"):
        load_scenario("paper-volume", {"mesh.kind": "conformal", "mesh.voxel_mm": 2.0})


def test_a_key_the_file_gives_for_another_kind_is_still_refused(tmp_path):
    """Only a kind a setting switches drops keys: the file's own mistake is its own."""
    path = tmp_path / "wrong.toml"
    path.write_text(SMALL_SCENARIO + '[mesh]\nkind = "conformal"\nvoxel_mm = 1.0\n')
    with pytest.raises(InputError, match=r"wrong\.toml: mesh\.voxel_mm: a key of mesh kind"):
        load_scenario(path, {"deposition.chips": 12})


def test_switching_the_chip_shape_drops_the_old_shapes_keys():
    star = load_scenario("paper-squares", {"chip.shape": "star", "chip.sides": 6})
    assert (star.chip.shape, star.chip.sides, star.chip.length_mm) == ("star", 6, 20.0)
    assert not hasattr(star.chip, "width_mm")  # a box's key: the star takes none


def test_switching_the_scenario_kind_drops_the_tables_it_lacks():
    drop = load_scenario("paper-squares", {"kind": "drop", "drop.drops": 3})
    assert (drop.kind, drop.drop.drops) == ("drop", 3)
    assert "mesh" not in {t.table for t in drop.tables}
    assert drop.deposition == load_scenario("paper-squares").deposition


def test_the_kind_switch_runs_end_to_end(tmp_path):
    """The issue's trial: paper-squares (1 mm voxels) as a conformal run, no file edited."""
    out = tmp_path / "conformal"
    result = _run("paper-squares", out, *TINY, "--set", "mesh.kind=conformal", "-v")
    assert result.returncode == 0, result.stderr
    assert "info: dropped mesh.voxel_mm: the kinds now chosen do not take them" in result.stderr
    text = (out / "scenario.toml").read_text()
    assert 'kind = "conformal"' in text and "voxel_mm" not in text.split("[mesh]")[1]


@pytest.mark.parametrize(
    "setting, shown",
    [
        ("depositon.chips=4", "--set depositon.chips: depositon: unknown key in the top level"),
        ("deposition.chipz=4", "--set deposition.chipz: unknown key in [deposition]"),
        ("deposition.chips=many", "--set deposition.chips: expected an integer, got str 'many'"),
        ("deposition.chips=0", "--set deposition.chips: must be positive (got 0)"),
        ("settling.speed_mm_s=nan", "--set settling.speed_mm_s: must be finite"),
        ("seed.x=1", "--set seed.x: seed is not a table"),
        ("deposition.chips", "--set deposition.chips: expected KEY=VALUE"),
    ],
)
def test_a_bad_setting_is_one_line_naming_it_and_nothing_is_written(
    small, tmp_path, setting, shown
):
    out = tmp_path / "never"
    before = tree(tmp_path)
    result = run_cli("run", str(small), "--to", "packing", "--out", str(out), "--set", setting)
    assert_refused(result, shown, tmp_path, before)  # one line: no warning, no traceback
    assert result.stderr.startswith(f"pipeline: error: {shown}"), result.stderr
    assert result.stdout == "" and not out.exists()


def test_a_cross_check_names_the_setting_that_broke_it():
    with pytest.raises(InputError) as caught:
        load_scenario("paper-squares", {"deposition.chips": 5})
    assert str(caught.value) == (
        "--set deposition.chips: deposition.batch_size: 54 is larger than deposition.chips (5)"
    )


def test_a_changed_setting_does_not_reuse_the_cached_stage(small, tmp_path):
    out = tmp_path / "cached"
    first = _run(small, out, *TINY)
    assert first.returncode == 0, first.stderr
    changed = ("--set", "deposition.chips=6", "--set", "deposition.batch_size=3")
    second = _run(small, out, *changed)
    assert second.returncode == 0, second.stderr
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["stages_reused"] == []
    assert [b["chips"] for b in manifest["packing"]["batches"]] == [3, 6]
    assert manifest["set"]["deposition.chips"] == 6
    third = _run(small, out, *changed)  # the same settings again: the stage is reused
    assert third.returncode == 0, third.stderr
    assert json.loads((out / "manifest.json").read_text())["stages_reused"] == ["packing"]


def test_scenarios_lists_every_builtin_once():
    result = run_cli("scenarios")
    assert result.returncode == 0, result.stderr
    assert result.stderr == ""
    files = sorted(p.stem for p in BUILTINS.glob("*.toml"))
    assert len(files) >= 10
    rows = [line.split(maxsplit=2) for line in result.stdout.splitlines()]
    assert [row[0] for row in rows] == files  # each once, sorted
    for name, kind, description in rows:
        assert kind == load_scenario(name).kind, name
        first = (BUILTINS / f"{name}.toml").read_text().splitlines()[0]
        assert first == f"# {description}", name


def test_every_builtin_opens_with_a_one_line_summary():
    """The description ``pipeline scenarios`` shows: the first paragraph of the leading
    comment, one line of at most 88 characters, followed by an empty comment line."""
    for path in sorted(BUILTINS.glob("*.toml")):
        lines = path.read_text().splitlines()
        assert lines[0].startswith("# ") and len(lines[0]) <= 88, path.name
        assert lines[0].endswith("."), path.name
        assert lines[1] == "#", path.name
