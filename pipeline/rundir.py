"""The run directory: the only writer of files besides the exporters it hands paths to.

A run is built in a hidden sibling directory and renamed into place when it is complete,
so a failed or interrupted run leaves nothing half-written under the requested name.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import shutil
from pathlib import Path
from typing import Any

from chipstack.core.errors import InputError, printable
from chipstack.pipeline.atomic import (
    read_journal,
    write_atomically,
)
from chipstack.pipeline.locks import DirectoryLock

__all__ = ["RunDirectory", "check_output_file", "StageWriter", "EnsembleDirectory"]

log = logging.getLogger(__name__)


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
                known = read_journal(state)
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
