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
import logging
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar

from chipstack.core.errors import printable
from chipstack.core.keys import (
    between,
    file_name,
    key,
    one_of,
)
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
    "printable",
]


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

    name: str = key("scenario", "", "name used in outputs and file names", file_name)
    kind: str = key(
        "stack",
        "",
        "`stack`: batch deposition on a square target; `drop`: single-chip drops; "
        "`container`: filling a cylinder; `conveyor`: a mat poured onto a moving belt",
    )  # checked against the kinds the registered stages run (core.scenario_data)
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
