"""Calibration study of ``pipeline diagnose`` on blind stack measurements, in resumable
parts: real depositions, not the analytic stand-in of ``tests/test_stack_diagnosis.py``.

Every case is a pseudo-experiment made by the simulation (``synthesize_quantities``,
the library behind ``pipeline synth``: the mean, sd and count of 5 measured stacks per
condition) and diagnosed without being told what made it. The conditions are small
stacks of 20 x 20 x 2 mm chips over an 80 mm square: 24, 36 and 48 chips, 2 repeats per
setting (the baseline 8). Each case's result is cached as one JSON file under
``benchmarks/results/diagnosis-stacks/<part>/`` (committed), so the study accumulates
across sessions; ``--minutes`` stops it between cases.

Parts:

* ``nulls``: effect-free measurements: "no significant gap" in >= 95 %.
* ``effects``: one case per stack effect, strength from the upper half of its prior:
  "explained" with the true effect first or in a tie set of at most 2; coverage of the
  95 % strength intervals.
* ``outside``: a stack effect withheld from the library; a measurement distortion (the
  heights read 10 % high): never "explained".

Usage: ``python benchmarks/bench_stack_diagnosis.py --part nulls [--cases N] [--minutes M]
[--workers N]``; ``--report`` prints the tables from the cache only.
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from calibration_study import cached, part_header, rate, strength_record, study_main

from chipstack.diagnosis.spec import QuantityData, load_experiment
from chipstack.diagnosis.stacks import diagnose_stacks, synthesize_quantities
from chipstack.packing.effects import EFFECTS
from chipstack.pipeline.execution import Executor
from chipstack.pipeline.scenario_files import load_scenario

RESULTS = Path(__file__).resolve().parent / "results" / "diagnosis-stacks"
STACK_EFFECTS = tuple(n for n in EFFECTS.names() if "stack" in EFFECTS.get(n).kinds)
PLANNED = {"nulls": 20, "effects": len(STACK_EFFECTS), "outside": 4}
# Raised whenever a change makes the cached cases stale. nulls 2, effects 4, outside 4:
# release_perturbation acts in stacks now (deposition calls Effect.release); before, it
# was a candidate in every library that could change nothing (issue 35).
METHOD = {"nulls": 2, "effects": 4, "outside": 4}
CHIPS = (24, 36, 48)
MEASUREMENTS = 5
SCENARIO = """name = "small-{chips}"
seed = 3
[chip]
length_mm = 20.0
width_mm = 20.0
thickness_mm = 2.0
[deposition]
chips = {chips}
batch_size = 12
target_size_mm = 80.0
release_height_mm = [60.0, 120.0]
"""
HEIGHTS = ("height_mean_mm", "height_max_mm")


def case_plan(part: str, index: int) -> dict:
    """The case ``index`` of ``part``, fixed by its index alone."""
    rng = np.random.default_rng([sum(map(ord, part)), index])
    plan = dict(
        part=part,
        index=index,
        truth={},
        library=list(STACK_EFFECTS),
        distortion=None,
        seed=2000 + index,
        diagnosis_seed=index,
    )
    if part == "effects":
        effect = STACK_EFFECTS[index % len(STACK_EFFECTS)]
        plan["truth"] = {effect: _upper_half(effect, rng)}
    elif part == "outside":
        if index < 3:
            effect = ("friction", "restitution", "cohesion")[index]
            plan["truth"] = {effect: _upper_half(effect, rng)}
            plan["library"] = [e for e in STACK_EFFECTS if e != effect]
        else:
            plan["distortion"] = dict(height_scale=1.10)
    return plan


def _upper_half(effect: str, rng: np.random.Generator) -> float:
    lo, hi = EFFECTS.get(effect).prior
    return float(rng.uniform((lo + hi) / 2, hi))


def spec_text(plan: dict) -> str:
    lines = [
        'kind = "stack"',
        f'name = "{plan["part"]} {plan["index"]}"',
        'observations = "data.csv"',
        "[diagnosis]",
        "effects = [" + ", ".join(f'"{e}"' for e in plan["library"]) + "]",
    ]
    for chips in CHIPS:
        lines += ["[[condition]]", f'name = "n{chips}"', f'scenario = "small-{chips}.toml"']
        lines.append("repeats = 2")
    return "\n".join(lines) + "\n"


def run_case(plan: dict, executor: Executor) -> dict:
    folder = Path(tempfile.mkdtemp(prefix="bench-stack-diagnosis-"))
    for chips in CHIPS:
        (folder / f"small-{chips}.toml").write_text(SCENARIO.format(chips=chips))
    (folder / "spec.toml").write_text(spec_text(plan))
    (folder / "data.csv").write_text("condition,quantity,value\n")
    experiment = load_experiment(folder / "spec.toml", load_scenario)
    start = time.perf_counter()
    rows = synthesize_quantities(
        experiment, plan["truth"], plan["seed"], executor.map, measurements=MEASUREMENTS
    )
    scale = (plan["distortion"] or {}).get("height_scale", 1.0)
    data: dict[str, dict[str, QuantityData]] = {}
    for r in rows:
        factor = scale if r["quantity"] in HEIGHTS else 1.0
        data.setdefault(r["condition"], {})[r["quantity"]] = QuantityData(
            factor * r["value"], factor * r["sd"], r["n"]
        )
    t0 = time.perf_counter()
    result = diagnose_stacks(experiment, data, executor.map, seed=plan["diagnosis_seed"])
    run = _summary(result, plan, time.perf_counter() - t0)
    return dict(
        plan=plan, method=METHOD[plan["part"]], runs=[run], wall_s=time.perf_counter() - start
    )


def _summary(result: dict, plan: dict, seconds: float) -> dict:
    which = result["which"] or {}
    ranking = which.get("ranking", [])
    record = dict(
        verdict=result["verdict"]["kind"],
        detection_p=min(t["p_holm"] for t in result["where"]["tests"]),
        best=which.get("best"),
        tie_set=which.get("indistinguishable", []),
        ranking=[e["effect"] for e in ranking],
        seconds=round(seconds, 1),
    )
    return {**record, **strength_record(ranking, plan["truth"])}


def report(part: str) -> None:
    cases = cached(RESULTS, part, METHOD)
    runs = part_header(f"stacks, {part}", cases, PLANNED[part])
    if not cases:
        return
    if part == "nulls":
        quiet = sum(r["verdict"] == "no significant gap" for r in runs)
        print(f"'no significant gap': {rate(quiet, len(runs))}; target >= 95 %")
        return
    if part == "effects":
        truth = [next(iter(c["plan"]["truth"])) for c in cases]
        good = [
            r["verdict"] == "explained" and t in r["tie_set"] and len(r["tie_set"]) <= 2
            for r, t in zip(runs, truth, strict=True)
        ]
        print(f"explained, true effect in a tie set of <= 2: {rate(sum(good), len(good))}")
        covered = [r["covered"] for r in runs if "covered" in r]
        print(f"95 % strength intervals covering the truth: {rate(sum(covered), len(covered))}")
    else:
        never = [r["verdict"] != "explained" for r in runs]
        print(f"not 'explained': {rate(sum(never), len(never))}; target >= 80 %")
    print("\n| truth | detection p (Holm) | verdict | best | tie set | strength [95 %] |")
    print("|---|---|---|---|---|---|")
    for c, r in zip(cases, runs, strict=True):
        what = c["plan"]["distortion"] or {k: round(v, 3) for k, v in c["plan"]["truth"].items()}
        fitted = (
            f"{r['strength']:.3g} [{r['strength_ci95'][0]:.3g}, {r['strength_ci95'][1]:.3g}]"
            if "strength" in r
            else ""
        )
        print(
            f"| {what} | {r['detection_p']:.3g} | {r['verdict']} | {r['best']} "
            f"| {', '.join(r['tie_set'])} | {fitted} |"
        )


def main() -> int:
    description = __doc__.splitlines()[0]
    return study_main(description, PLANNED, RESULTS, METHOD, case_plan, run_case, report)


if __name__ == "__main__":
    sys.exit(main())
