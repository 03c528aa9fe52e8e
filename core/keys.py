"""Declaring a scenario key: :func:`key` (its default, unit, one-line description and
check), the checks keys use, and the limits they share."""

from __future__ import annotations

import os
import re
from collections.abc import Callable
from dataclasses import field
from typing import Any

__all__ = [
    "key",
    "positive",
    "non_negative",
    "length",
    "duration",
    "value_range",
    "between",
    "one_of",
    "region",
    "MAX_SEED",
    "MAX_REPEATS",
    "MAX_DROPS",
    "MAX_WORKERS",
    "MAX_LENGTH_MM",
    "MAX_TIME_S",
    "LENGTH_UNITS_MM",
]


def key(
    default: Any,
    unit: str,
    doc: str,
    check: Callable[[Any], str | None] | None = None,
    *,
    path: bool = False,
    execution: bool = False,
):
    """A scenario key: its default, unit, one-line description and check (a function of
    the value returning the problem, or None when the value is good). ``path``: a file
    name, made absolute from the scenario file's folder when the scenario loads.
    ``execution``: how the work runs, not what it computes (a time limit), so not part of
    the stage cache's key: a run stopped by it resumes under another value."""
    metadata = {"unit": unit, "doc": doc, "check": check, "path": path, "execution": execution}
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


def file_name(value: str) -> str | None:
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
