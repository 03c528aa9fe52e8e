"""The catalogue of bad input, met from the command line.

Every case must be refused with one line on stderr naming the key, file, column or flag
at fault, exit status 2, no traceback, and nothing written: the folder the case works in
holds exactly what it held before. Sections: scenarios, geometry files, experiment specs
and observation files, run directories, command-line flags.
"""

from __future__ import annotations

import csv
import json
import os
import resource
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from conftest import SMALL_SCENARIO, assert_refused, drop_spec, run_cli, tree

# -- scenarios -----------------------------------------------------------------------------
BAD_SCENARIOS = {
    "unknown key": ("[deposition]\nchips = 10\nbatch_size = 5\ncolour = 3\n", "deposition.colour"),
    "unknown section": ("[chips]\nn = 3\n", "chips"),
    "wrong type": ('[deposition]\nchips = "many"\n', "deposition.chips"),
    "float count": ("[deposition]\nchips = 10.5\n", "deposition.chips"),
    "boolean size": ("[chip]\nlength_mm = true\n", "chip.length_mm"),
    "table for a number": ("[chip]\nlength_mm = { a = 1 }\n", "chip.length_mm"),
    "zero size": ("[chip]\nlength_mm = 0\n", "chip.length_mm"),
    "negative size": ("[deposition]\ntarget_size_mm = -150\n", "deposition.target_size_mm"),
    "absurd size": ("[deposition]\ntarget_size_mm = 1e300\n", "deposition.target_size_mm"),
    "absurd release": (
        "[deposition]\nrelease_height_mm = [1e300, 1e300]\n",
        "deposition.release_height_mm",
    ),
    "zero count": ("[deposition]\nchips = 0\n", "deposition.chips"),
    "zero batch": ("[deposition]\nbatch_size = 0\n", "deposition.batch_size"),
    "absurd count": ("[deposition]\nchips = 100000000\nbatch_size = 5\n", "deposition.chips"),
    "batch above chips": ("[deposition]\nchips = 10\nbatch_size = 20\n", "deposition.batch_size"),
    "nan": ("[settling]\nspeed_mm_s = nan\n", "settling.speed_mm_s"),
    "infinite": ("[chip]\nwidth_mm = inf\n", "chip.width_mm"),
    "inverted range": (
        "[deposition]\nrelease_height_mm = [200.0, 100.0]\n",
        "deposition.release_height_mm",
    ),
    "three-value range": (
        "[deposition]\nrelease_height_mm = [100.0, 150.0, 200.0]\n",
        "deposition.release_height_mm",
    ),
    "release touching the floor": (
        "[deposition]\nrelease_height_mm = [5.0, 200.0]\n",
        "deposition.release_height_mm",
    ),
    "infinite fibre direction": (
        "[chip]\nfibre_directions_deg = [inf]\n",
        "chip.fibre_directions_deg",
    ),
    "chip as thick as wide": ("[chip]\nwidth_mm = 2.0\n", "chip.thickness_mm"),
    "time step out of range": ("[physics]\ntime_step_s = 0.5\n", "physics.time_step_s"),
    "friction out of range": ("[physics]\nfriction = 1e9\n", "physics.friction"),
    "hold longer than cap": ("[settling]\nhold_time_s = 20.0\n", "settling.hold_time_s"),
    "negative seed": ("seed = -3\n", "seed"),
    "name with a slash": ('name = "../../escape"\n', "name"),
    "unknown preset": ('[physics]\npreset = "stiff"\n', "physics.preset"),
    "unknown shape": ('[chip]\nshape = "blob"\n', "chip.shape"),
    "unknown orientation": ('[deposition]\norientation = "tumbling"\n', "deposition.orientation"),
    "malformed": ("[deposition\nchips = 3\n", "malformed TOML"),
    "empty": ("", "empty"),
    "chip larger than the target": (
        "[chip]\nlength_mm = 200.0\nwidth_mm = 200.0\n",
        "chip.length_mm",
    ),
    "mix weights summing to zero": (
        '[[mix]]\nshape = "box"\nweight = 0.0\n',
        "mix: the weights sum to 0",
    ),
    "wrong length unit": ('[chip]\nshape = "file"\nfile = "c.obj"\nunits = "furlong"\n', "units"),
    "a geometry file for a box": (
        '[chip]\nshape = "box"\nfile = "c.obj"\n',
        "chip.file: a key of shape 'file', not of 'box'",
    ),
    "a star's key for a box": (
        "[chip]\ninner_ratio = 0.3\n",
        "chip.inner_ratio: a key of shape 'star', not of 'box'",
    ),
    "a box's key in a polygon mix": (
        '[[mix]]\nshape = "polygon"\nwidth_mm = 5.0\n',
        "mix[0].width_mm: a key of shape 'box', 'beam', 'fibre', not of 'polygon'",
    ),
    "a key no shape has": ('[chip]\nshape = "star"\nsidez = 5\n', "chip.sidez: unknown key"),
    "array nested 1,000 deep": ("a = " + "[" * 1000 + "]" * 1000 + "\n", "nested too deeply"),
    "a value of 600 kB": (
        '[deposition]\nchips = "' + "y" * 600_000 + '"\n',
        "... (600,002 characters)",
    ),
    "a file of 2 MB": ("# " + "n" * 2_000_000 + "\n", "at most 1,000,000 are read"),
    "crop to a region not given": ('[mesh]\ncrop = "region"\n', "mesh.region_mm: give"),
    "crop region of three numbers": (
        '[mesh]\ncrop = "region"\nregion_mm = [0.0, 1.0, 2.0]\n',
        "mesh.region_mm: must be [x_min, x_max, y_min, y_max]",
    ),
    "crop region inside out": (
        '[mesh]\ncrop = "region"\nregion_mm = [10.0, -10.0, -5.0, 5.0]\n',
        "mesh.region_mm: needs x_min < x_max",
    ),
    "crop region without crop": ("[mesh]\nregion_mm = [-5.0, 5.0, -5.0, 5.0]\n", "mesh.region_mm"),
    "periodic sides without a crop": (
        '[mesh]\nperiodic = true\npore_space = "box"\n',
        "mesh.periodic: needs a crop",
    ),
    "periodic sides without the pore space": (
        '[mesh]\nperiodic = true\ncrop = "target"\n',
        "mesh.periodic: needs a crop",
    ),
    "periodic sides of the conformal mesh": (
        '[mesh]\nkind = "conformal"\ncrop = "target"\npore_space = "box"\nperiodic = true\n',
        "mesh.periodic: a key of mesh kind 'voxel', 'both', not of 'conformal'",
    ),
    "periodic sides of both meshes": (
        '[mesh]\nkind = "both"\ncrop = "target"\npore_space = "box"\nperiodic = true\n',
        "mesh.periodic: the voxel mesh only (mesh.kind is 'both'",
    ),
    "the contact press's key for a voxel volume": (
        '[mesh]\nkind = "voxel"\npore_space = "box"\n[solve]\nfriction = 0.2\n',
        "solve.friction: a key of solve model 'contact', 'loose', not of 'volume'",
    ),
    "a table of another scenario kind": (
        "[conveyor]\nbelt_speed_mm_s = 5.0\n",
        "conveyor: not a table",
    ),
    "a voxel key for the contact model": (
        '[mesh]\nkind = "contact"\nvoxel_mm = 1.0\n',
        "mesh.voxel_mm: a key of mesh kind 'voxel', 'both', not of 'contact'",
    ),
    "crop of the contact model": ('[mesh]\nkind = "contact"\ncrop = "target"\n', "mesh.crop"),
    "unknown scenario kind": (
        'kind = "pour"\n',
        "kind: must be one of 'stack', 'drop', 'container', 'conveyor' (got 'pour')",
    ),
}


@pytest.mark.parametrize("case", sorted(BAD_SCENARIOS))
def test_bad_scenario(case, tmp_path):
    text, named = BAD_SCENARIOS[case]
    (tmp_path / "bad.toml").write_text(text)
    before = tree(tmp_path)
    result = run_cli("run", str(tmp_path / "bad.toml"), "--out", str(tmp_path / "out"))
    assert_refused(result, named, tmp_path, before)


def test_unknown_preset_lists_the_valid_ones(tmp_path):
    path = tmp_path / "bad.toml"
    path.write_text('[physics]\npreset = "stiff"\n')
    result = run_cli("run", str(path), "--out", str(tmp_path / "o"))
    assert "default" in result.stderr and "paper" in result.stderr


# -- geometry files ------------------------------------------------------------------------
CUBE_VERTICES = [(x, y, z) for x in (0, 20) for y in (0, 10) for z in (0, 2)]
CUBE_FACES = [
    (1, 2, 4), (1, 4, 3), (5, 7, 8), (5, 8, 6), (1, 5, 6), (1, 6, 2),
    (3, 4, 8), (3, 8, 7), (1, 3, 7), (1, 7, 5), (2, 6, 8), (2, 8, 4),
]  # fmt: skip


def _obj(vertices=CUBE_VERTICES, faces=CUBE_FACES) -> str:
    lines = [f"v {x} {y} {z}" for x, y, z in vertices]
    return "\n".join(lines + [f"f {a} {b} {c}" for a, b, c in faces]) + "\n"


def _two_cubes(shift: float) -> str:
    moved = [(x + shift, y, z) for x, y, z in CUBE_VERTICES]
    faces = CUBE_FACES + [(a + 8, b + 8, c + 8) for a, b, c in CUBE_FACES]
    return _obj(CUBE_VERTICES + moved, faces)


BAD_GEOMETRY_FILES = {
    "empty file": ("c.stl", "", "the geometry file is empty"),
    "garbage bytes": ("c.stl", b"\x00\xff" * 300, "c.stl"),
    "open surface": ("c.obj", _obj(faces=CUBE_FACES[:-2]), "not watertight"),
    "a face turned inside out": (
        "c.obj",
        _obj(faces=[*CUBE_FACES[:-1], CUBE_FACES[-1][::-1]]),
        "c.obj",
    ),
    "two separate bodies": ("c.obj", _two_cubes(40.0), "separate bodies"),
    "self-intersecting (two cubes through each other)": ("c.obj", _two_cubes(5.0), "c.obj"),
    "NaN vertex": ("c.obj", _obj(vertices=[(float("nan"), 0, 0), *CUBE_VERTICES[1:]]), "c.obj"),
    "no faces": ("c.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\n", "c.obj"),
    "unsupported type": ("c.step", _obj(), "unsupported geometry file type '.step'"),
    "missing file": (None, None, "geometry file not found"),
    # a 20 mm chip said to be in metres
    "metres read as millimetres": ("c.obj", _obj(), "chip (22360.7 mm across) is larger"),
    # numbers out of range, refused before any arithmetic on them (class 2)
    "coordinates of 1e150": (
        "c.obj",
        _obj(vertices=[tuple(1e150 * v for v in p) for p in CUBE_VERTICES]),
        "c.obj: a vertex lies 2e+151 mm from the origin",
    ),
    "coordinates of 1e200": (
        "c.obj",
        _obj(vertices=[tuple(1e200 * v for v in p) for p in CUBE_VERTICES]),
        "c.obj: a vertex lies 2e+201 mm from the origin",
    ),
    "coordinates of 1e-300 (no volume)": (
        "c.obj",
        _obj(vertices=[tuple(1e-300 * v for v in p) for p in CUBE_VERTICES]),
        "c.obj",
    ),
    # sizes checked before reading (class 3): sparse files cost nothing to make
    "sparse 10 GB STL": ("c.stl", ("sparse", 10 * 2**30), "at most 67,108,864 are read"),
    "binary STL declaring more triangles than it holds": (
        "c.stl",
        b"\0" * 80 + (1_000_000).to_bytes(4, "little") + b"\0" * 50,
        "declaring 1,000,000 triangles (50,000,084 bytes) holds 134 bytes",
    ),
    "binary STL of 1,000,000 triangles": (
        "c.stl",
        ("sparse-stl", 1_000_000),
        "declares 1,000,000 triangles; at most 200,000",
    ),
}


def _write_case_file(path: Path, content) -> None:
    """Bytes, text, or a sparse file: (\"sparse\", size) or (\"sparse-stl\", triangles),
    a binary STL header declaring that many."""
    if isinstance(content, tuple):
        kind, n = content
        with open(path, "wb") as f:
            if kind == "sparse-stl":
                f.write(b"\0" * 80 + n.to_bytes(4, "little"))
                n = 84 + 50 * n
            f.truncate(n)
        return
    path.write_bytes(content if isinstance(content, bytes) else content.encode())


@pytest.mark.parametrize("case", sorted(BAD_GEOMETRY_FILES))
def test_bad_geometry_file(case, tmp_path):
    name, content, named = BAD_GEOMETRY_FILES[case]
    name = name or "nope.stl"
    if content is not None:
        _write_case_file(tmp_path / name, content)
    units = 'units = "m"\n' if case.startswith("metres") else ""
    (tmp_path / "s.toml").write_text(f'[chip]\nshape = "file"\nfile = "{name}"\n{units}')
    before = tree(tmp_path)
    result = run_cli("run", str(tmp_path / "s.toml"), "--out", str(tmp_path / "out"))
    assert_refused(result, named, tmp_path, before)


# -- experiment specs and observation files -------------------------------------------------
def _write_drops(path: Path, rows: list[list], header=("condition", "drop", "x_mm", "y_mm")):
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(header)
        writer.writerows(rows)


def _good_rows(n=12):
    rows = []
    for condition in ("low", "high"):
        rows += [[condition, k, 0.5 * k, -0.25 * k] for k in range(1, n + 1)]
    return rows


def _rows_with(change: Callable[[list[list]], None]) -> list[list]:
    rows = _good_rows()
    change(rows)
    return rows


def _set(row: int, column: int, value):
    return lambda rows: rows[row].__setitem__(column, value)


HEADER = ("condition", "drop", "x_mm", "y_mm")
BAD_OBSERVATIONS = {
    "missing column": (
        ("condition", "drop", "x_mm"),
        [r[:3] for r in _good_rows()],
        "missing column 'y_mm'",
    ),
    "misnamed column": (
        ("condition", "drop", "x", "y_mm"),
        _good_rows(),
        "missing column 'x_mm' (columns needed",
    ),
    "duplicated column": (
        ("condition", "drop", "x_mm", "x_mm"),
        _good_rows(),
        "column 'x_mm' appears twice",
    ),
    "not a number": (HEADER, _rows_with(_set(1, 2, "abc")), "line 3: x_mm 'abc' is not a number"),
    "NaN": (HEADER, _rows_with(_set(4, 2, "nan")), "x_mm must be finite"),
    "infinite": (HEADER, _rows_with(_set(4, 3, "inf")), "y_mm must be finite"),
    "undefined condition": (
        HEADER,
        _rows_with(_set(5, 0, "middle")),
        "condition 'middle' is not defined in the spec",
    ),
    "too few drops": (
        HEADER,
        [r for r in _good_rows() if r[0] == "high"]
        + [r for r in _good_rows() if r[0] == "low"][:9],
        "has 9 drops; at least 10 are needed",
    ),
    "duplicated drop id": (HEADER, _rows_with(_set(1, 1, 1)), "drop '1' of 'low' appears twice"),
    "a condition without drops": (
        HEADER,
        [r for r in _good_rows() if r[0] == "low"],
        "no drops for condition 'high'",
    ),
    "empty file": (None, None, "the observations file is empty"),
    # numbers out of range (class 2), named by file, line and column
    "1e308 mm": (HEADER, _rows_with(_set(3, 2, "1e308")), "line 5: x_mm 1e+308 is outside"),
    "a position 20 m away": (HEADER, _rows_with(_set(6, 3, "-20000")), "line 8: y_mm -20000"),
    "a yaw of 1e5 degrees": (
        (*HEADER, "yaw_deg"),
        [[*r, 100000.0 if k == 2 else 10.0] for k, r in enumerate(_good_rows())],
        "line 4: yaw_deg 100000 is outside [-360, 360]",
    ),
    "a tilt of -1e300 degrees": (
        (*HEADER, "tilt_deg"),
        [[*r, -1e300 if k == 7 else 1.0] for k, r in enumerate(_good_rows())],
        "line 9: tilt_deg -1e+300 is outside",
    ),
    # size checked before reading (class 3)
    "sparse 100 MB observations": ("sparse", 100 * 2**20, "at most 67,108,864 are read"),
}


@pytest.mark.parametrize("case", sorted(BAD_OBSERVATIONS))
def test_bad_observation_file(case, tmp_path):
    header, rows, named = BAD_OBSERVATIONS[case]
    spec = drop_spec(tmp_path, effects=("friction",))
    data = tmp_path / "data.csv"
    if header is None:
        data.write_text("")
    elif header == "sparse":
        _write_case_file(data, (header, rows))
    else:
        _write_drops(data, rows, header)
    before = tree(tmp_path)
    result = run_cli("diagnose", str(spec), "--out", str(tmp_path / "out"), "--workers", "1")
    assert_refused(result, named, tmp_path, before)


CONDITION = '[[condition]]\nname = "low"\nheight_mm = 200\n'
BAD_SPECS = {
    "unknown kind": ('kind = "pour"\nobservations = "data.csv"\n', "kind: expected one of"),
    "no condition": ('kind = "drop"\nobservations = "data.csv"\n', "condition: give at least one"),
    "negative height": (
        'kind = "drop"\nobservations = "data.csv"\n' + CONDITION.replace("200", "-5"),
        "condition[0].height_mm: -5 is outside",
    ),
    "release below the chip's half length": (
        'kind = "drop"\nobservations = "data.csv"\n' + CONDITION.replace("200", "8"),
        "condition[0].height_mm: 8 mm does not clear half the chip's largest extent (14.1 mm)",
    ),
    "unknown key": (
        'kind = "drop"\nobservations = "data.csv"\ncolour = 1\n' + CONDITION,
        "spec.colour: unknown key",
    ),
    "malformed TOML": ('kind = "drop"\nobservations = "data.csv"\n[[condition', "malformed TOML"),
    "missing observations file": (
        'kind = "drop"\nobservations = "missing.csv"\n' + CONDITION,
        "missing.csv",
    ),
    "unknown effect": (
        'kind = "drop"\nobservations = "data.csv"\n[diagnosis]\neffects = ["wind"]\n' + CONDITION,
        "diagnosis.effects: unknown effect 'wind'; valid names:",
    ),
    "unknown held-out scheme": (
        'kind = "drop"\nobservations = "data.csv"\n[diagnosis]\nheld_out = "thirds"\n' + CONDITION,
        "diagnosis.held_out: 'thirds' is not one of 'halves', 'conditions'",
    ),
    "halves of a stack experiment": (
        'kind = "stack"\nobservations = "data.csv"\n[diagnosis]\nheld_out = "halves"\n'
        '[[condition]]\nname = "a"\nscenario = "paper-squares"\n',
        "diagnosis.held_out: stack experiments hold out whole conditions",
    ),
    "unknown release tilt": (
        'kind = "drop"\nobservations = "data.csv"\n[diagnosis]\nrelease_tilt = "guessed"\n'
        + CONDITION,
        "diagnosis.release_tilt: 'guessed' is not one of 'fitted', 'known'",
    ),
    "release tilt of a stack experiment": (
        'kind = "stack"\nobservations = "data.csv"\n[diagnosis]\nrelease_tilt = "fitted"\n'
        '[[condition]]\nname = "a"\nscenario = "paper-squares"\n',
        "diagnosis.release_tilt: only drop experiments have a release tilt, not stack",
    ),
    "one repeat per setting": (
        'kind = "stack"\nobservations = "data.csv"\n'
        '[[condition]]\nname = "a"\nscenario = "paper-squares"\nrepeats = 1\n',
        "condition[0].repeats: 1 is outside [2, 1000]",
    ),
}


@pytest.mark.parametrize("case", sorted(BAD_SPECS))
def test_bad_experiment_spec(case, tmp_path):
    text, named = BAD_SPECS[case]
    _write_drops(tmp_path / "data.csv", _good_rows())
    (tmp_path / "spec.toml").write_text(text)
    before = tree(tmp_path)
    result = run_cli("diagnose", str(tmp_path / "spec.toml"), "--out", str(tmp_path / "o"))
    assert_refused(result, named, tmp_path, before)


def test_a_file_not_in_the_expected_format_is_never_quoted(tmp_path):
    """An observations path pointing at any other file (outside the spec's folder too) is
    refused without a word of its content reaching the terminal."""
    secret = tmp_path / "private" / "token.txt"
    secret.parent.mkdir()
    secret.write_text("SECRET-TOKEN-4711,root:x:0:0\nmore secrets\n")
    folder = tmp_path / "specs"
    folder.mkdir()
    spec = drop_spec(folder, effects=("friction",))
    spec.write_text(spec.read_text().replace('"data.csv"', '"../private/token.txt"'))
    before = tree(tmp_path)
    result = run_cli("diagnose", str(spec), "--out", str(tmp_path / "out"), "--workers", "1")
    assert_refused(result, "token.txt: missing column 'condition'", tmp_path, before)
    assert "SECRET" not in result.stderr and "root:x" not in result.stderr


def test_a_spreadsheet_csv_with_a_byte_order_mark_is_read_like_plain_utf8(tmp_path):
    """ "CSV UTF-8" from a spreadsheet starts with a byte-order mark: same observations."""
    from chipstack.diagnosis.spec import load_experiment, read_drop_observations
    from chipstack.pipeline.scenario_files import load_scenario

    spec = drop_spec(tmp_path, effects=("friction",))
    _write_drops(tmp_path / "data.csv", _good_rows())
    plain = read_drop_observations(load_experiment(spec, load_scenario))
    text = (tmp_path / "data.csv").read_text()
    (tmp_path / "data.csv").write_bytes(b"\xef\xbb\xbf" + text.encode())
    spec.write_bytes(b"\xef\xbb\xbf" + spec.read_bytes())  # the spec too
    marked = read_drop_observations(load_experiment(spec, load_scenario))
    assert sorted(marked) == sorted(plain) == ["high", "low"]
    for name in plain:
        assert np.array_equal(marked[name].positions, plain[name].positions)


def test_a_run_directory_edited_in_a_spreadsheet_reads_the_same(tmp_path, finished_run):
    """A poses table and a scenario saved back with a byte-order mark describe the same
    stack."""
    from chipstack.pipeline.stackfiles import load_run

    copy = tmp_path / "run"
    shutil.copytree(finished_run, copy)
    for name in ("scenario.toml", "packing/poses_after_batch_01.csv"):
        (copy / name).write_bytes(b"\xef\xbb\xbf" + (copy / name).read_bytes())
    scenario, history, _ = load_run(copy)
    plain_scenario, plain_history, _ = load_run(finished_run)
    assert scenario == plain_scenario
    assert np.array_equal(history[0].positions, plain_history[0].positions)


def test_synth_on_a_full_disk_leaves_no_partial_file(tmp_path):
    """The observations are written to a temporary name and renamed: a disk that fills
    while writing is one line, and neither the file nor its temporary is left."""
    spec = drop_spec(tmp_path)
    before = tree(tmp_path)
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "chipstack.pipeline",
            "synth",
            str(spec),
            "-o",
            str(tmp_path / "d.csv"),
        ]
        + ["--drops", "40", "--workers", "1"],
        capture_output=True,
        text=True,
        preexec_fn=_small_fsize,
        timeout=600,
    )
    assert_refused(result, "d.csv: cannot write (File too large)", tmp_path, before)


def test_validate_expands_home_and_writes_a_whole_run_directory(tmp_path):
    """``--out ~/v`` means the home folder (no folder named ``~``); the result is a run
    directory with its manifest, replaced only with --overwrite."""
    home = tmp_path / "home"
    home.mkdir()
    args = [sys.executable, "-m", "chipstack.pipeline", "validate", "--cases", "drop"]
    args += ["--repeats", "2", "--drops", "5", "--workers", "1", "--out", "~/v"]
    env = {**os.environ, "HOME": str(home)}
    first = subprocess.run(args, capture_output=True, text=True, env=env, cwd=tmp_path)
    assert first.returncode == 0, first.stderr
    assert not (tmp_path / "~").exists()
    manifest = json.loads((home / "v" / "manifest.json").read_text())
    assert manifest["kind"] == "validation" and manifest["cases"] == ["drop"]
    assert (home / "v" / "validation.md").is_file()
    again = subprocess.run(args, capture_output=True, text=True, env=env, cwd=tmp_path)
    assert again.returncode == 2 and "use --overwrite" in again.stderr
    replaced = subprocess.run([*args, "--overwrite"], capture_output=True, text=True, env=env)
    assert replaced.returncode == 0, replaced.stderr


# -- run directories -----------------------------------------------------------------------
@pytest.fixture(scope="module")
def finished_run(tmp_path_factory) -> Path:
    """A real packing run to damage (copied per case)."""
    folder = tmp_path_factory.mktemp("finished")
    (folder / "s.toml").write_text(SMALL_SCENARIO)
    result = run_cli("run", str(folder / "s.toml"), "--out", str(folder / "run"), "--quiet")
    assert result.returncode == 0, result.stderr
    return folder / "run"


def _small_fsize():
    # A file system with room for nothing: every write past 512 bytes fails (EFBIG).
    resource.setrlimit(resource.RLIMIT_FSIZE, (512, 512))


def _read_only(folder: Path) -> Callable[[], None]:
    """Make ``folder`` unwritable, also for root (immutable); returns the undo."""
    if os.geteuid() != 0:
        folder.chmod(0o555)
        return lambda: folder.chmod(0o755)
    made = subprocess.run(["chattr", "+i", str(folder)], capture_output=True)
    if made.returncode != 0:
        pytest.skip(f"root cannot make a read-only folder here: {made.stderr.decode().strip()}")
    return lambda: subprocess.run(["chattr", "-i", str(folder)], check=True)


def _case_run_dir(case: str, d: Path, run: Path):
    """(arguments, expected text, undo) for run-directory case ``case`` in folder ``d``."""
    scenario = d / "s.toml"
    scenario.write_text(SMALL_SCENARIO)
    undo = None
    if case == "output is a file":
        (d / "out").write_text("x")
        return ["run", str(scenario), "--out", str(d / "out")], "not a directory", undo
    if case == "output holds other files":
        (d / "out").mkdir()
        (d / "out" / "thesis.tex").write_text("x")
        args = ["run", str(scenario), "--out", str(d / "out"), "--overwrite"]
        return args, "no manifest.json", undo
    if case == "output holds an ensemble":
        shutil.copytree(run, d / "out")
        text = (
            (d / "out" / "manifest.json").read_text().replace('"kind": "run"', '"kind": "ensemble"')
        )
        (d / "out" / "manifest.json").write_text(text)
        return ["run", str(scenario), "--out", str(d / "out")], "ensemble", undo
    if case == "output is a symbolic link":
        (d / "real").mkdir()
        (d / "out").symlink_to(d / "real")
        return ["run", str(scenario), "--out", str(d / "out")], "symbolic link", undo
    if case == "output is the current directory":
        return ["run", str(scenario), "--out", "."], "current directory", undo
    if case == "read-only output folder":
        (d / "locked").mkdir()
        undo = _read_only(d / "locked")
        return ["run", str(scenario), "--out", str(d / "locked" / "out")], "cannot write", undo
    if case == "validate: output holds other files":
        (d / "home").mkdir()
        (d / "home" / "validation.md").write_text("my notes")
        return ["validate", "--out", str(d / "home"), "--overwrite"], "no manifest.json", undo
    if case == "validate: read-only output folder":
        (d / "locked").mkdir()
        undo = _read_only(d / "locked")
        return ["validate", "--out", str(d / "locked")], "cannot write", undo
    if case == "compare: read-only output folder":
        (d / "locked").mkdir()
        undo = _read_only(d / "locked")
        args = ["compare", str(run), str(run), "--out", str(d / "locked" / "c")]
        return args, "cannot write", undo
    if case == "describe: not a run":
        (d / "notes").mkdir()
        return ["describe", str(d / "notes")], "not a run directory (no manifest.json)", undo
    if case == "describe: missing directory":
        return ["describe", str(d / "gone")], "no such run directory", undo
    copy = d / "run"
    shutil.copytree(run, copy)
    if case == "describe: corrupted manifest":
        (copy / "manifest.json").write_text("{ not json")
        return ["describe", str(copy)], "manifest.json: unreadable manifest", undo
    if case == "describe: manifest nested 100,000 deep":
        (copy / "manifest.json").write_text("[" * 100_000 + "]" * 100_000)
        return ["describe", str(copy)], "manifest.json: unreadable manifest (nested too", undo
    if case == "describe: NaN pose":
        poses = copy / "packing" / "poses_after_batch_02.csv"
        lines = poses.read_text().splitlines()
        fields = lines[3].split(",")
        fields[3] = "nan"
        lines[3] = ",".join(fields)
        poses.write_text("\n".join(lines) + "\n")
        return ["describe", str(copy)], "line 4: NaN or infinite value in column x_mm", undo
    if case == "describe: batch beyond 64 bits":
        poses = copy / "packing" / "poses_after_batch_02.csv"
        lines = poses.read_text().splitlines()
        fields = lines[3].split(",")
        fields[1] = "9" * 30
        lines[3] = ",".join(fields)
        poses.write_text("\n".join(lines) + "\n")
        return ["describe", str(copy)], "line 4: batch 999999999999999999999999999999 is out", undo
    if case.startswith("describe: shape") or case == "describe: flat convex piece":
        path = copy / "packing" / "shapes.json"
        data = json.loads(path.read_text())
        shape = data["shapes"][0]
        if case == "describe: shape with no vertices":
            shape["vertices"], expected = [], "has 0 vertices (a solid needs 4)"
        elif case == "describe: flat convex piece":
            piece = np.array(shape["convex_pieces"][0], dtype=float)
            piece[:, 2] = 0.0
            shape["convex_pieces"][0], expected = piece.tolist(), "convex piece 0 is flat"
        else:
            shape["vertices"] = (np.array(shape["vertices"]) * 1e149).tolist()
            expected = "has coordinates beyond 10000 mm"
        path.write_text(json.dumps(data))
        return ["describe", str(copy)], expected, undo
    if case == "describe: sparse poses file of 1 GB":
        with open(copy / "packing" / "poses_after_batch_01.csv", "r+b") as f:
            f.truncate(2**30)
        return ["describe", str(copy)], "poses_after_batch_01.csv: the poses file holds", undo
    if case == "describe: sparse manifest of 1 GB":
        with open(copy / "manifest.json", "r+b") as f:
            f.truncate(2**30)
        return ["describe", str(copy)], "manifest.json: the manifest holds 1,073,741,824", undo
    if case == "describe: shapes file in UTF-16":
        path = copy / "packing" / "shapes.json"
        path.write_bytes(path.read_text().encode("utf-16"))
        return ["describe", str(copy)], "shapes.json: the shapes file is not UTF-8", undo
    if case == "describe: duplicated chip id":
        poses = copy / "packing" / "poses_after_batch_01.csv"
        lines = poses.read_text().splitlines()
        lines[2] = lines[1]
        poses.write_text("\n".join(lines) + "\n")
        return ["describe", str(copy)], "poses_after_batch_01.csv line 3: chip 0, expected 1", undo
    if case == "describe: missing batch file":
        (copy / "packing" / "poses_after_batch_01.csv").unlink()
        return ["describe", str(copy)], "batch files must be numbered 1 to N", undo
    if case == "compare: missing run":
        return ["compare", str(d / "gone"), str(copy), "--out", str(d / "cmp")], "gone", undo
    raise AssertionError(case)


RUN_DIRECTORY_CASES = [
    "output is a file",
    "output holds other files",
    "output holds an ensemble",
    "output is a symbolic link",
    "output is the current directory",
    "read-only output folder",
    "describe: not a run",
    "describe: missing directory",
    "describe: corrupted manifest",
    "describe: manifest nested 100,000 deep",
    "describe: NaN pose",
    "describe: batch beyond 64 bits",
    "describe: shape with no vertices",
    "describe: flat convex piece",
    "describe: shape coordinates of 1e150 mm",
    "describe: duplicated chip id",
    "describe: missing batch file",
    "describe: sparse poses file of 1 GB",
    "describe: sparse manifest of 1 GB",
    "describe: shapes file in UTF-16",
    "validate: output holds other files",
    "validate: read-only output folder",
    "compare: read-only output folder",
    "compare: missing run",
]


@pytest.mark.parametrize("case", RUN_DIRECTORY_CASES)
def test_bad_run_directory(case, tmp_path, finished_run):
    d = tmp_path / "case"
    d.mkdir()
    args, named, undo = _case_run_dir(case, d, finished_run)
    before = tree(d)
    try:
        result = run_cli(*args, cwd=d)
    finally:
        if undo is not None:
            undo()
    assert_refused(result, named, d, before)


def _no_room_at_all():
    # Not even the lock's few bytes fit (EFBIG on the first byte written).
    resource.setrlimit(resource.RLIMIT_FSIZE, (0, 0))


def _run_on_a_full_disk(tmp_path, limit) -> tuple[subprocess.CompletedProcess, dict]:
    """The small scenario run into ``tmp_path`` by a process whose file-size limit is set
    by ``limit``; returns the result and the folder as it was before."""
    (tmp_path / "s.toml").write_text(SMALL_SCENARIO)
    before = tree(tmp_path)
    result = subprocess.run(
        [sys.executable, "-m", "chipstack.pipeline", "run", str(tmp_path / "s.toml")]
        + ["--out", str(tmp_path / "out"), "--quiet"],
        capture_output=True,
        text=True,
        preexec_fn=limit,
        timeout=600,
    )
    return result, before


def test_a_disk_full_before_the_lock_is_written(tmp_path):
    """The lock is the first file written: on a disk with no room, one line and no empty
    lock left behind (it would make the next run wait for a stale lock)."""
    result, before = _run_on_a_full_disk(tmp_path, _no_room_at_all)
    assert_refused(result, "cannot lock (File too large)", tmp_path, before)


def test_a_full_output_folder(tmp_path):
    """No room at all: refused at the first write, and nothing is left."""
    result, before = _run_on_a_full_disk(tmp_path, _small_fsize)
    assert_refused(
        result, "cannot write the run (File too large); nothing was written", tmp_path, before
    )


# -- command-line flags --------------------------------------------------------------------
BAD_FLAGS = {
    "seed not a number": (["run", "--seed", "abc"], "--seed"),
    "negative seed": (["run", "--seed", "-1"], "--seed: must be between 0 and"),
    "seed beyond 64 bits": (["run", "--seed", str(2**64)], "--seed: must be between 0 and"),
    "unknown stage": (["run", "--to", "consolidate"], "--to consolidate: unknown stage"),
    "stage with a newline": (["run", "--to", "mesh\nmore"], "--to"),
    "one repeat": (["run", "--repeats", "1"], "--repeats: must be between 2"),
    "absurd repeats": (["run", "--repeats", "5000"], "--repeats: must be between 2"),
    "unknown mesh format": (["run", "--to", "mesh", "--formats", "stl"], "--formats"),
    "unknown descriptor": (
        ["run", "--to", "geometry", "--descriptors", "colour"],
        "unknown descriptor 'colour'; valid names: contacts",
    ),
    "descriptors without geometry": (
        ["run", "--descriptors", "contacts"],
        "--descriptors: only with --to geometry",
    ),
    "workers without repeats": (["run", "--workers", "2"], "--workers"),
    "unknown validation case": (["validate", "--cases", "nope"], "--cases"),
    # every count has an upper bound (class 7), refused before anything starts
    "100,000 workers": (["run", "--repeats", "3", "--workers", "100000"], "--workers: must be"),
    "100,000 validation workers": (["validate", "--workers", "100000"], "--workers: must be"),
    "100,000 diagnosis workers": (["diagnose", "s.toml", "--workers", "100000"], "--workers"),
    "a billion validation drops": (["validate", "--drops", "1000000000"], "--drops: must be"),
    "a million validation repeats": (["validate", "--repeats", "1000000"], "--repeats: must"),
    "missing scenario file": (["run", "nope.toml"], "nope.toml"),
    "scenario is a directory": (["run", "."], "is a directory"),
}


@pytest.mark.parametrize("case", sorted(BAD_FLAGS))
def test_bad_flag(case, tmp_path):
    args, named = BAD_FLAGS[case]
    if args[0] == "run" and not (len(args) > 1 and args[1].endswith((".toml", "."))):
        (tmp_path / "s.toml").write_text(SMALL_SCENARIO)
        args = ["run", "s.toml", *args[1:]]
    before = tree(tmp_path)
    result = (
        run_cli(*args, "--out", "out", cwd=tmp_path)
        if args[0] == "run"
        else run_cli(*args, cwd=tmp_path)
    )
    assert_refused(result, named, tmp_path, before)


BAD_SYNTH_FLAGS = {
    "unknown effect": (["--effect", "wind=1"], "--effect: unknown effect 'wind'; valid names:"),
    "effect without strength": (["--effect", "warp"], "expected NAME=STRENGTH"),
    "strength not a number": (["--effect", "warp=abc"], "strength 'abc' is not a number"),
    "strength beyond the prior": (["--effect", "warp=50"], "outside the prior range"),
    "effect of another kind": (["--effect", "vibration=100"], "acts on stack, container"),
    "zero drops": (["--drops", "0"], "--drops: must be between 1 and 100000"),
    "NaN noise": (["--position-sd-mm", "nan"], "--position-sd-mm: must be between 0 and 100"),
    "negative noise": (["--angle-sd-deg", "-1"], "--angle-sd-deg: must be between 0 and 45"),
    "100,000 workers": (["--workers", "100000"], "--workers: must be between 1 and"),
    "a billion drops": (["--drops", "1000000000"], "--drops: must be between 1 and 100000"),
}


@pytest.mark.parametrize("case", sorted(BAD_SYNTH_FLAGS))
def test_bad_synth_flag(case, tmp_path):
    args, named = BAD_SYNTH_FLAGS[case]
    spec = drop_spec(tmp_path)
    before = tree(tmp_path)
    result = run_cli("synth", str(spec), "-o", str(tmp_path / "data.csv"), *args)
    assert_refused(result, named, tmp_path, before)


def test_the_catalogue_holds_at_least_40_cases():
    cases = (
        len(BAD_SCENARIOS)
        + len(BAD_GEOMETRY_FILES)
        + len(BAD_OBSERVATIONS)
        + len(BAD_SPECS)
        + len(RUN_DIRECTORY_CASES)
        + 1  # the full output folder
        + len(BAD_FLAGS)
        + len(BAD_SYNTH_FLAGS)
    )
    assert cases >= 40
