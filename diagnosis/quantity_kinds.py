"""The quantity measures, registered by scenario kind: how a deposition of each kind is
reduced to the quantities a stack or container diagnosis compares. They are implemented
(and registered) by :mod:`diagnosis.stacks`, imported when one is first asked for:
listing the names loads no numerical library."""

from __future__ import annotations

from collections.abc import Callable

from chipstack.core.registry import Registry

__all__ = ["QUANTITY_MEASURES"]

QUANTITY_MEASURES: Registry[Callable] = Registry("quantity measure", "chipstack.quantity_measures")
QUANTITY_MEASURES.declare("chipstack.diagnosis.stacks", "stack", "container")
