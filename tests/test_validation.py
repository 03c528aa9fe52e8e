"""The paper's validation cases: drop statistics (analytic and simulated), the container
fill, and `pipeline validate` end to end on reduced cases."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from conftest import run_cli

from chipstack.packing import scenario_from_dict
from chipstack.packing.fill import container_fill
from chipstack.packing.scatter import disc_radius, drop_statistics, rayleigh_p


def test_drop_statistics_of_points_on_the_diagonals():
    # 40 points on the four diagonals: perfectly 4-fold, axis at 45 deg (the corners).
    r = np.linspace(1, 10, 10)
    xy = np.vstack(
        [
            np.column_stack([r * math.cos(a), r * math.sin(a)])
            for a in np.radians([45, 135, 225, 315])
        ]
    )
    stats = drop_statistics(xy)
    assert stats["anisotropy"] == pytest.approx(1.0)
    assert stats["axis_deg"] == pytest.approx(45.0)
    assert stats["corner_offset_deg"] == pytest.approx(0.0, abs=1e-9)
    assert stats["anisotropy_p"] < 1e-10
    assert stats["disc95_mm"] == pytest.approx(10.0)  # 38 of 40 within r = 10
    assert stats["distance_sd_mm"] == pytest.approx(np.std(np.tile(r, 4), ddof=1))
    # on the axes instead: along the sides, 45 deg from the corners
    side = drop_statistics(
        xy
        @ np.array(
            [
                [math.cos(math.pi / 4), math.sin(math.pi / 4)],
                [-math.sin(math.pi / 4), math.cos(math.pi / 4)],
            ]
        )
    )
    assert side["corner_offset_deg"] == pytest.approx(45.0)


def test_disc_radius_and_rayleigh_against_known_values():
    assert disc_radius(np.arange(1, 101), 0.95) == 95
    assert disc_radius(np.arange(1, 21), 0.95) == 19
    # Zar's example: n = 10, R = 0.5 gives p close to exp(-2.5) corrected, about 0.079
    assert rayleigh_p(0.5, 10) == pytest.approx(0.0789, abs=0.002)
    # points uniform in a disc have no preferred direction (in a square they would)
    rng = np.random.default_rng(0)
    angle, radius = rng.uniform(0, 2 * np.pi, 2000), np.sqrt(rng.uniform(size=2000))
    disc = np.column_stack([radius * np.cos(angle), radius * np.sin(angle)])
    assert drop_statistics(disc)["anisotropy_p"] > 0.01


def test_container_fill_counts_centres_inside():
    positions = np.array([[0, 0, 5], [9.9, 0, 1], [10.1, 0, 1], [0, 0, 10.5], [0, 0, -0.1]])
    fill = container_fill(positions, np.full(5, 2.0), 10.0, 10.0)
    assert fill["chips_inside"] == 2
    assert fill["volume_fraction"] == pytest.approx(4.0 / (math.pi * 100 * 10))


def test_simulated_drops_scatter_along_the_corners():
    """Paper 4.2: the X-shaped scatter points along the chip's corners. 200 drops make the
    4-fold harmonic significant; its axis must be nearer the corners than the sides
    (within 22.5 deg of them)."""
    from chipstack.packing.drop import drop_chips

    scenario = scenario_from_dict({"kind": "drop", "seed": 0, "drop": {"drops": 200}})
    result = drop_chips(scenario)
    assert result.settled.all()
    flat = np.abs(result.positions[:, 2] - 1.0) < 0.05
    assert flat.mean() > 0.95, result.positions[~flat, 2]  # nearly all flat on the floor
    stats = drop_statistics(result.positions[:, :2])
    assert stats["anisotropy_p"] < 1e-3
    assert stats["corner_offset_deg"] < 22.5
    # turning the release by 30 deg turns the scatter with it
    turned = scenario_from_dict(
        {"kind": "drop", "seed": 0, "drop": {"drops": 200, "yaw_deg": 30.0}}
    )
    moved = drop_chips(turned)
    stats = drop_statistics(moved.positions[:, :2], yaw_deg=30.0)
    assert stats["anisotropy_p"] < 1e-3 and stats["corner_offset_deg"] < 22.5


def test_drop_run_writes_its_files_and_refuses_later_stages(tmp_path):
    out = tmp_path / "drops"
    result = run_cli("run", "single-chip-drop", "--out", str(out), "--quiet")
    assert result.returncode == 0, result.stderr
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["drop"]["drops"] == 50
    assert (out / "packing" / "figures" / "fig15_drops.png").stat().st_size > 10_000
    lines = (out / "packing" / "drops.csv").read_text().splitlines()
    assert len(lines) == 51 and lines[0].startswith("drop,shape,x_mm")
    refused = run_cli("run", "single-chip-drop", "--to", "geometry", "--out", str(tmp_path / "x"))
    assert refused.returncode == 2 and "only the packing stage" in refused.stderr
    assert not (tmp_path / "x").exists()


@pytest.mark.slow
def test_small_container_fills_and_counts(tmp_path):
    """Rods of aspect ratio 10 in a container of radius L and height L (a quarter of the
    paper's, to keep the test short): it fills, and the volume fraction is that of the
    seeds' loose random rod packing near a wall. Measured (seeds 0 to 4, 2026-12-02): 0.318,
    0.323, 0.280, 0.348, 0.328, a mean of 0.319 and an sd of 0.025 (one rod is 0.0025 of
    the container), below Freeman et al.'s 0.37 at 4 L, as the wall at one rod length
    leaves more room unfilled; held to the mean within 3 sd."""
    scenario = tmp_path / "c.toml"
    scenario.write_text(
        """
name = "small-container"
kind = "container"
[chip]
shape = "fibre"
section = "cylinder"
length_mm = 20.0
thickness_mm = 2.0
[deposition]
chips = 600
batch_size = 10
[container]
radius_mm = 20.0
height_mm = 20.0
[settling]
speed_mm_s = 10.0
wake_speed_mm_s = 100.0
"""
    )
    out = tmp_path / "run"
    result = run_cli("run", str(scenario), "--out", str(out), "--quiet")
    assert result.returncode == 0, result.stderr
    fill = json.loads((out / "manifest.json").read_text())["container"]
    assert fill["full"]
    assert fill["volume_fraction"] == pytest.approx(0.319, abs=3 * 0.025)


def test_validate_end_to_end_on_reduced_cases(tmp_path):
    out = tmp_path / "validation"
    result = run_cli(
        "validate", "--cases", "drop,mixed", "--repeats", "2", "--drops", "30", "--out", str(out)
    )
    assert result.returncode == 0, result.stderr
    assert "| case | quantity | paper | measured | ours (mean ± sd) |" in result.stdout
    report = json.loads((out / "validation.json").read_text())
    cases = {row["case"] for row in report["rows"]}
    assert cases == {"drop", "mixed (Fig. 18)"}
    assert (out / "fig15_drops.png").is_file()
    assert (out / "mixed" / "mesh" / "stack_voxel.vtu").is_file()
    bad = run_cli("validate", "--cases", "drop,blob", "--out", str(tmp_path / "v2"))
    assert bad.returncode == 2 and "valid: drop, mat, container, mixed" in bad.stderr
