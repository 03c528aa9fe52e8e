"""Process sweeps: an ensemble at every point of a grid of scenario values, and every
scalar descriptor against each swept key with 95 % intervals (``pipeline sweep``).

Each point is an ordinary ensemble directory (``OUT/<key>=<value>...``), run on the
execution layer (Dask: a local cluster, or ``--scheduler``) and resumed like one, so an
interrupted sweep started again with the same arguments goes on where it stopped and
``pipeline compare`` works between any two points. The sweep's table
(``sweep.json``, ``sweep.csv``) and figures (``figures/sweep_<key>.png``) are written
once every point is done.
"""

from __future__ import annotations

import csv
import hashlib
import itertools
import json
import logging
import math
import shutil
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from chipstack.core.errors import InputError, brief, printable
from chipstack.core.scenario_data import scenario_from_dict
from chipstack.core.scenario_edits import changed_data
from chipstack.core.schema import Scenario
from chipstack.pipeline.atomic import write_atomically
from chipstack.pipeline.ensemble import run_ensemble
from chipstack.pipeline.run import stages_to
from chipstack.pipeline.scenario_files import dumps_toml

__all__ = ["parse_vary", "sweep_points", "run_sweep", "SWEEP_SCHEMA"]

log = logging.getLogger(__name__)

SWEEP_SCHEMA = "chipstack.sweep/1"
MAX_POINTS = 1000
# Which points an earlier start finished, and with what scenario: those are reused.
JOURNAL = "sweep-points.json"
# Manifest entries of the first stage whose numbers are descriptors of the result.
_RESULT_ENTRIES = ("packing", "conveyor", "container", "drop")


def parse_vary(texts: Sequence[str]) -> list[tuple[str, list[Any]]]:
    """``KEY=V1,V2,...`` (``--vary``) as (key, values): numbers where they parse, else
    strings, ``true``/``false`` as booleans."""
    keys: list[tuple[str, list[Any]]] = []
    for text in texts:
        key, sep, values = text.partition("=")
        key = key.strip()
        if not sep or not key or not values.strip():
            raise InputError(f"--vary {printable(text)}: expected KEY=VALUE[,VALUE...]")
        if key in (k for k, _ in keys):
            raise InputError(f"--vary {printable(key)}: given twice")
        parsed = [_value(v.strip()) for v in values.split(",") if v.strip()]
        if any("/" in str(v) or "\\" in str(v) for v in parsed):
            raise InputError(
                f"--vary {printable(key)}: values name the points' folders; no '/' or '\\'"
            )
        if len(set(map(repr, parsed))) != len(parsed):
            raise InputError(f"--vary {printable(key)}: a value is repeated")
        keys.append((key, parsed))
    if not keys:
        raise InputError("--vary: give at least one KEY=VALUE[,VALUE...]")
    return keys


def _value(text: str) -> Any:
    if text in ("true", "false"):
        return text == "true"
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text


def _point_name(values: dict[str, Any]) -> str:
    """The point's folder name, values as written on the command line (TOML's true)."""

    def shown(value: Any) -> str:
        return str(value).lower() if isinstance(value, bool) else str(value)

    return ",".join(f"{key}={shown(value)}" for key, value in values.items())


def sweep_points(
    scenario: Scenario, vary: list[tuple[str, list[Any]]]
) -> list[tuple[dict[str, Any], Scenario]]:
    """Every point of the grid: (its values, its validated scenario). Any value the
    scenario refuses is refused here, before anything runs, naming the key."""
    for key, _ in vary:
        if scenario.mix and key.startswith("chip."):
            raise InputError(
                f"--vary {printable(key)}: the scenario pours a [[mix]], which replaces [chip]"
            )
    points = []
    grid = list(itertools.product(*[values for _, values in vary]))
    if len(grid) > MAX_POINTS:
        raise InputError(f"--vary: {len(grid)} points, more than {MAX_POINTS}")
    for combination in grid:
        values = dict(zip([key for key, _ in vary], combination, strict=True))
        try:
            data = changed_data(scenario, values)
        except InputError as exc:  # an unknown key: named with an example
            raise InputError(
                f"--vary {exc}".replace(
                    "see docs/scenarios.md", "see docs/scenarios.md; e.g. conveyor.belt_speed_mm_s"
                )
            ) from None
        try:
            points.append((values, scenario_from_dict(data)))
        except InputError as exc:
            raise InputError(f"--vary {_point_name(values)}: {exc}") from None
    seen: dict[str, str] = {}
    for values, point in points:
        text = dumps_toml(point)
        if text in seen:
            raise InputError(
                f"--vary: points {seen[text]} and {_point_name(values)} are the same scenario"
            )
        seen[text] = _point_name(values)
    return points


def run_sweep(
    scenario: Scenario,
    vary: list[tuple[str, list[Any]]],
    out: str | Path,
    repeats: int,
    to: str | None = "geometry",
    overwrite: bool = False,
    progress: Callable[[int, int], None] | None = None,
    command: list[str] | None = None,
    workers: int | None = None,
    scheduler: str | None = None,
) -> tuple[Path, dict[str, Any]]:
    """An ensemble of ``repeats`` runs at every point of ``vary``'s grid, then the sweep's
    table and figures in ``out``. Returns (out, the sweep record)."""
    points = sweep_points(scenario, vary)
    for _, point in points:
        stages_to(to, point)  # a stage the kind lacks: refused before anything is written
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out}: exists and is not a directory")
    if overwrite:
        _clear_points(out, [_point_name(values) for values, _ in points])
    out.mkdir(parents=True, exist_ok=True)
    total = len(points) * repeats
    done = [0]

    def step(finished: int, _repeats: int) -> None:
        done[0] += finished
        if progress is not None:
            progress(done[0], total)

    journal_path = out / JOURNAL
    journal = _read(journal_path) if journal_path.is_file() else {}
    rows = []
    for values, point in points:
        name = _point_name(values)
        folder = out / name
        identity = {
            "scenario_sha256": hashlib.sha256(dumps_toml(point).encode()).hexdigest(),
            "repeats": repeats,
            "to": to,
        }
        if journal.get(name) == identity and (folder / "manifest.json").is_file():
            manifest = _read(folder / "manifest.json")  # finished by an earlier start
            step(repeats, repeats)
        else:
            _, manifest = run_ensemble(
                point,
                folder,
                repeats,
                to=to,
                # A point this sweep finished before with other settings is replaced.
                overwrite=name in journal,
                progress=step,
                command=command,
                workers=workers,
                scheduler=scheduler,
            )
            journal[name] = identity
            write_atomically(journal_path, json.dumps(journal, indent=1) + "\n")
        rows.append({"values": values, "dir": name, **_point_scalars(folder, manifest)})
    record = {
        "schema": SWEEP_SCHEMA,
        "scenario": scenario.name,
        "seed": scenario.seed,
        "repeats": repeats,
        "keys": [key for key, _ in vary],
        "confidence": 0.95,
        "points": rows,
    }
    (out / "sweep.json").write_text(json.dumps(record, indent=1) + "\n")
    write_sweep_table(out / "sweep.csv", record)
    if not any(p["scalars"] for p in rows):
        log.warning("the sweep's runs give no scalar to draw; no figures")
        return out, record
    from chipstack.export.process_figures import plot_sweep  # matplotlib only when drawing

    (out / "figures").mkdir(exist_ok=True)
    for key in record["keys"]:
        plot_sweep(out / "figures" / f"sweep_{key}.png", record, key)
    return out, record


def _clear_points(out: Path, names: list[str]) -> None:
    """--overwrite: remove the earlier runs of these points (and the journal) first, so
    an interrupted sweep resumes from this start, not the earlier one. A folder that is
    not an earlier run or ensemble is refused, and nothing is removed."""
    folders = [out / name for name in names if (out / name).exists()]
    for folder in folders:
        if not ((folder / "manifest.json").is_file() or (folder / "ensemble-state.json").is_file()):
            raise InputError(f"--out {folder}: not an earlier run (no manifest.json); not replaced")
    for folder in folders:
        shutil.rmtree(folder)
    (out / JOURNAL).unlink(missing_ok=True)


def _point_scalars(folder: Path, manifest: dict[str, Any]) -> dict[str, Any]:
    """Mean and 95 % interval of every scalar of one point: the geometry's descriptors
    (its ``ensemble.json``) and the numbers of the packing's result entries (a
    conveyor's mat, a container's fill) over the repeats' manifests."""
    # scipy.stats, 0.7 s to import: not for a sweep whose --vary is refused.
    from chipstack.geometry.stats import summarize

    scalars: dict[str, dict[str, Any]] = {}
    ensemble = folder / "ensemble.json"
    if ensemble.exists():
        summary = json.loads(ensemble.read_text())
        for name, descriptor in summary["descriptors"].items():
            for key, s in descriptor["scalars"].items():
                scalars[f"{name}.{key}"] = {
                    k: s[k] for k in ("unit", "n", "mean", "ci_low", "ci_high")
                }
    values: dict[str, list[float]] = {}
    for run in manifest["runs"]:
        entry = json.loads((folder / run / "manifest.json").read_text())
        for section in _RESULT_ENTRIES:
            for key, value in _numbers(entry.get(section), section):
                values.setdefault(key, []).append(value)
    for key, sample in values.items():
        if len(sample) != len(manifest["runs"]):
            continue  # missing from some runs (an undefined figure): no interval
        s = summarize(sample)
        scalars[key] = {
            "unit": "",
            "n": s.n,
            "mean": s.mean,
            "ci_low": s.ci_low if math.isfinite(s.ci_low) else None,
            "ci_high": s.ci_high if math.isfinite(s.ci_high) else None,
        }
    return {"scalars": scalars}


def _read(path: Path) -> dict[str, Any]:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise InputError(f"{path}: unreadable ({brief(str(exc))}); use --overwrite") from None


def _numbers(entry: Any, prefix: str):
    """(dotted key, value) of every finite number in a nested manifest entry."""
    if isinstance(entry, dict):
        for key, value in entry.items():
            yield from _numbers(value, f"{prefix}.{key}")
    elif isinstance(entry, int | float) and not isinstance(entry, bool):
        if math.isfinite(entry):
            yield prefix, float(entry)


def write_sweep_table(path: Path, record: dict[str, Any]) -> None:
    """One row per point: its values, then mean, low and high of every scalar."""
    names = sorted({name for row in record["points"] for name in row["scalars"]})
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        header = list(record["keys"])
        for name in names:
            header += [f"{name} mean", f"{name} ci_low", f"{name} ci_high"]
        writer.writerow(header)
        for row in record["points"]:
            line = [row["values"][key] for key in record["keys"]]
            for name in names:
                s = row["scalars"].get(name, {})
                line += [_cell(s.get("mean")), _cell(s.get("ci_low")), _cell(s.get("ci_high"))]
            writer.writerow(line)


def _cell(value: Any) -> str:
    return "" if value is None else f"{value:.6g}"
