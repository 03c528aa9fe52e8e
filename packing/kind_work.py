"""What the scenario kinds of :mod:`packing.kinds` run, write and read back: the batch
deposition with its checkpoints, the drops, the conveyor's pour, the files of each
(:mod:`packing.writers`) and the stack record read from a written folder.

The kinds are read at every command-line start and reach this module when one first
runs, writes or loads (it brings numpy, scipy and PyBullet)."""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np

from chipstack.core.errors import InputError, brief
from chipstack.core.stack import BatchResult, Stack
from chipstack.core.stages import StageInputs
from chipstack.packing.checkpoint import stack_from_arrays, state_from_arrays, state_to_arrays
from chipstack.packing.conveyor import ConveyorResult, check_conveyor, pour_mat, pour_timing
from chipstack.packing.deposition import deposit
from chipstack.packing.drop import drop_chips
from chipstack.packing.writers import (
    container_summary,
    packing_summary,
    write_drop_files,
    write_mat_files,
)

__all__ = [
    "check_conveyor",
    "container_summary",
    "deposit_stack",
    "drop_chips",
    "load_stack",
    "packing_summary",
    "pour",
    "write_drop_files",
    "write_mat_files",
]


def deposit_stack(inputs: StageInputs, stage_name: str) -> Stack:
    """The batch deposition of ``inputs.scenario``, resumed from its checkpoint and saving
    one after every batch when the run keeps them, reporting each batch."""
    scenario = inputs.scenario
    n_batches = -(-scenario.deposition.chips // scenario.deposition.batch_size)
    report = inputs.options.progress

    def progress(batch: int, result: BatchResult | None) -> None:
        if report is not None:
            detail = {}
            if result is not None:  # containers report only their last batch
                detail = {"chips": len(result.positions), "sim_s": f"{result.sim_time_s:.2f}"}
            report(stage_name, batch, n_batches, detail)

    checkpoint = inputs.checkpoint
    resume = checkpoint.resume(state_from_arrays) if checkpoint is not None else None
    if resume is not None:
        progress(resume.batches_done, resume.results[-1] if resume.results else None)
    on_batch = None
    if checkpoint is not None:

        def on_batch(state) -> None:
            checkpoint.save(state_to_arrays(state), state.batches_done)

    return deposit(scenario, progress=progress, resume=resume, on_batch=on_batch)


def pour(inputs: StageInputs, stage_name: str) -> ConveyorResult:
    """The conveyor's mat poured for ``inputs.scenario``, reporting each pour."""
    report = inputs.options.progress

    def progress(done: int, pours: int) -> None:
        if report is not None:
            report(stage_name, done, pours, {})

    if report is not None:
        report(stage_name, 0, pour_timing(inputs.scenario)[0], {})
    return pour_mat(inputs.scenario, progress)


def load_stack(folder: Path) -> Stack:
    """The stack record (``stack.npz``) back from a written folder."""
    path = folder / "stack.npz"
    try:
        with np.load(path, allow_pickle=False) as arrays:
            return stack_from_arrays(dict(arrays), str(path))
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
        raise InputError(f"{path}: unreadable stack record ({brief(str(exc))})") from None
