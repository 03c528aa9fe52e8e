"""A generic loop over the registered stages: single runs (cached, resumable) and
ensembles (on Dask). No stage is named here; each is an object from ``core.stages``."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import platform
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from chipstack.core.errors import InputError, printable
from chipstack.core.provenance import code_versions
from chipstack.core.scenario_data import scenario_to_dict
from chipstack.core.schema import Scenario
from chipstack.core.stages import (
    Stage,
    StageInputs,
    StageOptions,
    chain,
    check_stage_name,
    load_stages,
)
from chipstack.pipeline.scenario_files import dumps_toml
from chipstack.pipeline.staged_run import StagedRun

__all__ = [
    "run_pipeline",
    "derive_seed",
    "compute_run",
    "write_run",
    "stage_inputs",
]

log = logging.getLogger(__name__)


def derive_seed(seed: int, index: int) -> int:
    """The seed of repeat ``index`` of an ensemble seeded ``seed`` (independent streams).

    Depends only on (seed, index), never on how many repeats run or in which order.
    """
    import numpy as np  # here: every ``pipeline run`` imports this module before any check

    return int(np.random.SeedSequence([seed, index]).generate_state(1, dtype=np.uint32)[0])


def stages_to(to: str | None, scenario: Scenario | None = None) -> list[Stage]:
    """The stages a run ``--to to`` runs (None: the first stage only), refusing a stage
    the scenario's kind lacks."""
    to = to or load_stages()[0].name
    target = check_stage_name(to)
    if scenario is not None and scenario.kind not in target.kinds:
        first = load_stages()[0].name
        raise InputError(
            f"--to {printable(to)}: a {scenario.kind} scenario has only the {first} stage "
            f"(its results are in the run's manifest and {first}/ folder)"
        )
    stages = chain(to)
    if scenario is not None:
        for stage in stages:
            stage.check_run(scenario)
    return stages


def stage_inputs(scenario: Scenario, options: StageOptions | None = None) -> dict[str, str]:
    """The SHA-256 of what each stage's result depends on (the stage cache's keys).

    A stage's key holds the scenario tables it declares, what else it names
    (``Stage.key_extra``) and the keys of the stages upstream of it, so changing a key
    redoes exactly the stages downstream of it.
    """
    options = options or StageOptions()
    data = scenario_to_dict(scenario)
    hashes: dict[str, str] = {}
    for stage in load_stages():
        if scenario.kind not in stage.kinds:  # a stage that never runs on this kind
            continue
        key: dict[str, Any] = {name: hashes[name] for name in stage.upstream}
        # A table of another scenario kind is not in the scenario (nor in the key).
        key.update(
            {
                section: _result_keys(getattr(scenario, section, None), data[section])
                for section in stage.sections
                if section in data
            }
        )
        key.update(stage.key_extra(scenario, options))
        hashes[stage.name] = _sha256(key)
    return hashes


def _result_keys(section: Any, table: Any) -> Any:
    """A scenario table without its execution keys (``key(..., execution=True)``)."""
    if not (dataclasses.is_dataclass(section) and isinstance(table, dict)):
        return table
    skip = {f.name for f in dataclasses.fields(section) if f.metadata.get("execution")}
    return {name: value for name, value in table.items() if name not in skip}


def _sha256(data: Any) -> str:
    return hashlib.sha256(json.dumps(data, sort_keys=True).encode()).hexdigest()


def run_pipeline(
    scenario: Scenario,
    out: str | Path,
    to: str | None = None,
    overwrite: bool = False,
    progress: Callable[..., None] | None = None,
    command: list[str] | None = None,
    descriptors: Sequence[str] | None = None,
    figures: bool = True,
    settings: Mapping[str, Any] | None = None,
) -> tuple[Path, Any, dict[str, Any]]:
    """Run the stages up to ``to`` into the run directory ``out``.

    Resumable and cached (see :class:`pipeline.staged_run.StagedRun`): after a crash the same
    call resumes from the last completed batch or stage, and on a finished run it redoes
    only the stages whose inputs changed (``overwrite``: all of them). A stage always
    reads its upstream results back from their folders, so a fresh, a resumed and a
    cached run compute from the same numbers.

    ``progress(stage, done, total, detail)`` is called as stages advance. ``settings``:
    the keys changed on the command line (``--set``), already applied to ``scenario``,
    recorded in the manifest so the run can be repeated (the stage cache keys follow
    from the scenario itself).

    Returns (run directory, the first stage's result (None for drops), manifest).
    """
    wanted = stages_to(to, scenario)
    options = StageOptions(tuple(descriptors) if descriptors else None, figures, progress)
    for stage in wanted:
        stage.check_options(options)
    keys = stage_inputs(scenario, options)
    run = StagedRun(out, overwrite=overwrite)
    run.check()  # fail on a bad --out before minutes of simulation
    started = datetime.now(UTC).isoformat(timespec="seconds")
    times: dict[str, float] = {}
    reused: list[str] = []
    loaded: dict[str, Any] = {}
    by_name = {stage.name: stage for stage in load_stages()}

    def result(name: str) -> Any:
        if name not in loaded:
            loaded[name] = by_name[name].load(run.folder(name), scenario)
        return loaded[name]

    with run:
        resolved = dumps_toml(scenario)
        run.write_text("scenario.toml", resolved)
        for stage in wanted:
            if run.reusable(stage.name, keys[stage.name]):
                reused.append(stage.name)
                log.info("%s: reused (inputs unchanged)", stage.name)
                continue
            start = time.perf_counter()
            _run_stage(run, stage, keys[stage.name], StageInputs(scenario, options, result))
            times[stage.name] = round(time.perf_counter() - start, 3)
        for stage in load_stages()[len(wanted) :]:  # kept from an earlier run if still valid
            if stage.name in run.stages and (
                stage.name not in keys or not run.reusable(stage.name, keys[stage.name])
            ):
                run.invalidate(stage.name)
        manifest = _staged_manifest(run, scenario, command, resolved, times, reused, settings)
        manifest["started_utc"] = started
        first = result(wanted[0].name)
        run.complete(manifest)
    return Path(out), first, manifest


def _run_stage(run: StagedRun, stage: Stage, key: str, inputs: StageInputs) -> None:
    """Compute one stage and build its folder (renamed into place when complete)."""
    if stage.checkpointed:
        inputs.checkpoint = run.checkpoint(stage.name, key)
    else:
        run.invalidate(stage.name)
    value = stage.compute(inputs)
    with run.stage(stage.name, key) as record:
        output = stage.write(value, record.folder, inputs)
        record.summary, record.warnings = output.summary, output.warnings


def _provenance(scenario: Scenario, command, resolved: str, settings=None) -> dict[str, Any]:
    """The manifest fields every run has: tool, command, versions, scenario, seed and the
    keys set on the command line (``set``: dotted key to value, as ``--set`` gave them)."""
    return {
        "tool": "chipstack",
        "kind": "run",
        "command": command or [],
        "versions": code_versions(),
        "platform": platform.platform(),
        "scenario": scenario.name,
        "scenario_sha256": hashlib.sha256(resolved.encode()).hexdigest(),
        "seed": scenario.seed,
        "set": dict(settings or {}),
    }


def _stage_entries(summaries: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """Each completed stage's summary as it appears at the top of the manifest."""
    by_name = {stage.name: stage for stage in load_stages()}
    entries: dict[str, Any] = {}
    for name, summary in summaries.items():
        entries.update(by_name[name].manifest_entry(summary))
    return entries


def _staged_manifest(
    run: StagedRun, scenario: Scenario, command, resolved: str, times, reused, settings
) -> dict[str, Any]:
    """The run's manifest: provenance, and each stage's summary, input hash and timing."""
    manifest = _provenance(scenario, command, resolved, settings)
    completed = run.completed
    manifest["stages_completed"] = completed
    manifest["stages_reused"] = reused
    first = completed[0] if completed else None
    resumed = run.stages.get(first, {}).get("resumed_after_batch") if first else None
    if resumed is not None and first not in reused:
        manifest["resumed_after_batch"] = resumed
    manifest["finished_utc"] = datetime.now(UTC).isoformat(timespec="seconds")
    manifest["wall_time_s"] = times
    manifest.update(_stage_entries({s: run.stages[s].get("summary", {}) for s in completed}))
    for stage in completed[1:]:  # a later stage that went on from its own checkpoint
        later = run.stages[stage].get("resumed_after_batch")
        if later is not None and stage not in reused and isinstance(manifest.get(stage), dict):
            manifest[stage]["resumed_after_batch"] = later
    manifest["warnings"] = [w for s in completed for w in run.stages[s].get("warnings", [])]
    return manifest


@dataclass(frozen=True)
class RepeatResult:
    """What one run computed (in a worker): each stage's result, by stage name."""

    scenario: Scenario
    results: dict[str, Any]
    times: dict[str, float]
    started_utc: str
    to: str | None = None
    descriptors: tuple[str, ...] | None = field(default=None)

    @property
    def first(self) -> Any:
        return self.results[load_stages()[0].name]


def compute_run(
    scenario: Scenario,
    to: str | None,
    descriptors: Sequence[str] | None,
    progress: Callable[..., None] | None = None,
) -> RepeatResult:
    """Compute the stages up to ``to`` that may run in a worker, in memory (no files)."""
    started = datetime.now(UTC).isoformat(timespec="seconds")
    options = StageOptions(tuple(descriptors) if descriptors else None, False, progress)
    results: dict[str, Any] = {}
    handed: dict[str, Any] = {}
    times: dict[str, float] = {}
    for stage in stages_to(to, scenario):
        if not stage.in_ensembles:
            break
        start = time.perf_counter()
        results[stage.name] = stage.compute(StageInputs(scenario, options, handed.__getitem__))
        handed[stage.name] = stage.handoff(results[stage.name], scenario)
        times[stage.name] = round(time.perf_counter() - start, 3)
    return RepeatResult(scenario, results, times, started, to, options.descriptors)


def write_run(
    path: Callable[[str], Path],
    prefix: str,
    result: RepeatResult,
    to: str,
    command: list[str] | None,
    figures: bool,
    settings: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """Write one computed run's files under ``prefix`` (``path(name)`` gives where) and its
    manifest; stages up to ``to`` that the worker did not run are computed here
    (``settings``: as for :func:`run_pipeline`)."""
    scenario = result.scenario
    times = dict(result.times)
    wall = time.perf_counter()
    resolved = dumps_toml(scenario)
    path(f"{prefix}scenario.toml").write_text(resolved, encoding="utf-8")
    options = StageOptions(result.descriptors, figures)
    results = dict(result.results)
    summaries: dict[str, dict[str, Any]] = {}
    warnings: list[str] = []
    stages = stages_to(to, scenario)
    by_name = {stage.name: stage for stage in load_stages()}

    def handed(name: str) -> Any:
        return by_name[name].handoff(results[name], scenario)

    for stage in stages:
        inputs = StageInputs(scenario, options, handed)
        if stage.name not in results:
            start = time.perf_counter()
            results[stage.name] = stage.compute(inputs)
            times[stage.name] = round(time.perf_counter() - start, 3)
        folder = path(f"{prefix}{stage.name}/.keep").parent
        output = stage.write(results[stage.name], folder, inputs)
        summaries[stage.name] = output.summary
        warnings += output.warnings
    times["writing"] = round(time.perf_counter() - wall, 3)
    manifest = _provenance(scenario, command, resolved, settings)
    manifest.update(
        stages_completed=list(summaries),
        started_utc=result.started_utc,
        finished_utc=datetime.now(UTC).isoformat(timespec="seconds"),
        wall_time_s=times,
        warnings=warnings,
    )
    manifest.update(_stage_entries(summaries))
    path(f"{prefix}manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")
    return manifest
