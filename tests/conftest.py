"""Shared helpers: run the real CLI in a subprocess, write small scenarios."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from parts import REQUIRE_VARIABLE, require
from parts import needs as _needs_mark  # noqa: F401  (the mark's home: tests/parts.py)

SMALL_SCENARIO = """
name = "small"
seed = 3
[chip]
length_mm = 20.0
width_mm = 20.0
thickness_mm = 2.0
[deposition]
chips = 24
batch_size = 12
target_size_mm = 80.0
release_height_mm = [60.0, 120.0]
"""

DROP_SPEC = """
kind = "drop"
name = "two heights"
scenario = "single-chip-drop"
observations = "data.csv"
[measurement]
position_sd_mm = 0.5
angle_sd_deg = 0.5
[diagnosis]
sim_drops = {sim_drops}
bootstrap = 100
grid_points = 4
effects = {effects}
method = "{method}"
[[condition]]
name = "low"
height_mm = 200
[[condition]]
name = "high"
height_mm = 600
yaw_deg = 30
"""


def drop_spec(
    folder: Path,
    effects=("restitution", "friction", "compliant_floor"),
    sim=60,
    method="refit",
):
    """A two-condition drop experiment spec in ``folder`` (its data: ``data.csv``); by
    default "which" by the refit method (the amortised model choice builds a reference
    table: ``method = "amortised"`` with a small ``table_pools`` in its own tests)."""
    spec = folder / "spec.toml"
    listed = "[" + ", ".join(f'"{e}"' for e in effects) + "]"
    spec.write_text(DROP_SPEC.format(sim_drops=sim, effects=listed, method=method))
    return spec


def write_box_obj(path: Path, side_mm: float, thickness_mm: float) -> Path:
    """A square plate ``side_mm`` wide and ``thickness_mm`` thick as an OBJ file (a
    ``file`` chip's geometry)."""
    corners = [(x, y, z) for x in (0, side_mm) for y in (0, side_mm) for z in (0, thickness_mm)]
    faces = ["1 2 4 3", "5 7 8 6", "1 5 6 2", "3 4 8 7", "1 3 7 5", "2 6 8 4"]
    path.write_text(
        "".join(f"v {x} {y} {z}\n" for x, y, z in corners) + "".join(f"f {f}\n" for f in faces)
    )
    return path


def run_cli(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "chipstack.pipeline", *args],
        capture_output=True,
        text=True,
        cwd=cwd,
        timeout=600,
    )


def run_scenario(text: str, folder: Path, to: str, name: str = "scenario") -> Path:
    """``pipeline run`` of the scenario ``text`` (written into ``folder``) up to stage
    ``to``; asserts it succeeded and returns its run directory."""
    scenario = folder / f"{name}.toml"
    scenario.write_text(text)
    out = folder / f"{name}-run"
    result = run_cli("run", str(scenario), "--to", to, "--out", str(out), "--quiet")
    assert result.returncode == 0, result.stderr
    return out


@pytest.fixture(scope="session")
def reference_run(tmp_path_factory) -> Path:
    """The paper's reference stack as ``make run`` makes it (``pipeline run --to mesh
    --seed 0`` on ``paper-squares``: 270 chips, the 1 mm voxel mesh in every format): its
    run directory. Ask for it from one module only (``--dist loadfile`` runs a module on
    one worker; another module would run it again)."""
    out = tmp_path_factory.mktemp("reference") / "paper-squares"
    result = run_cli("run", "--to", "mesh", "--out", str(out), "--seed", "0", "--quiet")
    assert result.returncode == 0, result.stderr
    return out


def _content(path: Path):
    """A file's bytes; for the sparse giants of the bad-input catalogue, its size and mtime
    (reading 10 GB of zeros would take the test a minute)."""
    if not path.is_file():
        return None
    status = path.stat()
    if status.st_size > 2**24:
        return (status.st_size, status.st_mtime_ns)
    return path.read_bytes()


def tree(folder: Path) -> dict[str, bytes | tuple | None]:
    """Every path under ``folder`` (hidden ones too) with its content."""
    return {p.relative_to(folder).as_posix(): _content(p) for p in sorted(folder.rglob("*"))}


def assert_refused(result: subprocess.CompletedProcess, named: str, folder: Path, before) -> None:
    """The command was refused as every bad input must be: exit status 2, one line on
    stderr holding ``named``, no traceback, and ``folder`` exactly as ``before``
    (:func:`tree`): nothing written, not even half."""
    assert result.returncode == 2, (result.returncode, result.stderr)
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert "Traceback" not in result.stderr
    assert named in lines[0], lines[0]
    assert tree(folder) == before, "a refused input wrote something"


@pytest.fixture
def small_scenario(tmp_path: Path) -> Path:
    path = tmp_path / "small.toml"
    path.write_text(SMALL_SCENARIO)
    return path


# The longest modules first, so that neither worker is left with a long one at the end
# (``--dist loadfile`` keeps a module on one worker; ``--no-loadscope-reorder`` makes
# xdist take this order instead of ordering modules by their number of tests). Seconds
# of one worker in a whole run (pytest -n 2, 2 cores, both busy; 2026-11-29, on a loaded
# machine: 2,066 s, about 1.85 times the 1,118 s of 2026-11-28); every module over 15 s
# is listed, so that none of them comes last by default.
_LONGEST_FIRST = (
    "test_image_mesh.py",  # 503
    "test_meshing.py",  # 684 before the node moves' trials were batched (about 510 after)
    "test_diagnosis.py",  # 355
    "test_resume.py",  # 337
    "test_freezing.py",  # 273
    "test_bad_input.py",  # 240
    "test_conveyor.py",  # 263 (about 235 with the short mat poured once)
    "test_paper_descriptors.py",  # 219
    "test_model_choice.py",  # 192
    "test_validation.py",  # 163
    "test_plugins.py",  # 109
    "test_sweep.py",  # 99
    "test_diagnosis_csv.py",  # 97
    "test_geometry_cli.py",  # 82
    "test_clients.py",  # about 70 (37 alone, 2026-12-02)
    "test_execution.py",  # 70
    "test_contracts.py",  # 60
    "test_api.py",  # 52
    "test_solve.py",  # 50
    "test_architecture.py",  # 48
    "test_resolve.py",  # 31
    "test_figures.py",  # 30
    "test_cli_set.py",  # 11 to 20 s alone (not yet timed in a whole run)
    "test_reliability.py",  # 24
    "test_stack_diagnosis.py",  # 23
    "test_cli.py",  # 19
)


def pytest_collection_modifyitems(session, config, items):
    rank = {name: k for k, name in enumerate(_LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))


def pytest_configure(config):
    config.addinivalue_line(
        "markers", "needs(*parts): the optional parts the test needs (tests/parts.py)"
    )


def pytest_runtest_setup(item):
    for mark in item.iter_markers(name="needs"):
        for part in mark.args:
            require(part)


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    """Which optional parts were missing, and how many tests skipped (or, with the parts
    required, failed) for each: read from the reports, so that it also counts what
    xdist's workers did. Nothing when only collecting."""
    if config.option.collectonly:
        return
    counts: dict[tuple[str, str], tuple[int, str]] = {}
    for outcome in ("skipped", "failed", "error"):  # a part required at set-up: an error
        for report in terminalreporter.stats.get(outcome, []):
            longrepr = report.longrepr
            reason = longrepr[2] if isinstance(longrepr, tuple) else str(longrepr)
            reason = reason.removeprefix("Skipped: ")
            if outcome == "skipped" and reason.startswith("needs "):
                part, _, why = reason.removeprefix("needs ").partition(": ")
            elif outcome != "skipped" and f" is required ({REQUIRE_VARIABLE}=1): " in reason:
                part, _, why = reason.partition(f" is required ({REQUIRE_VARIABLE}=1): ")
                outcome = "failed"
            else:
                continue
            n, _ = counts.get((part, outcome), (0, why))
            counts[part, outcome] = (n + 1, why)
    terminalreporter.section("optional parts")
    if not counts:
        terminalreporter.write_line("every optional part was here: nothing skipped for one")
    for (part, outcome), (n, why) in sorted(counts.items()):
        terminalreporter.write_line(f"{part}: {n} tests {outcome} ({why})")
