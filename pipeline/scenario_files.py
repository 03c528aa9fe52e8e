"""Reading scenario files (TOML) and writing the resolved scenario back."""

from __future__ import annotations

import json
import tomllib
from collections.abc import Mapping
from importlib import resources
from pathlib import Path
from typing import Any

from chipstack.core.errors import InputError
from chipstack.core.files import read_text
from chipstack.core.schema import (
    Scenario,
    changed_data,
    kind_data,
    printable,
    scenario_from_dict,
    scenario_to_dict,
)

__all__ = ["BUILTIN", "builtin_names", "load_scenario", "dumps_toml", "with_overrides"]

BUILTIN = "paper-squares"
MAX_SCENARIO_BYTES = 1_000_000


def builtin_names() -> list[str]:
    folder = resources.files("chipstack.pipeline") / "scenarios"
    return sorted(
        p.name.removesuffix(".toml") for p in folder.iterdir() if p.name.endswith(".toml")
    )


def load_scenario(source: str | Path | None) -> Scenario:
    """A scenario from a TOML file, a built-in name, or (None) the paper's reference stack."""
    if source is None:
        source = BUILTIN
    shown = printable(source)
    try:
        path = Path(source)
        is_file, is_dir = path.is_file(), path.is_dir()
    except (OSError, ValueError) as exc:
        raise InputError(f"{shown}: unusable scenario path ({exc})") from None
    if not is_file:
        if str(source) in builtin_names():
            text = (
                resources.files("chipstack.pipeline") / "scenarios" / f"{source}.toml"
            ).read_text()
            return _parse(text, f"built-in scenario {source}", None)
        if is_dir:
            raise InputError(f"{shown}: is a directory, not a scenario file")
        raise InputError(
            f"{shown}: scenario file not found (built-in scenarios: {', '.join(builtin_names())})"
        )
    text = read_text(path, "scenario file", MAX_SCENARIO_BYTES)  # a scenario is a few kB
    return _parse(text, shown, str(path.resolve().parent))


def load_resolved(path: str | Path) -> Scenario:
    """The resolved scenario of a run directory (its ``scenario.toml``): read as
    :func:`load_scenario` reads a file, but without the keys and tables of other kinds
    that the files of earlier versions held (:func:`core.schema.kind_data`)."""
    shown = printable(path)
    text = read_text(Path(path), "scenario file", MAX_SCENARIO_BYTES)
    return _parse(text, shown, str(Path(path).resolve().parent), kind_data)


def with_overrides(scenario: Scenario, overrides: Mapping[str, Any]) -> Scenario:
    """``scenario`` with the dotted keys of ``overrides`` changed (``{"deposition.chips":
    60}``, ``{"mesh.kind": "conformal", "mesh.size_mm": 1.0}``), every value checked as if
    written in the file; an unknown key is refused, naming it."""
    return scenario_from_dict(changed_data(scenario, overrides))


def _parse(text: str, origin: str, base_dir: str | None, prepare=None) -> Scenario:
    if not text.strip():
        raise InputError(f"{origin}: the scenario file is empty")
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"{origin}: malformed TOML: {exc}") from None
    except RecursionError:
        raise InputError(f"{origin}: malformed TOML: arrays or tables nested too deeply") from None
    try:
        return scenario_from_dict(prepare(data) if prepare else data, base_dir)
    except InputError as exc:
        raise InputError(f"{origin}: {exc}") from None


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, str):
        # JSON escapes (quotes, backslash, control characters) are valid in TOML basic strings
        return json.dumps(value, ensure_ascii=False)
    if isinstance(value, list):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    raise TypeError(f"cannot write {type(value).__name__} to TOML")


def dumps_toml(scenario: Scenario) -> str:
    """The resolved scenario (every key, defaults filled in) as TOML that loads back equal."""
    data = scenario_to_dict(scenario)

    def is_tables(value: Any) -> bool:
        return isinstance(value, list) and any(isinstance(v, dict) for v in value)

    lines = [
        f"{k} = {_toml_value(v)}"
        for k, v in data.items()
        if not isinstance(v, dict) and not is_tables(v) and v != []
    ]
    for section, table in data.items():
        if isinstance(table, dict):
            if section == "chip" and data.get("mix"):
                continue  # a mix replaces [chip]; both may not be given
            lines += ["", f"[{section}]"] + [f"{k} = {_toml_value(v)}" for k, v in table.items()]
    for section, tables in data.items():
        if is_tables(tables):
            for table in tables:
                lines += ["", f"[[{section}]]"]
                lines += [f"{k} = {_toml_value(v)}" for k, v in table.items()]
    return "\n".join(lines) + "\n"
