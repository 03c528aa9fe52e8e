"""Wiring of the stages into a run (no physics, no geometry here)."""

from __future__ import annotations

import hashlib
import json
import logging
import platform
import time
from collections.abc import Callable, Sequence
from datetime import UTC, datetime
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np

from packing import BatchResult, Scenario, Stack, deposit
from packing.config import printable
from packing.errors import InputError
from packing.overlap import vertex_heights_mm
from pipeline.rundir import RunDirectory, StageWriter
from pipeline.scenario_files import dumps_toml

__all__ = [
    "STAGES",
    "run_pipeline",
    "run_ensemble",
    "describe_run",
    "derive_seed",
    "MAX_REPEATS",
]

log = logging.getLogger(__name__)

STAGES = ("packing", "geometry", "mesh")  # in order
PLANNED: tuple[str, ...] = ()
MAX_REPEATS = 1000


def _versions() -> dict[str, str]:
    versions = {"python": platform.python_version()}
    for package in ("chipstack", "pybullet", "numpy", "scipy", "manifold3d", "pyvista", "vtk"):
        try:
            versions[package] = metadata.version(package)
        except metadata.PackageNotFoundError:
            versions[package] = "not installed"
    return versions


def derive_seed(seed: int, index: int) -> int:
    """The seed of repeat ``index`` of an ensemble seeded ``seed`` (independent streams).

    Depends only on (seed, index), never on how many repeats run or in which order.
    """
    return int(np.random.SeedSequence([seed, index]).generate_state(1, dtype=np.uint32)[0])


def check_stage(to: str) -> None:
    if to not in STAGES:
        if to in PLANNED:
            raise InputError(
                f"--to {printable(to)}: stage not implemented yet; available: {', '.join(STAGES)}"
            )
        raise InputError(f"--to {printable(to)}: unknown stage; valid stages: {', '.join(STAGES)}")


def run_pipeline(
    scenario: Scenario,
    out: str | Path,
    to: str = "packing",
    overwrite: bool = False,
    progress: Callable[[int, BatchResult], None] | None = None,
    command: list[str] | None = None,
    descriptors: Sequence[str] | None = None,
    figures: bool = True,
) -> tuple[Path, Stack, dict[str, Any]]:
    """Run the stages up to ``to`` into the run directory ``out``.

    Returns (run directory, stack, manifest).
    """
    check_stage(to)
    if to != "packing":
        from geometry.describe import check_names

        check_names(descriptors)
    run = RunDirectory(out, overwrite=overwrite)
    run.check()  # fail on a bad --out before minutes of simulation
    with run:
        stack, manifest = _single_run(
            run, "", scenario, to, progress, command, descriptors, figures
        )
    return Path(out), stack, manifest


def _single_run(
    run: RunDirectory,
    prefix: str,
    scenario: Scenario,
    to: str,
    progress,
    command,
    descriptors,
    figures: bool,
) -> tuple[Stack, dict[str, Any]]:
    started = datetime.now(UTC)
    wall = time.perf_counter()
    stack = deposit(scenario, progress=progress)
    times = {"packing": round(time.perf_counter() - wall, 3)}
    resolved = dumps_toml(scenario)
    run.write_text(f"{prefix}scenario.toml", resolved)
    _write_packing(run, prefix, stack)
    stages = ["packing"]
    geometry_summary = None
    if to in ("geometry", "mesh"):
        from geometry.arrangement import arrangements_from_stack

        start = time.perf_counter()
        history = arrangements_from_stack(stack)
        geometry_summary = _geometry(
            run.path(f"{prefix}geometry/descriptors.json").parent,
            history,
            scenario,
            descriptors,
            figures,
        )
        times["geometry"] = round(time.perf_counter() - start, 3)
        stages.append("geometry")
    mesh_summary = None
    if to == "mesh":
        start = time.perf_counter()
        mesh_summary = _mesh(run.path(f"{prefix}mesh/x").parent, history[-1], scenario, figures)
        times["mesh"] = round(time.perf_counter() - start, 3)
        stages.append("mesh")
    times["total"] = round(time.perf_counter() - wall, 3)
    manifest = {
        "tool": "chipstack",
        "kind": "run",
        "command": command or [],
        "versions": _versions(),
        "platform": platform.platform(),
        "scenario": scenario.name,
        "scenario_sha256": hashlib.sha256(resolved.encode()).hexdigest(),
        "seed": scenario.seed,
        "stages_completed": stages,
        "started_utc": started.isoformat(timespec="seconds"),
        "finished_utc": datetime.now(UTC).isoformat(timespec="seconds"),
        "wall_time_s": times,
        "warnings": list(stack.warnings),
        "packing": _packing_summary(stack),
    }
    if geometry_summary is not None:
        manifest["geometry"] = geometry_summary
    if mesh_summary is not None:
        manifest["mesh"] = mesh_summary
    run.write_json(f"{prefix}manifest.json", manifest)
    return stack, manifest


def _geometry(
    folder: Path,
    history,
    scenario: Scenario,
    descriptors: Sequence[str] | None,
    figures: bool,
) -> dict[str, Any]:
    """Describe a stack and write the geometry stage's files into ``folder``."""
    from export.descriptors import write_description
    from geometry.describe import describe

    description = describe(history, scenario.geometry, descriptors)
    extra = {"scenario": scenario.name, "seed": scenario.seed, "chips": history[-1].n_chips}
    files = write_description(folder, description, history[-1], extra)
    if figures:
        from pipeline.figures import single_run_figures

        files += single_run_figures(folder / "figures", description, history[-1])
    return {
        "descriptors": list(description.records),
        "files": sorted(files),
        "descriptor_time_s": round(sum(description.timings_s.values()), 4),
    }


def _mesh(folder: Path, arrangement, scenario: Scenario, figures: bool) -> dict[str, Any]:
    """Mesh the stack, check the mesh and write its files into ``folder``."""
    from export.mesh_files import write_mesh
    from geometry.contacts import find_contacts
    from meshing import check_mesh, conformal_mesh, voxel_mesh
    from meshing.checks import assert_valid

    spec = scenario.mesh
    g = scenario.geometry
    table = find_contacts(arrangement, g.contact_gap_mm, g.contact_extent_mm)
    chips = table.chip_b >= 0
    surface_pairs = np.column_stack([table.chip_a, table.chip_b])[chips & (table.kind == 2)]
    kinds = ["voxel", "conformal"] if spec.kind == "both" else [spec.kind]
    summary: dict[str, Any] = {}
    for kind in kinds:
        stem = f"stack_{kind}"
        formats = list(spec.formats)
        if kind == "voxel":
            mesh = voxel_mesh(arrangement, spec.voxel_mm, spec.pore_space, g.layer_mm)
        else:
            msh = folder / f"{stem}.msh" if "msh" in formats else None
            mesh = conformal_mesh(
                arrangement,
                spec.size_mm,
                spec.pore_space,
                g.layer_mm,
                spec.min_quality,
                msh_path=msh,
            )
            formats = [f for f in formats if f != "msh"]  # gmsh wrote it, physical groups and all
        report = check_mesh(
            mesh, arrangement, surface_pairs, spec.min_quality if kind == "conformal" else 0.99
        )
        assert_valid(report)
        files = [p.name for p in write_mesh(folder, stem, mesh, formats)]
        if kind == "conformal" and "msh" in spec.formats:
            files.append(f"{stem}.msh")
        if figures:
            from pipeline.figures import mesh_figure

            files += mesh_figure(folder / f"{stem}.png", mesh)
        (folder / f"{stem}_checks.json").write_text(json.dumps(report, indent=2) + "\n")
        files.append(f"{stem}_checks.json")
        summary[kind] = {
            "elements": mesh.n_elements,
            "nodes": len(mesh.points),
            "quality_min": round(report["quality_min"], 4),
            "quality_p1": round(report["quality_p1"], 4),
            "chip_volume_error_max": report["chip_volume_error_max"],
            "total_volume_error": report["total_volume_error"],
            "info": mesh.info,
            "files": sorted(files),
        }
    return summary


def describe_run(
    run_dir: str | Path,
    descriptors: Sequence[str] | None = None,
    figures: bool = True,
    overwrite: bool = False,
) -> dict[str, Any]:
    """The geometry stage on an existing packing run: adds ``geometry/`` to it.

    Returns the updated manifest. Nothing is written unless the stage completes.
    """
    from geometry.describe import check_names
    from pipeline.stackfiles import load_run

    check_names(descriptors)
    scenario, history, manifest = load_run(run_dir)
    if "geometry" in manifest.get("stages_completed", []) and not overwrite:
        raise InputError(
            f"{printable(run_dir)}: already described (use --overwrite to describe it again)"
        )
    start = time.perf_counter()
    with StageWriter(run_dir, "geometry") as folder:
        summary = _geometry(folder, history, scenario, descriptors, figures)
        manifest["geometry"] = summary
        manifest["stages_completed"] = [
            s for s in manifest.get("stages_completed", []) if s != "geometry"
        ] + ["geometry"]
        manifest.setdefault("wall_time_s", {})["geometry"] = round(time.perf_counter() - start, 3)
    StageWriter.replace_json(Path(run_dir) / "manifest.json", manifest)
    return manifest


def run_ensemble(
    scenario: Scenario,
    out: str | Path,
    repeats: int,
    to: str = "geometry",
    overwrite: bool = False,
    progress: Callable[[int, int], None] | None = None,
    command: list[str] | None = None,
    descriptors: Sequence[str] | None = None,
) -> tuple[Path, dict[str, Any]]:
    """``repeats`` independent runs (seeds derived from the scenario's) and their statistics.

    Each repeat is a complete run in ``out/repeat_NN``; ``out/ensemble.json`` holds, for
    every descriptor, the mean and 95 % confidence interval over the repeats.
    """
    from geometry.describe import check_names
    from geometry.ensemble import summarize_runs

    check_stage(to)
    if not 2 <= repeats <= MAX_REPEATS:
        raise InputError(f"--repeats: must be between 2 and {MAX_REPEATS}, got {repeats}")
    if to == "geometry":
        check_names(descriptors)
    run = RunDirectory(out, overwrite=overwrite)
    run.check()
    seeds = [derive_seed(scenario.seed, k) for k in range(repeats)]
    started = datetime.now(UTC)
    wall = time.perf_counter()
    width = len(str(repeats - 1))
    with run:
        sections = []
        warnings = []
        for k, seed in enumerate(seeds):
            prefix = f"repeat_{k:0{width}d}/"
            stack, manifest = _single_run(
                run, prefix, scenario.with_seed(seed), to, None, command, descriptors, False
            )
            warnings += [f"repeat {k} (seed {seed}): {w}" for w in stack.warnings]
            if to == "geometry":
                described = json.loads(run.path(f"{prefix}geometry/descriptors.json").read_text())
                sections.append(described)
            if progress:
                progress(k + 1, repeats)
        summary = None
        if to == "geometry":
            summary = summarize_runs(sections, seeds)
            run.write_json("ensemble.json", summary)
            from pipeline.figures import ensemble_figures

            ensemble_figures(run.path("figures/x").parent, summary)
        manifest = {
            "tool": "chipstack",
            "kind": "ensemble",
            "command": command or [],
            "versions": _versions(),
            "scenario": scenario.name,
            "seed": scenario.seed,
            "repeats": repeats,
            "seeds": seeds,
            "seed_rule": "numpy SeedSequence([seed, index]).generate_state(1)[0]",
            "runs": [f"repeat_{k:0{width}d}" for k in range(repeats)],
            "stages_completed": ["packing"] + (["geometry"] if to == "geometry" else []),
            "started_utc": started.isoformat(timespec="seconds"),
            "finished_utc": datetime.now(UTC).isoformat(timespec="seconds"),
            "wall_time_s": {"total": round(time.perf_counter() - wall, 3)},
            "warnings": warnings,
        }
        run.write_json("manifest.json", manifest)
    return Path(out), manifest


def _write_packing(run: RunDirectory, prefix: str, stack: Stack) -> None:
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
        write_poses_csv(run.path(f"{prefix}packing/poses_after_{tag}.csv"), stack, result)
        write_contacts_csv(run.path(f"{prefix}packing/contacts_after_{tag}.csv"), result)
        n = len(result.positions)
        mesh = stack_polydata(
            stack.shapes,
            stack.shape_index[:n],
            result.positions,
            result.quaternions,
            stack.batch[:n],
        )
        write_stack_vtp(run.path(f"{prefix}packing/stack_after_{tag}.vtp"), mesh)
        series.append((float(result.batch), f"stack_after_{tag}.vtp"))
    write_pvd(run.path(f"{prefix}packing/stack.pvd"), series)


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
