"""The tables of scenario keys the docs show, generated from the keys' declarations
(docs/scenarios.md holds :func:`key_table_markdown` verbatim; a test checks it)."""

from __future__ import annotations

import dataclasses

from chipstack.core.schema import (
    ChipSpec,
    KindKeys,
    Scenario,
    kind_choice,
    parameter_fields,
    sections,
)

__all__ = ["key_table", "kind_key_table", "key_table_markdown"]


def key_table() -> list[tuple[str, str, str, str]]:
    """(key, unit, default, description) for every scenario key, for documentation; a
    key of the kinds a table chooses among is one row naming the kinds that declare it."""

    def rows_of(cls: type, prefix: str) -> list[tuple[str, str, str, str]]:
        rows = []
        for g in dataclasses.fields(cls):
            if g.name == "params":
                continue
            chooses = issubclass(cls, KindKeys) and g.name == cls.selector
            if not (chooses and kind_choice(cls.table).follows):  # else not a key of the file
                doc = g.metadata["doc"]
                rows.append((f"{prefix}.{g.name}", g.metadata["unit"], repr(g.default), doc))
            if chooses:
                rows += kind_rows(cls.table, prefix)
        return rows

    def kind_rows(table: str, prefix: str) -> list[tuple[str, str, str, str]]:
        by_key: dict[str, list[tuple[str, dataclasses.Field]]] = {}
        choice = kind_choice(table)
        for name in choice.names():
            for f in parameter_fields(choice.parameters_of(name, table)).values():
                by_key.setdefault(f.name, []).append((name, f))
        rows = []
        for name, owners in by_key.items():
            unit = owners[0][1].metadata["unit"]
            defaults = {repr(f.default) for _, f in owners}
            default = defaults.pop() if len(defaults) == 1 else "per kind"
            by_doc: dict[str, list[str]] = {}  # kinds that describe the key alike, together
            for kind, f in owners:
                by_doc.setdefault(f.metadata["doc"], []).append(f"`{kind}`")
            doc = "; ".join(f"{', '.join(kinds)}: {text}" for text, kinds in by_doc.items())
            rows.append((f"{prefix}.{name}", unit, default, doc))
        return rows

    rows = []
    for f in dataclasses.fields(Scenario):
        if f.name == "tables":
            for cls in sections():
                rows += rows_of(cls, cls.table)
        elif f.name == "chip":
            rows += rows_of(ChipSpec, "chip")
        else:
            rows.append((f.name, f.metadata["unit"], repr(f.default), f.metadata["doc"]))
    return rows


def kind_key_table(table: str) -> dict[str, list[tuple[str, str, str, str]]]:
    """(key, unit, default, description) of each kind's own keys, by kind name: what
    the docs list under each shape and mesh kind."""
    choice = kind_choice(table)
    return {
        name: [
            (f.name, f.metadata["unit"], repr(f.default), f.metadata["doc"])
            for f in parameter_fields(choice.parameters_of(name, table)).values()
        ]
        for name in choice.names()
    }


def key_table_markdown() -> str:
    """The README's table of scenario keys (a test checks the README holds it verbatim)."""
    lines = ["| key | unit | default | meaning |", "|---|---|---|---|"]
    lines += [
        f"| `{key}` | {unit or '-'} | `{default}` | {doc} |"
        for key, unit, default, doc in key_table()
    ]
    return "\n".join(lines)
