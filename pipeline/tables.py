"""Where the diagnosis keeps its reference tables: a directory of named files, written
atomically (a killed build leaves whole pools or none), shared by every diagnosis on the
machine. The default is the user's cache directory (``$XDG_CACHE_HOME/chipstack/tables``
or ``~/.cache/chipstack/tables``); ``pipeline diagnose --tables DIR`` chooses another."""

from __future__ import annotations

import os
import re
from pathlib import Path

from chipstack.core.errors import InputError, printable
from chipstack.pipeline.atomic import write_atomically

__all__ = ["DirectoryStore", "default_tables_dir"]

_NAME = re.compile(r"^[A-Za-z0-9_.+-]+$")


def default_tables_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "chipstack" / "tables"


class DirectoryStore:
    """A :class:`diagnosis.reference_table.TableStore` in a directory (made on first
    write)."""

    def __init__(self, path: str | Path, shown: str = "--tables") -> None:
        self.path = Path(path).expanduser()
        self.shown = shown
        if self.path.exists() and not self.path.is_dir():
            raise InputError(f"{shown} {printable(str(self.path))}: is not a directory")

    def _file(self, name: str) -> Path:
        if not _NAME.match(name):
            raise ValueError(f"table entry name {name!r} has characters a file name cannot")
        return self.path / name

    def load(self, name: str) -> bytes | None:
        path = self._file(name)
        try:
            return path.read_bytes()
        except FileNotFoundError:
            return None

    def save(self, name: str, blob: bytes) -> None:
        try:
            self.path.mkdir(parents=True, exist_ok=True)
            write_atomically(self._file(name), blob)
        except OSError as exc:
            raise InputError(
                f"{self.shown} {printable(str(self.path))}: cannot write ({exc.strerror or exc})"
            ) from None
