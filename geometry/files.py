"""Files of the geometry stage: descriptors.json, CSV tables and maps, the voxel image."""

from __future__ import annotations

import csv
import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from chipstack.core.arrangement import stack_history
from chipstack.core.schema import Scenario
from chipstack.core.stages import StageInputs, StageOutput
from chipstack.geometry.describe import Description, in_output_order
from chipstack.geometry.descriptor_kinds import DESCRIPTORS
from chipstack.geometry.run_figures import single_run_figures

__all__ = ["write_description"]


def _write_csv(path: Path, header: list[str], rows) -> None:
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(header)
        writer.writerows(rows)


# Ten significant digits: the last ones of a float depend on which OpenBLAS kernel the CPU
# gets (Haswell, SkylakeX and Sandybridge kernels differ in the 16th digit of the
# orientation tensor), and a result file must not change with the machine it ran on.
JSON_DIGITS = 10


def _rounded(value: Any) -> Any:
    """``value`` with every finite float cut to ``JSON_DIGITS`` significant digits."""
    if isinstance(value, dict):
        return {key: _rounded(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_rounded(item) for item in value]
    if isinstance(value, (float, np.floating)) and np.isfinite(value):
        return float(f"{float(value):.{JSON_DIGITS}g}")
    return value


def write_description(
    folder: Path, description: Description, arrangement, extra: dict[str, Any]
) -> list[str]:
    """Write ``descriptors.json`` and the tables of every computed descriptor into ``folder``.

    ``arrangement`` is the described stack (its final state). Returns the files written.
    """
    written = [_write_chips(folder, description, arrangement)]
    data = _rounded({**description.to_json(), **extra})
    (folder / "descriptors.json").write_text(json.dumps(data, indent=2) + "\n")
    written.append("descriptors.json")
    for name, record in description.records.items():
        descriptor = DESCRIPTORS.get(name)
        for file, (header, rows) in descriptor.tables(record).items():
            _write_csv(folder / file, header, rows)
            written.append(file)
        written += descriptor.files(record, folder)
    return written


def _write_chips(folder: Path, description: Description, arrangement) -> str:
    """chips.csv: one row per chip with every per-chip figure that was computed."""
    records = description.records
    n = arrangement.n_chips
    layer = np.floor(arrangement.positions[:, 2] / description.spec.layer_mm).astype(int)
    columns: dict[str, list] = {
        "chip": list(range(n)),
        "batch": arrangement.batch.tolist(),
        "layer": np.maximum(layer, 0).tolist(),
        "inside_target": arrangement.inside_target().astype(int).tolist(),
    }
    # Each descriptor's own per-chip columns, in the order the descriptors declare.
    for name in in_output_order(records):
        for column, values in DESCRIPTORS.get(name).chip_columns(records[name]).items():
            if column in columns or len(values) != n:
                problem = "is already a column" if column in columns else f"has not {n} values"
                raise ValueError(f"descriptor {name!r}: its chips.csv column {column!r} {problem}")
            columns[column] = values
    _write_csv(folder / "chips.csv", list(columns), zip(*columns.values(), strict=True))
    return "chips.csv"


def write_description_files(result: Description, folder: Path, inputs: StageInputs) -> StageOutput:
    """A computed description's files in ``folder`` and its manifest entry."""
    history = stack_history(inputs.result("packing"))
    summary = write_geometry(folder, result, history, inputs.scenario, inputs.options.figures)
    return StageOutput(summary)


def write_geometry(
    folder: Path, description: Description, history, scenario: Scenario, figures: bool
) -> dict[str, Any]:
    """Write a computed description's files into ``folder``; returns the manifest entry."""
    extra = {"scenario": scenario.name, "seed": scenario.seed, "chips": history[-1].n_chips}
    files = write_description(folder, description, history[-1], extra)
    if figures:
        files += single_run_figures(folder / "figures", description, history[-1])
    return {
        "descriptors": list(description.records),
        "files": sorted(files),
        "descriptor_time_s": round(sum(description.timings_s.values()), 4),
        "descriptor_times_s": {k: round(v, 4) for k, v in description.timings_s.items()},
    }


def report_lines(summary: Mapping[str, Any], folder: Path) -> list[str]:
    """The command line's summary of the written ``descriptors.json``: each descriptor's
    headline."""
    d = json.loads((folder / "descriptors.json").read_text())["descriptors"]
    known = in_output_order(d)
    parts = [DESCRIPTORS.get(n).headline(d[n]) for n in known]
    seconds = summary["descriptor_time_s"]
    return [f"descriptors in {seconds:.2f} s: " + "; ".join(p for p in parts if p)]
