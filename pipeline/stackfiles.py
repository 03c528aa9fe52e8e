"""Reading a packing result back from a run directory (for `pipeline describe`)."""

from __future__ import annotations

import csv
import re
from pathlib import Path

import numpy as np

from chipstack.core.arrangement import Arrangement
from chipstack.core.errors import InputError
from chipstack.core.files import read_json, read_text
from chipstack.core.keys import MAX_LENGTH_MM
from chipstack.core.schema import Scenario, printable
from chipstack.export.tables import POSE_COLUMNS
from chipstack.packing.shapes import make_shape, shape_from_record, varies_per_chip
from chipstack.pipeline.scenario_files import load_resolved

__all__ = ["load_run"]

_POSES = re.compile(r"poses_after_batch_(\d+)\.csv")


def load_run(run_dir: str | Path) -> tuple[Scenario, list[Arrangement], dict]:
    """The scenario, the stack after every batch, and the manifest of a finished run.

    Raises :class:`InputError` naming the directory or file and what is wrong with it.
    """
    run = Path(run_dir)
    shown = printable(run_dir)
    if not run.is_dir():
        raise InputError(f"{shown}: no such run directory")
    manifest_path = run / "manifest.json"
    if not manifest_path.is_file():
        raise InputError(f"{shown}: not a run directory (no manifest.json)")
    manifest = read_json(manifest_path, "manifest")
    stages = manifest.get("stages_completed") if isinstance(manifest, dict) else None
    if stages is not None and not (
        isinstance(stages, list) and all(isinstance(s, str) for s in stages)
    ):
        raise InputError(f"{manifest_path}: stages_completed must be a list of stage names")
    if not stages or "packing" not in stages:
        raise InputError(f"{shown}: holds no packing result (run `pipeline run --to packing`)")
    scenario_path = run / "scenario.toml"
    if not scenario_path.is_file():
        raise InputError(f"{shown}: no scenario.toml; the packing result cannot be read")
    scenario = load_resolved(scenario_path)
    if not scenario.chosen.later_stages:  # a conveyor's stack: its panel
        raise InputError(
            f"{shown}: a {scenario.kind} run has no stack to describe (see its manifest)"
        )
    files = sorted(
        (int(m.group(1)), p)
        for p in (run / "packing").glob("poses_after_batch_*.csv")
        if (m := _POSES.fullmatch(p.name))
    )
    if not files:
        raise InputError(f"{shown}: holds no packing result (no packing/poses_after_batch_*.csv)")
    numbers = [n for n, _ in files]
    if numbers != list(range(1, len(files) + 1)):
        raise InputError(f"{run / 'packing'}: batch files must be numbered 1 to N, got {numbers}")
    shapes = _read_shapes(run / "packing" / "shapes.json", scenario)
    history = []
    previous = 0
    for number, path in files:
        arrangement = _read_poses(path, shapes, scenario.deposition.target_size_mm)
        if arrangement.n_chips <= previous:
            raise InputError(
                f"{path}: {arrangement.n_chips} chips, not more than batch {number - 1}"
            )
        if arrangement.batch.max(initial=0) != number:
            raise InputError(f"{path}: last batch column is not {number}")
        previous = arrangement.n_chips
        history.append(arrangement)
    return scenario, history, manifest


def _read_shapes(path: Path, scenario: Scenario) -> dict:
    """The run's chip shapes by name (``packing/shapes.json``; runs from before that file
    existed rebuild their single shape from the scenario)."""
    if not path.is_file():
        if len(scenario.chips) == 1 and not varies_per_chip(scenario.chips[0]):
            shape = make_shape(scenario.chips[0])
            return {shape.name: shape}
        raise InputError(f"{path}: missing; the chip shapes of this run are unknown")
    data = read_json(path, "shapes file")
    if not isinstance(data, dict) or data.get("schema") != "chipstack.shapes/1":
        raise InputError(f"{path}: not a chipstack shapes file (schema chipstack.shapes/1)")
    records = data.get("shapes")
    if not isinstance(records, list) or not records:
        raise InputError(f"{path}: holds no shapes")
    shapes = {}
    for k, record in enumerate(records):
        if not isinstance(record, dict):
            raise InputError(f"{path}: shape {k} is not a table")
        shape = shape_from_record(record, f"{path} shape {k}")
        if shape.name in shapes:
            raise InputError(f"{path}: shape name {shape.name!r} appears twice")
        shapes[shape.name] = shape
    return shapes


def _read_poses(path: Path, shapes: dict, target_size_mm: float) -> Arrangement:
    text = read_text(path, "poses file")
    try:
        rows = list(csv.reader(text.splitlines()))
    except csv.Error as exc:
        raise InputError(f"{path}: unreadable poses file ({exc})") from None
    if not rows:
        raise InputError(f"{path}: empty poses file")
    if tuple(rows[0]) != POSE_COLUMNS:
        raise InputError(f"{path}: header must be {','.join(POSE_COLUMNS)}")
    body = rows[1:]
    if not body:
        raise InputError(f"{path}: no chips")
    numbers = np.empty((len(body), 7))
    batch = np.empty(len(body), dtype=np.int64)
    names = list(shapes)
    index = {name: k for k, name in enumerate(names)}
    shape_index = np.empty(len(body), dtype=np.int64)
    for line, row in enumerate(body, start=2):
        if len(row) != len(POSE_COLUMNS):
            raise InputError(f"{path} line {line}: {len(row)} fields, expected {len(POSE_COLUMNS)}")
        if row[0] != str(line - 2):
            raise InputError(f"{path} line {line}: chip {printable(row[0])}, expected {line - 2}")
        if row[2] not in index:
            raise InputError(
                f"{path} line {line}: shape {printable(row[2])} is not one of the run's "
                f"shapes ({', '.join(sorted(index)[:5])})"
            )
        shape_index[line - 2] = index[row[2]]
        try:
            batch[line - 2] = int(row[1])
            numbers[line - 2] = [float(v) for v in row[3:10]]
        except ValueError:
            raise InputError(f"{path} line {line}: a value is not a number") from None
        except OverflowError:  # an integer beyond the batch column's 64 bits
            raise InputError(
                f"{path} line {line}: batch {printable(row[1])} is out of range"
            ) from None
    if not np.isfinite(numbers).all():
        row, column = np.argwhere(~np.isfinite(numbers))[0]
        raise InputError(
            f"{path} line {row + 2}: NaN or infinite value in column {POSE_COLUMNS[3 + column]}"
        )
    far = np.abs(numbers[:, :3]) > MAX_LENGTH_MM
    if far.any():
        row, column = np.argwhere(far)[0]
        raise InputError(
            f"{path} line {row + 2}: {POSE_COLUMNS[3 + column]} beyond {MAX_LENGTH_MM:g} mm"
        )
    if batch.min() < 1 or (np.diff(batch) < 0).any():
        raise InputError(f"{path}: batch numbers must start at 1 and never decrease")
    quaternions = numbers[:, 3:7]
    norms = np.linalg.norm(quaternions, axis=1)
    if np.abs(norms - 1).max() > 1e-4:
        bad = int(np.argmax(np.abs(norms - 1))) + 2
        raise InputError(f"{path} line {bad}: quaternion is not of unit length")
    return Arrangement(
        tuple(shapes[name] for name in names),
        shape_index,
        numbers[:, :3],
        quaternions / norms[:, None],
        batch,
        target_size_mm,
    )
