"""Descriptor speed: every descriptor of one 270-chip stack and of a 2,700-chip stack.

Deposits the reference stack (seed 0) and a 2,700-chip stack (5 batches of 540 on a
475 mm target, the same depth), then times ``geometry.describe`` on each (all
descriptors, the contact types after every batch, the voxel image at the scenario's
voxel size). Targets: <= 1 s at 270 chips (the paper needed 210 s), <= 10 s at 2,700.
The figures are recorded as data (``pipeline.measured.record``, area ``geometry``;
``--no-record`` for a trial) and shown in docs/measured.md after ``make docs``.

    .venv/bin/python benchmarks/bench_geometry.py [--repeats 5] [--skip-large]
"""

from __future__ import annotations

import argparse
import statistics
import time

from chipstack.geometry import arrangements_from_stack, describe
from chipstack.packing import deposit, scenario_from_dict
from chipstack.pipeline.measured import record

PAPER_S = 210.0


def time_describe(history, spec, repeats: int) -> tuple[float, dict[str, float]]:
    times, parts = [], {}
    for _ in range(repeats):
        start = time.perf_counter()
        description = describe(history, spec)
        times.append(time.perf_counter() - start)
        parts = description.timings_s
    return statistics.median(times), parts


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--skip-large", action="store_true")
    parser.add_argument("--no-record", action="store_true", help="do not record the figures")
    args = parser.parse_args()

    cases = [("270 chips", {"seed": 0})]
    if not args.skip_large:
        cases.append(
            (
                "2700 chips",
                {
                    "seed": 0,
                    "deposition": {"chips": 2700, "batch_size": 540, "target_size_mm": 475.0},
                },
            )
        )
    results = {}
    for label, table in cases:
        scenario = scenario_from_dict(table)
        start = time.perf_counter()
        stack = deposit(scenario)
        print(f"{label}: deposited in {time.perf_counter() - start:.1f} s", flush=True)
        history = arrangements_from_stack(stack)
        median, parts = time_describe(history, scenario.geometry, args.repeats)
        results[label] = median
        detail = ", ".join(f"{k} {v:.3f}" for k, v in parts.items())
        print(f"{label}: all descriptors in {median:.3f} s (median of {args.repeats}); {detail}")
    print()
    small = results["270 chips"]
    print(f"270 chips: {small:.3f} s (target <= 1 s; paper 210 s: {PAPER_S / small:.0f}x faster)")
    if "2700 chips" in results:
        large = results["2700 chips"]
        print(
            f"2700 chips: {large:.3f} s (target <= 10 s); "
            f"{large / small:.1f}x the time for 10x the chips"
        )
    if args.no_record:
        return
    command = "python benchmarks/bench_geometry.py" + (" --skip-large" if args.skip_large else "")
    record(
        "geometry",
        "all descriptors, 270-chip reference stack",
        round(small, 3),
        "s",
        target="<= 1",
        command=command,
        note=f"median of {args.repeats}; the paper: 210 s",
        headline=True,
    )
    if "2700 chips" in results:
        record(
            "geometry",
            "all descriptors, 2,700-chip stack",
            round(results["2700 chips"], 2),
            "s",
            target="<= 10",
            command=command,
            note=f"median of {args.repeats}",
        )


if __name__ == "__main__":
    main()
