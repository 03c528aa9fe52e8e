"""Package attributes imported on first use (PEP 562).

The stage registry imports every stage module, hence its package's ``__init__``, at each
command-line start; a package that re-exported its numerical modules eagerly would make
even ``python -m pipeline --help`` import numpy, scipy, pybullet and gmsh (over a second).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from typing import Any

__all__ = ["lazy_attributes"]


def lazy_attributes(namespace: dict[str, Any], sources: Mapping[str, str]) -> Callable[[str], Any]:
    """A module ``__getattr__`` for the module whose ``globals()`` is ``namespace``:
    attribute ``name`` is imported from module ``sources[name]`` when first asked for,
    and kept in the module afterwards."""
    package = namespace["__name__"]

    def __getattr__(name: str) -> Any:
        if name not in sources:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(sources[name]), name)
        namespace[name] = value  # found directly from now on
        return value

    return __getattr__
