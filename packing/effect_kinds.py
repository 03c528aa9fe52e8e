"""The unmodelled effects, registered by name: what a diagnosis, ``--effect`` and a
scenario's effects may name. Each is declared by the object that implements it (in
:mod:`packing.effects`, with numpy and scipy), imported when first asked for: listing
and checking the names loads no numerical library."""

from __future__ import annotations

from typing import TYPE_CHECKING

from chipstack.core.registry import Registry

if TYPE_CHECKING:
    from chipstack.packing.effects import Effect

__all__ = ["EFFECTS"]

EFFECTS: Registry[Effect] = Registry("effect", "chipstack.effects")
for _name, _object in (
    ("air_drag", "AIR_DRAG"),
    ("release_perturbation", "RELEASE_PERTURBATION"),
    ("edge_rounding", "EDGE_ROUNDING"),
    ("warp", "WARP"),
    ("friction", "FRICTION"),
    ("restitution", "RESTITUTION"),
    ("compliant_floor", "COMPLIANT_FLOOR"),
    ("vibration", "VIBRATION"),
    ("cohesion", "COHESION"),
):
    EFFECTS.register_named(_name, f"chipstack.packing.effects:{_object}")
