"""The mesh formats, registered by name: what ``mesh.formats`` and ``--formats`` may ask
for. Each is declared by the writer that makes it (in :mod:`meshing.files`, with numpy
and meshio), imported when a mesh is written: checking a scenario's formats loads no
numerical library."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from chipstack.core.registry import Registry

if TYPE_CHECKING:
    from chipstack.meshing.mesh import VolumeMesh

__all__ = ["MESH_FORMATS"]

MESH_FORMATS: Registry[Callable[[Path, VolumeMesh], list[Path]]] = Registry(
    "mesh format", "chipstack.mesh_formats"
)
for _name in ("vtu", "msh", "xdmf", "inp"):
    MESH_FORMATS.register_named(_name, f"chipstack.meshing.files:write_{_name}")
