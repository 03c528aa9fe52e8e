"""The run directory: the only writer of files besides the exporters it hands paths to.

A run is built in a hidden sibling directory and renamed into place when it is complete,
so a failed or interrupted run leaves nothing half-written under the requested name.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import logging
import os
import shutil
import zipfile
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from chipstack.core.errors import InputError, printable
from chipstack.core.files import file_sha256, read_json
from chipstack.core.stages import Checkpoint, stage_names
from chipstack.pipeline.locks import DirectoryLock

__all__ = [
    "RunDirectory",
    "check_output_file",
    "StagedRun",
    "StageWriter",
    "EnsembleDirectory",
    "Interrupted",
    "write_atomically",
    "save_npz_atomically",
]

log = logging.getLogger(__name__)

MAX_JOURNAL_BYTES = 16 * 2**20  # a journal or manifest is a few kB to a few hundred


def _nearest_existing(path: Path) -> Path:
    for candidate in (path, *path.parents):
        if candidate.exists():
            return candidate
    return Path("/")


def check_output_file(given: str | Path, shown: str, overwrite: bool) -> Path:
    """The absolute path of an output file (``~`` expanded), refused early in one line
    naming ``shown`` if it is a directory, exists without ``overwrite``, or cannot be
    written; the file itself is then written to a temporary name and renamed."""
    try:
        target = Path(given).expanduser().absolute()
        if target.is_dir():
            raise InputError(f"{shown}: is a directory")
        if target.exists() and not overwrite:
            raise InputError(f"{shown}: file exists (use --overwrite)")
        if target.exists() and not os.access(target, os.W_OK):
            raise InputError(f"{shown}: cannot replace it (read-only or immutable)")
        if not target.parent.is_dir() or not os.access(target.parent, os.W_OK | os.X_OK):
            raise InputError(f"{shown}: cannot write in {printable(str(target.parent))}")
    except OSError as exc:
        raise InputError(f"{shown}: {exc.strerror or exc}") from None
    return target


class RunDirectory:
    """Context manager: ``with RunDirectory(out) as run: run.path("poses.csv") ...``.

    Only an empty directory or an earlier run (a directory holding ``manifest.json``) is
    ever replaced, and only with ``overwrite``; the current directory and its ancestors
    never are.
    """

    def __init__(self, target: str | Path, overwrite: bool = False) -> None:
        self.given = str(target)
        self.overwrite = overwrite
        try:
            self.target = Path(target).expanduser().absolute()
            self.target = self.target.parent.resolve() / self.target.name
        except (OSError, RuntimeError) as exc:
            raise InputError(f"--out {self.given!r}: unusable path ({exc})") from None
        self._partial = self.target.parent / f".{self.target.name}.partial-{os.getpid()}"

    def check(self) -> None:
        """Refuse early (before any work) if the target cannot or must not be written."""
        out = f"--out {self.given!r}"
        self.check_location()
        try:
            if self.target.exists():
                entries = list(self.target.iterdir())
                if entries and not self.overwrite:
                    raise InputError(f"{out}: directory exists and is not empty (use --overwrite)")
                if entries and not (self.target / "manifest.json").is_file():
                    raise InputError(f"{out}: not an earlier run (no manifest.json); not replaced")
        except OSError as exc:
            raise InputError(f"{out}: {exc.strerror or exc}") from None

    def check_location(self) -> None:
        """Refuse the current directory, its parents, links, files and unwritable places."""
        out = f"--out {self.given!r}"
        try:
            if self.target.name in ("", ".", ".."):
                raise InputError(f"{out}: not a usable run directory name")
            here = Path.cwd().resolve()
            if self.target == here or self.target in here.parents:
                raise InputError(f"{out}: is the current directory or one of its parents")
            if self.target.is_symlink():
                raise InputError(f"{out}: is a symbolic link; give the real directory")
            if self.target.exists() and not self.target.is_dir():
                raise InputError(f"{out}: exists and is not a directory")
            if self.target.is_dir() and not os.access(self.target, os.W_OK | os.X_OK):
                raise InputError(f"{out}: cannot write in it (read-only or immutable)")
            ancestor = _nearest_existing(self.target.parent)
            if not ancestor.is_dir() or not os.access(ancestor, os.W_OK | os.X_OK):
                raise InputError(f"{out}: cannot write under {str(ancestor)!r}")
        except OSError as exc:
            raise InputError(f"{out}: {exc.strerror or exc}") from None

    def __enter__(self) -> RunDirectory:
        self.check()
        self._lock = DirectoryLock(self.target, f"--out {self.given!r}")
        self._lock.acquire()
        try:
            self._partial.mkdir(parents=True)
        except OSError as exc:
            self._lock.release()
            raise InputError(f"--out {self.given!r}: cannot create ({exc.strerror})") from None
        return self

    @property
    def folder(self) -> Path:
        """The directory being built (renamed to the target when complete)."""
        return self._partial

    def path(self, name: str) -> Path:
        """Where to write ``name`` (relative to the run directory); folders are created."""
        path = self._partial / name
        path.parent.mkdir(parents=True, exist_ok=True)
        return path

    def write_text(self, name: str, text: str) -> Path:
        path = self.path(name)
        path.write_text(text, encoding="utf-8")
        return path

    def write_json(self, name: str, data: Any) -> Path:
        return self.write_text(name, json.dumps(data, indent=2) + "\n")

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        try:
            self._finish(exc_type, exc)
        finally:
            self._lock.release()

    def _finish(self, exc_type: object, exc: object) -> None:
        if exc_type is not None:
            shutil.rmtree(self._partial, ignore_errors=True)
            if isinstance(exc, OSError):  # a full disk, a vanished directory, ...
                raise InputError(
                    f"--out {self.given!r}: cannot write the run ({exc.strerror or exc})"
                ) from None
            return
        try:
            if self.target.exists():
                shutil.rmtree(self.target)
            os.replace(self._partial, self.target)
        except OSError as error:
            shutil.rmtree(self._partial, ignore_errors=True)
            raise InputError(
                f"--out {self.given!r}: cannot write the run ({error.strerror or error})"
            ) from None


class StageWriter:
    """Context manager adding one stage's folder to an existing run directory.

    ``with StageWriter(run, "geometry") as folder: ...`` builds the folder hidden inside the
    run and swaps it in only when the block completes, so an error or interruption leaves
    the run as it was.
    """

    def __init__(self, run_dir: str | Path, name: str) -> None:
        self.run = Path(run_dir)
        self.name = name
        self._partial = self.run / f".{name}.partial-{os.getpid()}"

    def __enter__(self) -> Path:
        if not os.access(self.run, os.W_OK | os.X_OK):
            raise InputError(f"{str(self.run)!r}: run directory is not writable")
        self._lock = DirectoryLock(self.run.absolute(), repr(str(self.run)))
        self._lock.acquire()
        try:
            self._partial.mkdir()
        except OSError as exc:
            self._lock.release()
            raise InputError(f"{str(self.run)!r}: cannot write ({exc.strerror})") from None
        return self._partial

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        try:
            self._finish(exc_type, exc)
        finally:
            self._lock.release()

    def _finish(self, exc_type: object, exc: object) -> None:
        if exc_type is not None:
            shutil.rmtree(self._partial, ignore_errors=True)
            if isinstance(exc, OSError):
                raise InputError(
                    f"{str(self.run)!r}: cannot write the {self.name} stage ({exc.strerror or exc})"
                ) from None
            return
        final = self.run / self.name
        old = self.run / f".{self.name}.old-{os.getpid()}"
        try:
            if final.exists():
                os.replace(final, old)
            os.replace(self._partial, final)
        except OSError as error:
            shutil.rmtree(self._partial, ignore_errors=True)
            raise InputError(
                f"{str(self.run)!r}: cannot write the {self.name} stage ({error.strerror})"
            ) from None
        shutil.rmtree(old, ignore_errors=True)


class EnsembleDirectory:
    """An ensemble's directory, written run by run so an interrupted ensemble resumes.
    Use as a context manager: it holds the directory's lock.

    While unfinished it holds ``ensemble-state.json`` (what the ensemble is: scenario hash,
    seed, repeats, ...). Each run is built hidden and renamed to ``repeat_K`` when written;
    the ensemble's own files are moved in at the end, and the state file removed. Started
    again with the same arguments, the ensemble skips the runs already there.
    """

    STATE = "ensemble-state.json"

    def __init__(self, target: str | Path, identity: dict[str, Any], overwrite: bool = False):
        self.given = str(target)
        self.identity = identity
        self.target = Path(target).expanduser().absolute()
        self._created = False
        out = f"--out {self.given!r}"
        checker = RunDirectory(target, overwrite=True)
        checker.check_location()
        self.target = checker.target
        self.resuming = False
        self._clear_first = False
        if self.target.exists():
            entries = list(self.target.iterdir())
            state = self.target / self.STATE
            if state.is_file():
                known = _read_journal(state)
                if overwrite:
                    self._clear_first = True
                elif known == identity:
                    self.resuming = True
                    self._created = True
                else:
                    raise InputError(
                        f"{out}: holds an unfinished ensemble of other settings "
                        "(use --overwrite to start again)"
                    )
            elif entries:
                if not (self.target / "manifest.json").is_file():
                    raise InputError(f"{out}: not an earlier run (no manifest.json); not replaced")
                if not overwrite:
                    raise InputError(
                        f"{out}: holds a finished run or ensemble (use --overwrite to replace it)"
                    )
                self._clear_first = True

    def __enter__(self) -> EnsembleDirectory:
        """Holds the directory's lock while the ensemble runs."""
        self._lock = DirectoryLock(self.target, f"--out {self.given!r}")
        self._lock.acquire()
        return self

    def __exit__(self, *exc: object) -> None:
        self._lock.release()

    def _clear(self) -> None:
        shutil.rmtree(self.target)

    def _ensure(self) -> None:
        if self._created:
            return
        try:
            if self._clear_first:  # only now: a failure before any result keeps the old one
                self._clear()
                self._clear_first = False
            self.target.mkdir(parents=True, exist_ok=True)
            write_atomically(self.target / self.STATE, json.dumps(self.identity, indent=2) + "\n")
        except OSError as exc:
            raise InputError(f"--out {self.given!r}: cannot create ({exc.strerror})") from None
        self._created = True

    def finished(self, names: list[str]) -> set[str]:
        """The runs already written (from an interrupted earlier start)."""
        if not self.resuming:
            return set()
        for stale in self.target.glob(".*.partial-*"):  # left by a killed earlier start
            shutil.rmtree(stale, ignore_errors=True)
        return {n for n in names if (self.target / n / "manifest.json").is_file()}

    def file(self, name: str) -> Path:
        return self.target / name

    @contextlib.contextmanager
    def run(self, name: str):
        """Yields ``path(relative name) -> Path`` inside a hidden folder renamed to ``name``."""
        self._ensure()
        partial = self.target / f".{name}.partial-{os.getpid()}"
        shutil.rmtree(partial, ignore_errors=True)

        def path(relative: str) -> Path:
            p = partial / relative
            p.parent.mkdir(parents=True, exist_ok=True)
            return p

        try:
            yield path
            final = self.target / name
            if final.exists():
                shutil.rmtree(final)
            os.replace(partial, final)
        except BaseException:
            shutil.rmtree(partial, ignore_errors=True)
            raise

    def complete(self, finish) -> None:
        """Write the ensemble's own files with ``finish(path)`` and mark it finished."""
        with self.run(".complete") as path:
            finish(path)
        staged = self.target / ".complete"
        for item in staged.iterdir():
            destination = self.target / item.name
            if destination.is_dir():
                shutil.rmtree(destination)
            os.replace(item, destination)
        staged.rmdir()
        (self.target / self.STATE).unlink(missing_ok=True)


# -- single runs: built stage by stage, resumable, cached ----------------------------------


class Interrupted(KeyboardInterrupt):
    """An interrupted run; ``hint`` says what was kept (for the one-line message)."""

    def __init__(self, hint: str) -> None:
        super().__init__(hint)
        self.hint = hint


def _fsync_file(path: Path) -> None:
    with open(path, "rb") as f:
        os.fsync(f.fileno())


def write_atomically(path: Path, data: bytes | str) -> Path:
    """Write ``path`` through a temporary sibling renamed over it: a reader (or a run
    resumed after a crash) sees the old file or the new one, never a part."""
    temporary = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        with open(temporary, "wb") as f:
            f.write(data.encode("utf-8") if isinstance(data, str) else data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(temporary, path)
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise
    return path


def save_npz_atomically(path: Path, arrays: dict[str, Any]) -> str:
    """Write ``arrays`` as an ``.npz`` file atomically; returns the SHA-256 of its bytes."""
    import numpy as np  # here: every run imports this module before its scenario's checks

    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    data = buffer.getvalue()
    write_atomically(path, data)
    return hashlib.sha256(data).hexdigest()


def _link_or_copy(source: str, destination: str) -> None:
    # Hard links cost nothing; every later write replaces a file (rename) or writes a new
    # one, so the linked original is never changed. Where links fail, copy.
    try:
        os.link(source, destination)
    except OSError:
        shutil.copy2(source, destination)


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
                    known = _read_journal(manifest)
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
            journal = _read_journal(self.work / self.JOURNAL)
            if journal is not None and journal.get("kind") == "run":
                self.journal, self.resumed = journal, True
                log.info("resuming the unfinished run in %s", self.work)
                for stale in self.work.glob(".*.tmp*"):  # a stage or file a kill cut short
                    _remove(stale)
                return
            log.warning("%s: unreadable journal; starting the run again", self.work)
            shutil.rmtree(self.work)
        if not self.overwrite and (self.target / self.JOURNAL).is_file():
            shutil.copytree(self.target, self.work, copy_function=_link_or_copy, symlinks=True)
            self.journal = _read_journal(self.work / self.JOURNAL) or {}
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
            _remove(self.work / name)
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
        _remove(partial)
        partial.mkdir()
        record = StageRecord(partial)
        try:
            yield record
            for file in partial.rglob("*"):
                if file.is_file():
                    _fsync_file(file)
            _remove(self.work / name)
            os.replace(partial, self.work / name)
        except BaseException:
            _remove(partial)
            raise
        entry = {"inputs_sha256": inputs, "status": "complete"}
        entry["completed_utc"] = _now()
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
        keep = isinstance(exc, OSError | KeyboardInterrupt) and self._kept()
        if not keep:
            # Bad input or broken physics: the same command would fail the same way, so
            # what was done is of no use; nothing is left behind.
            shutil.rmtree(self.work, ignore_errors=True)
        where = f"the completed stages and batches are kept in {str(self.work)!r}"
        if isinstance(exc, KeyboardInterrupt):
            raise Interrupted(
                f"{where}: run the same command to resume" if keep else "nothing was written"
            ) from None
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


def _read_journal(path: Path) -> dict[str, Any] | None:
    """The JSON table at ``path``, or None when it is missing, damaged or not a table."""
    try:
        data = read_json(path, "journal", MAX_JOURNAL_BYTES)
    except InputError:
        return None
    return data if isinstance(data, dict) else None


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)


def _now() -> str:
    return datetime.now(UTC).isoformat(timespec="seconds")
