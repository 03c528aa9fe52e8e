"""Wiring of the stages into a run (no physics, no geometry here)."""

from __future__ import annotations

import hashlib
import platform
import time
from collections.abc import Callable
from datetime import UTC, datetime
from importlib import metadata
from pathlib import Path
from typing import Any

from packing import BatchResult, Scenario, Stack, deposit
from packing.config import printable
from packing.errors import InputError
from packing.overlap import vertex_heights_mm
from pipeline.rundir import RunDirectory
from pipeline.scenario_files import dumps_toml

__all__ = ["STAGES", "run_pipeline"]

STAGES = ("packing",)  # in order; later issues add geometry and mesh
PLANNED = ("geometry", "mesh")


def _versions() -> dict[str, str]:
    versions = {"python": platform.python_version()}
    for package in ("chipstack", "pybullet", "numpy", "scipy", "pyvista", "vtk"):
        try:
            versions[package] = metadata.version(package)
        except metadata.PackageNotFoundError:
            versions[package] = "not installed"
    return versions


def run_pipeline(
    scenario: Scenario,
    out: str | Path,
    to: str = "packing",
    overwrite: bool = False,
    progress: Callable[[int, BatchResult], None] | None = None,
    command: list[str] | None = None,
) -> tuple[Path, Stack, dict[str, Any]]:
    """Run the stages up to ``to`` into the run directory ``out``.

    Returns (run directory, stack, manifest).
    """
    if to not in STAGES:
        if to in PLANNED:
            raise InputError(
                f"--to {printable(to)}: stage not implemented yet; available: {', '.join(STAGES)}"
            )
        raise InputError(f"--to {printable(to)}: unknown stage; valid stages: {', '.join(STAGES)}")
    run = RunDirectory(out, overwrite=overwrite)
    run.check()  # fail on a bad --out before minutes of simulation
    started = datetime.now(UTC)
    wall = time.perf_counter()
    stack = deposit(scenario, progress=progress)
    deposition_wall = time.perf_counter() - wall
    resolved = dumps_toml(scenario)
    with run:
        run.write_text("scenario.toml", resolved)
        _write_packing(run, stack)
        manifest = {
            "tool": "chipstack",
            "command": command or [],
            "versions": _versions(),
            "platform": platform.platform(),
            "scenario": scenario.name,
            "scenario_sha256": hashlib.sha256(resolved.encode()).hexdigest(),
            "seed": scenario.seed,
            "stages_completed": ["packing"],
            "started_utc": started.isoformat(timespec="seconds"),
            "finished_utc": datetime.now(UTC).isoformat(timespec="seconds"),
            "wall_time_s": {
                "packing": round(deposition_wall, 3),
                "total": round(time.perf_counter() - wall, 3),
            },
            "warnings": list(stack.warnings),
            "packing": _packing_summary(stack),
        }
        run.write_json("manifest.json", manifest)
    return Path(out), stack, manifest


def _write_packing(run: RunDirectory, stack: Stack) -> None:
    from export import (
        stack_polydata,
        write_contacts_csv,
        write_poses_csv,
        write_pvd,
        write_stack_vtp,
    )

    series = []
    for result in stack.batches:
        tag = f"batch_{result.batch:02d}"
        write_poses_csv(run.path(f"packing/poses_after_{tag}.csv"), stack, result)
        write_contacts_csv(run.path(f"packing/contacts_after_{tag}.csv"), result)
        n = len(result.positions)
        mesh = stack_polydata(
            stack.shapes,
            stack.shape_index[:n],
            result.positions,
            result.quaternions,
            stack.batch[:n],
        )
        write_stack_vtp(run.path(f"packing/stack_after_{tag}.vtp"), mesh)
        series.append((float(result.batch), f"stack_after_{tag}.vtp"))
    write_pvd(run.path("packing/stack.pvd"), series)


def _packing_summary(stack: Stack) -> dict[str, Any]:
    batches = [
        {
            "batch": r.batch,
            "chips": len(r.positions),
            "settled": r.settled,
            "sim_time_s": round(r.sim_time_s, 4),
            "wall_time_s": round(r.wall_time_s, 3),
            "steps": r.steps,
            "wakes": r.wakes,
            "contact_points": len(r.contacts),
            "outside_target": r.outside_target,
            "max_floor_penetration_mm": round(r.max_floor_penetration_mm, 5),
            "max_chip_penetration_mm": round(r.max_chip_penetration_mm, 5),
            "top_mm": round(_top(stack, r), 3),
        }
        for r in stack.batches
    ]
    return {
        "chips": stack.n_chips,
        "batches": batches,
        "outside_target": stack.batches[-1].outside_target,
        "all_settled": all(r.settled for r in stack.batches),
    }


def _top(stack: Stack, result: BatchResult) -> float:
    """Height of the highest point of any chip (mm): the top of the stack."""
    n = len(result.positions)
    top = 0.0
    for k, shape in enumerate(stack.shapes):
        mine = stack.shape_index[:n] == k
        if mine.any():
            heights = vertex_heights_mm(
                result.positions[mine], result.quaternions[mine], shape.vertices
            )
            top = max(top, float(heights.max()))
    return top
