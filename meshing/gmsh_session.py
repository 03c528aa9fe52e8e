"""A gmsh session as a context manager: one fresh model, finalised on exit even on error
(gmsh keeps one global state per process). Its own module so that every mesher and the
sliver removal can open one without importing each other."""

from __future__ import annotations

import threading

__all__ = ["GmshSession"]

_LOCK = threading.Lock()


class GmshSession:
    """``with GmshSession() as gmsh:`` a fresh gmsh model, finalised on exit even on error.

    gmsh keeps one global state per process, so sessions cannot nest or overlap.
    """

    def __init__(self, threads: int = 1) -> None:
        self.threads = threads

    def __enter__(self):
        import gmsh

        if not _LOCK.acquire(blocking=False):
            raise RuntimeError("a gmsh session is already open in this process")
        try:
            gmsh.initialize(readConfigFiles=False, interruptible=False)
            gmsh.option.setNumber("General.Terminal", 0)
            gmsh.option.setNumber("General.NumThreads", self.threads)
            gmsh.model.add("stack")
        except Exception:
            _LOCK.release()
            raise
        self._gmsh = gmsh
        return gmsh

    def __exit__(self, *exc: object) -> None:
        try:
            self._gmsh.finalize()
        finally:
            _LOCK.release()
