"""``pipeline synth SPEC``: pseudo-experimental observations from the simulation with
chosen effects, written to a CSV file."""

from __future__ import annotations

import argparse

from chipstack.pipeline.diagnose import synth

__all__ = ["main"]


def main(args: argparse.Namespace) -> None:
    path, rows = synth(
        args.spec,
        args.effect,
        args.seed,
        args.output,
        drops=args.drops,
        measurements=args.measurements,
        overwrite=args.overwrite,
        workers=args.workers,
        position_sd_mm=args.position_sd_mm,
        angle_sd_deg=args.angle_sd_deg,
    )
    print(f"{rows} observations written to {path}")
