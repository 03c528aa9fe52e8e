"""Experiment specs (TOML) and observation files (CSV): reading and checking.

A spec names the kind of experiment, the chip (through a base scenario, optionally with
a ``[chip]`` table on top), how measurements were taken, and the conditions; the
observations file holds what was measured. See the README, "Sim-to-real diagnosis".
"""

from __future__ import annotations

import csv
import dataclasses
import math
import tomllib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from chipstack.core.errors import InputError
from chipstack.core.files import number, read_text
from chipstack.core.keys import MAX_LENGTH_MM
from chipstack.core.scenario_data import scenario_from_dict, scenario_to_dict
from chipstack.core.schema import ChipSpec, Scenario, printable
from chipstack.diagnosis.experiment_kinds import EXPERIMENT_KINDS

# The data model is re-exported: the diagnosis's readers and callers take it from here.
from chipstack.diagnosis.model import (
    Condition,
    DiagnosisSettings,
    DropData,
    Experiment,
    QuantityData,
)
from chipstack.diagnosis.quantity_kinds import QUANTITIES
from chipstack.packing.drop import DropProtocol
from chipstack.packing.effects import EFFECTS

__all__ = [
    "EXPERIMENT_KINDS",
    "Condition",
    "DiagnosisSettings",
    "DropData",
    "Experiment",
    "ExperimentKind",
    "QuantityData",
    "load_experiment",
    "read_drop_observations",
    "read_quantity_observations",
]

DROP_COLUMNS = ("condition", "drop", "x_mm", "y_mm")
DROP_OPTIONAL = ("yaw_deg", "tilt_deg")
QUANTITY_COLUMNS = ("condition", "quantity", "value")
QUANTITY_OPTIONAL = ("sd", "n")
MAX_SPEC_BYTES = 1_000_000  # a spec is a few kB
MAX_QUANTITY = 1e6  # beyond any stack quantity (mm, %, counts per chip)
# What an observation may be, checked before any arithmetic (positions within 10 m of the
# aim, angles within a turn).
OBSERVATION_RANGES = {
    "x_mm": (-MAX_LENGTH_MM, MAX_LENGTH_MM),
    "y_mm": (-MAX_LENGTH_MM, MAX_LENGTH_MM),
    "yaw_deg": (-360.0, 360.0),
    "tilt_deg": (-180.0, 180.0),
    "value": (-MAX_QUANTITY, MAX_QUANTITY),
    "sd": (0.0, MAX_QUANTITY),
    "n": (1.0, MAX_QUANTITY),
}
MIN_DROPS = 10


_TOP_KEYS = {
    "name",
    "kind",
    "scenario",
    "observations",
    "chip",
    "measurement",
    "condition",
    "diagnosis",
}


def _number(value, key: str, low: float = -math.inf, high: float = math.inf) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise InputError(f"{key}: expected a number, got {value!r}")
    value = float(value)
    if not math.isfinite(value):
        raise InputError(f"{key}: must be finite, got {value!r}")
    if not low <= value <= high:
        raise InputError(f"{key}: {value:g} is outside [{low:g}, {high:g}]")
    return value


def _integer(value, key: str, low: int, high: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise InputError(f"{key}: expected an integer, got {value!r}")
    if not low <= value <= high:
        raise InputError(f"{key}: {value} is outside [{low}, {high}]")
    return value


def _table(data: dict, key: str, allowed: set[str]) -> dict:
    if not isinstance(data, dict):
        raise InputError(f"{key}: expected a table, got {data!r}")
    unknown = sorted(set(data) - allowed)
    if unknown:
        raise InputError(
            f"{key}.{unknown[0]}: unknown key; valid keys: {', '.join(sorted(allowed))}"
        )
    return data


def load_experiment(
    path: str | Path, load_scenario: Callable[[str | Path], Scenario]
) -> Experiment:
    """Parse and check an experiment spec; ``load_scenario`` resolves scenario names."""
    shown = printable(path)
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{shown}: experiment spec not found")
    text = read_text(path, "experiment spec", MAX_SPEC_BYTES)
    if not text.strip():
        raise InputError(f"{shown}: the experiment spec is empty")
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"{shown}: malformed TOML: {exc}") from None
    try:
        return _experiment(data, path.resolve().parent, load_scenario)
    except InputError as exc:
        raise InputError(f"{shown}: {exc}") from None


def _experiment(data: dict, base: Path, load_scenario) -> Experiment:
    _table(data, "spec", _TOP_KEYS)
    kind = data.get("kind")
    if not isinstance(kind, str) or kind not in EXPERIMENT_KINDS:
        valid = ", ".join(EXPERIMENT_KINDS.in_order())
        raise InputError(f"kind: expected one of {valid}, got {kind!r}")
    behaviour = EXPERIMENT_KINDS.get(kind)
    name = data.get("name", "experiment")
    if not isinstance(name, str) or not name.strip():
        raise InputError(f"name: expected a non-empty string, got {name!r}")
    observations = data.get("observations")
    if not isinstance(observations, str) or not observations:
        raise InputError("observations: expected the path of the observations CSV file")
    observations_path = (base / observations).resolve()
    base_name = data.get("scenario", behaviour.default_scenario)
    scenario = None
    if base_name is not None:
        if not isinstance(base_name, str):
            raise InputError(f"scenario: expected a scenario name or file, got {base_name!r}")
        scenario = _scenario_ref(base_name, base, load_scenario, "scenario")
    if "chip" in data:
        if scenario is None:
            raise InputError("chip: give a base `scenario` for the chip to go with")
        merged = scenario_to_dict(scenario)
        merged.pop("mix", None)
        given = _table(data["chip"], "chip", set(data["chip"]))  # keys: checked below
        base_chip = merged["chip"]
        if given.get("shape", base_chip["shape"]) != base_chip["shape"]:
            # Another shape: the base's own keys, not its shape's (the new shape's keys
            # are refused by name if they are not its own).
            own = {f.name for f in dataclasses.fields(ChipSpec)}
            base_chip = {k: v for k, v in base_chip.items() if k in own}
        merged["chip"] = {**base_chip, **given}
        try:
            scenario = scenario_from_dict(merged, str(base))
        except InputError as exc:
            raise InputError(str(exc)) from None
    if scenario is not None and behaviour.scenario_kind not in (None, scenario.kind):
        # A base of another kind (a stack's chip dropped): the experiment's kind, with its
        # own tables, before the conditions read them.
        scenario = dataclasses.replace(scenario, kind=behaviour.scenario_kind)
    measurement = _table(
        data.get("measurement", {}), "measurement", {"position_sd_mm", "angle_sd_deg"}
    )
    position_sd = _number(
        measurement.get("position_sd_mm", 0.0), "measurement.position_sd_mm", 0, 100
    )
    angle_sd = _number(measurement.get("angle_sd_deg", 0.0), "measurement.angle_sd_deg", 0, 45)
    settings = _settings(data.get("diagnosis", {}), kind)
    raw = data.get("condition")
    if not isinstance(raw, list) or not raw:
        raise InputError("condition: give at least one [[condition]] table")
    conditions = [
        behaviour.condition(entry, f"condition[{k}]", scenario, base, load_scenario)
        for k, entry in enumerate(raw)
    ]
    names = [c.name for c in conditions]
    duplicated = sorted({n for n in names if names.count(n) > 1})
    if duplicated:
        raise InputError(f"condition: name {duplicated[0]!r} is given twice")
    if scenario is None:
        scenario = conditions[0].scenario
    if behaviour.scenario_kind not in (None, scenario.kind):
        scenario = dataclasses.replace(scenario, kind=behaviour.scenario_kind)
    return Experiment(
        name=name.strip(),
        kind=kind,
        scenario=scenario,
        conditions=tuple(conditions),
        observations=observations_path,
        position_sd_mm=position_sd,
        angle_sd_deg=angle_sd,
        settings=settings,
    )


def _scenario_ref(value: str, base: Path, load_scenario, key: str) -> Scenario:
    candidate = base / value
    try:
        return load_scenario(candidate if candidate.is_file() else value)
    except InputError as exc:
        raise InputError(f"{key}: {exc}") from None


def _settings(data: dict, kind: str) -> DiagnosisSettings:
    fields = {f.name for f in dataclasses.fields(DiagnosisSettings)}
    data = _table(data, "diagnosis", fields)
    values: dict = {}
    if "sim_drops" in data:
        values["sim_drops"] = _integer(data["sim_drops"], "diagnosis.sim_drops", 20, 100_000)
    if "bootstrap" in data:
        values["bootstrap"] = _integer(data["bootstrap"], "diagnosis.bootstrap", 50, 100_000)
    if "grid_points" in data:
        values["grid_points"] = _integer(data["grid_points"], "diagnosis.grid_points", 3, 50)
    if "held_out" in data:
        values["held_out"] = _held_out(data["held_out"], kind)
    if "release_tilt" in data:
        values["release_tilt"] = _release_tilt(data["release_tilt"], kind)
    if "alpha" in data:
        values["alpha"] = _number(data["alpha"], "diagnosis.alpha", 1e-6, 0.5)
    for name, allowed in (("method", METHODS), ("detection", DETECTIONS)):
        if name in data:
            values[name] = _one_of(data[name], f"diagnosis.{name}", allowed)
    if "table_pools" in data:
        values["table_pools"] = _integer(data["table_pools"], "diagnosis.table_pools", 4, 400)
    if "effects" in data:
        effects = data["effects"]
        if not isinstance(effects, list) or not all(isinstance(e, str) for e in effects):
            raise InputError("diagnosis.effects: expected a list of effect names")
        for name in effects:
            effect = EFFECTS.get(name, key="diagnosis.effects")
            if kind not in effect.kinds:
                raise InputError(
                    f"diagnosis.effects: {name!r} acts on {', '.join(effect.kinds)}, not {kind}"
                )
        values["effects"] = tuple(dict.fromkeys(effects))
    return DiagnosisSettings(**values)


def _one_of(value, key: str, allowed: tuple[str, ...]) -> str:
    if value not in allowed:
        raise InputError(f"{key}: {value!r} is not one of {', '.join(map(repr, allowed))}")
    return value


HELD_OUT = ("halves", "conditions")
METHODS = ("amortised", "refit")
DETECTIONS = ("combined", "exact")


def _held_out(value, kind: str) -> str:
    if value not in HELD_OUT:
        raise InputError(
            f"diagnosis.held_out: {value!r} is not one of {', '.join(map(repr, HELD_OUT))}"
        )
    if value not in EXPERIMENT_KINDS.get(kind).held_out:
        raise InputError(
            f"diagnosis.held_out: {kind} experiments hold out whole conditions; "
            '"halves" splits the drops of a drop experiment'
        )
    return value


RELEASE_TILT = ("fitted", "known")


def _release_tilt(value, kind: str) -> str:
    if value not in RELEASE_TILT:
        raise InputError(
            f"diagnosis.release_tilt: {value!r} is not one of {', '.join(map(repr, RELEASE_TILT))}"
        )
    if not EXPERIMENT_KINDS.get(kind).release_tilt:
        raise InputError(
            f"diagnosis.release_tilt: only drop experiments have a release tilt, not {kind}"
        )
    return value


def _drop_condition(entry, key: str, scenario: Scenario) -> Condition:
    entry = _table(entry, key, {"name", "height_mm", "yaw_deg", "tilt_deg"})
    name = entry.get("name")
    if not isinstance(name, str) or not name.strip() or "," in name:
        raise InputError(f"{key}.name: expected a name without commas, got {name!r}")
    default = scenario.drop
    height = _number(entry.get("height_mm", default.height_mm), f"{key}.height_mm", 1e-3, 1e5)
    # The chip's own extent from its shape (a file chip's length_mm is not its size).
    half_extent = scenario.chips[0].chosen.extent(scenario.chips[0])[0] / 2
    if height <= half_extent:
        raise InputError(
            f"{key}.height_mm: {height:g} mm does not clear half the chip's largest extent "
            f"({half_extent:.1f} mm)"
        )
    yaw = _number(entry.get("yaw_deg", default.yaw_deg), f"{key}.yaw_deg", -360, 360)
    tilt = _number(entry.get("tilt_deg", default.tilt_deg), f"{key}.tilt_deg", 0, 90)
    return Condition(name=name, protocol=DropProtocol(height, yaw, tilt))


def _scenario_condition(entry, key, kind, scenario, base, load_scenario) -> Condition:
    entry = _table(entry, key, {"name", "scenario", "repeats"})
    name = entry.get("name")
    if not isinstance(name, str) or not name.strip() or "," in name:
        raise InputError(f"{key}.name: expected a name without commas, got {name!r}")
    ref = entry.get("scenario")
    if ref is None:
        if scenario is None:
            raise InputError(f"{key}.scenario: each condition needs a scenario")
        own = scenario
    else:
        if not isinstance(ref, str):
            raise InputError(f"{key}.scenario: expected a scenario name or file, got {ref!r}")
        own = _scenario_ref(ref, base, load_scenario, f"{key}.scenario")
    if own.kind != kind:
        raise InputError(f"{key}.scenario: is a {own.kind!r} scenario, the spec's kind is {kind!r}")
    repeats = _integer(entry.get("repeats", 2), f"{key}.repeats", 2, 1000)
    return Condition(name=name, scenario=own, repeats=repeats)


def _read_rows(path: Path, required: tuple[str, ...], optional: tuple[str, ...]):
    shown = printable(path)
    if not path.is_file():
        raise InputError(f"{shown}: observations file not found")
    text = read_text(path, "observations file")
    try:
        rows = list(csv.reader(text.splitlines()))
    except csv.Error as exc:
        raise InputError(f"{shown}: unreadable observations file ({exc})") from None
    rows = [r for r in rows if r and any(cell.strip() for cell in r)]
    if not rows:
        raise InputError(f"{shown}: the observations file is empty")
    header = [h.strip() for h in rows[0]]
    # Only the expected column names are ever quoted: the file may be any file, and its
    # first line anything (a secret).
    allowed = required + optional
    duplicated = sorted({h for h in header if header.count(h) > 1 and h in allowed})
    if duplicated:
        raise InputError(f"{shown}: column {duplicated[0]!r} appears twice")
    missing = [c for c in required if c not in header]
    if missing:
        raise InputError(
            f"{shown}: missing column {missing[0]!r} (columns needed: {', '.join(required)}; "
            f"optional: {', '.join(optional)}; the first line is not quoted)"
        )
    unknown = [h for h in header if h not in required + optional]
    if unknown:
        raise InputError(
            f"{shown}: unknown column {printable(unknown[0])!r} "
            f"(allowed: {', '.join(required + optional)})"
        )
    if len(rows) == 1:
        raise InputError(f"{shown}: no observations below the header")
    records = []
    for line, row in enumerate(rows[1:], start=2):
        if len(row) != len(header):
            raise InputError(
                f"{shown}, line {line}: {len(row)} fields, the header has {len(header)}"
            )
        records.append((line, dict(zip(header, (c.strip() for c in row), strict=True))))
    return shown, header, records


def _float(cell: str, shown: str, line: int, column: str) -> float:
    low, high = OBSERVATION_RANGES[column]
    return number(cell, f"{shown}, line {line}", column, low, high)


def _condition_of(row: dict, known: set[str], shown: str, line: int) -> str:
    """The spec's name of a row's condition: the same name, or the one name that differs
    from it only in case (a spreadsheet's "H200" for the spec's "h200"); a name that
    matches two of the spec's up to case, or none, is refused."""
    name = row["condition"]
    if name in known:
        return name
    folded = sorted(k for k in known if k.casefold() == name.casefold())
    if len(folded) == 1:
        return folded[0]
    if folded:
        raise InputError(
            f"{shown}, line {line}, column condition: {printable(name)!r} matches the spec's "
            f"conditions {', '.join(map(repr, folded))} only up to case; write one exactly"
        )
    raise InputError(
        f"{shown}, line {line}: condition {printable(name)!r} is not defined in the spec "
        f"(defined: {', '.join(sorted(known))})"
    )


def read_drop_observations(experiment: Experiment) -> dict[str, DropData]:
    """Drops by condition, checked against the spec (every condition, at least
    ``MIN_DROPS`` drops each, unique drop ids), keyed by the spec's condition names."""
    shown, header, records = _read_rows(experiment.observations, DROP_COLUMNS, DROP_OPTIONAL)
    known = {c.name for c in experiment.conditions}
    by_condition: dict[str, dict[str, list]] = {}
    for line, r in records:
        name = _condition_of(r, known, shown, line)
        drop = r["drop"]
        if not drop:
            raise InputError(f"{shown}, line {line}: empty drop id")
        rows = by_condition.setdefault(name, {"ids": [], "values": []})
        if drop in rows["ids"]:
            raise InputError(
                f"{shown}, line {line}: drop {printable(drop)!r} of {name!r} appears twice"
            )
        rows["ids"].append(drop)
        values = [_float(r[c], shown, line, c) for c in ("x_mm", "y_mm")]
        for column in DROP_OPTIONAL:
            if column in header:
                values.append(_float(r[column], shown, line, column))
        rows["values"].append(values)
    data = {}
    for condition in experiment.conditions:
        rows = by_condition.get(condition.name)
        if rows is None:
            raise InputError(f"{shown}: no drops for condition {condition.name!r}")
        if len(rows["ids"]) < MIN_DROPS:
            raise InputError(
                f"{shown}: condition {condition.name!r} has {len(rows['ids'])} drops; "
                f"at least {MIN_DROPS} are needed"
            )
        values = np.array(rows["values"], dtype=float)
        extra = {c: values[:, 2 + k] for k, c in enumerate(c for c in DROP_OPTIONAL if c in header)}
        data[condition.name] = DropData(values[:, :2], extra.get("yaw_deg"), extra.get("tilt_deg"))
    return data


def read_quantity_observations(
    experiment: Experiment, known_quantities: tuple[str, ...]
) -> dict[str, dict[str, QuantityData]]:
    """Quantities by condition and name, checked against the spec and the quantities
    the simulation can compute."""
    shown, header, records = _read_rows(
        experiment.observations, QUANTITY_COLUMNS, QUANTITY_OPTIONAL
    )
    known = {c.name for c in experiment.conditions}
    data: dict[str, dict[str, QuantityData]] = {}
    for line, r in records:
        name = _condition_of(r, known, shown, line)
        quantity = r["quantity"]
        if quantity not in known_quantities:
            raise InputError(
                f"{shown}, line {line}: unknown quantity {printable(quantity)!r}; valid: "
                f"{', '.join(known_quantities)}"
            )
        if quantity in data.get(name, {}):
            raise InputError(f"{shown}, line {line}: {quantity!r} of {name!r} appears twice")
        value = _float(r["value"], shown, line, "value")
        sd = _float(r["sd"], shown, line, "sd") if r.get("sd") else math.nan
        if sd < 0:
            raise InputError(f"{shown}, line {line}: sd must not be negative, got {sd:g}")
        n = 1
        if r.get("n"):
            count = _float(r["n"], shown, line, "n")
            if count < 1 or count != int(count):
                raise InputError(f"{shown}, line {line}: n must be a whole number >= 1")
            n = int(count)
        data.setdefault(name, {})[quantity] = QuantityData(value, sd, n)
    for condition in experiment.conditions:
        if condition.name not in data:
            raise InputError(f"{shown}: no observations for condition {condition.name!r}")
    return data


# Experiment kinds: what an experiment of each kind observes, how its conditions are
# given, and which routines read, diagnose and synthesise it; the spec reader and the CLI
# ask the kind, never test its name. Plugins add kinds through the
# ``chipstack.experiment_kinds`` entry points.


class ExperimentKind:
    """One kind of experiment (subclass and register in :data:`EXPERIMENT_KINDS`)."""

    name: str = ""
    doc: str = ""
    default_scenario: str | None = None  # the base scenario when the spec names none
    scenario_kind: str | None = None  # the scenario kind it runs as (None: the scenario's)
    held_out: tuple[str, ...] = ("conditions",)  # the values diagnosis.held_out may take
    release_tilt: bool = False  # whether diagnosis.release_tilt applies
    # Its observations are many drops per condition, each a point cloud (tested by the
    # energy statistic, observables by max-T), not one value per quantity (G, Holm).
    replicated_drops: bool = False

    def condition(
        self, entry: Any, key: str, scenario: Scenario | None, base: Path, load_scenario
    ) -> Condition:
        """One ``[[condition]]`` table, checked (errors name ``key``)."""
        raise NotImplementedError

    def read_observations(self, experiment: Experiment) -> dict:
        """The observations file, checked against the spec: data by condition."""
        raise NotImplementedError

    def diagnose(
        self,
        experiment: Experiment,
        data: dict,
        run_many,
        seed: int,
        progress: Callable[[str], None] | None = None,
        tables=None,
    ) -> dict:
        """The diagnosis as a JSON-ready dict; ``tables`` (a
        :class:`diagnosis.reference_table.TableStore`) keeps what a kind amortises over
        diagnoses of one design."""
        raise NotImplementedError

    def synthesize(
        self,
        experiment: Experiment,
        strengths: dict[str, float],
        seed: int,
        run_many,
        drops: int,
        measurements: int | None,
    ) -> list[dict]:
        """Pseudo-experimental rows of the observations file, with these effects."""
        raise NotImplementedError


class DropExperiment(ExperimentKind):
    name = "drop"
    doc = "single chips dropped at release heights and yaws; where each comes to rest"
    default_scenario = "single-chip-drop"
    scenario_kind = "drop"
    held_out = ("halves", "conditions")
    release_tilt = True
    replicated_drops = True

    def condition(self, entry, key, scenario, base, load_scenario):
        return _drop_condition(entry, key, scenario)

    def read_observations(self, experiment):
        return read_drop_observations(experiment)

    def diagnose(self, experiment, data, run_many, seed, progress=None, tables=None):
        from chipstack.diagnosis.drops import diagnose_drops

        return diagnose_drops(experiment, data, run_many, seed, progress, tables=tables)

    def synthesize(self, experiment, strengths, seed, run_many, drops, measurements):
        from chipstack.diagnosis.synth import synthesize_drops

        return synthesize_drops(experiment, strengths, seed, drops, run_many)


class QuantityExperiment(ExperimentKind):
    """Whole depositions (a stack, a container fill) measured by scalar quantities."""

    def __init__(self, name: str, doc: str) -> None:
        self.name, self.doc = name, doc

    def condition(self, entry, key, scenario, base, load_scenario):
        return _scenario_condition(entry, key, self.name, scenario, base, load_scenario)

    def read_observations(self, experiment):
        return read_quantity_observations(experiment, tuple(QUANTITIES))

    def diagnose(self, experiment, data, run_many, seed, progress=None, tables=None):
        # A stack or container simulation costs seconds to minutes where a drop costs
        # milliseconds: a reference table of thousands of them is out of reach, so stacks
        # keep the refit method (``tables`` is not used).
        from chipstack.diagnosis.stacks import diagnose_stacks

        return diagnose_stacks(experiment, data, run_many, seed, progress)

    def synthesize(self, experiment, strengths, seed, run_many, drops, measurements):
        from chipstack.diagnosis.stacks import synthesize_quantities

        return synthesize_quantities(
            experiment, strengths, seed, run_many, measurements=measurements
        )


for _kind in (
    DropExperiment(),
    QuantityExperiment("stack", "stacks deposited per condition; contact and height figures"),
    QuantityExperiment("container", "container fills per condition; the volume fraction"),
):
    EXPERIMENT_KINDS.register(_kind.name, _kind)
