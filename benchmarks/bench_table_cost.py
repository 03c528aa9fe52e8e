"""What a drop diagnosis's reference table costs to simulate: the CPU seconds of one pool
of every model (the default number of noise-free drops at each release of the study's
design), measured in this process, and the wall time of the whole table on N cores that
follows (the pools are independent, so they divide over cores). A figure of CPU time, not
wall time: it holds on a busy machine.

Usage: ``python benchmarks/bench_table_cost.py [--pools 16] [--cores 2] [--record]``.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from bench_diagnosis import DROP_EFFECTS, case_plan, spec_text

from chipstack.diagnosis.reference_table import (
    NO_EFFECT,
    MemoryStore,
    ReferenceTable,
    simulate_pool,
)
from chipstack.diagnosis.spec import load_experiment
from chipstack.pipeline.scenario_files import load_scenario


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--pools", type=int, default=16, help="pools per effect")
    parser.add_argument("--cores", type=int, default=2)
    parser.add_argument("--record", action="store_true")
    args = parser.parse_args()
    folder = Path(tempfile.mkdtemp(prefix="bench-table-"))
    (folder / "spec.toml").write_text(spec_text(case_plan("effects", 0)))
    (folder / "data.csv").write_text("condition,drop,x_mm,y_mm\n")
    experiment = load_experiment(folder / "spec.toml", load_scenario)
    models = [NO_EFFECT, *DROP_EFFECTS]
    table = ReferenceTable(experiment, models, MemoryStore())
    cpu = {}
    for model in models:
        start = time.process_time()
        # The model's pool 8 (a strength mid-way through the Halton sequence).
        setting = table.settings(model, 9)[8]
        for c in experiment.conditions:
            simulate_pool(**table.call(c.name, setting))
        cpu[model] = time.process_time() - start
        print(f"{model}: {cpu[model]:.1f} CPU s per pool ({3 * table.pool_drops} drops)")
    pools = {m: (max(4, args.pools // 2) if m == NO_EFFECT else args.pools) for m in models}
    total = sum(cpu[m] * pools[m] for m in models)
    drops = sum(pools.values()) * 3 * table.pool_drops
    wall = total / args.cores
    print(
        f"table of {args.pools} pools per effect: {drops} drops, {total:.0f} CPU s, "
        f"{wall / 60:.1f} min of wall time on {args.cores} cores (target for the first "
        "diagnosis, table included: <= 10 min)"
    )
    if args.record:
        from chipstack.pipeline.measured import record

        record(
            "diagnosis",
            f"reference table of {args.pools} pools per effect, wall time on {args.cores} cores",
            round(wall, 1),
            "s",
            target="<= 600",
            command=f"python benchmarks/bench_table_cost.py --pools {args.pools} --record",
            note=f"{drops} drops; from CPU seconds of one pool per model",
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
