"""The one place pybullet is imported (quietly): the physics world and V-HACD use it."""

from __future__ import annotations

import ctypes
import os
import sys

__all__ = ["pybullet", "vhacd"]


def _import_pybullet_quietly():
    # pybullet prints its build time to stderr from C on import: noise in a one-line error.
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "w") as devnull:
            os.dup2(devnull.fileno(), 2)
            import pybullet as module

            ctypes.CDLL(None).fflush(None)  # the C buffer, before fd 2 is restored
    finally:
        os.dup2(saved, 2)
        os.close(saved)
    return module


pybullet = _import_pybullet_quietly()


def vhacd(source: str, target: str, log_file: str) -> None:
    """Approximate convex decomposition of the OBJ ``source`` into the OBJ ``target``."""
    pybullet.vhacd(
        source,
        target,
        log_file,
        resolution=1000000,
        concavity=1e-4,
        depth=32,
        maxNumVerticesPerCH=64,
    )
