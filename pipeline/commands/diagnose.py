"""``pipeline diagnose SPEC``: the sim-to-real diagnosis of an experiment, its progress
on stderr and its verdict."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from chipstack.pipeline.diagnose import diagnose

__all__ = ["main"]


def main(args: argparse.Namespace) -> None:
    out = args.out or f"runs/diagnose-{Path(args.spec).stem}"

    def progress(message: str) -> None:
        # The reference table's build takes minutes the first time: always shown.
        long_work = message.startswith(("reference table", "model choice"))
        if args.verbose or (long_work and not args.quiet):
            sys.stderr.write(f"pipeline: {message}\n")

    path, result = diagnose(
        args.spec,
        out,
        seed=args.seed,
        workers=args.workers,
        scheduler=args.scheduler,
        overwrite=args.overwrite,
        progress=progress,
        command=sys.argv,
        tables=args.tables,
    )
    if not args.quiet:
        print(f"{result['verdict']['kind']}: {result['verdict']['text']}")
        print(f"diagnosis in {result['wall_time_s']:.1f} s; report written to {path}/diagnosis.md")
