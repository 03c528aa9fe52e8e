"""The packing stage's stack writers, declared by name (the stack record and its time
series; plugins add more), and the loop that writes a settled stack with each.

Every command-line start loads the scenario kinds that write with these, and the
writers bring numpy, scipy and the packing's records: they are :mod:`packing.writers`'s
(with the drops', the container's and the conveyor mat's files and manifest entries),
which registers the declared names when a stack is first written."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from chipstack.core.registry import Registry

if TYPE_CHECKING:
    from chipstack.core.stack import Stack

__all__ = ["STACK_WRITERS", "StackWriter", "write_stack_files"]


@dataclass(frozen=True)
class StackWriter:
    """One kind of file the packing stage writes for a settled stack: what it is,
    the files it makes (shown in the docs) and whether later stages read it (``record``:
    always written; a plugin's writer is an extra and may be absent from older runs)."""

    name: str
    files: str  # the file names it writes, as the docs show them
    doc: str
    write: Callable[[Path, Stack], list[str]]  # (folder, stack) -> files written
    record: bool = False


STACK_WRITERS: Registry[StackWriter] = Registry("stack writer", "chipstack.stack_writers")
# The built-in writers, in the order they write (the exact record first).
STACK_WRITERS.declare("chipstack.packing.writers", "record", "poses", "contacts", "vtk")


def write_stack_files(folder: Path, stack: Stack) -> list[str]:
    """Every registered stack writer's files (the exact record first); returns the names
    written."""
    written: list[str] = []
    for name in STACK_WRITERS.in_order():
        written += STACK_WRITERS.get(name).write(folder, stack)
    return written
