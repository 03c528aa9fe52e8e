"""``pipeline sweep SCENARIO --vary KEY=V1,V2,...``: an ensemble at every point of the
grid, with a progress bar, and a line of scalars per point."""

from __future__ import annotations

import argparse
import sys

from tqdm import tqdm

from chipstack.core.stages import check_stage_name
from chipstack.pipeline.commands import resumable_interrupt
from chipstack.pipeline.scenario_files import load_scenario
from chipstack.pipeline.sweep import parse_vary, run_sweep, sweep_points

__all__ = ["main"]


def main(args: argparse.Namespace) -> None:
    scenario = load_scenario(args.scenario)
    if args.seed is not None:
        scenario = scenario.with_seed(args.seed)
    vary = parse_vary(args.vary)
    check_stage_name(args.to)
    points = sweep_points(scenario, vary)  # every point checked before anything runs
    out = args.out or f"runs/sweep-{scenario.name}"
    bar = tqdm(
        total=len(points) * args.repeats,
        desc="sweep",
        unit="run",
        disable=args.quiet,
        file=sys.stderr,
    )

    def progress(done: int, total: int) -> None:
        bar.update(done - bar.n)

    try:
        path, record = run_sweep(
            scenario,
            vary,
            out,
            args.repeats,
            to=args.to,
            overwrite=args.overwrite,
            progress=progress,
            command=sys.argv,
            workers=args.workers,
            scheduler=args.scheduler,
        )
    except KeyboardInterrupt:
        bar.close()
        resumable_interrupt("points and runs", out)
    finally:
        bar.close()
    if args.quiet:
        return
    print(f"{len(record['points'])} points x {args.repeats} repeats; written to {path}")
    shown = [
        n
        for n in (
            "conveyor.areal_weight.mean_g_m2",
            "conveyor.areal_weight.cv",
            "conveyor.thickness.mean_mm",
            "conveyor.orientation.order_cos2",
            "stack.mean_height_mm",
            "stack.volume_fraction",
        )
        if any(n in p["scalars"] for p in record["points"])
    ]
    for point in record["points"]:
        cells = []
        for name in shown:
            s = point["scalars"].get(name)
            if s and s["mean"] is not None:
                half = "" if s["ci_high"] is None else f" +- {(s['ci_high'] - s['mean']):.3g}"
                cells.append(f"{name.split('.', 1)[1]} {s['mean']:.4g}{half}")
        print(f"{point['dir']}: " + "; ".join(cells))
