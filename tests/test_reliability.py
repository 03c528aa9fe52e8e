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
    out = tmp_path / "run"
    lock = tmp_path / ".run.lock"
    first = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "pipeline",
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
