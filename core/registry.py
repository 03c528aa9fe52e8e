"""Registries by name that refuse silent overwrite and list the valid names on a miss.

A registry given an entry-point group also holds what installed packages declare there
(``[project.entry-points."chipstack.shapes"]``, say: ``name = "module:object"``), loaded the
first time it is asked: a plugin adds a shape, descriptor, mesh kind or effect without
touching a file of the project (``tests/plugins`` holds one)."""

from __future__ import annotations

import importlib
from collections.abc import Iterator
from importlib import metadata
from typing import Any, Generic, TypeVar

from chipstack.core.errors import InputError
from chipstack.core.lazy import named

T = TypeVar("T")


class _Named:
    """An entry declared by the ``module:attribute`` that holds it, imported when first
    asked for: a registry of light declarations loads no numerical library."""

    def __init__(self, target: str) -> None:
        self.target = target

    def load(self) -> Any:
        return named(self.target)


class _Declared:
    """An entry whose object the module ``module`` registers when it is imported (its
    registry lists the name without importing it)."""

    def __init__(self, module: str) -> None:
        self.module = module


class Registry(Generic[T]):
    """A name -> object mapping for one kind of pluggable thing (shapes, presets, ...)."""

    def __init__(self, kind: str, entry_points: str | None = None) -> None:
        self.kind = kind
        self.entry_points = entry_points  # the group plugins declare their items in
        self._items: dict[str, T] = {}
        self._plugins_loaded = entry_points is None
        self._plugin_error: RuntimeError | None = None

    def register(self, name: str, item: T) -> T:
        if name in self._items and not isinstance(self._items[name], _Declared):
            raise KeyError(f"{self.kind} {name!r} is already registered")
        self._items[name] = item
        return item

    def declare(self, module: str, *names: str) -> None:
        """Declare ``names`` (in this order), registered by ``module`` when it is imported:
        the first :meth:`get` of one imports it (a module of light declarations lists
        what a heavy one implements)."""
        for name in names:
            self.register(name, _Declared(module))  # type: ignore[arg-type]

    def register_named(self, name: str, target: str) -> None:
        """Register ``name`` as the object at ``target`` (``"module:attribute"``), imported
        the first time it is asked for (:meth:`names` and ``in`` do not import it)."""
        self.register(name, _Named(target))  # type: ignore[arg-type]

    def _load_plugins(self) -> None:
        """Register what the installed packages declare in the entry-point group (once;
        a plugin that failed fails every later call the same way, not as an unknown
        name)."""
        if self._plugins_loaded:
            if self._plugin_error is not None:
                raise self._plugin_error
            return
        # Set first: a plugin module that imports this registry's module while it loads
        # must not start loading again.
        self._plugins_loaded = True
        for entry in sorted(metadata.entry_points(group=self.entry_points), key=lambda e: e.name):
            where = f"{self.kind} plugin {entry.name!r} ({entry.value})"
            try:
                item = entry.load()
            except Exception as exc:  # a broken plugin names itself, not a traceback deep in it
                self._plugin_error = RuntimeError(f"{where} failed to load: {exc}")
                raise self._plugin_error from exc
            if entry.name in self._items:
                self._plugin_error = RuntimeError(f"{where}: the name is already a {self.kind}")
                raise self._plugin_error
            self._items[entry.name] = item

    def get(self, name: str, key: str | None = None) -> T:
        """The item called ``name``; ``key`` names the config key in the error message."""
        self._load_plugins()
        try:
            item = self._items[name]
        except KeyError:
            where = f"{key}: " if key else ""
            raise InputError(
                f"{where}unknown {self.kind} {name!r}; valid names: {', '.join(self.names())}"
            ) from None
        if isinstance(item, _Named):
            item = self._items[name] = item.load()
        elif isinstance(item, _Declared):
            importlib.import_module(item.module)
            item = self._items[name]
            if isinstance(item, _Declared):  # a packaging error, not user input
                raise RuntimeError(f"{item.module} does not register {self.kind} {name!r}")
        return item

    def names(self) -> list[str]:
        """The registered names, sorted (for messages and listings)."""
        self._load_plugins()
        return sorted(self._items)

    def in_order(self) -> list[str]:
        """The registered names in the order they were registered (plugins last)."""
        self._load_plugins()
        return list(self._items)

    def __contains__(self, name: object) -> bool:
        self._load_plugins()
        return name in self._items

    def __iter__(self) -> Iterator[str]:
        return iter(self.names())
