"""Packing speed: the 270-chip reference deposition and a 2,700-chip stack.

Prints the median wall time of 5 reference runs (target <= 4 s on one core), the peak
resident memory of this process (target <= 500 MB), and seconds per chip at 270 and 2,700
chips on a 475 mm target (same depth; target: ratio <= 1.5), all measured in this run.

    .venv/bin/python benchmarks/bench_packing.py [--repeats 5] [--large-seeds 1]
"""

from __future__ import annotations

import argparse
import resource
import statistics
import time

from packing import deposit, scenario_from_dict


def timed(scenario) -> tuple[float, object]:
    start = time.perf_counter()
    stack = deposit(scenario)
    return time.perf_counter() - start, stack


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--large-seeds", type=int, default=1)
    args = parser.parse_args()

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


if __name__ == "__main__":
    main()
