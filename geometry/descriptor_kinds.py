"""The descriptors, registered by name: what ``--descriptors`` and a stack's description
may name. They are implemented (and registered) by :mod:`geometry.describe`, with numpy,
scipy and manifold3d, imported when one is first asked for: listing the names loads no
numerical library."""

from __future__ import annotations

from typing import TYPE_CHECKING

from chipstack.core.registry import Registry

if TYPE_CHECKING:
    from chipstack.geometry.describe import Descriptor

__all__ = ["DESCRIPTORS"]

DESCRIPTORS: Registry[Descriptor] = Registry("descriptor", "chipstack.descriptors")
DESCRIPTORS.declare(
    "chipstack.geometry.describe",
    "contacts",
    "thickness",
    "layers",
    "overlaps",
    "orientation",
    "stack",
    "voxels",
)
