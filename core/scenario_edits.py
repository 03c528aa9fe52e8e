"""Changes to a scenario's keys before it is built: dotted keys set on a file's data
(``--set``, :func:`set_keys`), on a built scenario (sweeps, :func:`changed_data`), and a
resolved file read with what its kinds do not hold dropped (:func:`kind_data`)."""

from __future__ import annotations

import copy
import dataclasses
import logging
from collections.abc import Mapping
from typing import Any

from chipstack.core.errors import InputError, brief, printable
from chipstack.core.scenario_data import _build, known_kinds, scenario_to_dict
from chipstack.core.schema import (
    ChipSpec,
    KindKeys,
    Scenario,
    kind_choice,
    parameter_fields,
    sections,
    tables_of,
)

log = logging.getLogger(__name__)

__all__ = ["changed_data", "kind_data", "set_keys"]


def _own_keys(cls: type) -> set[str]:
    """The keys a table that chooses a kind holds itself (not its kind's)."""
    return {f.name for f in dataclasses.fields(cls)} - {"params"}


def changed_data(scenario: Scenario, changes: Mapping[str, Any]) -> dict[str, Any]:
    """The scenario's plain data (:func:`scenario_to_dict`) with dotted keys changed as a
    scenario file would give them (``{"mesh.kind": "conformal", "mesh.size_mm": 1.0}``),
    ready for :func:`scenario_from_dict`.

    A change of a kind comes first: ``kind`` keeps only the new kind's tables, a table's
    selector (``chip.shape``, ``mesh.kind``) only the table's own keys and those of the old
    kind that the new one also declares. Every other key must be one the scenario (with
    its new kinds) declares; an unknown one raises ``InputError`` naming it.
    """
    data = scenario_to_dict(scenario)
    tables = {cls.table: cls for cls in sections()}
    choosing = {"chip": ChipSpec, **{t: c for t, c in tables.items() if issubclass(c, KindKeys)}}
    changes = dict(changes)

    def plain(value: Any) -> Any:
        return list(value) if isinstance(value, tuple) else value

    if "kind" in changes:
        data["kind"] = plain(changes.pop("kind"))
        if isinstance(data["kind"], str) and data["kind"] in known_kinds():
            kept = tables_of(data["kind"])
            data = {k: v for k, v in data.items() if k not in tables or k in kept}
    declared: dict[str, set[str]] = {}
    for table, cls in choosing.items():
        if not isinstance(data.get(table), dict):
            continue
        own = _own_keys(cls)
        choice = kind_choice(table)
        selector = f"{table}.{cls.selector}"
        if choice.follows is not None:
            own.discard(cls.selector)
            declared[table] = own | {
                n
                for name in choice.names()
                for n in parameter_fields(choice.parameters_of(name, table))
            }
            continue
        if selector in changes:
            kind = plain(changes.pop(selector))
            keys = parameter_fields(choice.parameters_of(kind, selector))  # unknown: refused
            data[table] = {k: v for k, v in data[table].items() if k in own or k in keys} | {
                cls.selector: kind
            }
        kind = data[table].get(cls.selector, cls.selector)
        declared[table] = own | set(parameter_fields(choice.parameters_of(kind, selector)))
    for key_, value in changes.items():
        section, _, name = str(key_).rpartition(".")
        table = data.get(section) if section else data
        known = declared.get(section, set(table) if isinstance(table, dict) else set())
        if not isinstance(table, dict) or name not in known:
            raise InputError(f"{printable(key_)}: no such scenario key (see docs/scenarios.md)")
        if isinstance(table.get(name), float) and type(value) is int:
            value = float(value)
        table[name] = plain(value)
    if data.get("mix"):
        data.pop("chip", None)
    else:
        data.pop("mix", None)
    return data


def kind_data(data: Mapping[str, Any]) -> dict[str, Any]:
    """A resolved scenario's data (``scenario.toml`` of a run directory) with what its
    kinds do not hold dropped: the tables of other scenario kinds and, in a table that
    chooses a kind, the keys of other kinds. Resolved files written before kinds owned
    their keys held every key of every kind, each with no effect on the run; a scenario
    file a user writes is not read this way (there, such a key is refused)."""
    out = dict(data)
    kind = out.get("kind", "stack")
    if isinstance(kind, str) and kind in known_kinds():
        kept = tables_of(kind)
        every = {cls.table for cls in sections()}
        out = {k: v for k, v in out.items() if k not in every or k in kept}
    choosing = {"chip": ChipSpec, "mix": ChipSpec}
    choosing |= {c.table: c for c in sections() if issubclass(c, KindKeys)}

    def trim(cls: type, table: Any) -> Any:
        if not isinstance(table, Mapping):
            return table
        choice = kind_choice(cls.table)
        own = _own_keys(cls)
        if choice.follows is not None:  # every model's keys may be there: the build decides
            return {k: v for k, v in table.items() if k != cls.selector}
        name = table.get(cls.selector, dataclasses.fields(cls)[0].default)
        try:
            keys = parameter_fields(choice.parameters_of(name, f"{cls.table}.{cls.selector}"))
        except InputError:
            return table  # an unknown kind: refused when the scenario is built
        return {k: v for k, v in table.items() if k in own or k in keys}

    for table, cls in choosing.items():
        if table == "mix" and isinstance(out.get("mix"), list):
            out["mix"] = [trim(cls, item) for item in out["mix"]]
        elif table in out:
            out[table] = trim(cls, out[table])
    for table, cls in choosing.items():  # a kind that follows from other tables
        choice = kind_choice(cls.table) if table != "mix" else None
        if choice is None or choice.follows is None or not isinstance(out.get(table), Mapping):
            continue
        try:
            built = {
                t: _build(c, out.get(t, {}), t)
                for t, c in choosing.items()
                if t != table and t != "mix" and isinstance(out.get(t), Mapping)
            }
            name = choice.follows(built)
            keys = parameter_fields(choice.parameters_of(name, f"{table}.{cls.selector}"))
        except InputError:
            continue  # refused when the scenario is built
        own = _own_keys(cls) - {cls.selector}
        out[table] = {k: v for k, v in out[table].items() if k in own or k in keys}
    return out


def set_keys(data: Mapping[str, Any], settings: Mapping[str, Any]) -> dict[str, Any]:
    """A parsed scenario file's data with the dotted keys of ``settings`` set, ready for
    :func:`scenario_from_dict` (which types and checks them as it does the file's).

    ``{"deposition.chips": 24, "mesh.kind": "conformal"}``: a missing table is created.
    When a setting changes a kind (``kind``, ``chip.shape``, ``mesh.kind``, or a kind that
    follows from them), the keys the file gave for the old kind that the new one does not
    take are dropped, read from the kinds' own declarations (:func:`kind_data`), and
    logged; a key that ``settings`` itself names is never dropped, so one that no chosen
    kind takes is refused when the scenario is built.

    Parameters
    ----------
    data : mapping
        The parsed file: it must build into a scenario (every key valid for its kinds).
    settings : mapping of str to value
        Dotted keys (``"mesh.voxel_mm"``) and their TOML values.

    Returns
    -------
    dict
        A new nested dict; ``data`` is not changed.

    Raises
    ------
    InputError
        A key whose path runs through a value that is not a table (``seed.x``), naming it.
    """
    changed = copy.deepcopy(dict(data))
    for dotted, value in settings.items():
        parts = str(dotted).split(".")
        node = changed
        for depth, part in enumerate(parts[:-1]):
            child = node.setdefault(part, {})
            if not isinstance(child, dict):
                held = "[[...]] tables" if isinstance(child, list) else brief(child)
                raise InputError(
                    f"{printable(dotted)}: {'.'.join(parts[: depth + 1])} is not a table "
                    f"(it holds {held})"
                )
            node = child
        node[parts[-1]] = copy.deepcopy(value)

    def named(path: str) -> bool:  # a key the settings give, or a table holding one
        return any(k == path or k.startswith((f"{path}.", f"{path}[")) for k in settings)

    # Every key of the file is valid for its kinds (it built), so what kind_data drops
    # from the changed data is exactly what a changed kind no longer takes.
    dropped: list[str] = []

    def keep(given: Any, kept: Any, prefix: str) -> Any:
        if isinstance(given, dict) and isinstance(kept, Mapping):
            out = {}
            for k, v in given.items():
                path = f"{prefix}.{k}" if prefix else str(k)
                if k in kept:
                    out[k] = keep(v, kept[k], path)
                elif named(path):
                    out[k] = v
                else:
                    dropped.append(path)
            return out
        if isinstance(given, list) and isinstance(kept, list) and len(given) == len(kept):
            pairs = enumerate(zip(given, kept, strict=True))
            return [keep(g, c, f"{prefix}[{i}]") for i, (g, c) in pairs]
        return given

    result = keep(changed, kind_data(changed), "")
    if dropped:
        log.info("dropped %s: the kinds now chosen do not take them", ", ".join(dropped))
    return result
