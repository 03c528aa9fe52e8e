"""Files written so that a reader, or a run resumed after a crash, sees the old file or
the new one, never a part; journals read back whole or not at all."""

from __future__ import annotations

import hashlib
import io
import os
import shutil
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from chipstack.core.errors import InputError
from chipstack.core.files import read_json

__all__ = [
    "write_atomically",
    "save_npz_atomically",
    "link_or_copy",
    "read_journal",
    "remove",
    "now",
    "MAX_JOURNAL_BYTES",
]

MAX_JOURNAL_BYTES = 16 * 2**20  # a journal or manifest is a few kB to a few hundred


def fsync_file(path: Path) -> None:
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


def link_or_copy(source: str, destination: str) -> None:
    # Hard links cost nothing; every later write replaces a file (rename) or writes a new
    # one, so the linked original is never changed. Where links fail, copy.
    try:
        os.link(source, destination)
    except OSError:
        shutil.copy2(source, destination)


def read_journal(path: Path) -> dict[str, Any] | None:
    """The JSON table at ``path``, or None when it is missing, damaged or not a table."""
    try:
        data = read_json(path, "journal", MAX_JOURNAL_BYTES)
    except InputError:
        return None
    return data if isinstance(data, dict) else None


def remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)


def now() -> str:
    return datetime.now(UTC).isoformat(timespec="seconds")
