"""``pipeline diagnose`` and ``pipeline synth``: wiring the diagnosis to files and Dask."""

from __future__ import annotations

import csv
import dataclasses
import io
import logging
import time
from collections.abc import Callable
from pathlib import Path

from chipstack.core.errors import InputError
from chipstack.core.keys import MAX_DROPS
from chipstack.core.schema import printable
from chipstack.diagnosis.spec import EXPERIMENT_KINDS, Experiment, load_experiment
from chipstack.packing.effects import EFFECTS, check_effects
from chipstack.pipeline.atomic import write_atomically
from chipstack.pipeline.execution import Executor
from chipstack.pipeline.rundir import RunDirectory, check_output_file
from chipstack.pipeline.scenario_files import load_scenario
from chipstack.pipeline.tables import DirectoryStore, default_tables_dir

__all__ = ["diagnose", "synth", "parse_effects"]

log = logging.getLogger(__name__)


def parse_effects(items: list[str] | None, kind: str) -> dict[str, float]:
    """``["air_drag=2", ...]`` checked against the registry and the priors."""
    strengths: dict[str, float] = {}
    for item in items or []:
        name, sep, value = item.partition("=")
        name = name.strip()
        if not sep or not name:
            raise InputError(f"--effect {item!r}: expected NAME=STRENGTH")
        EFFECTS.get(name, key="--effect")
        if name in strengths:
            raise InputError(f"--effect {name}: given twice")
        try:
            strengths[name] = float(value)
        except ValueError:
            raise InputError(f"--effect {name}: strength {value!r} is not a number") from None
    return check_effects(strengths, kind, key="--effect")


def diagnose(
    spec: str | Path,
    out: str | Path,
    seed: int = 0,
    workers: int | None = None,
    scheduler: str | None = None,
    overwrite: bool = False,
    progress: Callable[[str], None] | None = None,
    command: list[str] | None = None,
    tables: str | Path | None = None,
) -> tuple[Path, dict]:
    """Read and check everything, run the diagnosis on Dask, write the report. The
    reference tables of the amortised model choice are kept in ``tables`` (default: the
    user's cache directory), so a second diagnosis of a design reuses them."""
    if seed < 0:
        raise InputError("--seed: must not be negative")
    store = DirectoryStore(tables if tables is not None else default_tables_dir())
    experiment = load_experiment(spec, load_scenario)
    data = _observations(experiment)
    run_dir = RunDirectory(out, overwrite=overwrite)
    # The statistics, the simulations and the report are imported only once the inputs
    # are known to be good (seconds of scipy and matplotlib that a typo need not pay for).
    from chipstack.diagnosis.report import write_diagnosis

    start = time.perf_counter()
    with run_dir as run:  # locked from here: a second diagnosis into it is refused
        with Executor(workers=workers, scheduler=scheduler) as executor:
            kind = EXPERIMENT_KINDS.get(experiment.kind)
            result = kind.diagnose(experiment, data, executor.map, seed, progress, tables=store)
        result["wall_time_s"] = time.perf_counter() - start
        result["command"] = list(command or [])
        result["spec"] = str(Path(spec).resolve())
        result["observations_file"] = str(experiment.observations)
        write_diagnosis(run, result)
        run.write_json("manifest.json", _manifest(result, experiment))
    return run_dir.target, result


def _observations(experiment: Experiment):
    return EXPERIMENT_KINDS.get(experiment.kind).read_observations(experiment)


def _manifest(result: dict, experiment: Experiment) -> dict:
    return {
        "command": result["command"],
        "stage": "diagnosis",
        "experiment": experiment.name,
        "kind": experiment.kind,
        "seed": result["seed"],
        "wall_time_s": result["wall_time_s"],
        "verdict": result["verdict"]["kind"],
    }


def synth(
    spec: str | Path,
    effects: list[str] | None,
    seed: int,
    output: str | Path,
    drops: int = 50,
    overwrite: bool = False,
    workers: int | None = None,
    position_sd_mm: float | None = None,
    angle_sd_deg: float | None = None,
    measurements: int | None = None,
) -> tuple[Path, int]:
    """Pseudo-experimental observations with the given effects, written atomically;
    measurement noise as in the spec unless given here."""
    if seed < 0:
        raise InputError("--seed: must not be negative")
    if not 1 <= drops <= MAX_DROPS:
        raise InputError(f"--drops: must be between 1 and {MAX_DROPS}, got {drops}")
    for flag, value, top in (
        ("--position-sd-mm", position_sd_mm, 100.0),
        ("--angle-sd-deg", angle_sd_deg, 45.0),
    ):
        if value is not None and not 0 <= value <= top:  # also refuses NaN
            raise InputError(f"{flag}: must be between 0 and {top:g}, got {value}")
    experiment = load_experiment(spec, load_scenario)
    if position_sd_mm is not None:
        experiment = dataclasses.replace(experiment, position_sd_mm=position_sd_mm)
    if angle_sd_deg is not None:
        experiment = dataclasses.replace(experiment, angle_sd_deg=angle_sd_deg)
    strengths = parse_effects(effects, experiment.kind)
    shown = f"-o {printable(output)}"
    target = check_output_file(output, shown, overwrite)
    kind = EXPERIMENT_KINDS.get(experiment.kind)
    with Executor(workers=workers) as executor:
        rows = kind.synthesize(experiment, strengths, seed, executor.map, drops, measurements)
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=list(rows[0]), lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    try:
        write_atomically(target, buffer.getvalue())
    except OSError as exc:
        raise InputError(f"{shown}: cannot write ({exc.strerror or exc})") from None
    return target, len(rows)
