"""How the model choice's cross-validated accuracy depends on the reference table's
size: pools per effect J (strengths covered) against drops per pool P (datasets cut from
each), on the study's design (3 conditions x 50 drops), from the study's stored table
(benchmarks/cache/tables, 32 pools of 200 drops per effect). A pool's first P drops are
exactly a pool of P drops (a drop depends on its pool's seed and its own index), so
every P is read from the same pools; nothing is simulated. The table's cost is
proportional to J x P: this chose the default drops per pool and pools per effect.

Usage: ``python benchmarks/bench_table_size.py [--record]``.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np
from bench_diagnosis import DROP_EFFECTS, TABLES, case_plan, spec_text

from chipstack.diagnosis.model_choice import _counts, _cross_validated, _Design
from chipstack.diagnosis.observables import symmetry_order
from chipstack.diagnosis.reference_table import NO_EFFECT, ReferenceTable
from chipstack.diagnosis.spec import load_experiment
from chipstack.pipeline.scenario_files import load_scenario

SIZES = [
    (200, 8),
    (200, 16),
    (200, 24),
    (200, 32),
    (100, 8),
    (100, 16),
    (100, 24),
    (100, 32),
    (50, 16),
    (50, 24),
]
SEEDS = (0, 1)  # forest seeds averaged (the folds follow the seed too)
TREES = 150


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--record", action="store_true")
    args = parser.parse_args()
    folder = Path(tempfile.mkdtemp(prefix="bench-table-size-"))
    plan = case_plan("effects", 0)
    (folder / "spec.toml").write_text(spec_text(plan))
    (folder / "data.csv").write_text("condition,drop,x_mm,y_mm\n")
    experiment = load_experiment(folder / "spec.toml", load_scenario)
    models = [NO_EFFECT, *DROP_EFFECTS]
    drops = {c.name: plan["drops"] for c in experiment.conditions}
    order = symmetry_order(experiment.scenario)
    rows = []
    for pool_drops, pools in SIZES:
        table = ReferenceTable(experiment, models, TABLES, pool_drops)
        table.load()
        if min(table.count(m) for m in DROP_EFFECTS) < pools:
            print(f"P={pool_drops} J={pools}: the stored table holds fewer pools; skipped")
            continue
        design = _Design(experiment, table, drops, order, True, True)
        X, y, groups, _, _, _ = design.arrays(_counts(models, pools))
        accuracy = np.mean(
            [
                np.mean(_cross_validated(X, y, groups, len(models), s, TREES).argmax(1) == y)
                for s in SEEDS
            ]
        )
        rows.append((pool_drops, pools, len(y), float(accuracy)))
        print(
            f"{pool_drops} drops per pool, {pools} pools per effect ({len(y)} datasets): "
            f"cross-validated accuracy {100 * accuracy:.1f} % (cost {pool_drops * pools} "
            "pool-drops per effect and condition)",
            flush=True,
        )
    if args.record:
        from chipstack.pipeline.measured import record

        for pool_drops, pools, datasets, accuracy in rows:
            record(
                "diagnosis",
                f"model choice CV accuracy, {pools} pools of {pool_drops} drops per effect",
                round(100 * accuracy, 1),
                "%",
                command="python benchmarks/bench_table_size.py --record",
                note=f"study design 3 x 50 drops, {datasets} datasets, {TREES} trees, "
                f"mean of {len(SEEDS)} seeds",
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
