"""Packages whose re-exported names are imported on first use, and objects named by
``"module:attribute"`` imported when first used.

A light declaration (a shape, a mesh kind, a stage) names the heavy object that does its
work by such a string, resolved by :func:`named`: the declarations load at every start
without the numerical libraries, and the implementing modules import theirs at the top.

The stage registry imports every stage module, hence its package's ``__init__``, at each
command-line start; a package that re-exported its numerical modules eagerly would make
even ``python -m chipstack.pipeline --help`` import numpy, scipy, pybullet and gmsh (over a second).
"""

from __future__ import annotations

import importlib
import sys
import types
from collections.abc import Mapping
from typing import Any

__all__ = ["lazy_package", "named"]


def named(target: str) -> Any:
    """The object ``target`` names (``"package.module:attribute"``), its module imported
    on the first call (Python keeps it: later calls only look it up)."""
    module, _, attribute = target.partition(":")
    return getattr(importlib.import_module(module), attribute)


class _LazyPackage(types.ModuleType):
    """A package module whose names in ``_lazy_sources`` are imported when first read."""

    def __getattr__(self, name: str) -> Any:  # only called for names not bound yet
        source = self.__dict__["_lazy_sources"].get(name)
        if source is None:
            raise AttributeError(f"module {self.__name__!r} has no attribute {name!r}")
        value = named(f"{source}:{name}")
        self.__dict__[name] = value  # found directly from now on
        return value

    def __setattr__(self, name: str, value: Any) -> None:
        # The import system binds each submodule it loads in its package. A name the
        # package re-exports from the submodule of the same name (``geometry.describe``,
        # the function) stays the re-exported object, as the eager import left it.
        if isinstance(value, types.ModuleType):
            if self.__dict__["_lazy_sources"].get(name) == value.__name__:
                value = getattr(value, name)
        super().__setattr__(name, value)


def lazy_package(name: str, sources: Mapping[str, str]) -> None:
    """Make package ``name`` (call it from its ``__init__`` with ``__name__``) import
    attribute ``attr`` from module ``sources[attr]`` when it is first read. A light module
    does the same for names it held before they moved to a heavy one."""
    module = sys.modules[name]
    module.__dict__["_lazy_sources"] = dict(sources)
    module.__class__ = _LazyPackage
