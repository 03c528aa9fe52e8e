"""Reliability: one writer per output directory (a lock, stale locks detected)."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

from conftest import run_cli


def _dead_pid() -> int:
    process = subprocess.Popen([sys.executable, "-c", "pass"])
    process.wait()
    return process.pid


def test_second_run_into_the_same_directory_is_refused(tmp_path, small_scenario):
    # A first run long enough (96 chips) that it still holds its lock when the second
    # command, which takes over a second to start, asks for it.
    small_scenario.write_text(small_scenario.read_text().replace("chips = 24", "chips = 96"))
    out = tmp_path / "run"
    lock = tmp_path / ".run.lock"
    first = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "chipstack.pipeline",
            "run",
            str(small_scenario),
            "--out",
            str(out),
            "--quiet",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.time() + 60
        while not lock.exists() and time.time() < deadline:
            time.sleep(0.05)
        assert lock.exists(), "the first run never took its lock"
        second = run_cli("run", str(small_scenario), "--out", str(out), "--overwrite")
        assert second.returncode == 2
        assert f"another run (process {first.pid}" in second.stderr
        assert len(second.stderr.strip().splitlines()) == 1
    finally:
        _, err = first.communicate(timeout=300)
    assert first.returncode == 0, err
    assert (out / "manifest.json").is_file()
    assert not lock.exists()  # released


def test_a_stale_lock_is_detected_and_taken(tmp_path, small_scenario):
    out = tmp_path / "run"
    lock = tmp_path / ".run.lock"
    lock.write_text(
        json.dumps(
            {
                "pid": _dead_pid(),
                "host": __import__("socket").gethostname(),
                "started": time.time() - 60,
            }
        )
    )
    result = run_cli("run", str(small_scenario), "--out", str(out), "--quiet")
    assert result.returncode == 0, result.stderr
    assert "removed a stale lock left by process" in result.stderr
    assert (out / "manifest.json").is_file()
    assert not lock.exists()


def test_an_unreadable_lock_is_stale(tmp_path, small_scenario):
    out = tmp_path / "run"
    (tmp_path / ".run.lock").write_text("garbage")
    result = run_cli("run", str(small_scenario), "--out", str(out), "--quiet")
    assert result.returncode == 0, result.stderr
    assert "removed a stale lock" in result.stderr


def test_describe_refuses_a_run_another_process_holds(tmp_path, small_scenario):
    out = tmp_path / "run"
    assert run_cli("run", str(small_scenario), "--out", str(out), "--quiet").returncode == 0
    holder = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        (tmp_path / ".run.lock").write_text(
            json.dumps(
                {
                    "pid": holder.pid,
                    "host": __import__("socket").gethostname(),
                    "started": time.time(),
                }
            )
        )
        result = run_cli("describe", str(out))
        assert result.returncode == 2
        assert "another run" in result.stderr
        assert not (out / "geometry").exists()
    finally:
        holder.kill()
        holder.wait()
    result = run_cli("describe", str(out))  # the holder is gone: its lock is stale
    assert result.returncode == 0, result.stderr
    assert Path(out / "geometry" / "descriptors.json").is_file()


# -- physics going wrong is detected, not written --------------------------------------------
def _world_with_chip(z_mm: float, x_mm: float = 0.0):
    import numpy as np

    from chipstack.core.schema import ChipSpec
    from chipstack.packing.presets import PRESETS
    from chipstack.packing.sections import PhysicsSpec
    from chipstack.packing.shapes import make_shape
    from chipstack.packing.world import ChipWorld

    world = ChipWorld(PRESETS.get("default"), PhysicsSpec()).__enter__()
    chip = world.add_chip(
        make_shape(ChipSpec(), None, 1.0),
        np.array([x_mm, 0.0, z_mm]),
        np.array([0.0, 0.0, 0.0, 1.0]),
    )
    return world, chip


def test_energy_growing_without_bound_is_an_error_naming_the_chips():
    import numpy as np
    import pytest

    from chipstack.core.errors import SimulationError
    from chipstack.packing.settling import RestTracker

    world, chip = _world_with_chip(50.0)
    try:
        tracker = RestTracker(world, 0.25, 10)
        tracker.add([chip])  # brings m g 50 mm
        tracker.update(20.0)
        # A solver blow-up, as a kick no physics gave: 100 m/s upwards.
        world.set_velocity(chip, np.array([0.0, 0.0, 1e5]), np.zeros(3))
        world.step()
        with pytest.raises(SimulationError, match=r"kinetic energy grew .* chips \[0\]"):
            tracker.update(20.0)
    finally:
        world.__exit__(None, None, None)


def test_chips_leaving_the_domain_are_frozen_and_reported(small_scenario):

    from chipstack.packing.settling import settle
    from chipstack.pipeline.scenario_files import load_scenario

    scenario = load_scenario(small_scenario)
    # 20 x the scenario's largest size (4 m here) is the domain: 5 m is beyond.
    world, chip = _world_with_chip(10.0, x_mm=5000.0)
    try:
        warnings: list[str] = []
        done, *_ = settle(world, [chip], scenario, warnings=warnings)
        assert done
        assert len(warnings) == 1 and "chips [0] left the domain" in warnings[0]
        position = world.poses()[0][0]
        assert position[0] == 5000.0 and position[2] > 9.0  # frozen where it was seen
    finally:
        world.__exit__(None, None, None)
