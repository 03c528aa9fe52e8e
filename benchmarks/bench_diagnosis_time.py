"""How long one drop diagnosis of 3 conditions x 50 drops takes, and whether it
reproduces the calibration study.

With the amortised model choice (issue 54) the first diagnosis of a design builds its
reference table (target <= 10 min on this 2-core machine, table included) and every later
one reuses it (target <= 10 s): ``--tables DIR`` keeps the table there (default: a new
empty directory, so the first case pays for the table and the others reuse it; the
first case's time and the median of the others are printed against the two targets).

Reruns the first ``--cases`` cases of the study's ``effects`` part (one per drop effect
for the default 7; same data, same diagnosis seed) on ``--workers`` local Dask workers,
one after the other, and prints each diagnosis's wall time (the synthetic data's making
excluded, as a user's data are read, not made), their median and longest against the
target, and whether each result equals the one cached by
``bench_diagnosis.py --part effects`` (verdict, best effect, tie set, fitted strengths
and the tie test's p-values, to the last digit): a check that the diagnosis is
reproducible across processes and code changes that claim to leave it alone. Run it on
an otherwise idle machine; nothing is cached.

Usage: ``python benchmarks/bench_diagnosis_time.py [--cases 7 | --indices K ...]
[--workers 2]``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time

from bench_diagnosis import METHOD, RESULT_FIELDS, RESULTS, _blind_data, _summary, case_plan
from calibration_study import current

from chipstack.diagnosis.drops import diagnose_drops
from chipstack.pipeline.execution import Executor
from chipstack.pipeline.tables import DirectoryStore

TARGET_S = 120.0  # the refit method's target (issue 35)
FIRST_TARGET_S = 600.0  # amortised: the first diagnosis of a design, its table included
SECOND_TARGET_S = 10.0  # amortised: a diagnosis of a design already tabled


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cases", type=int, default=7, help="the first N effects cases")
    parser.add_argument("--indices", type=int, nargs="+", help="these effects cases instead")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--tables", default=None, help="table store (default: a new one)")
    args = parser.parse_args()
    times, same = [], 0
    tables = DirectoryStore(args.tables or tempfile.mkdtemp(prefix="bench-tables-"))
    with Executor(workers=args.workers) as executor:
        for index in args.indices or range(args.cases):
            plan = case_plan("effects", index)
            _, experiment, data = _blind_data(plan, executor)
            start = time.perf_counter()
            result = diagnose_drops(
                experiment, data, executor.map, seed=plan["diagnosis_seeds"][0], tables=tables
            )
            seconds = time.perf_counter() - start
            times.append(seconds)
            run = _summary(result, plan, seconds)
            path = RESULTS / "effects" / f"case-{index:03d}.json"
            cached = json.loads(path.read_text()) if path.exists() else None
            differ = (
                []
                if cached is None
                else [k for k in RESULT_FIELDS if run[k] != cached["runs"][0][k]]
            )
            if cached is None or not current(cached, METHOD):
                check = "no current cached case to compare"
            elif not differ:
                same += 1
                check = "identical to the cached study case"
            else:
                check = f"DIFFERS from the cached study case in {', '.join(differ)}"
            truth = ", ".join(f"{k} {v:.3g}" for k, v in plan["truth"].items())
            print(
                f"effects case {index}: {truth}: {seconds:.1f} s, {run['verdict']}, "
                f"best {run['best']}; {check}",
                flush=True,
            )
    if len(times) >= 2:
        later = statistics.median(times[1:])
        print(
            f"first diagnosis of the design (its table built unless --tables held it): "
            f"{times[0]:.1f} s, target {FIRST_TARGET_S:.0f} s; later ones: median "
            f"{later:.1f} s, target {SECOND_TARGET_S:.0f} s (ratio {later / SECOND_TARGET_S:.2f})"
        )
    median, longest = statistics.median(times), max(times)
    print(
        f"{len(times)} diagnoses on {args.workers} workers: median {median:.1f} s, longest "
        f"{longest:.1f} s; target {TARGET_S:.0f} s (median / target {median / TARGET_S:.2f}, "
        f"longest / target {longest / TARGET_S:.2f}); {sum(t <= TARGET_S for t in times)} of "
        f"{len(times)} within it; {same} of {len(times)} identical to the cached study"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
