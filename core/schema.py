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

import copy
import dataclasses
import logging
import math
import os
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar

from chipstack.core.errors import InputError, brief, printable
from chipstack.core.stages import load_stages

log = logging.getLogger(__name__)

__all__ = [
    "ChipSpec",
    "KindChoice",
    "KindKeys",
    "Parameters",
    "Section",
    "Scenario",
    "sections",
    "scenario_from_dict",
    "scenario_to_dict",
    "changed_data",
    "kind_data",
    "set_keys",
    "key_table",
    "key",
    "printable",
]


def key(
    default: Any,
    unit: str,
    doc: str,
    check: Callable[[Any], str | None] | None = None,
    *,
    path: bool = False,
):
    """A scenario key: its default, unit, one-line description and check (a function of
    the value returning the problem, or None when the value is good). ``path``: a file
    name, made absolute from the scenario file's folder when the scenario loads."""
    metadata = {"unit": unit, "doc": doc, "check": check, "path": path}
    return field(default=default, metadata=metadata)


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
class Parameters:
    """Base of a kind's own parameter table: a frozen dataclass of :func:`key` fields that
    a shape, a mesh kind (any kind a table chooses by name) declares as ``parameters``.

    The keys sit in the choosing table of the scenario file as before (``[chip]`` with
    ``shape = "star"`` takes ``sides`` and ``inner_ratio``); the scenario holds the chosen
    kind's table only, so a key of another kind is refused by name and a plugin's kind
    brings keys of its own. Keys several kinds share are declared once, on a common base.
    """

    def check(self, key: str) -> None:
        """Refuse combinations of this kind's keys that cannot work (``InputError`` naming
        ``key.<name>``, ``key`` the table's path: ``chip``, ``mix[2]``, ``mesh``)."""


@dataclass(frozen=True)
class KindChoice:
    """How a table's selector key chooses among registered kinds, each with its own
    :class:`Parameters` (declared by the stage that owns the kinds: ``Stage.kind_choices``).

    what: what a kind is called in messages (``shape``, ``mesh kind``).
    names: the valid names, for messages and documentation.
    resolve: ``resolve(name, key)``, the object(s) the name stands for; an unknown name
        raises ``InputError`` naming ``key`` and listing the valid names.
    parameters: ``parameters(resolved)``, the chosen kind's parameter table.
    follows: ``follows(tables)``, the kind's name from the scenario's other tables, when
        no key of the file chooses it.
    """

    what: str
    names: Callable[[], Sequence[str]]
    resolve: Callable[[str, str], Any]
    parameters: Callable[[Any], type[Parameters]]
    # The kind follows from the scenario's other tables (by name) instead of a key of the
    # file: the solve model from [mesh]. The selector is then not written or read.
    follows: Callable[[Mapping[str, Any]], str] | None = None

    def parameters_of(self, name: str, key: str) -> type[Parameters]:
        return self.parameters(self.resolve(name, key))

    @classmethod
    def of_registry(cls, registry: Any) -> KindChoice:
        """The kinds of ``registry`` (a :class:`core.registry.Registry`), each with its
        ``parameters`` (none declared: no keys of its own)."""
        return cls(
            registry.kind,
            registry.in_order,
            lambda name, key: registry.get(name, key=key),
            lambda kind: getattr(kind, "parameters", Parameters),
        )


def kind_choice(table: str) -> KindChoice:
    """The :class:`KindChoice` a registered stage declares for ``table``."""
    for stage in load_stages():
        choice = getattr(stage, "kind_choices", {}).get(table)
        if choice is not None:
            return choice
    raise RuntimeError(f"no registered stage declares the kinds of [{table}]")  # packaging


def parameter_fields(cls: type) -> dict[str, dataclasses.Field]:
    """The declared keys of a :class:`Parameters` table, by name, in order."""
    return {f.name: f for f in dataclasses.fields(cls)}


def _set_fields(obj: Any, values: dict[str, Any], skip: str) -> list[dataclasses.Field]:
    """Set a frozen dataclass's fields (but ``skip``) from ``values`` (popping what it
    takes) or their defaults, for a custom ``__init__``; returns the fields set."""
    fields = [f for f in dataclasses.fields(obj) if f.name != skip]
    for f in fields:
        if f.name in values:
            value = values.pop(f.name)
        elif f.default_factory is not dataclasses.MISSING:
            value = f.default_factory()
        else:
            value = f.default
        object.__setattr__(obj, f.name, value)
    return fields


class KindKeys:
    """Mixin of a frozen table whose selector key (``selector``: ``shape``, ``kind``) names
    a kind with its own :class:`Parameters`: the table's own keys are its fields, the
    chosen kind's are held in ``params`` and read as the table's (``chip.sides``); a key
    of another kind is not there (``AttributeError`` naming the kind).

    ``Table(selector=name, **keys)`` takes both: a kind key goes into ``params``; with
    ``params=`` given (``dataclasses.replace``), its keys that the kind declares are kept.
    """

    table: ClassVar[str] = ""
    selector: ClassVar[str] = ""

    def __init__(self, **values: Any) -> None:
        own = _set_fields(self, values, skip="params")
        choice = kind_choice(self.table)
        chosen = choice.resolve(getattr(self, self.selector), f"{self.table}.{self.selector}")
        object.__setattr__(self, "_chosen", chosen)
        parameters = choice.parameters(chosen)
        declared = parameter_fields(parameters)
        given = values.pop("params", None)
        kept = {}
        if given is not None:
            kept = {n: getattr(given, n) for n in parameter_fields(type(given)) if n in declared}
        taken = (set(declared) & ({f.name for f in own} | set(dir(KindKeys)))) - {"check"}
        if taken:  # a packaging error of the kind, not user input
            raise TypeError(
                f"{type(self).__name__}: kind keys {sorted(taken)} shadow the table's own"
            )
        unknown = sorted(set(values) - set(declared))
        if unknown:
            raise TypeError(
                f"{type(self).__name__}: {', '.join(unknown)} not keys of "
                f"{kind_choice(self.table).what} {getattr(self, self.selector)!r}"
            )
        object.__setattr__(self, "params", parameters(**{**kept, **values}))

    @property
    def chosen(self) -> Any:
        """What the selector names, resolved once when the table was made: the shape, the
        mesh kinds. Callers ask it what it can do, never its name."""
        chosen = self.__dict__.get("_chosen")
        if chosen is None:  # unpickled (the resolved object is not sent along)
            choice = kind_choice(self.table)
            chosen = choice.resolve(getattr(self, self.selector), f"{self.table}.{self.selector}")
            object.__setattr__(self, "_chosen", chosen)
        return chosen

    def __getstate__(self) -> dict[str, Any]:
        return {k: v for k, v in self.__dict__.items() if k != "_chosen"}

    def __getattr__(self, name: str) -> Any:
        # Only reached when ordinary lookup fails: a key of the chosen kind. Dunder
        # lookups (pickle, copy) on an instance not yet filled in fail the ordinary way.
        params = self.__dict__.get("params")
        if params is None or name.startswith("__"):
            raise AttributeError(name)
        if name in parameter_fields(type(params)):
            return getattr(params, name)
        kind = self.__dict__.get(self.selector)
        raise AttributeError(
            f"{self.table}.{name} is not a key of {kind_choice(self.table).what} {kind!r}"
        )

    def paths(self) -> dict[str, str]:
        """The chosen kind's file keys (declared with ``path``) that are set, by name."""
        return {
            name: getattr(self.params, name)
            for name, f in parameter_fields(type(self.params)).items()
            if f.metadata.get("path") and getattr(self.params, name)
        }

    def keys(self) -> dict[str, Any]:
        """Every key of the table with its value, the kind's right after the selector (a
        selector that follows from other tables is not a key of the file)."""
        derived = kind_choice(self.table).follows is not None
        out: dict[str, Any] = {}
        for f in dataclasses.fields(self):
            if f.name == "params":
                continue
            if not (derived and f.name == self.selector):
                out[f.name] = getattr(self, f.name)
            if f.name == self.selector:
                out.update(
                    {n: getattr(self.params, n) for n in parameter_fields(type(self.params))}
                )
        return out


@dataclass(frozen=True, init=False)
class ChipSpec(KindKeys):
    """A chip: its shape, the shape's own keys (sizes in mm; ``chip.params``, read as
    ``chip.sides``), how its size varies and its fibres (degrees in the chip plane).
    Each shape's keys are listed under it in docs/packing.md (Chip shapes)."""

    table: ClassVar[str] = "chip"
    selector: ClassVar[str] = "shape"

    shape: str = key("box", "", "chip shape, from the shape registry (see Chip shapes)")
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
    # The shape's own keys (its ``parameters``), filled in from the shape's table.
    params: Parameters = field(default=None, metadata={"doc": "the shape's own keys"})


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


def tables_of(kind: str) -> dict[str, type[Section]]:
    """The tables a scenario of ``kind`` holds, by name: those declared for it (a
    table's ``kinds``), and those of the stages that run on it (a drop scenario, packed
    only, holds no ``[mesh]``)."""
    runs = {cls.table: stage.kinds for stage in load_stages() for cls in stage.owned_sections}
    return {
        cls.table: cls
        for cls in sections()
        if (kind in cls.kinds if cls.kinds else kind in runs.get(cls.table, (kind,)))
    }


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
        _set_fields(self, values, skip="tables")
        values.pop("_by_table", None)  # Scenario(**other.__dict__): derived from the tables
        values.pop("_chosen", None)
        by_table = {table: cls() for table, cls in tables_of(self.kind).items()}
        # The tables of another kind are dropped when the kind changes (replace(kind=...)).
        given = {t.table: t for t in values.pop("tables", ()) if t.table in by_table}
        given.update(values)
        for table, value in given.items():
            if table not in by_table:
                raise TypeError(
                    f"Scenario: no table {table!r} in a {self.kind!r} scenario; its tables: "
                    f"{', '.join(by_table)}"
                )
            if type(value) is not type(by_table[table]):
                raise TypeError(
                    f"Scenario: [{table}] must be a {type(by_table[table]).__name__}, "
                    f"got {type(value).__name__}"
                )
            by_table[table] = value
        for table, value in by_table.items():  # a kind that follows from other tables
            if isinstance(value, KindKeys) and (follows := kind_choice(table).follows):
                derived = follows(by_table)
                if getattr(value, value.selector) != derived:
                    by_table[table] = dataclasses.replace(value, **{value.selector: derived})
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
    def chosen(self) -> Any:
        """The scenario kind ``kind`` names, resolved once (the packing stage declares the
        kinds: ``Stage.scenario_choice``); callers ask it what it can do."""
        chosen = self.__dict__.get("_chosen")
        if chosen is None:
            choice = next(
                c for c in (getattr(s, "scenario_choice", None) for s in load_stages()) if c
            )
            chosen = choice.resolve(self.kind, "kind")
            object.__setattr__(self, "_chosen", chosen)
        return chosen

    def __getstate__(self) -> dict[str, Any]:
        return {k: v for k, v in self.__dict__.items() if k != "_chosen"}

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


def _check_kind(kind: str) -> None:
    """The kinds the registered stages run (a stage's ``kinds``; the packing stage's come
    from the scenario-kind registry)."""
    known = _known_kinds()
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
        if isinstance(data["kind"], str) and data["kind"] in _known_kinds():
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


def _known_kinds() -> list[str]:
    return list(dict.fromkeys(k for stage in load_stages() for k in stage.kinds))


def kind_data(data: Mapping[str, Any]) -> dict[str, Any]:
    """A resolved scenario's data (``scenario.toml`` of a run directory) with what its
    kinds do not hold dropped: the tables of other scenario kinds and, in a table that
    chooses a kind, the keys of other kinds. Resolved files written before kinds owned
    their keys held every key of every kind, each with no effect on the run; a scenario
    file a user writes is not read this way (there, such a key is refused)."""
    out = dict(data)
    kind = out.get("kind", "stack")
    if isinstance(kind, str) and kind in _known_kinds():
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
