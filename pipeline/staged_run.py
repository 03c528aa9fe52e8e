"""A single run, built stage by stage in a hidden sibling directory: resumable after a
crash (each stage's state saved as it goes), cached (a stage whose inputs are unchanged is
reused), and renamed into place only when complete."""

from __future__ import annotations

import contextlib
import json
import logging
import os
import shutil
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from chipstack.core.errors import InputError, StoppedEarly
from chipstack.core.files import file_sha256
from chipstack.core.stages import Checkpoint, stage_names
from chipstack.pipeline.atomic import (
    fsync_file,
    link_or_copy,
    now,
    read_journal,
    remove,
    save_npz_atomically,
    write_atomically,
)
from chipstack.pipeline.locks import DirectoryLock
from chipstack.pipeline.rundir import RunDirectory

__all__ = ["StagedRun", "StageRecord", "Interrupted", "RunCheckpoint"]

log = logging.getLogger(__name__)


class Interrupted(KeyboardInterrupt):
    """An interrupted run; ``hint`` says what was kept (for the one-line message)."""

    def __init__(self, hint: str) -> None:
        super().__init__(hint)
        self.hint = hint


@dataclass
class StageRecord:
    """What a finished stage puts in the manifest (filled in by the caller)."""

    folder: Path
    summary: dict[str, Any] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)


class StagedRun:
    """A single run's directory, built stage by stage so that nothing is lost or
    half-written, and rebuilt only where its inputs changed.

    The run is assembled in a hidden sibling (``.NAME.partial``) and renamed to ``NAME``
    when every asked-for stage is done. In it, ``manifest.json`` is the journal: for each
    stage, the hash of its inputs and whether it is complete; for the packing stage in
    progress, how many batches are done (their state is in ``.packing-state.npz``). Each
    stage's folder is built hidden and renamed into place when complete; every other file
    is written to a temporary name and renamed. So after a crash or ``kill -9`` the same
    command finds the journal and resumes from the last completed batch or stage.

    Run again on a finished run, a stage whose inputs hash is unchanged is reused (its
    files hard-linked into the new build, so the finished run stays whole until the new
    one replaces it); a stage whose inputs changed, and every stage after it, is redone.
    ``overwrite`` redoes everything.
    """

    JOURNAL = "manifest.json"

    def __init__(self, target: str | Path, overwrite: bool = False) -> None:
        self._checker = RunDirectory(target, overwrite=True)
        self.given = self._checker.given
        self.target = self._checker.target
        self.overwrite = overwrite
        self.work = self.target.parent / f".{self.target.name}.partial"
        self._old = self.target.parent / f".{self.target.name}.old"
        self.journal: dict[str, Any] = {}
        self.resumed = False
        self._lock: DirectoryLock | None = None

    # -- opening -----------------------------------------------------------------------------
    def check(self) -> None:
        """Refuse early (before any work) a target that cannot or must not be written."""
        out = f"--out {self.given!r}"
        self._checker.check_location()
        try:
            if self.target.exists() and any(self.target.iterdir()):
                manifest = self.target / self.JOURNAL
                if not manifest.is_file():
                    raise InputError(f"{out}: not an earlier run (no manifest.json); not replaced")
                if not self.overwrite:
                    known = read_journal(manifest)
                    if known is None or known.get("kind") != "run":
                        raise InputError(
                            f"{out}: holds an ensemble or an unreadable manifest, not a single "
                            "run (use --overwrite to replace it)"
                        )
        except OSError as exc:
            raise InputError(f"{out}: {exc.strerror or exc}") from None

    def __enter__(self) -> StagedRun:
        self.check()
        self._lock = DirectoryLock(self.target, f"--out {self.given!r}")
        self._lock.acquire()
        try:
            self._open()
        except OSError as exc:
            self._lock.release()
            reason = exc.strerror or exc
            raise InputError(f"--out {self.given!r}: cannot create ({reason})") from None
        except BaseException:
            self._lock.release()
            raise
        return self

    def _open(self) -> None:
        if self._old.exists():  # left by a swap a crash cut short; the new run is in place
            shutil.rmtree(self._old, ignore_errors=True)
        if self.overwrite and self.work.exists():
            shutil.rmtree(self.work)
        if self.work.is_dir():
            journal = read_journal(self.work / self.JOURNAL)
            if journal is not None and journal.get("kind") == "run":
                self.journal, self.resumed = journal, True
                log.info("resuming the unfinished run in %s", self.work)
                for stale in self.work.glob(".*.tmp*"):  # a stage or file a kill cut short
                    remove(stale)
                return
            log.warning("%s: unreadable journal; starting the run again", self.work)
            shutil.rmtree(self.work)
        if not self.overwrite and (self.target / self.JOURNAL).is_file():
            shutil.copytree(self.target, self.work, copy_function=link_or_copy, symlinks=True)
            self.journal = read_journal(self.work / self.JOURNAL) or {}
            self.journal.setdefault("stages", {})
            return
        self.work.mkdir(parents=True)
        self.journal = {"tool": "chipstack", "kind": "run", "status": "running", "stages": {}}
        self._write_journal()

    # -- the journal -------------------------------------------------------------------------
    @property
    def stages(self) -> dict[str, Any]:
        stages = self.journal.setdefault("stages", {})
        if not isinstance(stages, dict):
            self.journal["stages"] = stages = {}
        return stages

    def _write_journal(self) -> None:
        self.journal["status"] = "running"
        write_atomically(self.work / self.JOURNAL, json.dumps(self.journal, indent=2) + "\n")

    @property
    def completed(self) -> list[str]:
        """The stages complete in the build, in order."""
        return [
            s
            for s in stage_names()
            if isinstance(self.stages.get(s), dict) and self.stages[s].get("status") == "complete"
        ]

    def reusable(self, stage: str, inputs: str) -> bool:
        """Whether ``stage`` is complete here with inputs hashing to ``inputs``."""
        entry = self.stages.get(stage)
        return (
            isinstance(entry, dict)
            and entry.get("status") == "complete"
            and entry.get("inputs_sha256") == inputs
            and (self.work / stage).is_dir()
        )

    def invalidate(self, stage: str) -> None:
        """Drop ``stage`` and every stage after it (their folders and journal entries)."""
        names = stage_names()
        for name in names[names.index(stage) :]:
            self.stages.pop(name, None)
            remove(self.work / name)
            for state in _state_files(self.work, name):
                state.unlink(missing_ok=True)
        self.journal["stages_completed"] = self.completed
        self._write_journal()

    def checkpoint(self, stage: str, inputs: str) -> RunCheckpoint:
        """Start ``stage`` (one that saves partial state), keeping what a killed run of it
        with the same inputs completed; the stage resumes through the returned object."""
        entry = self.stages.get(stage)
        if not (
            isinstance(entry, dict)
            and entry.get("status") == "running"
            and entry.get("inputs_sha256") == inputs
            and any(state.is_file() for state in _state_files(self.work, stage))
        ):
            self.invalidate(stage)
            self.stages[stage] = {"inputs_sha256": inputs, "status": "running"}
            self.stages[stage]["batches_completed"] = 0
            self._write_journal()
        return RunCheckpoint(self, stage)

    @contextlib.contextmanager
    def stage(self, name: str, inputs: str):
        """Build stage ``name``'s folder hidden; on success rename it into place and record
        it complete with the caller's summary (``record.summary``, ``record.warnings``)."""
        partial = self.work / f".{name}.tmp"
        remove(partial)
        partial.mkdir()
        record = StageRecord(partial)
        try:
            yield record
            for file in partial.rglob("*"):
                if file.is_file():
                    fsync_file(file)
            remove(self.work / name)
            os.replace(partial, self.work / name)
        except BaseException:
            remove(partial)
            raise
        entry = {"inputs_sha256": inputs, "status": "complete"}
        entry["completed_utc"] = now()
        entry.update(summary=record.summary, warnings=record.warnings)
        previous = self.stages.get(name)
        if isinstance(previous, dict) and "resumed_after_batch" in previous:
            entry["resumed_after_batch"] = previous["resumed_after_batch"]
        self.stages[name] = entry
        for state in _state_files(self.work, name):
            state.unlink(missing_ok=True)
        self.journal["stages_completed"] = self.completed
        self._write_journal()

    def folder(self, stage: str) -> Path:
        return self.work / stage

    def write_text(self, name: str, text: str) -> Path:
        return write_atomically(self.work / name, text)

    # -- closing -----------------------------------------------------------------------------
    def complete(self, manifest: dict[str, Any]) -> None:
        """Write the final manifest and put the run in place under its name."""
        stages = self.stages
        self.journal = manifest
        self.journal["stages"] = stages
        final = {**manifest, "status": "complete"}
        write_atomically(self.work / self.JOURNAL, json.dumps(final, indent=2) + "\n")
        if self.target.exists():
            os.replace(self.target, self._old)
        os.replace(self.work, self.target)
        shutil.rmtree(self._old, ignore_errors=True)

    def _kept(self) -> bool:
        """Whether the build holds work worth resuming (a batch or a stage)."""
        if not self.work.is_dir():
            return False
        return any(
            isinstance(e, dict) and (e.get("status") == "complete" or e.get("batches_completed"))
            for e in self.stages.values()
        )

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        try:
            self._close(exc_type, exc)
        finally:
            if self._lock is not None:
                self._lock.release()

    def _close(self, exc_type: object, exc: object) -> None:
        if exc_type is None:
            return
        out = f"--out {self.given!r}"
        keep = isinstance(exc, OSError | KeyboardInterrupt | StoppedEarly) and self._kept()
        if not keep:
            # Bad input or broken physics: the same command would fail the same way, so
            # what was done is of no use; nothing is left behind.
            shutil.rmtree(self.work, ignore_errors=True)
        where = f"the completed stages and batches are kept in {str(self.work)!r}"
        if isinstance(exc, KeyboardInterrupt):
            raise Interrupted(
                f"{where}: run the same command to resume" if keep else "nothing was written"
            ) from None
        if isinstance(exc, StoppedEarly):
            if keep:
                raise StoppedEarly(f"{exc}; {where}") from None
            raise StoppedEarly(f"{exc}; nothing was written") from None
        if isinstance(exc, OSError):
            reason = exc.strerror or str(exc)
            if keep:
                raise InputError(
                    f"{out}: cannot write the run ({reason}); {where}: free space or fix "
                    "the directory, then run the same command to resume"
                ) from None
            raise InputError(
                f"{out}: cannot write the run ({reason}); nothing was written"
            ) from None


class RunCheckpoint(Checkpoint):
    """A stage's partial state in the build: ``.STAGE-state.npz`` (and the one before it,
    ``.STAGE-state.prev.npz``), with the journal's count of completed steps (batches)
    and the SHA-256 of each good state file.

    A state file is written first and recorded in the journal after, and the previous
    good state is kept until the new one is recorded. So a file that a kill or a full disk
    cut short, or that was damaged later, fails its checksum: the stage resumes from the
    other one, or from the start, with one warning, and never sticks on it.
    """

    def __init__(self, run: StagedRun, stage: str) -> None:
        self.run, self.stage = run, stage
        self.path, self.previous = _state_files(run.work, stage)

    @property
    def _entry(self) -> dict[str, Any]:
        return self.run.stages[self.stage]

    def _good_states(self) -> dict[str, int]:
        """Checksum to batch count of the state files the journal recorded."""
        states = self._entry.get("states")
        if not isinstance(states, dict):
            return {}
        return {k: v for k, v in states.items() if isinstance(v, int) and v >= 0}

    def resume(self, decode):
        """``decode(arrays, where)`` of the latest good saved state, or None to start afresh
        (nothing saved, or nothing that passes its checksum and decodes)."""
        good = self._good_states()
        found = [p for p in (self.path, self.previous) if p.is_file()]
        damaged = []
        for path in found:
            count = good.get(file_sha256(path))
            if count is None:
                damaged.append(path)
                continue
            state = self._decode(path, decode)
            if state is None or getattr(state, "batches_done", None) != count:
                damaged.append(path)
                continue
            if damaged:
                log.warning(
                    "%s: damaged checkpoint (its checksum or contents differ from the "
                    "journal); resuming %s after batch %d from the one before it",
                    damaged[0],
                    self.stage,
                    count,
                )
            self._entry["batches_completed"] = count
            self._entry["resumed_after_batch"] = count
            self.run._write_journal()
            log.info("resuming %s after batch %d", self.stage, count)
            return state
        if damaged:
            log.warning(
                "%s: damaged checkpoint (its checksum or contents differ from the journal) "
                "and no good one before it; starting %s from the start",
                damaged[0],
                self.stage,
            )
        for path in found:
            path.unlink(missing_ok=True)
        self._entry["batches_completed"] = 0
        self._entry["states"] = {}
        self.run._write_journal()
        return None

    @staticmethod
    def _decode(path: Path, decode):
        import numpy as np  # here, not at the top: see save_npz_atomically

        try:
            with np.load(path, allow_pickle=False) as arrays:
                return decode(dict(arrays), str(path))
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, InputError):
            return None

    def save(self, arrays: dict[str, Any], done: int) -> None:
        """Record ``done`` completed batches: the state file first, then the journal; the
        state before it is kept until then."""
        good = self._good_states()
        if self.path.is_file():
            os.replace(self.path, self.previous)
        digest = save_npz_atomically(self.path, arrays)
        latest = max(good.values(), default=-1)  # the state just moved aside
        keep = {k: v for k, v in good.items() if v == latest}
        keep[digest] = done
        self._entry["states"] = keep
        self._entry["batches_completed"] = done
        self.run._write_journal()


def _state_files(work: Path, stage: str) -> tuple[Path, Path]:
    """The stage's latest saved state and the one before it."""
    return work / f".{stage}-state.npz", work / f".{stage}-state.prev.npz"
