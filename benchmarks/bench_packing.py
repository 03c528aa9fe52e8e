"""Packing speed: the 270-chip reference deposition and a 2,700-chip stack; with
``--conveyor``, mats poured onto a moving belt.

Prints the median wall time of 5 reference runs (target <= 4 s on one core), the peak
resident memory of this process (target <= 500 MB), and seconds per chip at 270 and 2,700
chips on a 475 mm target (same depth; target: ratio <= 1.5), all measured in this run.

``--conveyor N [N ...]``: the line of a 440 x 540 mm panel (the paper's chips, the paper
stack's areal density, a belt 540 mm wide at 20 mm/s, 136 chips/s) poured with N chips
each, one process per mat (so each peak memory is its own); prints per N the wall time,
ms per chip, the most chips the engine held and the peak memory, and the ratios to the
smallest N (targets: 3,000 chips <= 60 s; ms per chip at 30,000 within 1.2 x that at
300; memory growing no faster than the mat). Each mat's figures are kept in
benchmarks/results/conveyor/<N>.json, so a long study resumes (``--fresh`` remeasures).

The figures against their targets are recorded as data (``pipeline.measured.record``,
area ``packing``; ``--no-record`` for a trial) and shown in docs/measured.md after
``make docs``.

    .venv/bin/python benchmarks/bench_packing.py [--repeats 5] [--large-seeds 1]
    .venv/bin/python benchmarks/bench_packing.py --conveyor 300 3000 30000
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

from chipstack.packing import deposit, scenario_from_dict
from chipstack.pipeline.measured import record

COMMAND = "python benchmarks/bench_packing.py"


def timed(scenario) -> tuple[float, object]:
    start = time.perf_counter()
    stack = deposit(scenario)
    return time.perf_counter() - start, stack


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--large-seeds", type=int, default=1)
    parser.add_argument("--conveyor", type=int, nargs="+", default=None, metavar="N")
    parser.add_argument("--fresh", action="store_true", help="remeasure cached mats")
    parser.add_argument("--one-mat", type=int, default=None, help=argparse.SUPPRESS)
    parser.add_argument("--no-record", action="store_true", help="do not record the figures")
    args = parser.parse_args()
    if args.one_mat is not None:
        print(json.dumps(one_mat(args.one_mat)))
        return
    if args.conveyor:
        conveyor_study(args.conveyor, args.fresh, not args.no_record)
        return

    small = []
    for seed in range(args.repeats):
        seconds, stack = timed(scenario_from_dict({"seed": seed}))
        small.append(seconds)
        last = stack.batches[-1]
        print(
            f"270 chips seed {seed}: {seconds:.2f} s wall, settled "
            f"{all(b.settled for b in stack.batches)}, max penetration "
            f"{last.max_chip_penetration_mm:.3f} mm (chips) "
            f"{last.max_floor_penetration_mm:.3f} mm (floor)",
            flush=True,
        )
    peak_small_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024

    large = []
    for seed in range(args.large_seeds):
        seconds, stack = timed(
            scenario_from_dict(
                {
                    "seed": seed,
                    "deposition": {"chips": 2700, "batch_size": 540, "target_size_mm": 475.0},
                }
            )
        )
        large.append(seconds)
        print(
            f"2700 chips seed {seed}: {seconds:.2f} s wall, settled "
            f"{all(b.settled for b in stack.batches)}, max penetration "
            f"{stack.batches[-1].max_chip_penetration_mm:.3f} mm",
            flush=True,
        )
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024

    median_small = statistics.median(small)
    per_chip_small = median_small / 270
    per_chip_large = statistics.median(large) / 2700
    print()
    print(
        f"reference deposition (270 chips): median {median_small:.2f} s over {len(small)} runs "
        f"(target <= 4 s; paper: 150 s, {150 / median_small:.0f}x faster)"
    )
    print(
        f"peak memory: {peak_small_mb:.0f} MB after the 270-chip runs (target <= 500 MB), "
        f"{peak_mb:.0f} MB with the 2700-chip run"
    )
    print(
        f"seconds per chip: {per_chip_small * 1e3:.2f} ms at 270, "
        f"{per_chip_large * 1e3:.2f} ms at 2700; ratio {per_chip_large / per_chip_small:.2f} "
        f"(target <= 1.5)"
    )
    if args.no_record:
        return
    spread = f"{min(small):.2f} to {max(small):.2f} s"
    record(
        "packing",
        "270-chip reference deposition",
        round(median_small, 2),
        "s",
        target="<= 4",
        command=COMMAND,
        note=f"median of {len(small)}, {spread}; the paper: 150 s on an i9",
        headline=True,
    )
    record(
        "packing",
        "peak memory after the 270-chip runs",
        round(peak_small_mb),
        "MB",
        target="<= 500",
        command=COMMAND,
        note=f"{peak_mb:.0f} MB with the 2,700-chip run",
    )
    record(
        "packing",
        "cost per chip, 2,700 against 270 chips",
        round(per_chip_large / per_chip_small, 2),
        "x",
        target="<= 1.5",
        command=COMMAND,
        note=f"{per_chip_large * 1e3:.1f} against {per_chip_small * 1e3:.1f} ms per chip",
    )


RESULTS = Path(__file__).parent / "results" / "conveyor"


def panel_line(chips: int):
    """The line of a 440 x 540 mm panel: the paper's chips at the paper stack's areal
    density (0.012 chips/mm^2), a belt 540 mm wide at 20 mm/s, so 136 chips/s."""
    from chipstack.core.scenario_data import scenario_from_dict

    return scenario_from_dict(
        {
            "kind": "conveyor",
            "chip": {"fibre_directions_deg": [0.0, 90.0]},
            "deposition": {"chips": chips, "batch_size": 4, "target_size_mm": 1.0},
            "conveyor": {
                "belt_speed_mm_s": 20.0,
                "pour_rate_chips_s": 136.0,
                "zone_length_mm": 40.0,
                "zone_width_mm": 540.0,
                "belt_width_mm": 540.0,
                "run_in_mm": 0.0,
            },
        }
    )


def one_mat(chips: int) -> dict:
    from chipstack.packing.conveyor import pour_mat

    start = time.perf_counter()
    mat = pour_mat(panel_line(chips)).mat
    wall = time.perf_counter() - start
    return {
        "chips": chips,
        "wall_s": round(wall, 2),
        "ms_per_chip": round(1e3 * wall / chips, 2),
        "sim_s": round(mat.sim_time_s, 2),
        "steps": mat.steps,
        "wakes": mat.wakes,
        "most_in_engine": mat.most_in_world,
        "peak_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
        "settled": mat.settled,
    }


def conveyor_study(sizes: list[int], fresh: bool, keep: bool = True) -> None:
    RESULTS.mkdir(parents=True, exist_ok=True)
    rows = []
    for chips in sorted(sizes):
        path = RESULTS / f"{chips}.json"
        if fresh or not path.exists():
            done = subprocess.run(
                [sys.executable, __file__, "--one-mat", str(chips)],
                capture_output=True,
                text=True,
                check=True,
            )
            path.write_text(done.stdout.strip().splitlines()[-1] + "\n")
        row = json.loads(path.read_text())
        rows.append(row)
        print(
            f"{chips:6d} chips: {row['wall_s']:8.1f} s wall, {row['ms_per_chip']:6.1f} ms per "
            f"chip, {row['sim_s']:7.1f} s simulated, {row['wakes'] / chips:5.1f} wakes per chip, "
            f"at most {row['most_in_engine']} chips in the engine, peak {row['peak_mb']:.0f} MB",
            flush=True,
        )
    first = rows[0]
    for row in rows[1:]:
        print(
            f"{row['chips']} against {first['chips']} chips: ms per chip x "
            f"{row['ms_per_chip'] / first['ms_per_chip']:.2f}, peak memory x "
            f"{row['peak_mb'] / first['peak_mb']:.2f} for x "
            f"{row['chips'] / first['chips']:.0f} the chips"
        )
    if not keep or not fresh:
        return  # figures read back from the cache were recorded when they were measured
    command = f"{COMMAND} --conveyor {' '.join(str(n) for n in sorted(sizes))} --fresh"
    by_chips = {row["chips"]: row for row in rows}
    if 3000 in by_chips:
        row = by_chips[3000]
        record(
            "packing",
            "conveyor line, 3,000 chips",
            row["wall_s"],
            "s",
            target="<= 60",
            command=command,
            note=f"a 440 x 540 mm panel's line; peak {row['peak_mb']:.0f} MB",
            headline=True,
        )
    if 300 in by_chips and 30000 in by_chips:
        small, large = by_chips[300], by_chips[30000]
        record(
            "packing",
            "conveyor line, cost per chip, 30,000 against 300 chips",
            round(large["ms_per_chip"] / small["ms_per_chip"], 2),
            "x",
            target="<= 1.2",
            command=command,
            note=f"{large['ms_per_chip']:.1f} against {small['ms_per_chip']:.1f} ms per chip",
        )


if __name__ == "__main__":
    main()
