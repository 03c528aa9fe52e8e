"""Registries by name that refuse silent overwrite and list the valid names on a miss."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Generic, TypeVar

from core.errors import InputError

T = TypeVar("T")


class Registry(Generic[T]):
    """A name -> object mapping for one kind of pluggable thing (shapes, presets, ...)."""

    def __init__(self, kind: str) -> None:
        self.kind = kind
        self._items: dict[str, T] = {}

    def register(self, name: str, item: T) -> T:
        if name in self._items:
            raise KeyError(f"{self.kind} {name!r} is already registered")
        self._items[name] = item
        return item

    def get(self, name: str, key: str | None = None) -> T:
        """The item called ``name``; ``key`` names the config key in the error message."""
        try:
            return self._items[name]
        except KeyError:
            where = f"{key}: " if key else ""
            raise InputError(
                f"{where}unknown {self.kind} {name!r}; valid names: {', '.join(self.names())}"
            ) from None

    def names(self) -> list[str]:
        """The registered names, sorted (for messages and listings)."""
        return sorted(self._items)

    def in_order(self) -> list[str]:
        """The registered names in the order they were registered."""
        return list(self._items)

    def __contains__(self, name: object) -> bool:
        return name in self._items

    def __iter__(self) -> Iterator[str]:
        return iter(self.names())
