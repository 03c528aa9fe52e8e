"""The quantity measures, registered by scenario kind: how a deposition of each kind is
reduced to the quantities a stack or container diagnosis compares, and those quantities
(``QUANTITIES``: what an observations file may name). The measures are implemented (and
registered) by :mod:`diagnosis.stacks`, imported when one is first asked for: listing the
names and reading observations load no numerical library."""

from __future__ import annotations

from collections.abc import Callable

from chipstack.core.registry import Registry

__all__ = ["MAX_LAYERS", "QUANTITIES", "QUANTITY_MEASURES"]

QUANTITY_MEASURES: Registry[Callable] = Registry("quantity measure", "chipstack.quantity_measures")
QUANTITY_MEASURES.declare("chipstack.diagnosis.stacks", "stack", "container")

# name -> (unit, meaning, kinds)
QUANTITIES: dict[str, tuple[str, str, tuple[str, ...]]] = {
    "volume_fraction": (
        "",
        "chip volume over the container's (containers: centres inside) or over "
        "the target area times the mean height (stacks)",
        ("stack", "container"),
    ),
    "chips_inside": ("", "chips whose centre of mass is inside the container", ("container",)),
    "height_mean_mm": ("mm", "mean height of the stack's top surface", ("stack",)),
    "height_max_mm": ("mm", "highest point of the stack", ("stack",)),
    "contacts_per_chip": ("", "contacts (point + line + surface) per chip", ("stack",)),
    "contacts_point_per_chip": ("", "point contacts per chip", ("stack",)),
    "contacts_line_per_chip": ("", "line contacts per chip", ("stack",)),
    "contacts_surface_per_chip": ("", "surface contacts per chip", ("stack",)),
}
MAX_LAYERS = 30
for _k in range(MAX_LAYERS):
    QUANTITIES[f"layer_filling_{_k}"] = (
        "",
        f"chips whose centre lies in layer {_k} (2 mm layers by default) over a full layer "
        "(target area over chip area)",
        ("stack",),
    )
