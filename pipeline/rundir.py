"""The run directory: the only writer of files besides the exporters it hands paths to.

A run is built in a hidden sibling directory and renamed into place when it is complete,
so a failed or interrupted run leaves nothing half-written under the requested name.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path
from typing import Any

from packing.errors import InputError

__all__ = ["RunDirectory"]


class RunDirectory:
    """Context manager: ``with RunDirectory(out) as run: run.path("poses.csv") ...``."""

    def __init__(self, target: str | Path, overwrite: bool = False) -> None:
        self.target = Path(target)
        self.overwrite = overwrite
        self._partial = self.target.parent / f".{self.target.name}.partial-{os.getpid()}"

    def check(self) -> None:
        """Refuse early (before any work) if the target cannot be written."""
        if self.target.exists() and not self.target.is_dir():
            raise InputError(f"--out {self.target}: exists and is not a directory")
        if self.target.exists() and any(self.target.iterdir()) and not self.overwrite:
            raise InputError(
                f"--out {self.target}: directory exists and is not empty (use --overwrite)"
            )
        parent = self.target.parent if str(self.target.parent) else Path(".")
        if parent.exists() and not os.access(parent, os.W_OK):
            raise InputError(f"--out {self.target}: parent directory is not writable")

    def __enter__(self) -> RunDirectory:
        self.check()
        try:
            self._partial.mkdir(parents=True)
        except OSError as exc:
            raise InputError(f"--out {self.target}: cannot create ({exc.strerror})") from None
        return self

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
        return self.write_text(name, json.dumps(data, indent=2, sort_keys=False) + "\n")

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        if exc_type is not None:
            shutil.rmtree(self._partial, ignore_errors=True)
            return
        if self.target.exists():
            shutil.rmtree(self.target)
        os.replace(self._partial, self.target)
