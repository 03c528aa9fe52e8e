"""``pipeline compare RUN_A RUN_B``: the comparison of two ensembles, and its table."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from chipstack.pipeline.compare import compare_runs

__all__ = ["main"]


def main(args: argparse.Namespace) -> None:
    out = args.out or f"runs/compare-{Path(args.run_a).name}-{Path(args.run_b).name}"
    _, table = compare_runs(args.run_a, args.run_b, out, overwrite=args.overwrite, command=sys.argv)
    if not args.quiet:
        print(table, end="")
        print(f"written to {out}")
