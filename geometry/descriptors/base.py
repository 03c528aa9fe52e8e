"""What every descriptor is made of: the :class:`Descriptor` record a module of
:mod:`geometry.descriptors` ends with, the :class:`Context` of intermediate results the
descriptors share, and the JSON pieces (:func:`scalar`, :func:`profile`) a section holds."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from chipstack.core.arrangement import Arrangement
from chipstack.geometry.rays import RayMaps, ray_maps
from chipstack.geometry.sections import GeometrySpec
from chipstack.geometry.solids import chip_solids, union_solid

__all__ = ["Context", "Descriptor", "Table", "bands", "figure_module", "profile", "scalar"]


def scalar(value: float, unit: str, doc: str) -> dict[str, Any]:
    value = float(value)
    return {"value": value if np.isfinite(value) else None, "unit": unit, "doc": doc}


def profile(
    index: Sequence[float],
    values: Sequence[float],
    index_name: str,
    unit: str,
    doc: str,
    pad: float | str | None = 0.0,
) -> dict[str, Any]:
    """A profile section; ``pad`` is its value at an index a stack does not reach (layers
    above its top: 0 chips), ``"last"`` to repeat the last value (cumulative profiles), or
    None when such an index has no value."""
    return {
        "pad": pad,
        "index_name": index_name,
        "index": [float(v) if isinstance(v, float) else v for v in index],
        "values": [None if not np.isfinite(v) else float(v) for v in values],
        "unit": unit,
        "doc": doc,
    }


class Context:
    """Intermediate results shared by descriptors (the union, the ray maps), made once."""

    def __init__(self, history: Sequence[Arrangement], spec: GeometrySpec) -> None:
        self.history = list(history)
        self.final = self.history[-1]
        self.spec = spec

    @cached_property
    def union(self):
        return union_solid(chip_solids(self.final))

    @cached_property
    def rays(self) -> RayMaps:
        return ray_maps(self.final, self.spec.pixel_mm)


Table = tuple[list[str], Iterable[list]]  # CSV header and rows


def _no_tables(record: Any) -> dict[str, Table]:
    return {}


def _no_files(record: Any, folder: Path) -> list[str]:
    return []


def _no_figures(record: Any, section: dict[str, Any], folder: Path) -> list[str]:
    return []


def _no_ensemble_figures(summary: dict[str, Any], folder: Path) -> list[str]:
    return []


def _no_comparison_figures(
    labels: tuple[str, str], summaries: tuple[dict[str, Any], dict[str, Any]], folder: Path
) -> list[str]:
    return []


def _no_columns(record: Any) -> dict[str, list]:
    return {}


def _no_headline(section: dict[str, Any]) -> str | None:
    return None


def bands(profile: dict[str, Any]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An ensemble profile's mean and its 95 % band (the mean where the band is
    undefined: a single repeat)."""

    def array(key: str) -> np.ndarray:
        return np.array([np.nan if v is None else v for v in profile[key]], dtype=float)

    mean = array("mean")
    low, high = array("ci_low"), array("ci_high")
    return mean, np.where(np.isnan(low), mean, low), np.where(np.isnan(high), mean, high)


@dataclass(frozen=True)
class Descriptor:
    """A registered descriptor: how to compute it and what it writes.

    compute(ctx) -> (record of arrays, JSON section); tables(record) -> {CSV name:
    (header, rows)}; files(record, folder) -> other files written (names);
    figures(record, section, folder) -> figures drawn into ``folder`` (names);
    ensemble_figures(summary, folder) -> the same over an ensemble's repeats, from this
    descriptor's part of ``ensemble.json`` (with 95 % bands); comparison_figures(labels,
    summaries, folder) -> two ensembles side by side (``pipeline compare``);
    chip_columns(record) -> {column: one value per chip} for ``chips.csv``; headline(section)
    -> its part of the stage's one-line report, or None; ensemble_scalars: the scalars an
    ensemble's summary on the command line shows with their intervals. ``order``: where
    its columns and its part of the reports come among the other descriptors' (lower
    first; the built-ins keep the order their files have always had).
    """

    name: str
    doc: str
    compute: Callable[[Context], tuple[Any, dict[str, Any]]]
    tables: Callable[[Any], dict[str, Table]] = _no_tables
    files: Callable[[Any, Path], list[str]] = _no_files
    figures: Callable[[Any, dict[str, Any], Path], list[str]] = _no_figures
    ensemble_figures: Callable[[dict[str, Any], Path], list[str]] = _no_ensemble_figures
    comparison_figures: Callable[[tuple, tuple, Path], list[str]] = _no_comparison_figures
    chip_columns: Callable[[Any], dict[str, list]] = _no_columns
    ensemble_scalars: tuple[str, ...] = ()
    headline: Callable[[dict[str, Any]], str | None] = _no_headline
    order: int = 100


def figure_module() -> ModuleType:
    """:mod:`export.figures`, imported when a descriptor's figure is first drawn: it brings
    matplotlib, which a description without figures never needs."""
    from chipstack.export import figures

    return figures
