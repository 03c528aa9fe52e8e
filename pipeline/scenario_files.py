"""Reading scenario files (TOML) and writing the resolved scenario back."""

from __future__ import annotations

import json
import re
import tomllib
from collections.abc import Mapping
from importlib import resources
from pathlib import Path
from typing import Any

from chipstack.core.errors import InputError
from chipstack.core.files import read_text
from chipstack.core.scenario_data import scenario_from_dict, scenario_to_dict
from chipstack.core.scenario_edits import changed_data, kind_data, set_keys
from chipstack.core.schema import Scenario, printable

__all__ = [
    "BUILTIN",
    "builtin_names",
    "builtin_summaries",
    "load_scenario",
    "dumps_toml",
    "parse_setting",
    "with_overrides",
]

BUILTIN = "paper-squares"
MAX_SCENARIO_BYTES = 1_000_000


def builtin_names() -> list[str]:
    folder = resources.files("chipstack.pipeline") / "scenarios"
    return sorted(
        p.name.removesuffix(".toml") for p in folder.iterdir() if p.name.endswith(".toml")
    )


def _builtin_text(name: str) -> str:
    return (resources.files("chipstack.pipeline") / "scenarios" / f"{name}.toml").read_text()


def _leading_summary(text: str) -> str:
    """The first paragraph of a TOML file's leading comment, on one line (the comment
    lines before the first key, up to the first empty ``#`` line)."""
    lines = []
    for line in text.splitlines():
        if not line.startswith("#"):
            break
        body = line.removeprefix("#").strip()
        if not body:
            break
        lines.append(body)
    return " ".join(lines)


def builtin_summaries() -> list[tuple[str, str, str]]:
    """Every built-in scenario, what ``pipeline scenarios`` lists.

    Returns
    -------
    list of (str, str, str)
        (name, kind, description), sorted by name. The description is the first
        paragraph of the file's leading comment: each built-in opens with a one-line
        paragraph saying what it is (a test holds them to it).
    """
    return [
        (name, load_scenario(name).kind, _leading_summary(_builtin_text(name)))
        for name in builtin_names()
    ]


# A dotted scenario key as --set takes it: bare TOML key names joined by dots.
_DOTTED = re.compile(r"[A-Za-z0-9_-]+(\.[A-Za-z0-9_-]+)*")


def parse_setting(text: str) -> tuple[str, Any]:
    """One ``pipeline run --set`` argument as its dotted key and value.

    Parameters
    ----------
    text : str
        ``KEY=VALUE``. The value is read as a TOML value (``24``, ``1.5``, ``true``,
        ``["vtu", "msh"]``, ``"conformal"``); text that is not one is taken as a bare
        string (``conformal``), so that a name needs no quotes.

    Returns
    -------
    (str, value)
        The key (``"mesh.kind"``) and the value, unchecked: the schema checks it when the
        scenario is built (:func:`load_scenario`).

    Raises
    ------
    InputError
        No ``=``, or a key that is not dotted names; the message names the setting.
    """
    key_, sep, raw = str(text).partition("=")
    key_ = key_.strip()
    if not sep:
        raise InputError(f"--set {printable(text)}: expected KEY=VALUE (e.g. deposition.chips=24)")
    if not _DOTTED.fullmatch(key_):
        raise InputError(
            f"--set {printable(key_)}: not a scenario key (dotted names, e.g. mesh.kind)"
        )
    raw = raw.strip()
    try:
        parsed = tomllib.loads(f"value = {raw}")
    except (tomllib.TOMLDecodeError, RecursionError):
        return key_, raw
    # "1\nname = 'x'" parses, but as two keys: it is not one value, so it is text
    return (key_, parsed["value"]) if list(parsed) == ["value"] else (key_, raw)


def load_scenario(source: str | Path | None, settings: Mapping[str, Any] | None = None) -> Scenario:
    """A scenario from a TOML file, a built-in name, or (None) the paper's reference stack.

    Parameters
    ----------
    source : str, Path or None
        A scenario file, a built-in name (:func:`builtin_names`) or None (``paper-squares``).
    settings : mapping of str to value, optional
        Dotted keys to change (``pipeline run --set``: :func:`parse_setting`), applied to
        the file's data before the scenario is built (:func:`core.scenario_edits.set_keys`), so
        each is typed and checked as if written in the file.

    Returns
    -------
    Scenario

    Raises
    ------
    InputError
        One line naming the problem. The file is checked first, so that its own errors
        name the file and a setting's name ``--set`` and the key.
    """
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
            return _parse(_builtin_text(str(source)), f"built-in scenario {source}", None, settings)
        if is_dir:
            raise InputError(f"{shown}: is a directory, not a scenario file")
        raise InputError(
            f"{shown}: scenario file not found (built-in scenarios: {', '.join(builtin_names())})"
        )
    text = read_text(path, "scenario file", MAX_SCENARIO_BYTES)  # a scenario is a few kB
    return _parse(text, shown, str(path.resolve().parent), settings)


def load_resolved(path: str | Path) -> Scenario:
    """The resolved scenario of a run directory (its ``scenario.toml``): read as
    :func:`load_scenario` reads a file, but without the keys and tables of other kinds
    that the files of earlier versions held (:func:`core.scenario_edits.kind_data`)."""
    shown = printable(path)
    text = read_text(Path(path), "scenario file", MAX_SCENARIO_BYTES)
    return _parse(text, shown, str(Path(path).resolve().parent), prepare=kind_data)


def with_overrides(scenario: Scenario, overrides: Mapping[str, Any]) -> Scenario:
    """``scenario`` with the dotted keys of ``overrides`` changed (``{"deposition.chips":
    60}``, ``{"mesh.kind": "conformal", "mesh.size_mm": 1.0}``), every value checked as if
    written in the file; an unknown key is refused, naming it."""
    return scenario_from_dict(changed_data(scenario, overrides))


def _parse(
    text: str,
    origin: str,
    base_dir: str | None,
    settings: Mapping[str, Any] | None = None,
    prepare=None,
) -> Scenario:
    if not text.strip():
        raise InputError(f"{origin}: the scenario file is empty")
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"{origin}: malformed TOML: {exc}") from None
    except RecursionError:
        raise InputError(f"{origin}: malformed TOML: arrays or tables nested too deeply") from None
    if prepare:
        data = prepare(data)
    try:
        scenario = scenario_from_dict(data, base_dir)
    except InputError as exc:
        raise InputError(f"{origin}: {exc}") from None
    if not settings:
        return scenario
    try:
        return scenario_from_dict(set_keys(data, settings), base_dir)
    except InputError as exc:
        raise InputError(_setting_error(str(exc), list(settings))) from None


def _setting_error(message: str, keys: list[str]) -> str:
    """The schema's message about the changed data, led by the setting it concerns: the
    key it names (``deposition.chips: expected an integer``), the setting under the table
    it names (``depositon: unknown key``), the one it mentions (``deposition.batch_size:
    54 is larger than deposition.chips``), or else all of them."""
    named = message.split(":", 1)[0]
    for k in keys:
        if message.startswith(f"{k}: "):
            return f"--set {message}"
    for k in keys:
        if k.startswith((f"{named}.", f"{named}[")) or k in message:
            return f"--set {k}: {message}"
    return f"--set {', '.join(keys)}: {message}"


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
