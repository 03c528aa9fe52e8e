"""`pipeline validate`: the paper's validation cases rerun, our values beside the paper's.

Cases (``CASES``), each a built-in scenario:

* ``drop`` (section 4.2, Fig. 15): ``single-chip-drop``, repeated; spread and 4-fold
  anisotropy of the final positions;
* ``mat`` (section 5, Fig. 16): ``fibre-mat``, 1,000 fibres on a 100 mm target;
* ``container`` (section 5, Fig. 17): ``container-ar10`` and ``container-ar25``;
* ``mixed`` (Fig. 18): ``mixed-shapes``, described, meshed and rendered.

Every repeat of every case is one task for the execution layer (Dask), so they run in
parallel; results are gathered here, written to ``validation.json`` and
``validation.md``, and returned as table rows.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable, Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from chipstack.core.arrangement import arrangements_from_stack
from chipstack.core.errors import InputError
from chipstack.core.keys import MAX_DROPS, MAX_REPEATS
from chipstack.core.overlap import vertex_heights_mm
from chipstack.core.schema import printable
from chipstack.export.process_figures import plot_drops
from chipstack.export.render import render_stack
from chipstack.export.vtk import stack_polydata
from chipstack.geometry.contacts import find_contacts
from chipstack.packing import deposit
from chipstack.packing.drop import drop_chips
from chipstack.packing.scatter import drop_statistics
from chipstack.packing.shapes import shape_from_record, shape_record
from chipstack.packing.writers import container_summary
from chipstack.pipeline.execution import Executor
from chipstack.pipeline.run import compute_run, derive_seed, write_run
from chipstack.pipeline.rundir import RunDirectory
from chipstack.pipeline.scenario_files import load_scenario

__all__ = ["CASES", "validate", "PAPER"]

log = logging.getLogger(__name__)

CASES = ("drop", "mat", "container", "mixed")

# The paper's figures and the measured references it quotes (facts.md).
PAPER = {
    ("mat", "volume fraction (%)"): (6.68, "Mahé's model 6.61"),
    ("mat", "fibre-fibre contacts"): (2169, "Mahé's model 2212 ± 42"),
    ("container AR 25", "volume fraction (%)"): (14.8, "Freeman et al. about 18"),
    ("container AR 10", "volume fraction (%)"): (28.6, "Freeman et al. about 37"),
}
MEASURED = {"container AR 25": 18.0, "container AR 10": 37.0}


def _drop_task(scenario) -> dict:
    drops = drop_chips(scenario)
    stats = drop_statistics(drops.positions[:, :2], scenario.drop.yaw_deg)
    stats["xy"] = drops.positions[:, :2].tolist()
    return stats


def _mat_task(scenario) -> dict:
    stack = deposit(scenario)
    arrangement = arrangements_from_stack(stack)[-1]
    g = scenario.geometry
    table = find_contacts(arrangement, g.contact_gap_mm, g.contact_extent_mm)
    between = int((table.chip_b >= 0).sum())
    shape = stack.shapes[0]
    top = float(vertex_heights_mm(stack.positions, stack.quaternions, shape.vertices).max())
    inside = stack.inside_target()
    area = scenario.deposition.target_size_mm**2
    volume = sum(stack.shapes[k].volume_mm3 for k in stack.shape_index)
    inside_volume = sum(stack.shapes[k].volume_mm3 for k in stack.shape_index[inside])
    return {
        "fibres": stack.n_chips,
        "inside_target": int(inside.sum()),
        "top_mm": top,
        "volume_fraction_all": volume / (area * top),
        "volume_fraction_inside": inside_volume / (area * top),
        "contacts_fibre_fibre": between,
        "contacts_with_floor": int(len(table.chip_a)),
        "shape": shape_record(shape),
        "positions": stack.positions.tolist(),
        "quaternions": stack.quaternions.tolist(),
    }


def _container_task(scenario) -> dict:
    return container_summary(deposit(scenario), scenario)


def _mixed_task(scenario):
    return compute_run(scenario, "geometry", None)


def _call(function: Callable, scenario) -> Any:
    return function(scenario)


def _mean_sd(values: Sequence[float]) -> tuple[float, float]:
    values = np.asarray(values, dtype=float)
    return float(values.mean()), float(values.std(ddof=1)) if len(values) > 1 else 0.0


def validate(
    out: str | Path,
    cases: Sequence[str] = CASES,
    repeats: int = 10,
    drops: int = 50,
    seed: int = 0,
    workers: int | None = None,
    scheduler: str | None = None,
    progress: Callable[[int, int], None] | None = None,
    overwrite: bool = False,
    command: list[str] | None = None,
) -> list[dict[str, Any]]:
    """Run the validation cases into the directory ``out`` (written as a whole when done,
    with the guards of every run directory); returns the table rows (also written)."""
    _check_arguments(cases, repeats, drops)
    run = RunDirectory(out, overwrite=overwrite)
    run.check()
    tasks = _tasks(cases, repeats, drops, seed)
    results, errors = _run(tasks, workers, scheduler, progress)
    with run:
        rows = _rows(results, run.folder, seed)
        report = {"seed": seed, "repeats": repeats, "drops": drops, "rows": rows, "errors": errors}
        run.write_json("validation.json", report)
        run.write_text("validation.md", table_markdown(rows) + "\n")
        run.write_json(
            "manifest.json",
            {
                "tool": "chipstack",
                "kind": "validation",
                "command": command or [],
                "cases": list(cases),
                "seed": seed,
                "repeats": repeats,
                "drops": drops,
                "errors": len(errors),
                "finished_utc": datetime.now(UTC).isoformat(timespec="seconds"),
            },
        )
    return rows


def _check_arguments(cases: Sequence[str], repeats: int, drops: int) -> None:
    for case in cases:
        if case not in CASES:
            raise InputError(
                f"--cases: unknown case {printable(case)!r}; valid: {', '.join(CASES)}"
            )
    if not 2 <= repeats <= MAX_REPEATS:
        raise InputError(f"--repeats: must be between 2 and {MAX_REPEATS}, got {repeats}")
    if not 2 <= drops <= MAX_DROPS:
        raise InputError(f"--drops: must be between 2 and {MAX_DROPS}, got {drops}")


def _tasks(
    cases: Sequence[str], repeats: int, drops: int, seed: int
) -> list[tuple[str, Callable, Any]]:
    """(result key, task function, scenario) of every repeat of every case."""

    def repeated(key: str, function: Callable, base) -> list[tuple[str, Callable, Any]]:
        return [(key, function, base.with_seed(derive_seed(seed, k))) for k in range(repeats)]

    tasks: list[tuple[str, Callable, Any]] = []
    if "drop" in cases:
        base = load_scenario("single-chip-drop")
        base = dataclasses.replace(base, drop=dataclasses.replace(base.drop, drops=drops))
        tasks += repeated("drop", _drop_task, base)
    if "mat" in cases:
        tasks += repeated("mat", _mat_task, load_scenario("fibre-mat"))
    if "container" in cases:
        for name in ("container-ar25", "container-ar10"):
            tasks += repeated(name, _container_task, load_scenario(name))
    if "mixed" in cases:
        tasks.append(("mixed", _mixed_task, load_scenario("mixed-shapes").with_seed(seed)))
    return tasks


def _run(
    tasks: list[tuple[str, Callable, Any]],
    workers: int | None,
    scheduler: str | None,
    progress: Callable[[int, int], None] | None,
) -> tuple[dict[str, list], list[str]]:
    """Run the tasks on the execution layer: results by key, and one line per failure."""

    results: dict[str, list] = {}
    errors: list[str] = []

    def on_result(j: int, value: Any) -> None:
        results.setdefault(tasks[j][0], []).append(value)
        if progress:
            progress(1, len(tasks))

    def on_error(j: int, error: BaseException) -> None:
        errors.append(f"{tasks[j][0]} (seed {tasks[j][2].seed}): {type(error).__name__}: {error}")
        log.warning("%s", errors[-1])
        if progress:
            progress(1, len(tasks))

    with Executor(workers=workers, scheduler=scheduler) as executor:
        executor.run(
            _call,
            [(function, scenario) for _, function, scenario in tasks],
            on_result,
            on_error,
        )
    return results, errors


def _row(case, quantity, ours, paper=None, measured=None, definition="") -> dict[str, Any]:
    mean, sd = ours
    reference = paper if paper is not None else measured
    difference = (
        100 * (mean - reference) / reference
        if isinstance(reference, int | float) and reference
        else None
    )
    return {
        "case": case,
        "quantity": quantity,
        "paper": paper,
        "measured": measured,
        "ours_mean": mean,
        "ours_sd": sd,
        "difference_pct": difference,
        "definition": definition,
    }


def _rows(results: dict[str, list], folder: Path, seed: int) -> list[dict[str, Any]]:
    rows: list[dict[str, Any]] = []
    if "drop" in results:
        rows += _drop_rows(results["drop"], folder)
    if "mat" in results:
        rows += _mat_rows(results["mat"], folder)
    for name, label in (
        ("container-ar25", "container AR 25"),
        ("container-ar10", "container AR 10"),
    ):
        if name in results:
            rows.append(_container_row(results[name], label))
    if "mixed" in results:
        rows.append(_mixed_row(results["mixed"][0], folder))
    return rows


def _drop_rows(runs: list[dict], folder: Path) -> list[dict[str, Any]]:
    """Fig. 15: the scatter of the single-chip drops, per experiment and pooled."""

    first = runs[0]
    plot_drops(folder / "fig15_drops.png", np.array(first["xy"]), first)
    pooled = drop_statistics(np.vstack([np.array(r["xy"]) for r in runs]))
    significant = sum(r["anisotropy_p"] < 0.05 for r in runs)
    return [
        _row(
            "drop",
            "sd of distance to (0,0) (mm)",
            _mean_sd([r["distance_sd_mm"] for r in runs]),
            "Fig. 15",
            definition=f"{first['drops']} drops per experiment, {len(runs)} experiments",
        ),
        _row(
            "drop",
            "95 % disc radius (mm)",
            _mean_sd([r["disc95_mm"] for r in runs]),
            "Fig. 15",
            definition="smallest disc centred on (0,0) holding 95 %",
        ),
        _row(
            "drop",
            "4-fold anisotropy (resultant of 4 theta)",
            _mean_sd([r["anisotropy"] for r in runs]),
            "X along corners",
            definition=f"significant (Rayleigh p < 0.05) in {significant} of {len(runs)}; "
            f"pooled over {pooled['drops']} drops p = {pooled['anisotropy_p']:.2g}",
        ),
        _row(
            "drop",
            "4-fold axis from corner directions (deg)",
            _mean_sd([r["corner_offset_deg"] for r in runs]),
            0.0,
            definition=f"pooled axis {pooled['axis_deg']:.1f} deg, corners at 45 "
            f"deg (offset {pooled['corner_offset_deg']:.1f} deg)",
        ),
    ]


def _mat_rows(runs: list[dict], folder: Path) -> list[dict[str, Any]]:
    """Fig. 16: the fibre mat's volume fraction and contacts against the paper's."""
    _mat_figure(folder / "fig16_mat.png", runs[0])
    fraction_paper, fraction_model = PAPER[("mat", "volume fraction (%)")]
    contacts_paper, contacts_model = PAPER[("mat", "fibre-fibre contacts")]
    return [
        _row(
            "mat",
            "volume fraction (%)",
            _mean_sd([100 * r["volume_fraction_all"] for r in runs]),
            fraction_paper,
            fraction_model,
            definition="all fibre volume / (target area x height of the top)",
        ),
        _row(
            "mat",
            "volume fraction over the target (%)",
            _mean_sd([100 * r["volume_fraction_inside"] for r in runs]),
            fraction_paper,
            definition="fibres with centre over the target, same box",
        ),
        _row(
            "mat",
            "fibre-fibre contacts",
            _mean_sd([r["contacts_fibre_fibre"] for r in runs]),
            contacts_paper,
            contacts_model,
            definition="touching pairs (gap < 0.05 mm), floor excluded",
        ),
        _row(
            "mat",
            "fibres over the target",
            _mean_sd([r["inside_target"] for r in runs]),
            definition="of 1,000 poured",
        ),
    ]


def _container_row(runs: list[dict], label: str) -> dict[str, Any]:
    """Fig. 17: a container's volume fraction against the paper's and Freeman's."""
    full = sum(r["full"] for r in runs)
    paper, _ = PAPER[(label, "volume fraction (%)")]
    return _row(
        label,
        "volume fraction (%)",
        _mean_sd([100 * r["volume_fraction"] for r in runs]),
        paper,
        MEASURED[label],
        definition=f"rods with centre inside / cylinder; {full} of {len(runs)} filled",
    )


def _mixed_row(result, folder: Path) -> dict[str, Any]:
    """Fig. 18: the mixed stack written as a run (described, meshed and rendered)."""

    run = RunDirectory(folder / "mixed", overwrite=True)
    with run:
        manifest = write_run(run.path, "", result, "mesh", ["validate"], True)
    mesh = manifest["mesh"]["voxel"]
    return _row(
        "mixed (Fig. 18)",
        "chips; voxel hexahedra",
        (float(manifest["packing"]["chips"]), 0.0),
        definition=f"{mesh['elements']:,} hexahedra; picture in mixed/",
    )


def _mat_figure(path: Path, run: dict) -> None:
    """Fig. 16: the fibre mat rendered (pyvista, off screen); skipped with a warning if no
    renderer is available."""

    shape = shape_from_record(run["shape"], "fibre-mat run")
    positions = np.array(run["positions"])
    mesh = stack_polydata(
        (shape,),
        np.zeros(len(positions), int),
        positions,
        np.array(run["quaternions"]),
        np.ones(len(positions), int),
    )
    try:
        render_stack(path, mesh)
    except RuntimeError as exc:
        log.warning("mat picture not rendered: %s", exc)


def table_markdown(rows: list[dict[str, Any]]) -> str:
    """The validation table: case, quantity, paper, measured, ours (mean ± sd), difference."""

    def show(value) -> str:
        if value is None:
            return "-"
        if isinstance(value, float):
            return f"{value:.3g}"
        return str(value)

    lines = [
        "| case | quantity | paper | measured | ours (mean ± sd) | difference | definition |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        ours = f"{r['ours_mean']:.3g} ± {r['ours_sd']:.2g}"
        diff = (
            "-"
            if r["difference_pct"] is None or math.isnan(r["difference_pct"])
            else (f"{r['difference_pct']:+.1f} %")
        )
        lines.append(
            f"| {r['case']} | {r['quantity']} | {show(r['paper'])} | {show(r['measured'])} | "
            f"{ours} | {diff} | {r['definition']} |"
        )
    return "\n".join(lines)
