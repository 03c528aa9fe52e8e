"""The built-in ``loose-press`` scenario pressed loose, to its target: how long the solver
takes, in how many steps and Newton iterations, and what it reaches.

    python benchmarks/bench_loose_press.py [--out DIR] [--part-s 900] [--parts 12]

Runs ``pipeline run loose-press --to solve --out DIR`` in parts of ``--part-s`` seconds
of solver time (``solve.time_limit_s``): a part that stops at its limit keeps the
accepted steps as checkpoints and the next part resumes from them, so the study can be
stopped and run again and only loses the step under way. The solver time is the sum of
the steps' own times (``force_displacement.csv``), whatever the number of parts.

Records (``pipeline.measured.record``, area ``loose-press``; ``--no-record`` for a
trial) the solver time against the issue's 10 minutes, the steps, Newton iterations and
degrees of freedom, the smallest gap of any accepted step (must stay above zero), the
nominal pressure reached against 2 MPa, the void fraction of the stack's box before and
after, and the steps where the platen force fell (a chip slipping off its support).
"""

from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CACHE = ROOT / "benchmarks" / "cache" / "loose-press"
AREA = "loose-press"


def _part(out: Path, part_s: float) -> tuple[int, str]:
    command = [
        sys.executable,
        "-m",
        "chipstack.pipeline",
        "run",
        "loose-press",
        "--to",
        "solve",
        "--out",
        str(out),
        "--quiet",
        "--set",
        f"solve.time_limit_s={part_s:g}",
    ]
    done = subprocess.run(command, cwd=ROOT, check=False, capture_output=True, text=True)
    return done.returncode, done.stderr.strip()


def _history(solve: Path) -> list[dict[str, float]]:
    with open(solve / "force_displacement.csv", newline="") as f:
        return [{k: float(v) for k, v in row.items()} for row in csv.DictReader(f)]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=CACHE, help="run directory (resumed)")
    parser.add_argument("--part-s", type=float, default=900.0, help="solver seconds a part")
    parser.add_argument("--parts", type=int, default=12, help="parts at most")
    parser.add_argument("--no-record", action="store_true", help="print, record nothing")
    args = parser.parse_args(argv)

    solve = args.out / "solve"
    started = time.perf_counter()
    for part in range(1, args.parts + 1):
        if (solve / "press_summary.json").exists():
            break
        code, message = _part(args.out, args.part_s)
        print(f"part {part}: exit {code} after {time.perf_counter() - started:.0f} s {message}")
        if code != 0 and "time limit" not in message:  # a stop at the limit resumes
            return code
    if not (solve / "press_summary.json").exists():
        print(f"not finished after {args.parts} parts; run again to go on")
        return 1

    summary = json.loads((solve / "press_summary.json").read_text())
    history = _history(solve)
    solver_s = sum(row["seconds"] for row in history)
    forces = [row["platen_force_n"] for row in history]
    # Under a travel drive the force may fall where a chip slips off its support: the
    # steps where it fell by more than 1 % are counted and named, not hidden.
    drops = [
        k + 2
        for k, (a, b) in enumerate(zip(forces[:-1], forces[1:], strict=True))
        if b < a - 0.01 * abs(a)
    ]
    model = summary.get("model", {})
    dofs = float(model.get("dofs", model.get("n_dof", 0)))
    command = "python benchmarks/bench_loose_press.py"
    figures = [
        ("24-chip loose press, solver time", solver_s, "s", "<= 600", True),
        ("24-chip loose press, steps", float(len(history)), "", "", False),
        ("24-chip loose press, Newton iterations", summary["newton_iterations"], "", "", False),
        ("24-chip loose press, degrees of freedom", dofs, "", "", False),
        ("24-chip loose press, smallest gap", summary["smallest_gap_mm"], "mm", "> 0", False),
        ("24-chip loose press, travel", summary["press_mm"], "mm", "", False),
        (
            "24-chip loose press, nominal pressure reached",
            summary["nominal_pressure_mpa"],
            "MPa",
            ">= 2",
            True,
        ),
        (
            "24-chip loose press, void fraction before",
            summary["void_fraction_start"],
            "",
            "",
            False,
        ),
        ("24-chip loose press, void fraction after", summary["void_fraction"], "", "", False),
        (
            "24-chip loose press, steps where the platen force fell",
            float(len(drops)),
            "",
            "",
            False,
        ),
    ]
    note = (
        f"{len(history)} steps of 1 % of the stack's height, hot chips; "
        f"{solver_s / max(len(history), 1):.1f} s a step; force fell at steps {drops or 'none'}"
    )
    for name, value, unit, target, headline in figures:
        print(f"{name}: {value:.6g} {unit} (target {target or '-'})")
        if not args.no_record:
            from chipstack.pipeline.measured import record

            record(
                AREA,
                name,
                float(value),
                unit,
                target=target,
                command=command,
                note=note,
                headline=headline,
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
