"""The scenario: its typed, frozen configuration, how it is assembled and validated.

A scenario is a nested table (usually read from TOML). Its top-level keys and the chip
(``[chip]``, ``[[mix]]``: the data model every stage shares) are declared here; every
other table is declared by the stage package that reads it (``packing.sections``,
``geometry.sections``, ``meshing.sections``) as a :class:`Section` and listed in its
stage's ``owned_sections``, and the core assembles the scenario from the tables the
registered stages own (:func:`sections`). Every key is declared once, with its type,
unit, default, one-line description and check (:func:`key`); the validator, the key
table of docs/scenarios.md and the resolved-scenario writer are all driven by these
declarations, so they cannot drift apart.
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar

from chipstack.core.errors import InputError, brief, printable
from chipstack.core.stages import load_stages

__all__ = [
    "ChipSpec",
    "Section",
    "Scenario",
    "sections",
    "scenario_from_dict",
    "scenario_to_dict",
    "key_table",
    "key",
    "printable",
]


def key(default: Any, unit: str, doc: str, check: Callable[[Any], str | None] | None = None):
    """A scenario key: its default, unit, one-line description and check (a function of
    the value returning the problem, or None when the value is good)."""
    return field(default=default, metadata={"unit": unit, "doc": doc, "check": check})


MAX_SEED = 2**63 - 1  # seeds are recorded in JSON manifests and TOML: 64-bit integers
MAX_REPEATS = 1000  # runs of an ensemble, repeats of a validation case
MAX_DROPS = 100_000  # drops of one experiment or condition
# Local worker processes: a few per core pay for waiting on files; thousands only hang.
MAX_WORKERS = 4 * (os.cpu_count() or 1)
MAX_LENGTH_MM = 1e4  # 10 m: beyond any conveyor, and safely inside float arithmetic
MAX_TIME_S = 1e4


def positive(value: Any) -> str | None:
    return None if value > 0 else "must be positive"


def length(value: float) -> str | None:
    if value <= 0:
        return "must be positive"
    return None if value <= MAX_LENGTH_MM else f"must not exceed {MAX_LENGTH_MM:g} mm"


def duration(value: float) -> str | None:
    if value <= 0:
        return "must be positive"
    return None if value <= MAX_TIME_S else f"must not exceed {MAX_TIME_S:g} s"


def _name(value: str) -> str | None:
    ok = value and len(value) <= 100 and re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9._-]*", value)
    return None if ok else "must be 1-100 letters, digits, '.', '_' or '-' (used in file names)"


def non_negative(value: Any) -> str | None:
    return None if value >= 0 else "must not be negative"


def value_range(lo: float | None = None, hi: float | None = None):
    def check(value: tuple[float, float]) -> str | None:
        if len(value) != 2:
            return "must be a pair [low, high]"
        a, b = value
        if a > b:
            return f"low {a} is above high {b}"
        if lo is not None and a < lo:
            return f"must not go below {lo}"
        if hi is not None and b > hi:
            return f"must not go above {hi}"
        return None

    return check


def between(lo: float, hi: float):
    def check(value: float) -> str | None:
        return None if lo <= value <= hi else f"must be between {lo} and {hi}"

    return check


def one_of(*names: str):
    def check(value: str) -> str | None:
        return None if value in names else f"must be one of {', '.join(map(repr, names))}"

    return check


def region(value: tuple[float, ...]) -> str | None:
    if value == ():
        return None
    if len(value) != 4:
        return f"must be [x_min, x_max, y_min, y_max] (4 numbers), got {len(value)}"
    x0, x1, y0, y1 = value
    if not (x0 < x1 and y0 < y1):
        return f"needs x_min < x_max and y_min < y_max, got {list(value)}"
    if max(abs(v) for v in value) > MAX_LENGTH_MM:
        return f"must lie within {MAX_LENGTH_MM:g} mm of the target's centre"
    return None


LENGTH_UNITS_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0, "um": 1e-3, "in": 25.4}


@dataclass(frozen=True)
class ChipSpec:
    """A chip shape and its size. Lengths in mm, fibre directions in degrees in the chip
    plane; which keys a shape reads is listed in the README (Chip shapes)."""

    shape: str = key("box", "", "chip shape, from the shape registry (see Chip shapes)")
    length_mm: float = key(
        20.0,
        "mm",
        "box, beam, fibre: length (local x); polygon, star, random_polygon: diameter of "
        "the circle through the corners",
        length,
    )
    width_mm: float = key(20.0, "mm", "box, beam: width (local y)", length)
    thickness_mm: float = key(
        2.0, "mm", "thickness (local z); a cylindrical beam or fibre's diameter", length
    )
    sides: int = key(6, "", "polygon: sides; star: points; random_polygon: corners", between(3, 64))
    inner_ratio: float = key(
        0.5, "", "star: radius of the notches over the radius of the tips", between(0.05, 0.95)
    )
    convex: bool = key(True, "", "random_polygon: convex outline (else star-shaped)")
    irregularity: float = key(
        0.5,
        "",
        "random_polygon (non-convex): corner radii uniform in [1 - irregularity, 1] x radius",
        between(0.0, 0.9),
    )
    section: str = key(
        "box", "", "beam, fibre: cross-section `box` or `cylinder`", one_of("box", "cylinder")
    )
    file: str = key("", "", "file: an STL, OBJ or PLY file (relative to the scenario file)")
    units: str = key(
        "mm",
        "",
        f"file: the length unit of the file's coordinates ({', '.join(LENGTH_UNITS_MM)})",
        one_of(*LENGTH_UNITS_MM),
    )
    size_distribution: str = key(
        "fixed",
        "",
        "in-plane size factor per chip: `fixed` (1), `uniform` (1 +- spread), `normal` "
        "(mean 1, sd spread) or `lognormal` (median 1, log-sd spread); thickness is kept",
        one_of("fixed", "uniform", "normal", "lognormal"),
    )
    size_spread: float = key(0.0, "", "spread of the size factor", between(0.0, 0.9))
    weight: float = key(
        1.0, "", "in a `[[mix]]`: relative frequency of this chip", between(0.0, 1e9)
    )
    fibre_directions_deg: tuple[float, ...] = key(
        (),
        "deg",
        "fibre directions in the chip plane from local x ([]: the shape's own, woven "
        "twill [0, 90] for plates, [0] along beams and fibres)",
    )


class Section:
    """Base of a scenario table (``[mesh]``, ``[deposition]``, ...): a frozen dataclass of
    :func:`key` fields, declared in the package of the stage that reads it and listed in
    that stage's ``owned_sections``.

    table: the table's name in a scenario file (and the scenario's attribute).
    kinds: the scenario kinds it belongs to (empty: every kind); a scenario lists the
    tables of every kind first.
    """

    table: ClassVar[str] = ""
    kinds: ClassVar[tuple[str, ...]] = ()

    def check(self) -> None:
        """Refuse combinations of this table's keys that cannot work (``InputError``
        naming the key); each key's own range is checked by its declaration."""


_sections: list[type[Section]] = []


def sections() -> tuple[type[Section], ...]:
    """Every scenario table the registered stages own, in the order a scenario lists them:
    the tables of every kind, then those of one kind, each in pipeline order (upstream
    stage first, a stage's own tables in its order)."""
    if not _sections:
        _sections[:] = assemble(load_stages())  # one assignment: a second thread redoes it
    return tuple(_sections)


def assemble(stages: list) -> list[type[Section]]:
    """The tables ``stages`` own (see :func:`sections`); a table two stages declare, or one
    named like a top-level key, is refused (a packaging error, not user input)."""
    owners: dict[str, str] = {}
    owned: list[type[Section]] = []
    top_level = {f.name for f in dataclasses.fields(Scenario)}
    for stage in stages:
        for cls in stage.owned_sections:
            if not (isinstance(cls, type) and issubclass(cls, Section) and cls.table):
                raise RuntimeError(f"stage {stage.name!r} owns {cls!r}, not a named Section")
            if cls.table in owners or cls.table in top_level or hasattr(Scenario, cls.table):
                first = owners.get(cls.table, "the top level")
                raise RuntimeError(
                    f"scenario table [{cls.table}] of stage {stage.name!r} is already "
                    f"declared by {first}"
                )
            owners[cls.table] = repr(stage.name)
            owned.append(cls)
    return [c for c in owned if not c.kinds] + [c for c in owned if c.kinds]


@dataclass(frozen=True, init=False)
class Scenario:
    """A complete, validated scenario: the top-level keys, the chip, and every table the
    stages own (read as attributes: ``scenario.mesh``, ``scenario.deposition``).

    ``Scenario(**keys)`` takes the top-level keys and tables by name (a missing one is
    its default), so that ``dataclasses.replace(scenario, mesh=...)`` works as for any
    frozen dataclass.
    """

    name: str = key("scenario", "", "name used in outputs and file names", _name)
    kind: str = key(
        "stack",
        "",
        "`stack`: batch deposition on a square target; `drop`: single-chip drops; "
        "`container`: filling a cylinder; `conveyor`: a mat poured onto a moving belt",
    )  # checked against the kinds the registered stages run (_check_kind)
    seed: int = key(0, "", "seed of every random draw (the CLI's --seed overrides it)")
    chip: ChipSpec = field(default_factory=ChipSpec)
    mix: tuple[ChipSpec, ...] = key(
        (),
        "",
        "a mix of chips, `[[mix]]` tables with the `[chip]` keys and a `weight` each; "
        "used instead of `[chip]`",
    )
    # Every table the stages own, in the order of sections(); read by attribute.
    tables: tuple[Section, ...] = field(default=())

    def __init__(self, **values: Any) -> None:
        for f in dataclasses.fields(self):
            if f.name == "tables":
                continue
            if f.name in values:
                value = values.pop(f.name)
            elif f.default_factory is not dataclasses.MISSING:
                value = f.default_factory()
            else:
                value = f.default
            object.__setattr__(self, f.name, value)
        values.pop("_by_table", None)  # Scenario(**other.__dict__): derived from the tables
        by_table = {cls.table: cls() for cls in sections()}
        given = {t.table: t for t in values.pop("tables", ())}
        given.update(values)
        for table, value in given.items():
            if table not in by_table:
                raise TypeError(f"Scenario: unknown table {table!r}; tables: {', '.join(by_table)}")
            if type(value) is not type(by_table[table]):
                raise TypeError(
                    f"Scenario: [{table}] must be a {type(by_table[table]).__name__}, "
                    f"got {type(value).__name__}"
                )
            by_table[table] = value
        object.__setattr__(self, "tables", tuple(by_table.values()))
        object.__setattr__(self, "_by_table", by_table)

    def __getattr__(self, name: str) -> Any:
        # Only reached when ordinary lookup fails: a table. Dunder lookups (pickle, copy)
        # on an instance not yet filled in must fail the ordinary way.
        by_table = self.__dict__.get("_by_table")
        if by_table is not None and name in by_table:
            return by_table[name]
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")

    @property
    def chips(self) -> tuple[ChipSpec, ...]:
        """The chip specs drawn from: the mix, or the single `[chip]`."""
        return self.mix or (self.chip,)

    def with_seed(self, seed: int) -> Scenario:
        return dataclasses.replace(self, seed=seed)


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


def _build(cls: type, table: Mapping[str, Any], prefix: str) -> Any:
    """A flat table (the chip, a section) from its TOML mapping."""
    if not isinstance(table, Mapping):
        raise InputError(f"{prefix}: expected a table, got {type(table).__name__}")
    declared = {f.name: f for f in dataclasses.fields(cls)}
    for key_ in table:
        if key_ not in declared:
            raise _unknown(key_, declared, prefix)
    values = {
        name: _value(f"{prefix}.{name}", f, table[name])
        for name, f in declared.items()
        if name in table
    }
    return cls(**values)


def _build_scenario(data: Mapping[str, Any]) -> Scenario:
    if not isinstance(data, Mapping):
        raise InputError(f"scenario: expected a table, got {type(data).__name__}")
    top = {f.name: f for f in dataclasses.fields(Scenario) if f.name != "tables"}
    tables = {cls.table: cls for cls in sections()}
    for key_ in data:
        if key_ not in top and key_ not in tables:
            raise _unknown(key_, [*top, *tables], "")
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
        elif name in data:
            values[name] = _value(name, f, data[name])
            if name == "kind":
                _check_kind(values[name])
    for name, cls in tables.items():
        values[name] = _build(cls, data.get(name, {}), name)
    return Scenario(**values)


def _check_kind(kind: str) -> None:
    """The kinds the registered stages run (a stage's ``kinds``; the packing stage's come
    from the scenario-kind registry)."""
    known = list(dict.fromkeys(k for stage in load_stages() for k in stage.kinds))
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
        stage.check(scenario)
    return scenario


def _resolve_files(scenario: Scenario, base_dir: str | None) -> Scenario:
    """Geometry-file paths made absolute, so the resolved scenario works from anywhere."""

    def resolve(spec: ChipSpec) -> ChipSpec:
        if not spec.file or os.path.isabs(spec.file):
            return spec
        return dataclasses.replace(
            spec, file=os.path.abspath(os.path.join(base_dir or os.getcwd(), spec.file))
        )

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


def key_table() -> list[tuple[str, str, str, str]]:
    """(key, unit, default, description) for every scenario key, for documentation."""

    def rows_of(cls: type, prefix: str) -> list[tuple[str, str, str, str]]:
        return [
            (f"{prefix}.{g.name}", g.metadata["unit"], repr(g.default), g.metadata["doc"])
            for g in dataclasses.fields(cls)
        ]

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


def key_table_markdown() -> str:
    """The README's table of scenario keys (a test checks the README holds it verbatim)."""
    lines = ["| key | unit | default | meaning |", "|---|---|---|---|"]
    lines += [
        f"| `{key}` | {unit or '-'} | `{default}` | {doc} |"
        for key, unit, default, doc in key_table()
    ]
    return "\n".join(lines)
