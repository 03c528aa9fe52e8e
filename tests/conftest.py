"""Shared helpers: run the real CLI in a subprocess, write small scenarios."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

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


def run_cli(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "pipeline", *args],
        capture_output=True,
        text=True,
        cwd=cwd,
        timeout=600,
    )


@pytest.fixture
def small_scenario(tmp_path: Path) -> Path:
    path = tmp_path / "small.toml"
    path.write_text(SMALL_SCENARIO)
    return path
