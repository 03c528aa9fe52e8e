"""The descriptors, registered by name: what ``--descriptors`` and a stack's description
may name. Each built-in is one module of :mod:`geometry.descriptors` that ends with its
``DESCRIPTOR`` (numpy, scipy and manifold3d at its top), named here by
``"module:DESCRIPTOR"`` and imported when it is first asked for: listing the names loads
no numerical library. A new built-in is one new module and one line below."""

from __future__ import annotations

from typing import TYPE_CHECKING

from chipstack.core.registry import Registry

if TYPE_CHECKING:
    from chipstack.geometry.descriptors.base import Descriptor

__all__ = ["DESCRIPTORS"]

DESCRIPTORS: Registry[Descriptor] = Registry("descriptor", "chipstack.descriptors")
# In this order: the order of descriptors.json's sections (Descriptor.order sets that of
# the columns and the reports).
for _name in (
    "contacts",
    "thickness",
    "layers",
    "overlaps",
    "orientation",
    "stack",
    "voxels",
    "coverage",
):
    DESCRIPTORS.register_named(_name, f"chipstack.geometry.descriptors.{_name}:DESCRIPTOR")
