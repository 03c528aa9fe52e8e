"""Wiring of the stages into a run (no physics, no geometry here)."""

from __future__ import annotations

import hashlib
import json
import logging
import platform
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np

from packing import BatchResult, Scenario, Stack, deposit
from packing.config import printable
from packing.errors import InputError, SimulationError
from packing.overlap import vertex_heights_mm
from pipeline.rundir import StagedRun, StageWriter, write_atomically
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


def check_stage(to: str, scenario: Scenario | None = None) -> None:
    if scenario is not None and scenario.kind != "stack" and to != "packing" and to in STAGES:
        raise InputError(
            f"--to {to}: a {scenario.kind} scenario has only the packing stage "
            "(its results are in the run's manifest and packing/ folder)"
        )
    if to not in STAGES:
        if to in PLANNED:
            raise InputError(
                f"--to {printable(to)}: stage not implemented yet; available: {', '.join(STAGES)}"
            )
        raise InputError(f"--to {printable(to)}: unknown stage; valid stages: {', '.join(STAGES)}")


def stage_inputs(
    scenario: Scenario, descriptors: Sequence[str] | None = None, figures: bool = True
) -> dict[str, str]:
    """The SHA-256 of what each stage's result depends on (the stage cache's keys).

    packing: every scenario key but the name and the [geometry] and [mesh] tables, the
    content of any chip geometry file, and the versions of the code; geometry: the
    packing's hash, [geometry], the descriptor list and figures; mesh: the packing's
    hash, [geometry] (layers and contact distances) and [mesh]. Changing a key thus
    redoes exactly the stages downstream of it.
    """
    from packing.config import scenario_to_dict

    data = scenario_to_dict(scenario)
    versions = _versions()
    files = {}
    for spec in scenario.chips:
        if spec.file:
            try:
                files[spec.file] = hashlib.sha256(Path(spec.file).read_bytes()).hexdigest()
            except OSError as exc:
                raise InputError(f"chip.file {spec.file!r}: unreadable ({exc.strerror})") from None
    packing = {k: v for k, v in data.items() if k not in ("name", "geometry", "mesh")}
    packing.update(files=files, versions=versions)
    if scenario.kind == "drop":
        packing["figures"] = figures  # the drop stage draws Fig. 15
    hashes = {"packing": _sha256(packing)}
    hashes["geometry"] = _sha256(
        {
            "packing": hashes["packing"],
            "geometry": data["geometry"],
            "descriptors": list(descriptors) if descriptors else None,
            "figures": figures,
        }
    )
    hashes["mesh"] = _sha256(
        {
            "packing": hashes["packing"],
            "geometry": data["geometry"],
            "mesh": data["mesh"],
            "figures": figures,
        }
    )
    return hashes


def _sha256(data: Any) -> str:
    return hashlib.sha256(json.dumps(data, sort_keys=True).encode()).hexdigest()


def run_pipeline(
    scenario: Scenario,
    out: str | Path,
    to: str = "packing",
    overwrite: bool = False,
    progress: Callable[[int, BatchResult], None] | None = None,
    command: list[str] | None = None,
    descriptors: Sequence[str] | None = None,
    figures: bool = True,
) -> tuple[Path, Stack | None, dict[str, Any]]:
    """Run the stages up to ``to`` into the run directory ``out``.

    Resumable and cached (see :class:`pipeline.rundir.StagedRun`): after a crash the same
    call resumes from the last completed batch or stage, and on a finished run it redoes
    only the stages whose inputs changed (``overwrite``: all of them). The result is the
    same, bit for bit, however often the run was interrupted.

    Returns (run directory, stack (None for drops), manifest).
    """
    check_stage(to, scenario)
    if to != "packing":
        from geometry.describe import check_names

        check_names(descriptors)
    inputs = stage_inputs(scenario, descriptors, figures)
    wanted = STAGES[: STAGES.index(to) + 1]
    run = StagedRun(out, overwrite=overwrite)
    run.check()  # fail on a bad --out before minutes of simulation
    started = datetime.now(UTC).isoformat(timespec="seconds")
    times: dict[str, float] = {}
    reused: list[str] = []
    loaded: dict[str, Any] = {}

    def packed() -> tuple[Stack, list]:
        """The packing's exact record and its arrangements, read once."""
        if not loaded:
            loaded["stack"] = _read_stack(run.folder("packing"))
            loaded["history"] = _history(loaded["stack"])
        return loaded["stack"], loaded["history"]

    with run:
        resolved = dumps_toml(scenario)
        run.write_text("scenario.toml", resolved)
        for stage in wanted:
            if run.reusable(stage, inputs[stage]):
                reused.append(stage)
                log.info("%s: reused (inputs unchanged)", stage)
                continue
            start = time.perf_counter()
            if stage == "packing":
                _packing_stage(run, scenario, inputs["packing"], progress, figures)
            else:
                run.invalidate(stage)
                history = packed()[1]
                with run.stage(stage, inputs[stage]) as record:
                    if stage == "geometry":
                        record.summary = _geometry(
                            record.folder, history, scenario, descriptors, figures
                        )
                    else:
                        record.summary = _mesh(record.folder, history[-1], scenario, figures)
            times[stage] = round(time.perf_counter() - start, 3)
        for stage in STAGES[len(wanted) :]:  # kept from an earlier run only if still valid
            if stage in run.stages and not run.reusable(stage, inputs[stage]):
                run.invalidate(stage)
        manifest = _staged_manifest(run, scenario, command, resolved, wanted, times, reused)
        manifest["started_utc"] = started
        stack = packed()[0] if scenario.kind != "drop" else None
        run.complete(manifest)
    return Path(out), stack, manifest


def _packing_stage(run: StagedRun, scenario: Scenario, inputs: str, progress, figures) -> None:
    """Deposit (resuming a killed run's batches) or drop, and write the packing folder."""
    resume = run.begin_packing(inputs)
    if scenario.kind == "drop":
        from packing.drop import drop_chips

        drops = drop_chips(scenario)
        with run.stage("packing", inputs) as record:
            statistics = _drop_files(_inside(record.folder), "", scenario, drops, figures)
            record.summary = {"drop": statistics}
            record.warnings = list(drops.warnings)
        return
    if resume is not None and progress is not None:
        progress(resume.batches_done, resume.results[-1] if resume.results else None)
    stack = deposit(scenario, progress=progress, resume=resume, on_batch=run.save_batch)
    with run.stage("packing", inputs) as record:
        _write_packing(_inside(record.folder), "", stack)
        record.summary = {"packing": _packing_summary(stack)}
        if scenario.kind == "container":
            record.summary["container"] = container_summary(stack, scenario)
        record.warnings = list(stack.warnings)


def _inside(folder: Path) -> Callable[[str], Path]:
    """``path(name)`` for a stage's files named ``STAGE/...``, built in ``folder``."""

    def path(name: str) -> Path:
        p = folder / name.split("/", 1)[1]
        p.parent.mkdir(parents=True, exist_ok=True)
        return p

    return path


def _read_stack(folder: Path) -> Stack:
    """The packing stage's exact record (``stack.npz``): later stages always start from
    it, so a resumed or cached run computes from the very numbers a fresh one does."""
    from packing.checkpoint import stack_from_arrays

    path = folder / "stack.npz"
    try:
        with np.load(path, allow_pickle=False) as arrays:
            return stack_from_arrays(dict(arrays), str(path))
    except (OSError, ValueError) as exc:
        raise InputError(f"{path}: unreadable stack record ({exc})") from None


def _history(stack: Stack):
    from geometry.arrangement import arrangements_from_stack

    return arrangements_from_stack(stack)


def _staged_manifest(
    run: StagedRun, scenario: Scenario, command, resolved: str, wanted, times, reused
) -> dict[str, Any]:
    """The run's manifest: provenance, and each stage's summary, input hash and timing."""
    manifest: dict[str, Any] = {
        "tool": "chipstack",
        "kind": "run",
        "command": command or [],
        "versions": _versions(),
        "platform": platform.platform(),
        "scenario": scenario.name,
        "scenario_sha256": hashlib.sha256(resolved.encode()).hexdigest(),
        "seed": scenario.seed,
    }
    completed = run.completed
    manifest["stages_completed"] = completed
    manifest["stages_reused"] = reused
    resumed = run.stages.get("packing", {}).get("resumed_after_batch")
    if resumed is not None and "packing" not in reused:
        manifest["resumed_after_batch"] = resumed
    manifest["finished_utc"] = datetime.now(UTC).isoformat(timespec="seconds")
    manifest["wall_time_s"] = times
    warnings: list[str] = []
    for stage in completed:
        entry = run.stages[stage]
        summary = entry.get("summary", {})
        if stage == "packing":
            manifest.update(summary)  # packing (container) or drop
        else:
            manifest[stage] = summary
        warnings += entry.get("warnings", [])
    manifest["warnings"] = warnings
    return manifest


@dataclass(frozen=True)
class RepeatResult:
    """What one run computed (in a worker): the stack and, beyond packing, its description."""

    scenario: Scenario
    stack: Stack | None
    description: Any
    history: Any
    times: dict[str, float]
    started_utc: str
    drops: Any = None


def compute_run(
    scenario: Scenario,
    to: str,
    descriptors: Sequence[str] | None,
    progress: Callable[[int, BatchResult], None] | None = None,
) -> RepeatResult:
    """Deposit (and describe) one stack; pure computation, so it can run on any worker."""
    started = datetime.now(UTC).isoformat(timespec="seconds")
    wall = time.perf_counter()
    if scenario.kind == "drop":
        from packing.drop import drop_chips

        drops = drop_chips(scenario)
        times = {"packing": round(time.perf_counter() - wall, 3)}
        return RepeatResult(scenario, None, None, None, times, started, drops)
    stack = deposit(scenario, progress=progress)
    times = {"packing": round(time.perf_counter() - wall, 3)}
    description = history = None
    if to in ("geometry", "mesh"):
        from geometry.arrangement import arrangements_from_stack
        from geometry.describe import describe

        start = time.perf_counter()
        history = arrangements_from_stack(stack)
        description = describe(history, scenario.geometry, descriptors)
        times["geometry"] = round(time.perf_counter() - start, 3)
    return RepeatResult(scenario, stack, description, history, times, started)


def write_run(
    path: Callable[[str], Path],
    prefix: str,
    result: RepeatResult,
    to: str,
    command: list[str] | None,
    figures: bool,
) -> dict[str, Any]:
    """Write one run's files under ``prefix`` (``path(name)`` gives where) and its manifest."""
    scenario, stack = result.scenario, result.stack
    times = dict(result.times)
    wall = time.perf_counter()
    resolved = dumps_toml(scenario)
    path(f"{prefix}scenario.toml").write_text(resolved, encoding="utf-8")
    stages = ["packing"]
    if result.drops is not None:
        return _write_drops(path, prefix, result, command, figures, resolved)
    _write_packing(path, prefix, stack)
    geometry_summary = None
    if result.description is not None:
        geometry_summary = _write_geometry(
            path(f"{prefix}geometry/descriptors.json").parent,
            result.description,
            result.history,
            scenario,
            figures,
        )
        stages.append("geometry")
    mesh_summary = None
    if to == "mesh":
        start = time.perf_counter()
        records = result.description.records if result.description is not None else {}
        contacts = records["contacts"].tables[-1] if "contacts" in records else None
        mesh_summary = _mesh(
            path(f"{prefix}mesh/x").parent, result.history[-1], scenario, figures, contacts
        )
        times["mesh"] = round(time.perf_counter() - start, 3)
        stages.append("mesh")
    times["writing"] = round(time.perf_counter() - wall, 3)
    manifest = _run_manifest(result, command, resolved, stages, times, stack.warnings)
    manifest["packing"] = _packing_summary(stack)
    if scenario.kind == "container":
        manifest["container"] = container_summary(stack, scenario)
    if geometry_summary is not None:
        manifest["geometry"] = geometry_summary
    if mesh_summary is not None:
        manifest["mesh"] = mesh_summary
    path(f"{prefix}manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")
    return manifest


def _run_manifest(result: RepeatResult, command, resolved: str, stages, times, warnings) -> dict:
    """The manifest fields every run has: tool, provenance, seed, stages, times, warnings."""
    return {
        "tool": "chipstack",
        "kind": "run",
        "command": command or [],
        "versions": _versions(),
        "platform": platform.platform(),
        "scenario": result.scenario.name,
        "scenario_sha256": hashlib.sha256(resolved.encode()).hexdigest(),
        "seed": result.scenario.seed,
        "stages_completed": stages,
        "started_utc": result.started_utc,
        "finished_utc": datetime.now(UTC).isoformat(timespec="seconds"),
        "wall_time_s": times,
        "warnings": list(warnings),
    }


def container_summary(stack: Stack, scenario: Scenario) -> dict[str, Any]:
    from geometry.container import container_fill

    volumes = np.array([stack.shapes[k].volume_mm3 for k in stack.shape_index])
    c = scenario.container
    return container_fill(stack.positions, volumes, c.radius_mm, c.height_mm)


def _write_drops(path, prefix, result: RepeatResult, command, figures, resolved) -> dict:
    """Files of a drop experiment and its manifest."""
    statistics = _drop_files(path, prefix, result.scenario, result.drops, figures)
    manifest = _run_manifest(
        result, command, resolved, ["packing"], dict(result.times), result.drops.warnings
    )
    manifest["drop"] = statistics
    path(f"{prefix}manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")
    return manifest


def _drop_files(path, prefix, scenario: Scenario, drops, figures: bool) -> dict:
    """Every final pose, the statistics and Fig. 15; returns the statistics."""
    from export.tables import write_drops_csv
    from geometry.scatter import drop_statistics

    write_drops_csv(path(f"{prefix}packing/drops.csv"), drops)
    statistics = drop_statistics(drops.positions[:, :2], scenario.drop.yaw_deg)
    statistics["settled"] = int(drops.settled.sum())
    path(f"{prefix}packing/drop_statistics.json").write_text(
        json.dumps(statistics, indent=2) + "\n"
    )
    if figures:
        from export.figures import plot_drops

        plot_drops(
            path(f"{prefix}packing/figures/fig15_drops.png"),
            drops.positions[:, :2],
            statistics,
            scenario.drop.yaw_deg,
        )
    return statistics


def _geometry(
    folder: Path,
    history,
    scenario: Scenario,
    descriptors: Sequence[str] | None,
    figures: bool,
) -> dict[str, Any]:
    """Describe a stack and write the geometry stage's files into ``folder``."""
    from geometry.describe import describe

    description = describe(history, scenario.geometry, descriptors)
    return _write_geometry(folder, description, history, scenario, figures)


def _write_geometry(folder: Path, description, history, scenario: Scenario, figures: bool):
    """Write a computed description's files into ``folder``; returns the manifest entry."""
    from export.descriptors import write_description

    extra = {"scenario": scenario.name, "seed": scenario.seed, "chips": history[-1].n_chips}
    files = write_description(folder, description, history[-1], extra)
    if figures:
        from pipeline.figures import single_run_figures

        files += single_run_figures(folder / "figures", description, history[-1])
    return {
        "descriptors": list(description.records),
        "files": sorted(files),
        "descriptor_time_s": round(sum(description.timings_s.values()), 4),
        "descriptor_times_s": {k: round(v, 4) for k, v in description.timings_s.items()},
    }


def _mesh(
    folder: Path, arrangement, scenario: Scenario, figures: bool, table=None
) -> dict[str, Any]:
    """Mesh the stack, check the mesh and write its files into ``folder``.

    ``table``: the stack's contacts when the geometry stage already found them.
    """
    from export.mesh_files import write_mesh
    from geometry.contacts import find_contacts
    from meshing import MeshingError, check_mesh, conformal_mesh, voxel_mesh
    from meshing.checks import assert_valid

    spec = scenario.mesh
    g = scenario.geometry
    if table is None:
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
            try:
                mesh = conformal_mesh(
                    arrangement,
                    spec.size_mm,
                    spec.pore_space,
                    g.layer_mm,
                    spec.min_quality,
                    msh_path=msh,
                )
            except MeshingError as exc:
                if spec.kind != "both":
                    raise
                # Both were asked for: the voxel mesh stands; the failure is reported.
                log.warning("%s", exc)
                summary[kind] = {"error": str(exc)}
                continue
            formats = [f for f in formats if f != "msh"]  # gmsh wrote it, physical groups and all
        tolerance = 0.02
        if kind == "voxel":
            # Voxel centres alias on plates tilted at rational slopes: a chip can gain or
            # lose a fraction of a voxel layer through its thickness (measured: 2.6 % for a
            # 2 mm plate tilted 14 deg at 0.5 mm voxels). Allow a quarter of a layer.
            thinnest = min(s.thickness_mm for s in arrangement.shapes)
            tolerance = max(tolerance, 0.25 * spec.voxel_mm / thinnest)
        report = check_mesh(
            mesh,
            arrangement,
            surface_pairs,
            spec.min_quality if kind == "conformal" else 0.99,
            chip_tolerance=tolerance,
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
    write_atomically(Path(run_dir) / "manifest.json", json.dumps(manifest, indent=2) + "\n")
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
    workers: int | None = None,
    scheduler: str | None = None,
) -> tuple[Path, dict[str, Any]]:
    """``repeats`` independent runs (seeds derived from the scenario's) and their statistics.

    The runs go through the execution layer (Dask: a local cluster, or ``scheduler``).
    Each finished run is written to ``out/repeat_K`` as it arrives, so an interrupted
    ensemble started again with the same arguments resumes where it stopped;
    ``out/ensemble.json`` then holds, for every descriptor, the mean and 95 % confidence
    interval over the repeats. A run that raises is reported with its seed; the others
    complete.
    """
    from geometry.describe import check_names
    from geometry.ensemble import summarize_runs
    from pipeline.execution import Executor
    from pipeline.rundir import EnsembleDirectory

    check_stage(to, scenario)
    if not 2 <= repeats <= MAX_REPEATS:
        raise InputError(f"--repeats: must be between 2 and {MAX_REPEATS}, got {repeats}")
    if to == "mesh":
        raise InputError("--to mesh: not with --repeats (mesh a single run)")
    if to == "geometry":
        check_names(descriptors)
    seeds = [derive_seed(scenario.seed, k) for k in range(repeats)]
    width = len(str(repeats - 1))
    names = [f"repeat_{k:0{width}d}" for k in range(repeats)]
    identity = {
        "scenario_sha256": hashlib.sha256(dumps_toml(scenario).encode()).hexdigest(),
        "seed": scenario.seed,
        "repeats": repeats,
        "to": to,
        "descriptors": list(descriptors) if descriptors else None,
    }
    with EnsembleDirectory(out, identity, overwrite=overwrite) as folder:
        started = datetime.now(UTC)
        wall = time.perf_counter()
        done = folder.finished(names)
        failures: dict[int, str] = {}
        warnings: list[str] = []
        todo = [k for k in range(repeats) if names[k] not in done]

        def on_result(k: int, result: RepeatResult) -> None:
            with folder.run(names[k]) as path:
                write_run(path, "", result, to, command, False)
            if progress:
                progress(1, repeats)

        def on_error(k: int, error: BaseException) -> None:
            message = f"{type(error).__name__}: {error}".splitlines()[0]
            failures[k] = message
            log.warning("repeat %d (seed %d) failed: %s", k, seeds[k], message)
            if progress:
                progress(1, repeats)

        if todo:
            with Executor(workers=workers, scheduler=scheduler) as executor:
                if progress:  # drawn once connected, so a bad --scheduler stays one line
                    progress(len(done), repeats)
                arguments = [(scenario.with_seed(seeds[k]), to, descriptors) for k in todo]

                def shift(callback):
                    return lambda j, value: callback(todo[j], value)

                executor.run(compute_run, arguments, shift(on_result), shift(on_error))
                n_workers = executor.n_workers
        else:
            n_workers = 0
            if progress:
                progress(len(done), repeats)
        good = [k for k in range(repeats) if k not in failures]
        for k in good:
            manifest = json.loads(folder.file(f"{names[k]}/manifest.json").read_text())
            warnings += [f"repeat {k} (seed {seeds[k]}): {w}" for w in manifest.get("warnings", [])]
        if not good:
            raise SimulationError(
                f"--repeats: all {repeats} runs failed (first: repeat {min(failures)}, seed "
                f"{seeds[min(failures)]}: {failures[min(failures)]})"
            )
        summary = None
        if to == "geometry" and len(good) >= 2:
            sections = [
                json.loads(folder.file(f"{names[k]}/geometry/descriptors.json").read_text())
                for k in good
            ]
            summary = summarize_runs(sections, [seeds[k] for k in good])
            summary["runs"] = [names[k] for k in good]
        elif to == "geometry":
            raise InputError(
                f"--repeats: only {len(good)} of {repeats} runs succeeded; no statistics "
                f"(failures: {'; '.join(f'repeat {k}: {m}' for k, m in failures.items())})"
            )
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
            "runs": [names[k] for k in good],
            "resumed_runs": sorted(done),
            "failed_runs": [
                {"repeat": k, "seed": seeds[k], "error": failures[k]} for k in sorted(failures)
            ],
            "workers": n_workers,
            "scheduler": scheduler or "local",
            "stages_completed": ["packing"] + (["geometry"] if to == "geometry" else []),
            "started_utc": started.isoformat(timespec="seconds"),
            "finished_utc": datetime.now(UTC).isoformat(timespec="seconds"),
            "wall_time_s": {"total": round(time.perf_counter() - wall, 3)},
            "warnings": warnings,
        }

        def finish(path: Callable[[str], Path]) -> None:
            if summary is not None:
                path("ensemble.json").write_text(json.dumps(summary, indent=2) + "\n")
                from pipeline.figures import ensemble_figures

                ensemble_figures(path("figures/x").parent, summary)
            path("manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")

        folder.complete(finish)
    return Path(out), manifest


def _write_packing(path: Callable[[str], Path], prefix: str, stack: Stack) -> None:
    from export import (
        stack_polydata,
        write_contacts_csv,
        write_poses_csv,
        write_pvd,
        write_stack_vtp,
    )
    from packing.checkpoint import stack_to_arrays
    from packing.shapes import shape_record

    shapes = {"schema": "chipstack.shapes/1", "shapes": [shape_record(s) for s in stack.shapes]}
    path(f"{prefix}packing/shapes.json").write_text(json.dumps(shapes) + "\n")
    # The exact record (float64 poses, contacts) later stages start from.
    np.savez(path(f"{prefix}packing/stack.npz"), **stack_to_arrays(stack))
    series = []
    for result in stack.batches:
        tag = f"batch_{result.batch:02d}"
        write_poses_csv(path(f"{prefix}packing/poses_after_{tag}.csv"), stack, result)
        write_contacts_csv(path(f"{prefix}packing/contacts_after_{tag}.csv"), result)
        n = len(result.positions)
        mesh = stack_polydata(
            stack.shapes,
            stack.shape_index[:n],
            result.positions,
            result.quaternions,
            stack.batch[:n],
        )
        write_stack_vtp(path(f"{prefix}packing/stack_after_{tag}.vtp"), mesh)
        series.append((float(result.batch), f"stack_after_{tag}.vtp"))
    write_pvd(path(f"{prefix}packing/stack.pvd"), series)


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
