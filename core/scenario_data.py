"""A scenario from its data and back: every value typed and checked against its key's
declaration (:mod:`core.schema`), tables assembled from the stages that own them, file
keys made absolute (:func:`scenario_from_dict`), and the resolved scenario as plain
TOML values (:func:`scenario_to_dict`)."""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Mapping
from typing import Any

from chipstack.core.errors import InputError, brief, printable
from chipstack.core.keys import (
    MAX_SEED,
)
from chipstack.core.schema import (
    ChipSpec,
    KindChoice,
    KindKeys,
    Scenario,
    kind_choice,
    parameter_fields,
    sections,
    tables_of,
)
from chipstack.core.stages import load_stages

__all__ = ["scenario_from_dict", "scenario_to_dict", "known_kinds"]


def _coerce(path: str, value: Any, annotation: str) -> Any:
    """Convert a TOML value to the declared type or raise naming the key."""

    def bad(expected: str) -> InputError:
        return InputError(f"{path}: expected {expected}, got {type(value).__name__} {brief(value)}")

    if annotation == "str":
        if not isinstance(value, str):
            raise bad("a string")
        return value
    if annotation == "bool":
        if not isinstance(value, bool):
            raise bad("true or false")
        return value
    if annotation == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            raise bad("an integer")
        return value
    if annotation == "float":
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise bad("a number")
        if not math.isfinite(value):
            raise InputError(f"{path}: must be finite, got {brief(value)}")
        return float(value)
    if annotation == "tuple[str, ...]":
        if not isinstance(value, list | tuple) or not all(isinstance(v, str) for v in value):
            raise bad("a list of strings")
        return tuple(value)
    if annotation.startswith("tuple[float"):
        if not isinstance(value, list | tuple):
            raise bad("a list of numbers")
        items = tuple(_coerce(f"{path}[{i}]", v, "float") for i, v in enumerate(value))
        if annotation == "tuple[float, float]" and len(items) != 2:
            raise InputError(f"{path}: expected a pair [low, high], got {len(items)} values")
        return items
    raise TypeError(f"undeclared type {annotation} for {path}")  # a bug here, not user input


def _value(path: str, f: dataclasses.Field, raw: Any) -> Any:
    """One key's TOML value converted to its declared type and checked."""
    value = _coerce(path, raw, str(f.type))
    check = f.metadata.get("check")
    problem = check(value) if check else None
    if problem:
        raise InputError(f"{path}: {problem} (got {brief(value)})")
    return value


def _unknown(key: Any, declared: Any, prefix: str) -> InputError:
    where = f"[{prefix}]" if prefix else "the top level"
    return InputError(
        f"{prefix + '.' if prefix else ''}{printable(key)}: unknown key in {where}; "
        f"valid keys: {', '.join(sorted(declared))}"
    )


def _build(
    cls: type, table: Mapping[str, Any], prefix: str, tables: Mapping[str, Any] | None = None
) -> Any:
    """A flat table (the chip, a section) from its TOML mapping; a table that chooses a
    kind (:class:`KindKeys`) takes its own keys and the chosen kind's (``tables``: the
    scenario's tables built so far, which a kind that follows from them is read from)."""
    if not isinstance(table, Mapping):
        raise InputError(f"{prefix}: expected a table, got {type(table).__name__}")
    declared = {f.name: f for f in dataclasses.fields(cls) if f.name != "params"}
    values: dict[str, Any] = {}
    if issubclass(cls, KindKeys):
        choice = kind_choice(cls.table)
        selector = declared[cls.selector]
        if choice.follows is not None:
            del declared[cls.selector]  # not a key of the file
            values[cls.selector] = choice.follows(tables or {})
        elif cls.selector in table:
            values[cls.selector] = _value(f"{prefix}.{cls.selector}", selector, table[cls.selector])
        kind = values.get(cls.selector, selector.default)
        parameters = choice.parameters_of(kind, f"{prefix}.{cls.selector}")
        declared.update(parameter_fields(parameters))
        for key_ in table:
            if key_ not in declared:
                raise _not_of_kind(key_, choice, kind, cls.table, declared, prefix)
    for key_ in table:
        if key_ not in declared:
            raise _unknown(key_, declared, prefix)
    values.update(
        {
            name: _value(f"{prefix}.{name}", f, table[name])
            for name, f in declared.items()
            if name in table
        }
    )
    if issubclass(cls, KindKeys):
        built = cls(**values)
        built.params.check(prefix)
        return built
    return cls(**values)


def _not_of_kind(
    key_: Any, choice: KindChoice, kind: str, table: str, declared: Mapping, prefix: str
) -> InputError:
    """A key the chosen kind does not declare: naming the kinds that do, if any."""
    owners = []
    for name in choice.names():
        try:
            if key_ in parameter_fields(choice.parameters_of(name, f"{prefix}.{table}")):
                owners.append(name)
        except InputError:  # a combined name whose part is missing: not an owner
            continue
    if not owners:
        return _unknown(key_, declared, prefix)
    follows = " (it follows from the scenario's other tables)" if choice.follows else ""
    return InputError(
        f"{prefix}.{printable(key_)}: a key of {choice.what} {', '.join(map(repr, owners))}, "
        f"not of {kind!r}{follows}; keys of [{prefix}] with {choice.what} {kind!r}: "
        f"{', '.join(sorted(declared))}"
    )


def _build_scenario(data: Mapping[str, Any]) -> Scenario:
    if not isinstance(data, Mapping):
        raise InputError(f"scenario: expected a table, got {type(data).__name__}")
    top = {f.name: f for f in dataclasses.fields(Scenario) if f.name != "tables"}
    every = {cls.table: cls for cls in sections()}
    for key_ in data:  # a key nothing declares; then the kind; then another kind's table
        if key_ not in top and key_ not in every:
            raise _unknown(key_, [*top, *every], "")
    kind = top["kind"].default
    if "kind" in data:
        kind = _value("kind", top["kind"], data["kind"])
        _check_kind(kind)
    tables = tables_of(kind)
    for key_ in data:
        if key_ in every and key_ not in tables:
            raise InputError(
                f"{key_}: not a table of a {kind!r} scenario (kind); its tables: "
                f"{', '.join(tables)}"
            )
    values: dict[str, Any] = {}
    for name, f in top.items():
        if name == "chip":
            values[name] = _build(ChipSpec, data.get(name, {}), name)
        elif name == "mix" and name in data:
            items = data[name]
            if not isinstance(items, list) or not all(isinstance(t, Mapping) for t in items):
                raise InputError(f"{name}: expected [[{name}]] tables")
            if not items:
                raise InputError(f"{name}: give at least one [[{name}]] table")
            values[name] = tuple(
                _build(ChipSpec, item, f"{name}[{i}]") for i, item in enumerate(items)
            )
        elif name == "kind":
            values[name] = kind
        elif name in data:
            values[name] = _value(name, f, data[name])
    for name, cls in tables.items():
        values[name] = _build(cls, data.get(name, {}), name, values)
    return Scenario(**values)


def known_kinds() -> list[str]:
    """The scenario kinds the registered stages run, in their order."""
    return list(dict.fromkeys(k for stage in load_stages() for k in stage.kinds))


def _check_kind(kind: str) -> None:
    """The kinds the registered stages run (a stage's ``kinds``; the packing stage's come
    from the scenario-kind registry)."""
    known = known_kinds()
    if kind not in known:
        raise InputError(f"kind: must be one of {', '.join(map(repr, known))} (got {brief(kind)})")


def scenario_from_dict(data: Mapping[str, Any], base_dir: str | None = None) -> Scenario:
    """Validate a nested mapping (a parsed TOML file) into a :class:`Scenario`.

    ``base_dir``: where relative geometry-file paths start (the scenario file's folder).
    Raises :class:`InputError` naming the first bad key.
    """
    if isinstance(data, Mapping) and "chip" in data and "mix" in data:
        raise InputError("mix: give either [chip] or [[mix]] tables, not both")
    scenario = _build_scenario(data)
    scenario = _resolve_files(scenario, base_dir)
    for table in scenario.tables:
        table.check()
    _check_top_level(scenario)
    for stage in load_stages():
        if scenario.kind in stage.kinds:
            stage.check(scenario)
    return scenario


def _resolve_files(scenario: Scenario, base_dir: str | None) -> Scenario:
    """File paths of the chips' keys (declared with ``path``) made absolute, so the
    resolved scenario works from anywhere."""

    def resolve(spec: ChipSpec) -> ChipSpec:
        relative = {
            name: os.path.abspath(os.path.join(base_dir or os.getcwd(), value))
            for name, value in spec.paths().items()
            if not os.path.isabs(value)
        }
        return dataclasses.replace(spec, **relative) if relative else spec

    return dataclasses.replace(
        scenario, chip=resolve(scenario.chip), mix=tuple(resolve(c) for c in scenario.mix)
    )


def _check_top_level(s: Scenario) -> None:
    """Checks of the top-level keys and the chips; each table checks its own keys
    (``Section.check``) and each stage what it needs (``Stage.check``)."""
    if not 0 <= s.seed <= MAX_SEED:
        raise InputError(f"seed: must be between 0 and {MAX_SEED} (got {brief(s.seed)})")
    if s.mix and sum(c.weight for c in s.mix) <= 0:
        raise InputError("mix: the weights sum to 0; give at least one chip a positive weight")


def scenario_to_dict(scenario: Scenario) -> dict[str, Any]:
    """The resolved scenario as a nested dict of plain TOML values (every key present):
    the top-level keys, then every table in the order of :func:`sections`."""

    def plain(value: Any) -> Any:
        if isinstance(value, KindKeys):
            return {name: plain(v) for name, v in value.keys().items()}
        if dataclasses.is_dataclass(value):
            return {f.name: plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
        if isinstance(value, tuple):
            return [plain(v) for v in value]
        return value

    data = {
        f.name: plain(getattr(scenario, f.name))
        for f in dataclasses.fields(scenario)
        if f.name != "tables"
    }
    data.update({table.table: plain(table) for table in scenario.tables})
    return data
