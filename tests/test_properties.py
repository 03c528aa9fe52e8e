"""Property-based tests (hypothesis) over scenario values: whatever a user writes, the
scenario loader either accepts it and the result round-trips through TOML, or refuses it
with an InputError naming the key, never another exception."""

from __future__ import annotations

import math
import re

from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from chipstack.core.errors import InputError
from chipstack.core.scenario_data import scenario_from_dict
from chipstack.pipeline.scenario_files import _parse, dumps_toml

KEYS = {
    "chip": [
        "length_mm",
        "width_mm",
        "thickness_mm",
        "shape",
        "sides",
        "inner_ratio",
        "size_distribution",
        "size_spread",
        "fibre_directions_deg",
    ],
    "deposition": ["chips", "batch_size", "target_size_mm", "release_height_mm", "orientation"],
    "physics": ["preset", "friction", "restitution", "time_step_s", "solver_iterations"],
    "settling": ["speed_mm_s", "hold_time_s", "wake_speed_mm_s", "max_time_s"],
    "drop": ["drops", "height_mm", "tilt_deg", "yaw_deg"],
}

scalars = st.one_of(
    st.integers(min_value=-(10**12), max_value=10**12),
    st.floats(allow_nan=True, allow_infinity=True),
    st.booleans(),
    st.text(max_size=8),
    st.sampled_from(["box", "star", "default", "paper", "uniform", "flat", "normal"]),
)
values = st.one_of(scalars, st.lists(scalars, max_size=3))


@st.composite
def scenario_tables(draw):
    data = {}
    for section in draw(st.lists(st.sampled_from(sorted(KEYS)), unique=True, max_size=3)):
        keys = draw(st.lists(st.sampled_from(KEYS[section]), unique=True, min_size=1, max_size=3))
        data[section] = {key: draw(values) for key in keys}
    if draw(st.booleans()):
        data["kind"] = draw(st.sampled_from(["stack", "drop", "container", "pile", 3]))
    if draw(st.booleans()):
        data["seed"] = draw(scalars)
    return data


def _finite(value) -> bool:
    if isinstance(value, float):
        return math.isfinite(value)
    if isinstance(value, list):
        return all(_finite(v) for v in value)
    return True


def _names_what_it_refuses(message: str, data: dict) -> bool:
    """The message begins with the path of what it refuses, then ": ": a key the data
    gives (``chip.length_mm``, ``seed``, an item ``deposition.release_height_mm[1]``); a
    table the data gives, refused whole (not a table of this kind of scenario); or, for a
    rule between keys, a key of a table the data gives (``chip.thickness_mm``, thinner
    than the given ``chip.length_mm``) or one whose message names the given key
    (``chip.length_mm`` against the given ``deposition.target_size_mm``). Naming only a
    table, or a key the data never touches, is not enough (5,000 examples: every message
    is one of these)."""
    tables = {s for s, table in data.items() if isinstance(table, dict)}
    given = {f"{s}.{k}" for s in tables for k in data[s]} | (set(data) - tables)
    head = re.match(r"^([a-z_]+)(?:\.([a-z_]+))?(?:\[\d+\])?: (.*)", message)
    if head is None:
        return False
    table, key, rest = head.groups()
    if key is None:
        return table in given or (
            table in tables and rest.startswith(("not a table of", "expected a table"))
        )
    return f"{table}.{key}" in given or table in tables or any(g in rest for g in given)


@settings(
    max_examples=300, deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow]
)
@given(scenario_tables())
@example({"deposition": {"chips": 10, "batch_size": 5}, "physics": {"friction": 0.3}})
@example({"drop": {"height_mm": 150.0, "tilt_deg": 3}, "kind": "drop", "seed": 4})
@example({"chip": {"length_mm": float("nan")}})
def test_scenario_values_are_accepted_or_refused_by_name(data):
    try:
        scenario = scenario_from_dict(data)
    except InputError as exc:
        message = str(exc)
        assert "\n" not in message and message
        assert _names_what_it_refuses(message, data), (message, data)
        return
    # Accepted: every number in it is finite, and it survives the trip through TOML.
    for table in data.values():
        if isinstance(table, dict):
            assert all(_finite(v) for v in table.values())
    assert _parse(dumps_toml(scenario), "round trip", None) == scenario
