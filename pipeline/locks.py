"""A lock per output directory, so two runs never write the same place at once.

The lock is a file beside the directory (``.NAME.lock``) created atomically with
``O_EXCL``, holding the owner's process id, host and start time. A lock whose process
is gone (same host, no such process) is stale: it is removed with a warning and taken.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import socket
import time
from pathlib import Path

from chipstack.core.errors import InputError

__all__ = ["DirectoryLock", "lock_path"]

log = logging.getLogger(__name__)


def lock_path(target: Path) -> Path:
    return target.parent / f".{target.name}.lock"


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process: alive
        return True
    return True


class DirectoryLock:
    """``with DirectoryLock(target, shown):`` holds the lock of ``target`` for the block."""

    def __init__(self, target: Path, shown: str) -> None:
        self.target = Path(target)
        self.shown = shown
        self.path = lock_path(self.target)
        self._held = False

    def acquire(self) -> None:
        owner = {"pid": os.getpid(), "host": socket.gethostname(), "started": time.time()}
        for attempt in range(2):
            try:
                self.path.parent.mkdir(parents=True, exist_ok=True)
                fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            except FileExistsError:
                if attempt == 0 and self._remove_if_stale():
                    continue
                raise InputError(self._busy_message()) from None
            except OSError as exc:
                raise InputError(f"{self.shown}: cannot lock ({exc.strerror or exc})") from None
            try:
                with os.fdopen(fd, "w") as f:
                    json.dump(owner, f)
            except OSError as exc:  # a full disk: leave no empty lock behind
                self.path.unlink(missing_ok=True)
                raise InputError(f"{self.shown}: cannot lock ({exc.strerror or exc})") from None
            self._held = True
            return

    def _owner(self) -> dict | None:
        try:
            data = json.loads(self.path.read_text())
            return data if isinstance(data, dict) and isinstance(data.get("pid"), int) else None
        except (OSError, ValueError, RecursionError):
            return None

    def _remove_if_stale(self) -> bool:
        owner = self._owner()
        if owner is None:
            # Unreadable: a writer killed between creating and filling it, or garbage.
            # Give a live writer a moment to fill it in before calling it stale.
            time.sleep(0.2)
            owner = self._owner()
        stale = owner is None or (
            owner.get("host") == socket.gethostname() and not _alive(owner["pid"])
        )
        if not stale:
            return False
        who = f"process {owner['pid']}" if owner else "an unknown process"
        log.warning("%s: removed a stale lock left by %s (no longer running)", self.shown, who)
        with contextlib.suppress(FileNotFoundError):
            self.path.unlink()
        return True

    def _busy_message(self) -> str:
        owner = self._owner() or {}
        since = owner.get("started")
        when = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(since)) if since else "?"
        return (
            f"{self.shown}: another run (process {owner.get('pid', '?')} on "
            f"{owner.get('host', '?')}, since {when}) is writing it; wait for it to finish, "
            f"or delete {str(self.path)!r} if that process is gone"
        )

    def release(self) -> None:
        if self._held:
            owner = self._owner()
            if owner is None or owner.get("pid") == os.getpid():
                with contextlib.suppress(FileNotFoundError):
                    self.path.unlink()
            self._held = False

    def __enter__(self) -> DirectoryLock:
        self.acquire()
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()
