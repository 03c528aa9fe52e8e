"""Ensemble speed through the Dask execution layer.

1. 10 repeats of the 270-chip reference stack (deposition only, files written as in
   ``pipeline run --repeats``) on 1 and on 2 local workers: the speed-up (target >= 1.8
   on this 2-core machine).
2. 200 single-chip drops on 1 worker: wall time of the batch against the sum of the runs'
   own compute time (measured inside each task): the layer's overhead (target < 10 %).

Cluster start-up is timed separately and not counted in either figure. Both figures are
recorded as data (``pipeline.measured.record``, area ``ensembles``; ``--no-record`` for a
trial) and shown in docs/measured.md after ``make docs``.

    .venv/bin/python benchmarks/bench_ensembles.py
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from chipstack.packing import scenario_from_dict
from chipstack.pipeline.ensemble import run_ensemble
from chipstack.pipeline.execution import Executor
from chipstack.pipeline.measured import record
from chipstack.pipeline.run import compute_run, derive_seed


def ensemble_seconds(workers: int) -> float:
    with tempfile.TemporaryDirectory() as folder:
        start = time.perf_counter()
        _, manifest = run_ensemble(
            scenario_from_dict({"seed": 0}), Path(folder) / "e", 10, to="packing", workers=workers
        )
        return time.perf_counter() - start, manifest["wall_time_s"]["total"]


def drops() -> tuple[float, float, float]:
    scenario = scenario_from_dict(
        {
            "name": "drop",
            "deposition": {"chips": 1, "batch_size": 1, "release_height_mm": [200.0, 200.0]},
        }
    )
    compute = []
    start = time.perf_counter()
    with Executor(workers=1) as executor:
        startup = time.perf_counter() - start
        arguments = [(scenario.with_seed(derive_seed(0, k)), "packing", None) for k in range(200)]
        begin = time.perf_counter()
        executor.run(
            compute_run,
            arguments,
            lambda k, result: compute.append(result.times["packing"]),
            lambda k, error: print(f"drop {k} failed: {error}"),
        )
        wall = time.perf_counter() - begin
    return startup, wall, sum(compute)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--no-record", action="store_true", help="do not record the figures")
    args = parser.parse_args()
    one_total, one = ensemble_seconds(1)
    two_total, two = ensemble_seconds(2)
    print(f"10 reference stacks, 1 worker: {one:.1f} s ({one_total:.1f} s with cluster start-up)")
    print(f"10 reference stacks, 2 workers: {two:.1f} s ({two_total:.1f} s with cluster start-up)")
    print(f"speed-up on 2 workers: {one / two:.2f}x (target >= 1.8x)")
    startup, wall, compute = drops()
    print(
        f"200 single-chip drops on 1 worker: {wall:.2f} s wall, {compute:.2f} s of compute in "
        f"the runs; overhead {100 * (wall / compute - 1):.1f} % (target < 10 %); "
        f"cluster start-up {startup:.1f} s"
    )
    if args.no_record:
        return
    command = "python benchmarks/bench_ensembles.py"
    record(
        "ensembles",
        "10 reference stacks, speed-up on 2 workers against 1",
        round(one / two, 2),
        "x",
        target=">= 1.8",
        command=command,
        note=f"{two:.1f} s against {one:.1f} s",
    )
    record(
        "ensembles",
        "overhead of the Dask layer, 200 single-chip drops on 1 worker",
        round(100 * (wall / compute - 1), 1),
        "%",
        target="< 10",
        command=command,
        note=f"{wall:.2f} s wall for {compute:.2f} s of compute",
    )


if __name__ == "__main__":
    main()
