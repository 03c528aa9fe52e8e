"""The deposition sites, registered by scenario kind: where a kind's chips land and
what holds them. Each is declared by its object (in :mod:`packing.sites`, with numpy),
imported when first asked for: listing the names loads no numerical library."""

from __future__ import annotations

from typing import TYPE_CHECKING

from chipstack.core.registry import Registry

if TYPE_CHECKING:
    from chipstack.packing.sites import Site

__all__ = ["SITES"]

SITES: Registry[Site] = Registry("deposition site", "chipstack.sites")
for _kind, _object in (
    ("stack", "SQUARE_TARGET"),
    ("drop", "DROP_SITE"),
    ("container", "CYLINDER"),
    ("conveyor", "POUR_ZONE"),
):
    SITES.register_named(_kind, f"chipstack.packing.sites:{_object}")
