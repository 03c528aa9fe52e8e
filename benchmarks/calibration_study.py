"""What the diagnosis's calibration studies share (``bench_diagnosis.py`` for drops,
``bench_stack_diagnosis.py`` for stacks): a resumable loop over planned cases, each
cached whole as one JSON file, and rates with their Clopper-Pearson intervals."""

from __future__ import annotations

import argparse
import json
import statistics
import time
from collections.abc import Callable
from pathlib import Path

from scipy.stats import binomtest

from chipstack.pipeline.execution import Executor


def rate(hits: int, n: int) -> str:
    """``hits / n`` as a percentage with its exact 95 % interval."""
    if n == 0:
        return "no cases yet"
    lo, hi = binomtest(hits, n).proportion_ci(0.95, method="exact")
    share = f"{hits} / {n} = {100 * hits / n:.1f} %"
    return f"{share} (95 % Clopper-Pearson {100 * lo:.1f} to {100 * hi:.1f} %)"


def current(record: dict, method: dict[str, int]) -> bool:
    """Made by its part's current method (cases cached before methods were stamped are
    method 1)."""
    return record.get("method", 1) == method[record["plan"]["part"]]


def cached(results: Path, part: str, method: dict[str, int]) -> list[dict]:
    """The part's cached cases made by its current method."""
    records = [json.loads(p.read_text()) for p in sorted((results / part).glob("*.json"))]
    return [r for r in records if current(r, method)]


def part_header(title: str, cases: list[dict], planned: int) -> list[dict]:
    """Print a part's heading and diagnosis times; its cases' first runs."""
    print(f"\n## {title}: {len(cases)} of {planned} planned cases cached")
    runs = [c["runs"][0] for c in cases]
    if runs:
        seconds = [r["seconds"] for r in runs]
        print(
            f"diagnosis time: median {statistics.median(seconds):.0f} s, max {max(seconds):.0f} s"
        )
    return runs


def strength_record(ranking: list[dict], truth: dict[str, float]) -> dict:
    """With one true effect in the ranking: its fitted strength, 95 % interval and
    whether the interval holds the truth."""
    if len(truth) != 1:
        return {}
    ((effect, strength),) = truth.items()
    entry = {e["effect"]: e for e in ranking}.get(effect)
    if entry is None:
        return {}
    lo, hi = entry["strength_ci95"]
    return dict(
        strength=entry["strength"], strength_ci95=[lo, hi], covered=bool(lo <= strength <= hi)
    )


def study_main(
    description: str,
    planned: dict[str, int],
    results: Path,
    method: dict[str, int],
    case_plan: Callable[[str, int], dict],
    run_case: Callable[[dict, Executor], dict],
    report: Callable[[str], None],
    record_figures: Callable[[str], None] | None = None,
) -> int:
    """The command line of a study: run the parts' missing cases (``--cases``,
    ``--minutes``, ``--workers``), then print every part's tables; ``--report`` prints
    them from the cache only."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--part", choices=sorted(planned), action="append")
    parser.add_argument(
        "--cases", type=int, default=None, help="cases of the part (default: planned)"
    )
    parser.add_argument("--minutes", type=float, default=None, help="stop after this long")
    parser.add_argument("--workers", type=int, default=None)
    parser.add_argument("--report", action="store_true", help="tables from the cache only")
    parser.add_argument(
        "--record",
        action="store_true",
        help="also record the parts' headline figures under benchmarks/results (measured.md)",
    )
    args = parser.parse_args()
    parts = args.part or sorted(planned)
    if not args.report:
        deadline = time.time() + 60 * args.minutes if args.minutes else float("inf")
        with Executor(workers=args.workers) as executor:
            for part in parts:
                folder = results / part
                folder.mkdir(parents=True, exist_ok=True)
                for index in range(args.cases or planned[part]):
                    path = folder / f"case-{index:03d}.json"
                    if path.exists() and current(json.loads(path.read_text()), method):
                        continue
                    if time.time() > deadline:
                        print("time budget spent; rerun to go on", flush=True)
                        break
                    record = run_case(case_plan(part, index), executor)
                    partial = path.with_suffix(".part")
                    partial.write_text(json.dumps(record, indent=1))
                    partial.replace(path)  # a case is cached whole or not at all
                    first = record["runs"][0]
                    print(
                        f"{part} {index:3d}: {first['verdict']:19s} best {first['best']} "
                        f"({record['wall_s']:.0f} s)",
                        flush=True,
                    )
    for part in parts:
        report(part)
        if args.record and record_figures is not None:
            record_figures(part)
    return 0
