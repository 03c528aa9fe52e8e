"""Crash safety and the stage cache, with real runs of the CLI.

A run is killed with SIGKILL at several points (after some batches, after a stage), then
the same command is run again; its files must equal, byte for byte, those of a run that
was never interrupted. A finished run run again reuses exactly the stages whose inputs
did not change.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import run_cli

SCENARIO = """
name = "resumable"
seed = 11
[chip]
length_mm = 20.0
width_mm = 10.0
thickness_mm = 2.0
[deposition]
chips = 48
batch_size = 8
target_size_mm = 70.0
release_height_mm = [40.0, 100.0]
[mesh]
voxel_mm = 1.0
"""
ARGS = ("--to", "mesh", "--formats", "vtu,inp", "--quiet")
VOLATILE = {"wall_time_s", "descriptor_time_s", "descriptor_times_s", "mesh_time_s"}


def _files(run: Path) -> dict[str, bytes]:
    """Every file of a run but its manifest (which records times and the command)."""
    return {
        p.relative_to(run).as_posix(): p.read_bytes()
        for p in sorted(run.rglob("*"))
        if p.is_file() and p.name != "manifest.json"
    }


def _stable(value):
    """A manifest without what differs between identical runs: times and the command."""
    if isinstance(value, dict):
        return {
            k: _stable(v)
            for k, v in value.items()
            if k not in VOLATILE
            and k not in ("command", "started_utc", "finished_utc", "completed_utc")
            and k not in ("stages_reused", "resumed_after_batch")
        }
    if isinstance(value, list):
        return [_stable(v) for v in value]
    return value


def _manifest(run: Path) -> dict:
    return json.loads((run / "manifest.json").read_text())


def _journal(partial: Path) -> dict:
    try:
        return json.loads((partial / "manifest.json").read_text())
    except (OSError, ValueError):
        return {}


@pytest.fixture(scope="module")
def scenario(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("resume") / "resumable.toml"
    path.write_text(SCENARIO)
    return path


@pytest.fixture(scope="module")
def reference(scenario) -> Path:
    out = scenario.parent / "reference"
    result = run_cli("run", str(scenario), "--out", str(out), *ARGS)
    assert result.returncode == 0, result.stderr
    return out


def _run_command(scenario: Path, out: Path) -> list[str]:
    """``pipeline run`` of ``scenario`` into ``out`` in a child interpreter."""
    return [
        sys.executable,
        "-m",
        "chipstack.pipeline",
        "run",
        str(scenario),
        "--out",
        str(out),
        *ARGS,
    ]


def _kill_when(scenario: Path, out: Path, reached) -> dict:
    """Start the run, SIGKILL it as soon as ``reached(journal)`` holds; returns the journal
    at the kill."""
    partial = out.parent / f".{out.name}.partial"
    process = subprocess.Popen(
        _run_command(scenario, out),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    deadline = time.time() + 300
    journal: dict = {}
    try:
        while process.poll() is None and time.time() < deadline:
            journal = _journal(partial)
            if reached(journal):
                os.kill(process.pid, signal.SIGKILL)
                break
            time.sleep(0.005)
    finally:
        if process.poll() is None and not reached(journal):
            process.kill()
        process.wait()
    assert process.returncode == -signal.SIGKILL, "the run ended before the kill point"
    return journal


def _batches(journal: dict) -> int:
    return journal.get("stages", {}).get("packing", {}).get("batches_completed", 0) or 0


def _complete(stage: str):
    return lambda j: j.get("stages", {}).get(stage, {}).get("status") == "complete"


KILL_POINTS = {
    "after batch 1": lambda j: _batches(j) >= 1,
    "after batch 4": lambda j: _batches(j) >= 4,
    "after the packing stage": _complete("packing"),
    "after the geometry stage": _complete("geometry"),
}


@pytest.mark.parametrize("point", list(KILL_POINTS))
def test_a_killed_run_resumes_to_the_same_bits(scenario, reference, tmp_path, point):
    out = tmp_path / "run"
    journal = _kill_when(scenario, out, KILL_POINTS[point])
    assert not out.exists(), "a killed first run must leave nothing under its name"
    assert (tmp_path / ".run.partial" / "manifest.json").is_file()
    assert (tmp_path / ".run.lock").exists()  # the dead process's lock, stale now

    again = run_cli("run", str(scenario), "--out", str(out), *ARGS)
    assert again.returncode == 0, again.stderr
    assert "stale lock" in again.stderr
    manifest = _manifest(out)
    if point.startswith("after batch"):
        done = _batches(journal)
        assert manifest["resumed_after_batch"] >= done  # it went on, not back to batch 0
        assert manifest["stages_reused"] == []
    else:
        stage = point.split()[2]
        assert stage in manifest["stages_reused"]
    assert _files(out) == _files(reference)
    assert _stable(manifest) == _stable(_manifest(reference))
    assert not list(tmp_path.glob(".run.*")), "the build, its state and the lock are gone"


def _truncate(path: Path) -> None:
    with open(path, "r+b") as f:
        f.truncate(path.stat().st_size // 2)


def _flip(path: Path) -> None:
    data = bytearray(path.read_bytes())
    middle = len(data) // 2
    data[middle : middle + 64] = bytes(b ^ 0xFF for b in data[middle : middle + 64])
    path.write_bytes(bytes(data))


DAMAGES = {
    "latest truncated": (_truncate, False),
    "latest with flipped bytes": (_flip, False),
    "both truncated": (_truncate, True),
}


@pytest.mark.parametrize("damage", list(DAMAGES))
def test_a_damaged_checkpoint_is_caught_and_the_run_finishes_to_the_same_bits(
    scenario, reference, tmp_path, damage
):
    """The packing state a kill left behind is damaged afterwards: the journal's checksum
    catches it, one warning says so, and the same command resumes from the state before
    it (or, with both damaged, from the start) to the uninterrupted run's bytes."""
    out = tmp_path / "run"
    journal = _kill_when(scenario, out, lambda j: _batches(j) >= 3)
    partial = tmp_path / ".run.partial"
    latest, previous = partial / ".packing-state.npz", partial / ".packing-state.prev.npz"
    assert latest.is_file() and previous.is_file()
    spoil, both = DAMAGES[damage]
    spoil(latest)
    if both:
        spoil(previous)

    again = run_cli("run", str(scenario), "--out", str(out), *ARGS)
    assert again.returncode == 0, again.stderr
    warnings = [line for line in again.stderr.splitlines() if "damaged checkpoint" in line]
    assert len(warnings) == 1, again.stderr
    manifest = _manifest(out)
    if both:
        assert "from the start" in warnings[0]
        assert "resumed_after_batch" not in manifest
    else:
        assert manifest["resumed_after_batch"] == _batches(journal) - 1
    assert _files(out) == _files(reference)
    assert _stable(manifest) == _stable(_manifest(reference))
    assert not list(tmp_path.glob(".run.*")), "the build, its state and the lock are gone"


def test_a_kill_while_updating_a_finished_run_leaves_it_whole(scenario, reference, tmp_path):
    """Rebuilding the mesh of a finished run, killed half way: the finished run stays as it
    was, and the next start completes the update."""
    out = tmp_path / "run"
    subprocess.run(["cp", "-a", str(reference), str(out)], check=True)
    before = _files(out)
    changed = tmp_path / "coarser.toml"
    changed.write_text(SCENARIO.replace("voxel_mm = 1.0", "voxel_mm = 0.4"))
    process = subprocess.Popen(
        [sys.executable, "-m", "chipstack.pipeline", "run", str(changed), "--out", str(out), *ARGS],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    partial = tmp_path / ".run.partial"
    deadline = time.time() + 120
    while time.time() < deadline and not (partial / ".mesh.tmp").exists():
        time.sleep(0.005)
    process.send_signal(signal.SIGKILL)
    process.wait()
    assert process.returncode == -signal.SIGKILL
    assert _files(out) == before
    again = run_cli("run", str(changed), "--out", str(out), *ARGS)
    assert again.returncode == 0, again.stderr
    assert _manifest(out)["stages_reused"] == ["packing", "geometry"]
    assert _files(out)["packing/stack.npz"] == before["packing/stack.npz"]
    assert _files(out)["mesh/stack_voxel.vtu"] != before["mesh/stack_voxel.vtu"]


def _inode(run: Path, name: str) -> int:
    return (run / name).stat().st_ino


def test_the_stage_cache_redoes_exactly_the_stages_downstream_of_a_change(
    scenario, reference, tmp_path
):
    out = tmp_path / "run"
    subprocess.run(["cp", "-a", str(reference), str(out)], check=True)
    files = {s: f"{s}/{n}" for s, n in [("packing", "stack.npz"), ("geometry", "descriptors.json")]}
    files["mesh"] = "mesh/stack_voxel.vtu"

    def rerun(text: str, *extra: str) -> tuple[list[str], dict[str, bool]]:
        before = {s: _inode(out, f) for s, f in files.items()}
        path = tmp_path / "changed.toml"
        path.write_text(text)
        result = run_cli("run", str(path), "--out", str(out), *ARGS, *extra)
        assert result.returncode == 0, result.stderr
        kept = {s: _inode(out, f) == before[s] for s, f in files.items()}
        return _manifest(out)["stages_reused"], kept

    everything = ["packing", "geometry", "mesh"]
    reused, kept = rerun(SCENARIO)
    assert reused == everything and all(kept.values())
    loud = run_cli("run", str(tmp_path / "changed.toml"), "--out", str(out), *ARGS[:-1])
    assert loud.returncode == 0, loud.stderr  # the summary of a run made of reused stages
    assert "reused (inputs unchanged): packing, geometry, mesh" in loud.stdout
    assert "deposition reused" in loud.stdout
    reused, kept = rerun(SCENARIO.replace('"resumable"', '"renamed"'))
    assert reused == everything and all(kept.values())  # the name is not an input
    assert _manifest(out)["scenario"] == "renamed"
    reused, kept = rerun(SCENARIO.replace("[mesh]\n", '[mesh]\npore_space = "box"\n'))
    assert reused == ["packing", "geometry"] and kept == {
        "packing": True,
        "geometry": True,
        "mesh": False,
    }
    reused, kept = rerun(SCENARIO + "[geometry]\nlayer_mm = 2.5\n")
    assert reused == ["packing"] and kept == {"packing": True, "geometry": False, "mesh": False}
    reused, kept = rerun(SCENARIO.replace("seed = 11", "seed = 12"))
    assert reused == [] and not any(kept.values())
    assert _files(out)["packing/stack.npz"] != _files(reference)["packing/stack.npz"]
    reused, kept = rerun(SCENARIO, "--overwrite")
    assert reused == [] and _files(out) == _files(reference)
    # --to packing on a meshed run keeps the later stages whose inputs are unchanged, and
    # drops those whose inputs changed (here the mesh formats, back to the default)
    changed = str(tmp_path / "changed.toml")
    result = run_cli("run", changed, "--out", str(out), "--quiet", "--formats", "vtu,inp")
    assert result.returncode == 0, result.stderr
    assert _manifest(out)["stages_completed"] == everything
    result = run_cli("run", changed, "--out", str(out), "--quiet")
    assert result.returncode == 0, result.stderr
    assert _manifest(out)["stages_completed"] == ["packing", "geometry"]
    assert not (out / "mesh").exists()


def _file_size_limit():
    # The disk fills: no file may grow past 20 kB (writes fail with EFBIG).
    import resource

    resource.setrlimit(resource.RLIMIT_FSIZE, (20_000, 20_000))


def test_a_full_disk_keeps_the_batches_and_the_run_resumes_once_there_is_room(
    scenario, reference, tmp_path
):
    out = tmp_path / "run"
    command = _run_command(scenario, out)
    full = subprocess.run(command, capture_output=True, text=True, preexec_fn=_file_size_limit)
    assert full.returncode == 2, full.stderr
    lines = full.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in full.stderr
    assert "cannot write the run (File too large)" in lines[0]
    assert "run the same command to resume" in lines[0]
    assert not out.exists()
    kept = _journal(tmp_path / ".run.partial")
    assert _batches(kept) >= 1
    again = run_cli("run", str(scenario), "--out", str(out), *ARGS)
    assert again.returncode == 0, again.stderr
    assert _manifest(out)["resumed_after_batch"] == _batches(kept)
    assert _files(out) == _files(reference)


def test_a_new_version_of_a_mesh_kind_redoes_the_mesh_and_what_follows(monkeypatch):
    # A run directory meshed by an older algorithm must not reuse its mesh: the kind's
    # version is part of the mesh stage's key (and so of the solve stage's).
    from chipstack.meshing.kinds import MESH_KINDS
    from chipstack.packing import scenario_from_dict
    from chipstack.pipeline.run import stage_inputs

    scenario = scenario_from_dict({"mesh": {"kind": "conformal"}})
    before = stage_inputs(scenario)
    monkeypatch.setattr(type(MESH_KINDS.get("conformal")), "version", 99)
    after = stage_inputs(scenario)
    changed = sorted(name for name in before if before[name] != after[name])
    assert changed == ["mesh", "solve"]
    voxel = scenario_from_dict({"mesh": {"kind": "voxel"}})
    voxel_before = stage_inputs(voxel)
    assert voxel_before["mesh"] != before["mesh"]
    assert stage_inputs(voxel) == voxel_before  # only the voxel kind's version counts
    monkeypatch.setattr(type(MESH_KINDS.get("voxel")), "version", 2)
    assert stage_inputs(voxel)["mesh"] != voxel_before["mesh"]
    assert stage_inputs(voxel)["geometry"] == voxel_before["geometry"]
