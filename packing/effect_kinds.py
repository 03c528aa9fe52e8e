"""The unmodelled effects, registered by name: what a diagnosis, ``--effect`` and a
scenario's effects may name. Each built-in is one module of :mod:`packing.effects`
(numpy and scipy at its top) that ends with its object, named here by ``"module:OBJECT"``
and imported when first asked for: listing and checking the names loads no numerical
library. A new built-in is one new module and one name below."""

from __future__ import annotations

from typing import TYPE_CHECKING

from chipstack.core.registry import Registry

if TYPE_CHECKING:
    from chipstack.packing.effects.base import Effect

__all__ = ["EFFECTS"]

EFFECTS: Registry[Effect] = Registry("effect", "chipstack.effects")
# In this order (the order of the docs' table and of the diagnosis's candidates).
for _name in (
    "air_drag",
    "release_perturbation",
    "edge_rounding",
    "warp",
    "friction",
    "restitution",
    "compliant_floor",
    "vibration",
    "cohesion",
):
    EFFECTS.register_named(_name, f"chipstack.packing.effects.{_name}:{_name.upper()}")
