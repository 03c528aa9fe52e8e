"""Ensembles: N independent runs of a scenario on Dask, each written as it arrives, and
the last stage's statistics over them."""

from __future__ import annotations

import hashlib
import json
import logging
import time
from collections.abc import Callable, Mapping, Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from chipstack.core.errors import InputError, SimulationError
from chipstack.core.keys import MAX_REPEATS
from chipstack.core.provenance import code_versions
from chipstack.core.schema import Scenario
from chipstack.core.stages import StageOptions
from chipstack.pipeline.execution import Executor
from chipstack.pipeline.run import RepeatResult, compute_run, derive_seed, stages_to, write_run
from chipstack.pipeline.rundir import EnsembleDirectory
from chipstack.pipeline.scenario_files import dumps_toml

__all__ = ["run_ensemble", "MAX_REPEATS"]

log = logging.getLogger(__name__)

SEED_RULE = "numpy SeedSequence([seed, index]).generate_state(1)[0]"


def run_ensemble(
    scenario: Scenario,
    out: str | Path,
    repeats: int,
    to: str | None = "geometry",
    overwrite: bool = False,
    progress: Callable[[int, int], None] | None = None,
    command: list[str] | None = None,
    descriptors: Sequence[str] | None = None,
    workers: int | None = None,
    scheduler: str | None = None,
    settings: Mapping[str, Any] | None = None,
) -> tuple[Path, dict[str, Any]]:
    """``repeats`` independent runs (seeds derived from the scenario's) and their statistics.

    The runs go through the execution layer (Dask: a local cluster, or ``scheduler``).
    Each finished run is written to ``out/repeat_K`` as it arrives, so an interrupted
    ensemble started again with the same arguments resumes where it stopped; the last
    stage's statistics over the repeats (the geometry stage: ``out/ensemble.json``, mean
    and 95 % confidence interval of every descriptor) follow. A run that raises is
    reported with its seed; the others complete. ``settings``: the keys set on the command
    line, already applied to ``scenario``, recorded in every manifest.
    """
    stages = stages_to(to, scenario)
    to = stages[-1].name
    if not 2 <= repeats <= MAX_REPEATS:
        raise InputError(f"--repeats: must be between 2 and {MAX_REPEATS}, got {repeats}")
    if not stages[-1].in_ensembles:
        raise InputError(f"--to {to}: not with --repeats (make it from a single run)")
    options = StageOptions(tuple(descriptors) if descriptors else None)
    for stage in stages:
        stage.check_options(options)
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
        failures, n_workers = _run_repeats(
            folder, scenario, names, seeds, done, to, descriptors, command, progress,
            workers, scheduler, settings,
        )  # fmt: skip
        good = [k for k in range(repeats) if k not in failures]
        if not good:
            first = min(failures)
            raise SimulationError(
                f"--repeats: all {repeats} runs failed (first: repeat {first}, seed "
                f"{seeds[first]}: {failures[first]})"
            )
        last = stages[-1]
        summary = _repeat_statistics(last, folder, names, seeds, good, failures)
        manifest = {
            **_ensemble_manifest(scenario, command, seeds, names, good, done, failures, settings),
            "workers": n_workers,
            "scheduler": scheduler or "local",
            "stages_completed": [s.name for s in stages],
            "started_utc": started.isoformat(timespec="seconds"),
            "finished_utc": datetime.now(UTC).isoformat(timespec="seconds"),
            "wall_time_s": {"total": round(time.perf_counter() - wall, 3)},
            "warnings": _repeat_warnings(folder, names, seeds, good),
        }

        def finish(path: Callable[[str], Path]) -> None:
            if summary is not None:
                last.write_repeats(summary, path)
            path("manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")

        folder.complete(finish)
    return Path(out), manifest


def _repeat_statistics(last, folder, names, seeds, good, failures) -> Any:
    """The last stage's statistics over the good repeats (None if it has none)."""
    if not last.repeat_statistics:
        return None
    if len(good) < 2:
        raise InputError(
            f"--repeats: only {len(good)} of {len(names)} runs succeeded; no statistics "
            f"(failures: {'; '.join(f'repeat {k}: {m}' for k, m in failures.items())})"
        )
    folders = [folder.file(f"{names[k]}/{last.name}") for k in good]
    return last.summarize_repeats(folders, [seeds[k] for k in good])


def _repeat_warnings(folder, names, seeds, good) -> list[str]:
    warnings = []
    for k in good:
        manifest = json.loads(folder.file(f"{names[k]}/manifest.json").read_text())
        warnings += [f"repeat {k} (seed {seeds[k]}): {w}" for w in manifest.get("warnings", [])]
    return warnings


def _ensemble_manifest(scenario, command, seeds, names, good, done, failures, settings) -> dict:
    """The ensemble manifest's provenance (``set``: the keys set on the command line) and
    run lists."""
    return {
        "tool": "chipstack",
        "kind": "ensemble",
        "command": command or [],
        "versions": code_versions(),
        "scenario": scenario.name,
        "seed": scenario.seed,
        "set": dict(settings or {}),
        "repeats": len(names),
        "seeds": seeds,
        "seed_rule": SEED_RULE,
        "runs": [names[k] for k in good],
        "resumed_runs": sorted(done),
        "failed_runs": [
            {"repeat": k, "seed": seeds[k], "error": failures[k]} for k in sorted(failures)
        ],
    }


def _run_repeats(
    folder: EnsembleDirectory,
    scenario: Scenario,
    names: list[str],
    seeds: list[int],
    done: set[str],
    to: str,
    descriptors,
    command,
    progress,
    workers: int | None,
    scheduler: str | None,
    settings: Mapping[str, Any] | None = None,
) -> tuple[dict[int, str], int]:
    """Run the repeats not yet written on the executor, writing each as it arrives.

    Returns (failure message by repeat, number of workers used)."""
    repeats = len(names)
    failures: dict[int, str] = {}
    todo = [k for k in range(repeats) if names[k] not in done]

    def on_result(k: int, result: RepeatResult) -> None:
        with folder.run(names[k]) as path:
            write_run(path, "", result, to, command, False, settings)
        if progress:
            progress(1, repeats)

    def on_error(k: int, error: BaseException) -> None:
        message = f"{type(error).__name__}: {error}".splitlines()[0]
        failures[k] = message
        log.warning("repeat %d (seed %d) failed: %s", k, seeds[k], message)
        if progress:
            progress(1, repeats)

    if not todo:
        if progress:
            progress(len(done), repeats)
        return failures, 0
    with Executor(workers=workers, scheduler=scheduler) as executor:
        if progress:  # drawn once connected, so a bad --scheduler stays one line
            progress(len(done), repeats)
        arguments = [(scenario.with_seed(seeds[k]), to, descriptors) for k in todo]

        def shift(callback):
            return lambda j, value: callback(todo[j], value)

        executor.run(compute_run, arguments, shift(on_result), shift(on_error))
        return failures, executor.n_workers
